"""Detection while the CT is still being read gives what detection on the whole CT gives.

The coarse scan must return every component exactly once whatever the steps it is fed in,
detection must never look at slices not yet read, and a read that fails (truncated data, a
bad checksum found only at the end) must fail the detection and leave the controller as it was.
"""

from __future__ import annotations

import gzip

import numpy as np
import pytest
import SimpleITK as sitk
from fixtures import phantom as ph
from scipy import ndimage

from EMRegModule.core.detection import detect as detect_module
from EMRegModule.core.detection import detect_markers
from EMRegModule.core.detection.components import GrowingComponents
from EMRegModule.core.detection.segmentation import CoarseScan
from EMRegModule.core.detection.settings import DetectionSettings, settings_from_dict
from EMRegModule.errors import EMRegError
from EMRegModule.io.fast_read import start_fast_read, writable_bytes
from EMRegModule.marker_model import MarkerModel
from EMRegModule.pipeline.controller import EMRegController


def _components(scan_steps: list[int], volume: np.ndarray) -> tuple[list, list]:
    scan = CoarseScan(volume, np.array([0.6, 0.6, 0.6]), MarkerModel(), DetectionSettings(coarse_step_mm=1.2))
    regions, too_large = [], []
    for slices in scan_steps:
        found, large = scan.advance(slices)
        regions += [tuple((s.start, s.stop) for s in r.slices) for r in found]
        too_large += [tuple(np.round(t.centroid_zyx, 6)) + (round(t.volume_mm3, 6),) for t in large]
    return sorted(regions), sorted(too_large)


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_coarse_scan_returns_each_component_once_whatever_the_steps(seed):
    rng = np.random.default_rng(seed)
    volume = np.full((200, 150, 150), -1000, dtype=np.int16)
    for _ in range(30):  # marker-sized blobs (0.6 mm voxels), some touching each other or the volume's ends
        z, y, x = rng.integers([0, 0, 0], volume.shape)
        size = rng.integers(12, 26, size=3)
        volume[z:z + size[0], y:y + size[1], x:x + size[2]] = 1000
    volume[20:190, 70:75, 70:75] = 1000  # a long rod: open over many steps, too large in the end
    volume[-16:, 120:140, 10:30] = 1000  # a blob at the last slices
    whole = _components([volume.shape[0]], volume)
    assert len(whole[0]) > 10 and len(whole[1]) >= 1
    for step in (1, 2, 5, 17):
        steps = list(range(step, volume.shape[0], step)) + [volume.shape[0]]
        assert _components(steps, volume) == whole, f"steps of {step} slices"
    uneven = sorted(set(rng.integers(1, volume.shape[0], size=12).tolist())) + [volume.shape[0]]
    assert _components(uneven, volume) == whole


@pytest.mark.parametrize("seed", range(4))
def test_growing_components_equal_the_labels_of_the_whole_volume(seed):
    """Blocks of rows joined through their boundary give scipy's 26-connected components of the whole: count,
    mean index and bounding box of each, every component once (arms that meet rows later, one-row blocks)."""
    rng = np.random.default_rng(seed)
    volume = rng.random((60, 35, 40)) < 0.03
    if seed % 2:
        volume = ndimage.binary_dilation(volume)
    volume[5:50, 3, 3:30] = volume[5:50, 30, 3:30] = True  # a U: two arms, joined only at row 49
    volume[49, 3:31, 3] = True
    labels, _ = ndimage.label(volume, structure=np.ones((3, 3, 3), dtype=bool))
    expected = []
    for label, box in enumerate(ndimage.find_objects(labels), start=1):
        members = np.argwhere(labels == label)
        expected.append((len(members), tuple(members.mean(axis=0)), tuple(s.start for s in box),
                         tuple(s.stop for s in box)))
    for min_count in (0, 4):  # specks below min_count are dropped unseen
        components, row = GrowingComponents(), 0
        found = []
        while row < len(volume):
            step = int(rng.integers(1, 7))
            last = row + step >= len(volume)
            complete = components.add(volume[row:row + step], last=last, min_count=min_count)
            found += [(c.count, tuple(c.mean_zyx), tuple(c.start_zyx), tuple(c.stop_zyx)) for c in complete]
            assert last or all(c.stop_zyx[0] < row + step for c in complete)  # never one the newest row touches
            row += step
        kept = [e for e in expected if e[0] >= min_count]
        assert sorted(found) == sorted(kept) and len(kept) > 2 and (min_count or len(found) > 20)


def _scene_with_metal_ahead() -> sitk.Image:
    """Markers in air along the slice axis; behind one of them (further along k) a metal block 14 mm away."""
    model = MarkerModel()
    geometry = ph.make_image_geometry((100, 100, 150), (0.6, 0.6, 0.6))
    ex, ey, ez = np.eye(3)
    objects = [ph.marker_object(model, (10.0, 30.0, 30.0), ex),  # spans z 22..38 mm
               ph.marker_object(model, (35.0, 25.0, 10.0), ez, spin_deg=20),
               ph.marker_object(model, (30.0, 30.0, 62.0), ey),
               ph.box_object((19.0, 30.0, 47.0), (4.0, 4.0, 3.0), 3071.0, kind="metal")]  # z 44..50 mm
    return ph.render(geometry, objects, noise_hu=15.0, seed=2)


def test_detection_never_reads_slices_before_they_arrive(monkeypatch):
    """Slices not yet 'read' hold marker-like poison: any early look would change the result.

    Streamed a coarse row at a time, so that each region starts as early as it can; the metal
    check of the first marker must see the metal that arrives only after the marker's slices.
    """
    monkeypatch.setattr(detect_module, "_STEP_ROWS", 1)
    image = _scene_with_metal_ahead()
    expected = detect_markers(image, MarkerModel())
    assert len(expected.markers) == 3
    truth = sitk.GetArrayViewFromImage(image)
    arriving = sitk.Image(image.GetSize(), image.GetPixelID())
    arriving.CopyInformation(image)
    buffer = writable_bytes(arriving).view(truth.dtype).reshape(truth.shape)
    buffer[...] = 1000  # in the marker band everywhere
    calls: list[int] = []

    def wait_for_slices(stop: int) -> None:
        start = calls[-1] if calls else 0
        buffer[start:stop] = truth[start:stop]
        calls.append(max(start, stop))

    whole_scan = CoarseScan(truth, np.asarray(image.GetSpacing())[::-1], MarkerModel(),
                            settings_from_dict(None, MarkerModel()))
    whole_scan.advance(truth.shape[0])
    all_metal = whole_scan.metal_zyx
    metal_checks: list[tuple[float, float]] = []
    metal_distance = detect_module.metal_distance_mm

    def spied_metal_distance(centroid, metal_zyx, *args):
        seen = metal_distance(centroid, metal_zyx, *args)
        metal_checks.append((seen, metal_distance(centroid, all_metal, *args)))
        return seen

    monkeypatch.setattr(detect_module, "metal_distance_mm", spied_metal_distance)
    streamed = detect_markers(arriving, MarkerModel(), wait_for_slices=wait_for_slices)
    assert len(calls) >= 50 and calls == sorted(calls)
    limit = DetectionSettings().metal_distance_mm + 0.5 * np.hypot(MarkerModel().height_mm,
                                                                    MarkerModel().bottom_diameter_mm)
    near = [(seen <= limit, whole <= limit) for seen, whole in metal_checks]
    assert any(whole for _, whole in near), "no candidate near metal: the check below would test nothing"
    assert all(seen == whole for seen, whole in near), "a metal check missed metal in slices not yet read"
    assert [m.id for m in streamed.markers] == [m.id for m in expected.markers]
    for got, want in zip(streamed.markers, expected.markers, strict=True):
        np.testing.assert_array_equal(got.origin, want.origin)
        np.testing.assert_array_equal(got.axis, want.axis)
    assert [r.reason for r in streamed.rejected] == [r.reason for r in expected.rejected]


def _gzip_nrrd(path, array_zyx: np.ndarray) -> bytes:
    header = "\n".join(["NRRD0004", "type: short", "dimension: 3", "space: left-posterior-superior",
                        "sizes: " + " ".join(str(n) for n in array_zyx.shape[::-1]),
                        "space directions: (0.6,0,0) (0,0.6,0) (0,0,0.6)", "endian: little", "encoding: gzip", "", ""])
    data = header.encode("ascii") + gzip.compress(array_zyx.astype("<i2").tobytes(), compresslevel=1)
    path.write_bytes(data)
    return data


def test_fill_announces_slices_and_reports_bad_data(tmp_path):
    array = np.random.default_rng(3).integers(-1000, 2000, size=(120, 200, 200)).astype(np.int16)
    good = tmp_path / "good.nrrd"
    data = _gzip_nrrd(good, array)
    fill = start_fast_read(good)
    fill.wait_for_slices(30)
    np.testing.assert_array_equal(sitk.GetArrayViewFromImage(fill.image)[:30], array[:30])
    np.testing.assert_array_equal(sitk.GetArrayViewFromImage(fill.result()), array)

    truncated = tmp_path / "truncated.nrrd"
    truncated.write_bytes(data[: len(data) // 2])
    fill = start_fast_read(truncated)
    with pytest.raises(EMRegError, match="truncated"):
        fill.wait_for_slices(fill.slice_count)
    with pytest.raises(EMRegError, match="truncated"):
        fill.result()

    bad_checksum = tmp_path / "bad_checksum.nrrd"
    bad_checksum.write_bytes(data[:-8] + bytes(b ^ 0xFF for b in data[-8:-4]) + data[-4:])  # CRC-32 flipped
    fill = start_fast_read(bad_checksum)
    with pytest.raises(EMRegError, match="corrupt"):
        fill.result()


def test_controller_is_unchanged_when_the_read_fails_late(tmp_path):
    """Every voxel arrives and detection finishes, but the gzip checksum at the end is wrong."""
    scene = ph.scene(decoys=False, metal=False, cut_marker=False, seed=6)  # 0.6 mm, 167 x 167 x 110 voxels
    path = tmp_path / "ct.nrrd"
    data = _gzip_nrrd(path, sitk.GetArrayViewFromImage(scene.image))
    intact = EMRegController()
    intact.make("detect", ct=path)
    assert len(intact.results.detection.markers) == len(scene.markers)  # the intact file: detection runs to the end
    path.write_bytes(data[:-8] + bytes(b ^ 0xFF for b in data[-8:-4]) + data[-4:])
    controller = EMRegController()
    with pytest.raises(EMRegError, match="corrupt"):
        controller.make("detect", ct=path)
    assert controller.inputs.image is None and controller.results.detection is None
