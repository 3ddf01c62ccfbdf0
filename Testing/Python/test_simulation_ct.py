"""The simulator's CT geometry: markers where truth.json says, absent markers absent, DICOM geometry."""

from __future__ import annotations

import numpy as np
import pytest
import SimpleITK as sitk
from conftest import load_truth

from EMRegModule.core.transforms import apply_transform, random_rotation, rotation_from_y_axis
from EMRegModule.io.case import find_ct
from EMRegModule.io.image import read_ct
from EMRegModule.marker_model import MarkerModel
from EMRegModule.simulation import ct
from EMRegModule.simulation.shapes import MarkerSolid, Posed


class _Sampler:
    """Mean CT value in a 3x3x3 voxel block around physical points (LPS)."""

    def __init__(self, case_dir):
        self.image = read_ct(find_ct(case_dir))
        self.array = sitk.GetArrayViewFromImage(self.image)
        self.size = np.asarray(self.image.GetSize())

    def __call__(self, point_lps) -> float:
        index = np.round(self.image.TransformPhysicalPointToContinuousIndex([float(v) for v in point_lps]))
        i, j, k = index.astype(int)
        assert np.all(index >= 1) and np.all(index < self.size - 1), f"{point_lps} outside the CT"
        return float(self.array[k - 1:k + 2, j - 1:j + 2, i - 1:i + 2].mean())


def _marker_points(marker: dict, model: MarkerModel) -> dict[str, list[np.ndarray]]:
    """Probe points in image space: deep inside the PVC, in air above/beside the top, in POM beside the slot."""
    marker_to_image = np.asarray(marker["marker_to_image"])
    r_bottom, h_bottom, h = model.bottom_diameter_mm / 2, model.bottom_height_mm, model.height_mm
    around = [np.array([np.cos(a), 0.0, np.sin(a)]) for a in np.radians([0, 90, 200, 300])]
    local = {
        "pvc": [np.array([0.0, h_bottom / 2, 0.0])] + [np.array([0.0, h_bottom / 2, 0.0]) + 4.0 * u for u in around]
        + [np.array([0.0, h_bottom + 2.0, 0.0]) + 1.8 * u for u in around[:2]],
        "air_above": [np.array([0.0, h + 3.0, 0.0])],
        "air_beside": [np.array([0.0, h_bottom + 5.0, 0.0]) + (model.top_diameter_mm / 2 + 3.5) * u for u in around],
        "pom_beside": [np.array([0.0, h_bottom / 2, 0.0]) + (r_bottom + 4.0) * u for u in around],
    }
    return {k: [apply_transform(marker_to_image, p) for p in v] for k, v in local.items()}


@pytest.mark.parametrize("case_name", ["standard_case", "hard_case"])
def test_markers_are_pvc_inside_and_not_outside(case_name, request):
    case = request.getfixturevalue(case_name)
    truth = load_truth(case)
    model = MarkerModel(**truth["marker_model"])
    sample = _Sampler(case)
    checked = 0
    for marker in truth["markers"]:
        if not marker["in_ct"]:
            continue
        points = _marker_points(marker, model)
        pvc = [sample(p) for p in points["pvc"]]
        assert 950 < np.median(pvc) < 1250 and min(pvc) > 600, (marker["label"], pvc)
        assert sample(points["air_above"][0]) < -700, marker["label"]
        assert max(sample(p) for p in points["air_beside"]) < 300, marker["label"]  # air, or patient nearby
        pom = [sample(p) for p in points["pom_beside"]]
        assert 250 < np.median(pom) < 450, (marker["label"], pom)  # the slot sits in the POM block
        checked += 1
    assert checked == sum(m["in_ct"] for m in truth["markers"]) >= 13


def test_pom_block_and_noise_level(standard_case):
    truth = load_truth(standard_case)
    frame_to_image = np.asarray(truth["frame"]["FrameToImage"])
    size = np.asarray(truth["frame"]["size_mm"])
    image = read_ct(find_ct(standard_case))
    # a 20 mm cube in the block's solid middle (below the bed cut)
    centre = apply_transform(frame_to_image, [0.25 * size[0], 0.0, 0.3 * size[2]])
    index = np.round(image.TransformPhysicalPointToContinuousIndex(centre.tolist())).astype(int)
    half = int(10 / min(image.GetSpacing()))
    block = sitk.GetArrayViewFromImage(image)[index[2] - half:index[2] + half, index[1] - half:index[1] + half,
                                              index[0] - half:index[0] + half].astype(float)
    assert abs(block.mean() - 340) < 8
    assert 0.8 * truth["ct"]["noise_hu"] < block.std() < 1.25 * truth["ct"]["noise_hu"]
    # noise is correlated (filtered): neighbouring voxels are alike
    flat = block - block.mean()
    correlation = float((flat[:, :, 1:] * flat[:, :, :-1]).mean() / flat.var())
    assert 0.1 < correlation < 0.9


def test_reference_sensor_saturates_with_streaks(standard_case):
    truth = load_truth(standard_case)
    image = read_ct(find_ct(standard_case))
    array = sitk.GetArrayViewFromImage(image)
    reference_to_image = np.asarray(truth["ReferenceToImage"])
    centre = reference_to_image[:3, 3]
    index = np.round(image.TransformPhysicalPointToContinuousIndex(centre.tolist())).astype(int)
    assert array[index[2], index[1], index[0]] == 3071
    # streaks live in the scanner's axial plane (constant LPS z) through the metal: the POM there,
    # 12..40 mm from the sensor, varies far more than the POM of a parallel plane 30 mm away
    image_to_frame = np.linalg.inv(np.asarray(truth["frame"]["FrameToImage"]))
    size = np.asarray(truth["frame"]["size_mm"])

    def pom_values(plane_offset_mm: float) -> list[float]:
        values = []
        for angle in np.radians(np.arange(0, 360, 3)):
            for radius in (12.0, 20.0, 28.0, 40.0):
                point = centre + [radius * np.cos(angle), radius * np.sin(angle), plane_offset_mm]
                x, y, z = apply_transform(image_to_frame, point)
                if abs(x) < size[0] / 2 - 3 and abs(y) < size[1] / 2 - 3 and 3 < z < 0.5 * size[2]:
                    idx = np.round(image.TransformPhysicalPointToContinuousIndex(point.tolist())).astype(int)
                    values.append(float(array[idx[2], idx[1], idx[0]]))
        return values

    near, far = pom_values(0.0), pom_values(30.0)
    assert len(near) > 50 and len(far) > 50
    assert np.std(far) < 40
    assert np.std(near) > 2.5 * np.std(far)


def test_absent_and_uncalibrated_markers(hard_case):
    truth = load_truth(hard_case)
    model = MarkerModel(**truth["marker_model"])
    absent = [m for m in truth["markers"] if not m["in_ct"]]
    uncalibrated = [m for m in truth["markers"] if not m["calibrated"]]
    assert len(absent) == 2 and all(m["calibrated"] for m in absent)
    assert len(uncalibrated) == 1 and uncalibrated[0]["in_ct"]
    sample = _Sampler(hard_case)
    for marker in absent:
        points = _marker_points(marker, model)
        assert max(sample(p) for p in points["pvc"]) < -700, marker["label"]  # an empty slot: air
        assert 250 < np.median([sample(p) for p in points["pom_beside"]]) < 450


def test_decoys_are_pvc_like_and_away_from_markers(hard_case):
    truth = load_truth(hard_case)
    sample = _Sampler(hard_case)
    kinds = {d["kind"] for d in truth["decoys"]}
    assert {"sphere", "rod", "box", "disc"} <= kinds
    origins = np.array([m["origin"] for m in truth["markers"]])
    for decoy in truth["decoys"]:
        assert 900 < sample(decoy["center"]) < 1300, decoy
        assert np.min(np.linalg.norm(origins - decoy["center"], axis=1)) > 20.0


def test_dicom_series_reads_back_with_truth_geometry(hard_case):
    truth = load_truth(hard_case)
    folder = hard_case / "ct"
    assert folder.is_dir() and not (hard_case / "ct.nrrd").exists()
    image = read_ct(folder)
    geometry = truth["image"]
    assert list(image.GetSize()) == geometry["size"]
    assert np.allclose(image.GetSpacing(), geometry["spacing"], atol=1e-5)
    assert np.allclose(image.GetSpacing(), [0.5, 0.5, 0.8], atol=1e-5)
    assert np.allclose(image.GetOrigin(), geometry["origin"], atol=1e-4)
    assert np.allclose(image.GetDirection(), geometry["direction"], atol=1e-6)
    direction = np.asarray(geometry["direction"]).reshape(3, 3)
    assert np.abs(direction).max(axis=0).min() < np.cos(np.radians(2.0))  # oblique
    assert direction[0, 0] < 0  # flipped in-plane: rows run towards patient right
    files = sorted(folder.glob("*.dcm"))
    assert len(files) == geometry["size"][2]
    reader = sitk.ImageFileReader()
    series = set()
    for path in (files[0], files[-1]):
        reader.SetFileName(str(path))
        reader.ReadImageInformation()
        assert reader.GetMetaData("0008|0060").strip() == "CT"
        assert float(reader.GetMetaData("0028|1052")) == -1024.0
        assert float(reader.GetMetaData("0018|0050")) == pytest.approx(0.8)
        series.add(reader.GetMetaData("0020|000e").strip())
    assert len(series) == 1


# --- synthesis units -------------------------------------------------------------------------


def _painted_marker(direction: np.ndarray, spacing, model: MarkerModel):
    """One marker painted (no blur/noise) on a small oblique grid; returns fill fraction and grid."""
    marker_to_image = np.eye(4)
    marker_to_image[:3, :3] = rotation_from_y_axis([0.3, -0.5, 0.8])
    marker_to_image[:3, 3] = [12.3, -40.7, 101.1]
    corners = np.array([[x, y, z] for x in (-9, 9) for y in (-1, 20) for z in (-9, 9)], dtype=float)
    grid = ct.grid_around(apply_transform(marker_to_image, corners), np.asarray(spacing), direction, 2.0)
    volume = np.full(grid.shape_kji, ct.AIR_HU, dtype=np.float32)
    layer = ct.Layer("marker", Posed(MarkerSolid(model), marker_to_image), 1100.0, 5)
    ct.paint_layers(volume, grid, np.eye(4), [layer])
    return (volume - ct.AIR_HU) / (1100.0 - ct.AIR_HU), grid, marker_to_image


@pytest.mark.parametrize("flip", [False, True])
def test_partial_volume_painting_keeps_volume_and_centroid(flip):
    model = MarkerModel()
    direction = random_rotation(np.random.default_rng(3), 30.0) @ (np.diag([1.0, 1.0, -1.0]) if flip else np.eye(3))
    fraction, grid, marker_to_image = _painted_marker(direction, (0.5, 0.55, 0.8), model)
    voxel = float(np.prod(grid.spacing))
    assert fraction.sum() * voxel == pytest.approx(model.volume_mm3, rel=0.01)
    k, j, i = np.indices(fraction.shape)
    index = np.stack([i, j, k], axis=-1).reshape(-1, 3)
    weights = fraction.reshape(-1)
    centroid = apply_transform(grid.index_to_image, (index * weights[:, None]).sum(axis=0) / weights.sum())
    expected = apply_transform(marker_to_image, [0.0, model.centroid_y_mm, 0.0])
    assert np.linalg.norm(centroid - expected) < 0.03
    partial = np.count_nonzero((fraction > 0.02) & (fraction < 0.98))
    assert partial > 0.2 * np.count_nonzero(fraction > 0.5)  # edges are graded, not binary


def test_grid_around_holds_points_for_any_direction():
    rng = np.random.default_rng(5)
    points = rng.uniform(-100, 100, (50, 3))
    for direction in (np.eye(3), random_rotation(rng, 40.0), random_rotation(rng, 40.0) @ np.diag([-1, 1, 1.0])):
        grid = ct.grid_around(points, np.array([0.5, 0.7, 1.1]), direction, 3.0)
        index = apply_transform(np.linalg.inv(grid.index_to_image), points)
        assert np.all(index >= 0) and np.all(index <= np.asarray(grid.size) - 1)


def test_bones_lie_near_some_markers(standard_case):
    """Hands rest on the top face beside markers: bone-bright voxels within 12 mm of a marker's surface."""
    truth = load_truth(standard_case)
    model = MarkerModel(**truth["marker_model"])
    image = read_ct(find_ct(standard_case))
    array = sitk.GetArrayViewFromImage(image)
    index_to_image = np.eye(4)
    index_to_image[:3, :3] = np.asarray(image.GetDirection()).reshape(3, 3) * np.asarray(image.GetSpacing())
    index_to_image[:3, 3] = image.GetOrigin()
    near = 0
    for marker in truth["markers"]:
        centre = apply_transform(marker["marker_to_image"], [0.0, model.height_mm / 2, 0.0])
        index = np.round(image.TransformPhysicalPointToContinuousIndex(centre.tolist())).astype(int)
        r = int(np.ceil(24 / min(image.GetSpacing())))
        lo = np.maximum(index - r, 0)
        block = array[lo[2]:index[2] + r, lo[1]:index[1] + r, lo[0]:index[0] + r]
        k, j, i = np.nonzero(block > 700)
        points = apply_transform(index_to_image, np.column_stack([i + lo[0], j + lo[1], k + lo[2]]))
        local = apply_transform(np.linalg.inv(marker["marker_to_image"]), points)
        distance = model.signed_distance(local)
        near += bool(np.any((distance > 3.0) & (distance < 12.0)))
    assert near >= 2, near
