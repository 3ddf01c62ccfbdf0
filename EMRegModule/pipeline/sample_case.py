"""The 3D Slicer module's self-test case (``EMRegTest``): a small simulated case (:mod:`EMRegModule.simulation`),
its ground truth, and a registration's error against it (image space, LPS mm)."""

from __future__ import annotations

import os
from pathlib import Path
from typing import Any

import numpy as np

from ..core.transforms import apply_transform, invert_rigid
from ..simulation.case import load_truth, simulate_case

__all__ = ["load_truth", "reference_to_image_error_mm", "simulate_sample_case"]

#: The self-test's frame (mm) and markers: smaller than the standard case's, so that it simulates in seconds.
SAMPLE_FRAME_MM = (220.0, 220.0, 140.0)
SAMPLE_MARKERS = 16


def simulate_sample_case(folder: str | os.PathLike[str], seed: int = 11) -> dict[str, Any]:
    """Write the self-test's standard-difficulty case into ``folder``; returns its ground truth (``truth.json``)."""
    return simulate_case(Path(folder), seed=seed, difficulty="standard", frame_size_mm=SAMPLE_FRAME_MM,
                         n_markers=SAMPLE_MARKERS)


def reference_to_image_error_mm(reference_to_image: np.ndarray, truth: dict[str, Any], points_image: Any) -> float:
    """The largest distance (mm) by which ``reference_to_image`` misplaces image points (LPS mm, N x 3) taken to the
    Reference frame by the case's true ``ReferenceToImage`` (``truth``, as :func:`load_truth` reads it)."""
    points = np.asarray(points_image, dtype=float).reshape(-1, 3)
    true_reference_to_image = np.asarray(truth["ReferenceToImage"], dtype=float)
    moved = apply_transform(reference_to_image, apply_transform(invert_rigid(true_reference_to_image), points))
    return float(np.max(np.linalg.norm(moved - points, axis=1)))
