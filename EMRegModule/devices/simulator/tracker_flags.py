"""What a simulated tracker says about the field at a sensor: its own distortion and volume flags.

The trackers report how far they trust a pose: the trakSTAR appends a METAL byte to each record (0 = no
distortion .. 127, :mod:`EMRegModule.devices.trakstar.protocol`); the Aurora reports each tool's RMS error (mm)
and port status bits (out of volume 0x40, partially out of volume 0x80, :mod:`EMRegModule.devices.aurora.protocol`).
Both simulators (:mod:`EMRegModule.devices.simulator.trakstar`, :mod:`EMRegModule.devices.simulator.aurora`) take
them from the same inputs here:

- a **distortion model**: anything with ``distortion_mm(position_mm) -> float``, the size of the position error
  (mm) the field makes at a sensor (Tracker frame, mm). A physical model (an induced dipole near the frame)
  plugs in unchanged; :class:`UniformDistortion` and :class:`PointDistortion` are the simple ones the command
  line gives (``emreg sim-tracker --distortion MM[@X,Y,Z,R]``);
- a **measurement volume** (Aurora): :class:`MeasurementVolume`, a box with a margin in which a tool is partly
  out (``--volume X0,Y0,Z0,X1,Y1,Z1[:MARGIN]``).

These set the flags only; moving the reported positions is the distortion model's own business.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Protocol

import numpy as np

from ...errors import EMRegError


class DistortionModel(Protocol):
    """A field distortion: the size (mm) of the position error it makes at a point of the Tracker frame (mm)."""

    def distortion_mm(self, position_mm: np.ndarray) -> float: ...


@dataclass(frozen=True)
class UniformDistortion:
    """The same distortion everywhere (mm)."""

    strength_mm: float

    def distortion_mm(self, position_mm: np.ndarray) -> float:
        return float(self.strength_mm)


@dataclass(frozen=True)
class PointDistortion:
    """A metal object at ``centre_mm`` (Tracker frame): ``strength_mm`` at ``radius_mm`` from it, falling off as
    the inverse cube of the distance (an induced dipole's field), capped at 8 times that within half the radius."""

    centre_mm: tuple[float, float, float]
    strength_mm: float
    radius_mm: float

    def distortion_mm(self, position_mm: np.ndarray) -> float:
        distance = float(np.linalg.norm(np.asarray(position_mm, dtype=float) - np.asarray(self.centre_mm)))
        return float(self.strength_mm * (self.radius_mm / max(distance, 0.5 * self.radius_mm)) ** 3)


def parse_distortion(text: str) -> DistortionModel:
    """``MM`` (uniform) or ``MM@X,Y,Z,R`` (:class:`PointDistortion`); :class:`EMRegError` for anything else."""
    strength, _, where = text.partition("@")
    try:
        value = float(strength)
        numbers = [float(v) for v in where.split(",")] if where else []
    except ValueError:
        numbers, value = [0.0], float("nan")
    if not np.isfinite(value) or value < 0 or len(numbers) not in (0, 4) or (numbers and numbers[3] <= 0):
        raise EMRegError(f"--distortion {text!r}: use MM (the same everywhere) or MM@X,Y,Z,R (a metal object at X,Y,Z "
                         "in the tracker's frame, distorting by MM at R mm from it), MM >= 0, R > 0")
    if not numbers:
        return UniformDistortion(value)
    return PointDistortion((numbers[0], numbers[1], numbers[2]), value, numbers[3])


#: METAL units per millimetre of distortion (choice: the watchdog's default limit of 20 is 0.5 mm).
METAL_PER_MM = 40.0


def trakstar_metal(distortion_mm: float, clean: float = 0.0) -> int:
    """The trakSTAR's METAL byte (0..127) for a distortion (mm) at the sensor: the worse of ``clean`` (what the
    recording or scene says) and ``METAL_PER_MM`` per mm."""
    return int(min(max(round(max(clean, METAL_PER_MM * distortion_mm)), 0), 127))


def aurora_error_mm(distortion_mm: float, clean_mm: float) -> float:
    """The Aurora's RMS error (mm) for a distortion (mm) at the tool: its clean fit error plus the distortion
    (choice: the coils' fit residual grows with the field's error)."""
    return float(clean_mm + distortion_mm)


@dataclass(frozen=True)
class MeasurementVolume:
    """The tracker's characterised volume, a box (Tracker frame, mm): inside, ``partly`` out within
    ``margin_mm`` of a face (some of the tool's coils outside), ``out`` beyond it."""

    low_mm: tuple[float, float, float]
    high_mm: tuple[float, float, float]
    margin_mm: float = 10.0

    def state(self, position_mm: np.ndarray) -> str:
        """``in``, ``partly`` or ``out`` for a sensor at ``position_mm``."""
        p = np.asarray(position_mm, dtype=float)
        low, high = np.asarray(self.low_mm), np.asarray(self.high_mm)
        if np.any(p < low) or np.any(p > high):
            return "out"
        if np.any(p < low + self.margin_mm) or np.any(p > high - self.margin_mm):
            return "partly"
        return "in"


def parse_volume(text: str) -> MeasurementVolume:
    """``X0,Y0,Z0,X1,Y1,Z1[:MARGIN]`` (mm) -> :class:`MeasurementVolume`; :class:`EMRegError` otherwise."""
    box, _, margin = text.partition(":")
    try:
        numbers = [float(v) for v in box.split(",")]
        margin_mm = float(margin) if margin else 10.0
    except ValueError:
        numbers, margin_mm = [], 0.0
    if len(numbers) != 6 or not all(np.isfinite(numbers)) or margin_mm < 0 or \
            any(a >= b for a, b in zip(numbers[:3], numbers[3:], strict=True)):
        raise EMRegError(f"--volume {text!r}: use X0,Y0,Z0,X1,Y1,Z1[:MARGIN] (mm, tracker frame, X0 < X1 ...)")
    return MeasurementVolume(tuple(numbers[:3]), tuple(numbers[3:]), margin_mm)  # type: ignore[arg-type]
