"""Golden-image regression tests of the report's renderers.

Each test renders a small fixed scene (Testing/Python/fixtures/samples.py) and compares it with
``Testing/Baseline/<name>.png`` using VTK's ``vtkImageDifference`` (shift tolerance off). The labels the
2D figures draw are recorded as data and compared with ``<name>.text.json`` exactly; their pixels are
judged by ink only, so that another version of OpenCV's font rasteriser does not fail a picture whose
bars, curves, outlines, colours and layout are unchanged (see fixtures/compare.py). On a
failure the rendered image and the difference image are written next to the failure
(``<failure dir>/<name>.actual.png`` and ``<name>.diff.png``; by default the pytest temp dir).

Regenerate the baselines on purpose (after an intended change in rendering) with
``EMREG_REGENERATE_BASELINES=1 pytest Testing/Python/test_golden_images.py`` or
``scripts/regenerate_baselines``, then look at the new PNGs before committing them.

The perturbation tests prove the comparison can fail: moving one marker by one voxel, changing the
colour map, or a label showing a wrong number must fail.
"""

from pathlib import Path

import numpy as np
import pytest
from fixtures import samples
from fixtures.compare import (
    REGENERATE_ENV,
    check_against_baseline,
    check_figure_against_baseline,
    compare_images,
    mask_text,
    regenerate_requested,
)

from EMRegModule.rendering.images import read_png
from EMRegModule.rendering.text import recorded_text

BASELINE_DIR = Path(__file__).resolve().parents[1] / "Baseline"

#: Largest accepted vtkImageDifference thresholded error. Identical renders give 0; a one-voxel
#: (0.5-0.6 mm) marker shift gives about 200-300 and a colour-map change 500 or more.
MAX_ERROR = 20.0

CT_VOXEL_3D_MM = 1.2 / 2  # the golden 3D scene's markers move by one voxel of the 0.6 mm sample CT
CT_VOXEL_SLICES_MM = 0.5


def _render(render, **options):
    """``(image, labels)``: a golden figure and the labels it drew."""
    with recorded_text() as labels:
        image = render(**options)
    return image, labels


@pytest.fixture(scope="module")
def figures():
    """Every golden image rendered once (unperturbed), with its labels."""
    return {name: _render(render) for name, render in samples.GOLDEN_IMAGES.items()}


@pytest.fixture(scope="module")
def rendered(figures):
    return {name: image for name, (image, _) in figures.items()}


@pytest.mark.parametrize("name", sorted(samples.GOLDEN_IMAGES))
def test_matches_baseline(name, figures, tmp_path):
    image, labels = figures[name]
    check_figure_against_baseline(image, labels, BASELINE_DIR / name, MAX_ERROR, failure_dir=tmp_path)
    if not regenerate_requested():
        baseline = read_png(BASELINE_DIR / name)
        assert baseline.shape == image.shape
        assert max(baseline.shape[:2]) <= 700  # baselines stay small


def test_rendering_is_deterministic(rendered):
    again = samples.golden_frame_image()
    assert np.array_equal(again, rendered["frame_scene.png"])
    assert np.array_equal(samples.golden_slices_image(), rendered["marker_slices.png"])


def _expect_failure(figure, name, tmp_path, match="image differs from the baseline"):
    image, labels = figure
    with pytest.raises(AssertionError, match=match) as info:
        check_figure_against_baseline(image, labels, BASELINE_DIR / name, MAX_ERROR, failure_dir=tmp_path)
    stem = Path(name).stem
    assert (tmp_path / f"{stem}.actual.png").is_file() and (tmp_path / f"{stem}.diff.png").is_file()
    diff = read_png(tmp_path / f"{stem}.diff.png")
    assert diff.shape == image.shape and diff.max() > 0
    return str(info.value)


skip_when_regenerating = pytest.mark.skipif(regenerate_requested(), reason="regenerating baselines")


@skip_when_regenerating
def test_marker_moved_by_one_voxel_fails(tmp_path):
    _expect_failure(_render(samples.golden_frame_image, shift_mm=(CT_VOXEL_3D_MM, 0.0, 0.0)), "frame_scene.png",
                    tmp_path)


@skip_when_regenerating
def test_colour_map_change_fails(tmp_path):
    _expect_failure(_render(samples.golden_frame_image, colormap="plasma"), "frame_scene.png", tmp_path)
    _expect_failure(_render(samples.golden_residual_bars_image, colormap="cividis"), "residual_bars.png", tmp_path)


@skip_when_regenerating
def test_ct_marker_moved_by_one_voxel_under_its_outline_fails(tmp_path):
    _expect_failure(_render(samples.golden_slices_image, ct_shift_mm=(CT_VOXEL_SLICES_MM, 0.0, 0.0)),
                    "marker_slices.png", tmp_path)


@skip_when_regenerating
def test_moved_marker_of_fre_curve_fails(tmp_path):
    _expect_failure(_render(samples.golden_fre_curve_image, l_chosen_mm=14.6), "fre_curve.png", tmp_path,
                    match="differ")


@skip_when_regenerating
def test_a_label_showing_a_wrong_number_fails(tmp_path):
    """The curve and its marker where they were, but the label says 14.30 mm: only the labels' data see it."""
    figure = _render(samples.golden_fre_curve_image, label_mm=14.3)
    message = _expect_failure(figure, "fre_curve.png", tmp_path, match="labels differ from the baseline")
    assert "l = 14.30 mm" in message and "l = 14.20 mm" in message


@skip_when_regenerating
def test_a_label_hidden_under_a_box_fails(tmp_path, figures):
    """The labels' data alone would pass a label that was never drawn; its ink in its box does not."""
    image, labels = figures["fre_curve.png"]
    hidden = mask_text(image, [labels[0].box])
    _expect_failure((hidden, labels), "fre_curve.png", tmp_path, match="ink")


@skip_when_regenerating
def test_a_missing_outline_fails(tmp_path):
    """A marker's fitted outline not drawn on its slices fails outside the labels' boxes."""
    _expect_failure(_render(samples.golden_slices_image, outline=False), "marker_slices.png", tmp_path)


@skip_when_regenerating
def test_a_moved_bar_fails(tmp_path, figures):
    """A bar 0.2 mm higher fails on its value label and, with every label's box left out, on its pixels."""
    moved_image, moved_labels = moved = _render(samples.golden_residual_bars_image, values=(0.2, 0.6, 1.3, 1.6, 0.9))
    _expect_failure(moved, "residual_bars.png", tmp_path, match="labels differ")
    image, labels = figures["residual_bars.png"]
    boxes = [item.box for item in (*labels, *moved_labels)]
    assert compare_images(mask_text(moved_image, boxes), mask_text(image, boxes)).error > 5 * MAX_ERROR


def test_comparison_metric_orders_perturbations(rendered):
    """Sub-voxel shifts give smaller errors than a voxel: the metric measures displacement, not noise."""
    base = rendered["frame_scene.png"]
    small = compare_images(samples.golden_frame_image(shift_mm=(0.1, 0.0, 0.0)), base).error
    voxel = compare_images(samples.golden_frame_image(shift_mm=(CT_VOXEL_3D_MM, 0.0, 0.0)), base).error
    assert 0 < small < voxel
    assert voxel > 5 * MAX_ERROR


def test_regeneration_option_writes_baselines(tmp_path, monkeypatch):
    monkeypatch.setenv(REGENERATE_ENV, "1")
    image = samples.golden_residual_bars_image()
    result = check_against_baseline(image, tmp_path / "new.png", MAX_ERROR)
    assert result.error == 0.0
    assert np.array_equal(read_png(tmp_path / "new.png"), image)
    monkeypatch.delenv(REGENERATE_ENV)
    with pytest.raises(AssertionError, match="missing"):
        check_against_baseline(image, tmp_path / "absent.png", MAX_ERROR)


def _oblique_flipped_copy(image):
    """The same CT resampled onto a rotated (30 degrees), left-handed, anisotropic voxel grid."""
    import SimpleITK as sitk

    from EMRegModule.core.transforms import axis_angle_to_rotation

    direction = axis_angle_to_rotation([0.3, -0.5, 1.0], np.radians(30.0)) @ np.diag([-1.0, 1.0, 1.0])
    spacing = np.array([0.45, 0.5, 0.6])
    size = np.array([160, 150, 110])
    centre = np.array(image.TransformContinuousIndexToPhysicalPoint([(s - 1) / 2 for s in image.GetSize()]))
    grid = sitk.Image([int(s) for s in size], sitk.sitkInt16)
    grid.SetSpacing(spacing.tolist())
    grid.SetDirection(direction.ravel().tolist())
    grid.SetOrigin((centre - direction @ (spacing * (size - 1) / 2)).tolist())
    return sitk.Resample(image, grid, sitk.Transform(), sitk.sitkLinear, -1000.0, sitk.sitkInt16)


def test_slices_and_surface_honour_an_oblique_flipped_anisotropic_ct():
    """Physical space, not voxel order: the same CT on another grid gives the same slices and surface."""
    from EMRegModule.marker_model import MarkerModel
    from EMRegModule.rendering.scene3d import ct_context_surface
    from EMRegModule.rendering.slices import SliceMarker, marker_slices_mosaic

    model = MarkerModel()
    fitted = samples.sample_markers()[:2]
    geometry = {"size": (136, 70, 45), "spacing_mm": 0.5, "origin": (-36.0, -32.0, -4.0), "supersample": 5}
    ct = samples.paint_sample_ct(fitted, model, **geometry)
    shifted = samples.paint_sample_ct(samples.sample_markers((CT_VOXEL_SLICES_MM, 0.0, 0.0), which=0)[:2], model,
                                      **geometry)
    oblique = _oblique_flipped_copy(ct)
    assert np.linalg.det(np.reshape(oblique.GetDirection(), (3, 3))) < 0

    def mosaic(image):
        markers = [SliceMarker(m.label, m.marker_to_image, m.label) for m in fitted]
        return marker_slices_mosaic(image, markers, model, columns=2, view_px=100, mm_per_px=0.25,
                                    window=(-1000.0, 1500.0))

    base = mosaic(ct)
    resampled_error = compare_images(mosaic(oblique), base).error  # only the resampling's blur differs
    voxel_error = compare_images(mosaic(shifted), base).error
    assert resampled_error < 0.5 * voxel_error, (resampled_error, voxel_error)

    surface, _ = ct_context_surface(ct, iso_value=500.0)
    surface_oblique, _ = ct_context_surface(oblique, iso_value=500.0)
    assert np.allclose(surface.bounds, surface_oblique.bounds, atol=1.0)
