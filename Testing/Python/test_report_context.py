"""The report's use of the CT: binning that follows the read, the cleaned context surface, slices sampled
as the CT arrives, and the batch's memory limit."""

from __future__ import annotations

import io

import numpy as np
import pytest
import SimpleITK as sitk
from fixtures import samples

from EMRegModule.io.image import open_ct, write_image
from EMRegModule.marker_model import MarkerModel
from EMRegModule.progress import Progress
from EMRegModule.rendering.context import BinnedCT, binned_ct, context_surface, otsu_threshold
from EMRegModule.rendering.slices import CTSampler, SliceMarker, StreamingMarkerViews, sample_marker_views
from EMRegModule.report import batch


def _volume(seed: int = 3) -> sitk.Image:
    """An oblique int16 CT with odd sizes (incomplete last blocks) and noise."""
    rng = np.random.default_rng(seed)
    array = rng.integers(-1100, 1500, size=(37, 41, 53)).astype(np.int16)  # (k, j, i)
    image = sitk.GetImageFromArray(array)
    image.SetSpacing([0.7, 0.8, 0.9])
    image.SetOrigin([-12.0, 5.0, 30.0])
    direction = np.array([[0.0, -1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, 1.0]])
    image.SetDirection(direction.ravel().tolist())
    return image


def test_binning_is_the_block_mean_with_binshrinks_geometry(tmp_path):
    image = _volume()
    binned = binned_ct(image, max_voxels=2000)
    f = binned.factor
    array = sitk.GetArrayFromImage(image).astype(float)
    nk, nj, ni = (s // f for s in array.shape)
    expected = array[:nk * f, :nj * f, :ni * f].reshape(nk, f, nj, f, ni, f).mean(axis=(1, 3, 5))
    assert f > 1 and binned.values.shape == (nk, nj, ni)
    np.testing.assert_allclose(binned.values, expected, atol=1e-3)
    shrunk = sitk.BinShrink(image, [f] * 3)  # ITK's geometry of the same binning
    index = np.array([1.0, 2.0, 3.0, 1.0])
    assert np.allclose((binned.index_to_image @ index)[:3], shrunk.TransformContinuousIndexToPhysicalPoint(
        index[:3].tolist()), atol=1e-9)
    # following a CT being read gives the same numbers, and tells which slices are there
    path = tmp_path / "ct.nrrd"
    write_image(image, path)
    fill = open_ct(path)
    announced: list[int] = []
    followed = binned_ct(fill, max_voxels=2000, on_slices=announced.append)
    assert np.array_equal(followed.values, binned.values)
    assert announced == sorted(announced) and announced[-1] == array.shape[0]


def _scene_volume(sheet: bool) -> BinnedCT:
    """Air with a solid block, a small separate blob and optionally a one-voxel sheet (a streak)."""
    values = np.full((40, 50, 60), -1000.0, dtype=np.float32)
    values[10:30, 10:40, 10:40] = 300.0  # the frame
    values[5:8, 44:47, 50:53] = 300.0  # a 27-voxel crumb away from it
    if sheet:
        values[2:38, 20, 0:60] = 400.0  # a thin sheet through everything
    return BinnedCT(values, np.diag([2.0, 2.0, 2.0, 1.0]), 1)


def test_context_surface_drops_streak_sheets_and_crumbs_but_keeps_the_frame():
    clean = context_surface(_scene_volume(sheet=False), iso_value=-350.0)
    streaked = context_surface(_scene_volume(sheet=True), iso_value=-350.0)
    plain = context_surface(_scene_volume(sheet=True), iso_value=-350.0, clean=False)
    frame_bounds = np.array([10, 39, 10, 39, 10, 29]) * 2.0  # x from i, y from j, z from k (mm)
    assert np.allclose(streaked.surface.bounds, clean.surface.bounds, atol=2.1)
    assert np.allclose(streaked.surface.bounds, frame_bounds, atol=2.1)
    assert plain.surface.bounds[1] > 110 and plain.surface.bounds[5] > 70  # the sheet is there without cleaning
    assert streaked.dropped_thin_voxels > 1000 and streaked.pieces == 1 and streaked.dropped_pieces >= 1
    assert "metal streaks" in streaked.description() and "1 connected piece" in streaked.description()
    # where the frame is kept, the surface is the plain iso-surface (same points on the block's faces)
    assert streaked.surface.n_points == pytest.approx(clean.surface.n_points, rel=0.05)


def test_otsu_threshold_ignores_metal():
    rng = np.random.default_rng(0)
    values = np.concatenate([rng.normal(-1000, 20, 50000), rng.normal(300, 20, 30000), np.full(200, 30000.0)])
    assert -900 < otsu_threshold(values) < 200


@pytest.mark.parametrize("padding_hu", [-2000.0, -3024.0])
def test_padding_outside_the_field_of_view_is_air_to_the_surface(padding_hu):
    """A scanner's padding outside its circular field of view (DICOM Pixel Padding Value) leaves the iso-value
    between air and the frame, and the surface on the frame: no cylinder around the field of view."""
    plain = _scene_volume(sheet=False)
    k, j, i = np.indices(plain.values.shape)
    padded = BinnedCT(plain.values.copy(), plain.index_to_image, 1)
    padded.values[(j - 25) ** 2 + (i - 30) ** 2 > 24**2] = padding_hu
    iso = otsu_threshold(padded.values)
    assert iso == pytest.approx(otsu_threshold(plain.values), abs=60.0) and -900 < iso < 200
    surface = context_surface(padded)
    assert np.allclose(surface.surface.bounds, np.array([10, 39, 10, 39, 10, 29]) * 2.0, atol=2.1)


def test_slices_sampled_while_the_ct_arrives_equal_those_of_the_whole_ct(tmp_path):
    model = MarkerModel()
    markers = samples.sample_markers()[:3]
    image = samples.paint_sample_ct(markers, model, size=(120, 120, 60), spacing_mm=0.6)
    path = tmp_path / "ct.nrrd"
    write_image(image, path)
    slice_markers = [SliceMarker(m.label, m.marker_to_image) for m in markers]
    fill = open_ct(path)
    streaming = StreamingMarkerViews(fill.image, slice_markers, model)
    binned_ct(fill, on_slices=streaming.sample_ready)
    sampler = CTSampler(image)
    for marker, views in zip(markers, streaming.views(), strict=True):
        expected = sample_marker_views(sampler, marker.marker_to_image, model, 140, 0.2)
        for got, want in zip(views, expected, strict=True):
            assert np.array_equal(got, want, equal_nan=True)


def test_batch_jobs_are_limited_by_memory(tmp_path, monkeypatch):
    folders = [str(tmp_path / f"run{i}") for i in range(4)]
    monkeypatch.setattr(batch, "ct_bytes_of_run", lambda folder: 3e9)
    monkeypatch.setattr(batch, "available_memory_bytes", lambda: 8e9)
    stream = io.StringIO()
    jobs = batch.memory_limited_jobs(folders, 4, Progress(stream))
    per_case = batch.CT_MEMORY_FACTOR * 3e9 + batch.LIBRARY_BYTES
    assert jobs == int(batch.MEMORY_SHARE * 8e9 // per_case) == 1
    assert "1 of the 4 jobs" in stream.getvalue() and "GB available" in stream.getvalue()
    monkeypatch.setattr(batch, "available_memory_bytes", lambda: 64e9)
    assert batch.memory_limited_jobs(folders, 4, Progress(io.StringIO())) == 4
    assert batch.memory_limited_jobs(folders[:2], 4, Progress(io.StringIO())) == 2


def test_batch_estimate_reads_the_ct_header_of_a_run(tmp_path):
    image = samples.empty_ct((30, 20, 10))
    case = tmp_path / "case"
    case.mkdir()
    write_image(image, case / "ct.nrrd")
    out = tmp_path / "out"
    out.mkdir()
    (out / "run.json").write_text(f'{{"case": "{case}", "ct": "{case / "ct.nrrd"}"}}', encoding="utf-8")
    assert batch.ct_bytes_of_run(out) == 30 * 20 * 10 * 2
    assert batch.ct_bytes_of_run(tmp_path) == 0.0  # no run.json: unknown


def test_progress_shows_throughput():
    stream = io.StringIO()
    with Progress(stream).step("reports", total=2, per_minute="cases") as step:
        step.advance()
        step.advance()
    assert "cases/min" in stream.getvalue()
