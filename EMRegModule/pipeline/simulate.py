"""A simulated case folder with its ground truth (``truth.json``), for ``emreg simulate`` and ``emreg demo``
(:func:`EMRegModule.simulation.case.simulate_case` makes it)."""

from __future__ import annotations

from pathlib import Path
from typing import Any

from ..progress import Progress
from ..simulation.case import simulate_case


def simulate(out: Path, seed: int = 0, difficulty: str = "standard", spacing_mm: float | None = None,
             progress: Progress | None = None, probe_axis: str | None = None,
             tool_tip_mm: tuple[float, float, float] | None = None, distortion_mm: float = 0.0,
             distortion_during: str = "both", distortion_onset_s: float | None = None) -> dict[str, Any]:
    """Write a simulated case into ``out`` and return its ground truth: the probe convention of its recordings
    (``+x_in``, ``+x_out``, ``none``; None: the default), a stylus whose tip is at ``tool_tip_mm`` in its sensor's
    frame (None: the pinhole probe), and a metal rod leaving ``distortion_mm`` RMS non-rigid error at the pinholes
    during ``distortion_during`` (calibration, navigation or both), from ``distortion_onset_s`` s on (None: from the
    start)."""
    options: dict[str, Any] = {"probe_axis": probe_axis} if probe_axis else {}
    if tool_tip_mm:
        options["tool_tip_mm"] = tuple(tool_tip_mm)
    if distortion_mm:
        options.update(distortion_mm=distortion_mm, distortion_during=distortion_during,
                       distortion_onset_s=distortion_onset_s)
    return simulate_case(Path(out), seed=seed, difficulty=difficulty, spacing_mm=spacing_mm, progress=progress,
                         **options)
