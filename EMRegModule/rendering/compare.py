"""Image comparison for golden-image tests with VTK's own metric (``vtkImageDifference``).

This is the comparison ``pyvista.compare_images`` and VTK's regression tests use: per
pixel colour differences above a threshold, averaged over the image (``ThresholdedError``),
with the shift tolerance turned off so that a one-pixel displacement counts.
"""

from __future__ import annotations

import os
from dataclasses import dataclass
from pathlib import Path

import numpy as np

#: Environment variable that makes golden-image tests rewrite their baselines.
REGENERATE_ENV = "EMREG_REGENERATE_BASELINES"


@dataclass
class ImageComparison:
    """Result of comparing an image with a baseline: the error and the difference image (RGB)."""

    error: float
    difference: np.ndarray


def _to_vtk(image_rgb: np.ndarray):
    from vtkmodules.util.numpy_support import numpy_to_vtk
    from vtkmodules.vtkCommonDataModel import vtkImageData

    image_rgb = np.ascontiguousarray(np.asarray(image_rgb, dtype=np.uint8)[::-1])  # VTK rows go bottom-up
    height, width = image_rgb.shape[:2]
    vtk_image = vtkImageData()
    vtk_image.SetDimensions(width, height, 1)
    scalars = numpy_to_vtk(image_rgb.reshape(-1, 3), deep=True)
    scalars.SetName("rgb")
    vtk_image.GetPointData().SetScalars(scalars)
    return vtk_image


def compare_images(actual_rgb: np.ndarray, baseline_rgb: np.ndarray, threshold: int = 10) -> ImageComparison:
    """Compare two RGB ``uint8`` images of the same size with ``vtkImageDifference``.

    ``threshold`` is the per-pixel colour difference ignored (as in VTK's regression tests);
    the returned ``error`` is VTK's thresholded error (0 for identical images).
    """
    from vtkmodules.util.numpy_support import vtk_to_numpy
    from vtkmodules.vtkImagingCore import vtkImageDifference

    actual_rgb = np.asarray(actual_rgb)
    baseline_rgb = np.asarray(baseline_rgb)
    if actual_rgb.shape != baseline_rgb.shape:
        raise ValueError(f"image sizes differ: {actual_rgb.shape} vs baseline {baseline_rgb.shape}")
    difference = vtkImageDifference()
    difference.SetThreshold(threshold)
    difference.AllowShiftOff()
    difference.SetInputData(_to_vtk(actual_rgb))
    difference.SetImageData(_to_vtk(baseline_rgb))
    difference.Update()
    output = difference.GetOutput()
    height, width = actual_rgb.shape[:2]
    diff = vtk_to_numpy(output.GetPointData().GetScalars()).reshape(height, width, -1)[::-1, :, :3]
    return ImageComparison(float(difference.GetThresholdedError()), np.ascontiguousarray(diff, dtype=np.uint8))


def regenerate_requested() -> bool:
    """True when ``EMREG_REGENERATE_BASELINES`` asks tests to rewrite their baselines."""
    return os.environ.get(REGENERATE_ENV, "").strip().lower() in ("1", "true", "yes", "on")


def check_against_baseline(
    actual_rgb: np.ndarray, baseline_path: str | os.PathLike[str], max_error: float, threshold: int = 10,
    failure_dir: str | os.PathLike[str] | None = None,
) -> ImageComparison:
    """Compare an image with its baseline PNG; on failure write the image and the difference.

    With ``EMREG_REGENERATE_BASELINES=1`` the baseline is (re)written from ``actual_rgb``
    instead. A missing baseline is an ``AssertionError`` that says how to create it. On a
    failed comparison ``<name>.actual.png`` and ``<name>.diff.png`` are written to
    ``failure_dir`` (default: beside the baseline) and an ``AssertionError`` names them.
    """
    from .images import read_png, write_png

    baseline_path = Path(baseline_path)
    if regenerate_requested():
        write_png(baseline_path, actual_rgb)
        return ImageComparison(0.0, np.zeros_like(actual_rgb))
    if not baseline_path.is_file():
        raise AssertionError(
            f"baseline {baseline_path} is missing; create it on purpose with {REGENERATE_ENV}=1 "
            "(or scripts/regenerate_baselines)"
        )
    result = compare_images(actual_rgb, read_png(baseline_path), threshold)
    if result.error > max_error:
        out = Path(failure_dir) if failure_dir is not None else baseline_path.parent
        stem = baseline_path.stem
        write_png(out / f"{stem}.actual.png", actual_rgb)
        write_png(out / f"{stem}.diff.png", result.difference)
        raise AssertionError(
            f"{baseline_path.name}: image differs from the baseline (error {result.error:.3f} > {max_error}); "
            f"see {out / (stem + '.actual.png')} and {out / (stem + '.diff.png')}; if the change is intended, "
            f"regenerate with {REGENERATE_ENV}=1"
        )
    return result
