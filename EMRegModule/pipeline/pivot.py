"""A tracked tool's tip from a pivot recording (``emreg pivot``, the 3D Slicer module's Pivot button): the tool
sensor's poses read from the recording (:func:`~EMRegModule.io.tool_files.pivot_poses`), then the pivot calibration
(:func:`~EMRegModule.core.tool.pivot_calibration`). Positions in mm, in the Reference frame (the Tracker frame when
the recording has no reference sensor)."""

from __future__ import annotations

import os

from ..core.tool import ToolCalibration, pivot_calibration
from ..io.tool_files import pivot_poses
from ..settings import Settings


def pivot_tool(recording: str | os.PathLike[str], settings: Settings, reference_port: int,
               probe_port: int) -> tuple[ToolCalibration, list[str]]:
    """The tool calibration (``TipToProbe``, mm) solved from the pivot recording at ``recording`` (a tracking CSV or
    a sequence file; ``settings``: the case's, for its sensor transform names), and the recording's warnings.
    Raises :class:`~EMRegModule.errors.NoSafeAnswerError` when the recording cannot give a safe tip."""
    poses, frame, name, warnings = pivot_poses(recording, settings, reference_port, probe_port)
    return pivot_calibration(poses, os.fspath(recording), frame, name), warnings
