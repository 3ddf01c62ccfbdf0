"""Guidance to a planned target: the numbers a surgeon steers by, from the tip's pose and the plan. Pure: arrays
in, arrays out, no file I/O (the plan file is read by :mod:`EMRegModule.core.plan`).

Frames and units: everything is in image space (the CT's LPS physical space, mm) and degrees. A plan is a target
``target_mm`` and, optionally, an entry ``entry_mm``; with an entry the planned line runs Entry -> Target with unit
direction ``u``. For each navigated sample (the tip of ``TipToImage``, or the probe sensor without a tool):

- ``target_distance_mm``: ``|target - tip|``;
- ``lateral_mm``: the tip's distance from the planned (infinite) line through Entry and Target;
- ``angle_deg``: the tool's axis against ``u`` (0: along the plan, 180: backwards);
- ``to_go_mm``: ``(target - tip) . u``, the depth left along the plan, negative once the tip is past the target.

Without an entry (a target alone) only ``target_distance_mm`` is defined; the other three are NaN (written empty).
The tool's axis is its shaft: the direction from the sensor's origin to the tip (``TipToProbe``'s translation),
fixed in the tip frame (:func:`shaft_in_tip`); a tool whose tip is at its sensor (closer than
:data:`MIN_SHAFT_MM`), and the pinhole probe without a tool file, have no axis (NaN angle).

The predicted error at the target (:func:`predicted_at_target`) adds, in quadrature, to the error model's end-to-end
RMS TRE there (:mod:`EMRegModule.core.error_model`: registration, tracking of the sensor's position, reference sensor,
placement) two terms of the tool: its own calibration error (a pivot's RMS, PLUS's ``Error=``) and its lever arm,
the sensor's orientation error carried to the tip (a tip ``d`` mm from the sensor moves ``d * theta`` for a rotation
error ``theta`` about either axis across the shaft: ``2 (d sigma)^2``, :data:`TOOL_ROTATION_SIGMA_DEG` per axis);
and gives the 95 % radius of an isotropic 3D Gaussian error with that RMS (:data:`RADIUS_95_PER_RMS`).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np

#: A tool's tip closer than this (mm) to its sensor's origin gives no shaft direction (no angle).
MIN_SHAFT_MM = 1.0

#: A plan whose Entry and Target are closer than this (mm) has no direction: refused.
MIN_PLAN_LENGTH_MM = 1.0

#: The 95 % radius of an isotropic 3D Gaussian error per its RMS: sqrt(chi2_3(0.95) / 3) = sqrt(7.8147 / 3).
RADIUS_95_PER_RMS = float(np.sqrt(7.814727903251178 / 3.0))

#: The tool sensor's orientation error per axis (degrees, one placement): a prior (the calibration of the pinhole
#: probe measures positions only). 0.25 degree: the case simulator's per-dwell error, half the trakSTAR's specified
#: 0.5 degree RMS static accuracy. On the simulated needle (118 mm, an exact tool file) it brings the prediction at
#: the targets from 0.43 to 0.85 mm RMS, against 0.94 mm measured over the 6 dwells (test_guidance: without it the
#: prediction was half the measured error).
TOOL_ROTATION_SIGMA_DEG = 0.25


@dataclass(frozen=True)
class Plan:
    """A planned target and, optionally, the entry of its trajectory (image space, LPS mm); ``source`` names the
    file it came from, ``coordinate_system`` what that file declared (``LPS`` / ``RAS``; the points are LPS)."""

    target_mm: np.ndarray
    entry_mm: np.ndarray | None = None
    source: str = ""
    coordinate_system: str = "LPS"

    @property
    def has_line(self) -> bool:
        """Whether the plan has a trajectory (an entry), not just a target."""
        return self.entry_mm is not None

    @property
    def direction(self) -> np.ndarray | None:
        """``u``: the unit vector Entry -> Target (3,), None for a target alone."""
        if self.entry_mm is None:
            return None
        line = np.asarray(self.target_mm, dtype=float) - np.asarray(self.entry_mm, dtype=float)
        return line / np.linalg.norm(line)

    @property
    def length_mm(self) -> float | None:
        """The planned path's length Entry -> Target (mm), None for a target alone."""
        if self.entry_mm is None:
            return None
        return float(np.linalg.norm(np.asarray(self.target_mm, dtype=float) - np.asarray(self.entry_mm, dtype=float)))

    def to_json(self) -> dict:
        """``{"target_mm": [..], "entry_mm": [..] | null, "length_mm": .., "coordinate_system": "LPS"}``."""
        def listed(v: np.ndarray | None) -> list[float] | None:
            return None if v is None else [round(float(x), 4) for x in v]

        length = self.length_mm
        return {"source": self.source, "coordinate_system": "LPS", "declared_coordinate_system": self.coordinate_system,
                "target_mm": listed(self.target_mm), "entry_mm": listed(self.entry_mm),
                "length_mm": None if length is None else round(length, 4)}


@dataclass(frozen=True)
class Guidance:
    """Per-sample guidance numbers (N,) each, NaN where undefined (module docstring): mm and degrees."""

    target_distance_mm: np.ndarray
    lateral_mm: np.ndarray
    angle_deg: np.ndarray
    to_go_mm: np.ndarray

    def __len__(self) -> int:
        return len(self.target_distance_mm)

    def closest(self, valid: np.ndarray | None = None) -> int | None:
        """Index of the sample closest to the target (among ``valid`` (N,) bool when given), None if there is none."""
        distance = np.where(np.ones(len(self), bool) if valid is None else valid, self.target_distance_mm, np.inf)
        if len(distance) == 0 or not np.isfinite(distance).any():
            return None
        return int(np.argmin(distance))


def shaft_in_tip(tip_to_probe: np.ndarray | None) -> np.ndarray | None:
    """A tool's axis (the unit direction from its sensor's origin to its tip) in the tip frame (3,), or None
    without a tool or with a tip closer than :data:`MIN_SHAFT_MM` to the sensor. ``tip_to_probe``: 4x4, mm."""
    if tip_to_probe is None:
        return None
    tip_to_probe = np.asarray(tip_to_probe, dtype=float)
    tip_mm = tip_to_probe[:3, 3]
    length = float(np.linalg.norm(tip_mm))
    if length < MIN_SHAFT_MM:
        return None
    return tip_to_probe[:3, :3].T @ (tip_mm / length)


def guidance(tip_to_image: np.ndarray, plan: Plan, shaft_tip: np.ndarray | None = None) -> Guidance:
    """The guidance numbers of tip poses ``tip_to_image`` ((N, 4, 4) or (4, 4), image LPS mm) against ``plan``.

    ``shaft_tip``: the tool's axis in the tip frame (:func:`shaft_in_tip`), None: no axis (NaN angle)."""
    poses = np.asarray(tip_to_image, dtype=float).reshape(-1, 4, 4)
    tip = poses[:, :3, 3]
    target = np.asarray(plan.target_mm, dtype=float)
    to_target = target - tip
    distance = np.linalg.norm(to_target, axis=1)
    u = plan.direction
    nan = np.full(len(tip), np.nan)
    if u is None:
        return Guidance(distance, nan, nan.copy(), nan.copy())
    to_go = to_target @ u
    lateral = np.linalg.norm(to_target - to_go[:, None] * u, axis=1)
    if shaft_tip is None:
        angle = nan
    else:
        axis = poses[:, :3, :3] @ np.asarray(shaft_tip, dtype=float)
        cosine = np.clip(axis @ u / np.linalg.norm(axis, axis=1), -1.0, 1.0)
        angle = np.degrees(np.arccos(cosine))
    return Guidance(distance, lateral, angle, to_go)


@dataclass(frozen=True)
class TargetPrediction:
    """The predicted error at the plan's target (mm): the error model's end-to-end RMS TRE there
    (``registration_rms_mm``), the tool's calibration error (``tool_rms_mm``, 0 when its file states none), the
    sensor's orientation error over the tool's lever arm (``lever_rms_mm``), their sum in quadrature (``rms_mm``)
    and its 95 % radius (``radius_95_mm``)."""

    rms_mm: float
    radius_95_mm: float
    registration_rms_mm: float
    tool_rms_mm: float
    lever_rms_mm: float = 0.0

    def to_json(self) -> dict:
        def number(value: float) -> float | None:
            return round(float(value), 4) if np.isfinite(value) else None

        return {"rms_mm": number(self.rms_mm), "radius_95_mm": number(self.radius_95_mm),
                "registration_rms_mm": number(self.registration_rms_mm), "tool_rms_mm": number(self.tool_rms_mm),
                "lever_rms_mm": number(self.lever_rms_mm),
                "model": "end-to-end RMS TRE of the error model at the target (+) the tool's calibration RMS (+) the "
                         f"sensor's orientation error ({TOOL_ROTATION_SIGMA_DEG:g} degree per axis) over the tip's "
                         "lever arm, in quadrature; 95 % radius of an isotropic 3D Gaussian with that RMS"}

    def summary(self) -> str:
        """``target 0.9 mm predicted (95 %: 1.6 mm)``."""
        return f"target {self.rms_mm:.1f} mm predicted (95 %: {self.radius_95_mm:.1f} mm)"


def predicted_at_target(end_to_end_rms_mm: float, tool_rms_mm: float | None = None,
                        lever_mm: float = 0.0) -> TargetPrediction:
    """:class:`TargetPrediction` from the error model's RMS TRE at the target (mm), the tool's calibration RMS (mm;
    None: its file states none) and the tip's distance from its sensor (``lever_mm``; 0: the sensor is navigated)."""
    tool = 0.0 if tool_rms_mm is None else float(tool_rms_mm)
    lever = float(np.sqrt(2.0) * float(lever_mm) * np.radians(TOOL_ROTATION_SIGMA_DEG))
    rms = float(np.sqrt(float(end_to_end_rms_mm) ** 2 + tool**2 + lever**2))
    return TargetPrediction(rms, RADIUS_95_PER_RMS * rms, float(end_to_end_rms_mm), tool, lever)



def predicted_at(model: Any, target_mm: np.ndarray, tool: Any = None) -> TargetPrediction:
    """:func:`predicted_at_target` at ``target_mm`` (3,, image LPS mm): ``model`` an
    :class:`~EMRegModule.core.error_model.ErrorModel` (its end-to-end RMS TRE there), ``tool`` a
    :class:`~EMRegModule.core.tool.ToolCalibration` (its ``rms_mm`` and its tip's lever ``|tip_mm|``) or None (the
    sensor
    is navigated)."""
    rms = float(model.budget(np.asarray(target_mm, dtype=float)[None]).rms_mm[0])
    if tool is None:
        return predicted_at_target(rms)
    return predicted_at_target(rms, tool.rms_mm, float(np.linalg.norm(tool.tip_mm)))

@dataclass(frozen=True)
class GuidanceReport:
    """What ``OUT/navigation.json`` says of a navigation with a plan: the plan, the tool, the predicted error at the
    target (None when the registration carries no error model), and the closest approach of the tip to the target
    among the OK samples (image LPS mm, s)."""

    plan: Plan
    prediction: TargetPrediction | None
    closest_index: int | None
    closest_time_s: float | None
    closest_position_mm: np.ndarray | None
    closest: dict | None
    samples: int
    tool: dict | None = None

    def to_json(self) -> dict:
        approach = None
        if self.closest is not None:
            approach = {"time_s": round(float(self.closest_time_s), 4),
                        "position_mm": [round(float(v), 4) for v in self.closest_position_mm],
                        **{key: (None if not np.isfinite(value) else round(float(value), 4))
                           for key, value in self.closest.items()}}
        return {"coordinate_system": "LPS", "plan": self.plan.to_json(), "tool": self.tool,
                "predicted_at_target": None if self.prediction is None else self.prediction.to_json(),
                "closest_approach": approach, "samples": int(self.samples)}

    def summary(self) -> str:
        """One line: the closest approach and the predicted error at the target."""
        parts = []
        if self.closest is not None:
            parts.append(f"closest {self.closest['target_distance_mm']:.2f} mm from the target at "
                         f"{self.closest_time_s:.2f} s")
        else:
            parts.append("no OK sample to approach the target")
        if self.prediction is not None:
            parts.append(self.prediction.summary())
        return "; ".join(parts)


def guidance_report(plan: Plan, numbers: Guidance, time_s: np.ndarray, tip_mm: np.ndarray,
                    ok: np.ndarray | None, prediction: TargetPrediction | None,
                    tool: dict | None = None) -> GuidanceReport:
    """The :class:`GuidanceReport` of a navigation: ``numbers`` per sample, their times ``time_s`` (N,, s), tip
    positions ``tip_mm`` (N, 3, image LPS mm) and ``ok`` (N,) bool (None: all OK)."""
    index = numbers.closest(ok)
    if index is None:
        return GuidanceReport(plan, prediction, None, None, None, None, len(numbers), tool)
    closest = {"target_distance_mm": float(numbers.target_distance_mm[index]),
               "lateral_mm": float(numbers.lateral_mm[index]), "angle_deg": float(numbers.angle_deg[index]),
               "to_go_mm": float(numbers.to_go_mm[index])}
    return GuidanceReport(plan, prediction, index, float(time_s[index]), np.asarray(tip_mm[index], dtype=float),
                          closest, len(numbers), tool)
