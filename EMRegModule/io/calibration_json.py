"""``OUT/frame_calibration.json``: the calibrated pinhole points
(:class:`~EMRegModule.core.calibration.FrameCalibration`, its JSON form ``to_json`` / ``from_json``), written
atomically and read back."""

from __future__ import annotations

import os
from pathlib import Path

from ..core.calibration import FrameCalibration
from .atomic import atomic_write_json, read_json


def write_frame_calibration(result: FrameCalibration, path: str | os.PathLike[str]) -> None:
    """Write ``frame_calibration.json`` atomically (spec layout plus extra keys)."""
    atomic_write_json(Path(path), result.to_json())


def read_frame_calibration(path: str | os.PathLike[str]) -> FrameCalibration:
    """Read a ``frame_calibration.json``; a missing or malformed file is an :class:`EMRegError`."""
    return FrameCalibration.from_json(read_json(path, "frame calibration JSON"), str(path))
