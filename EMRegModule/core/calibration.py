"""Frame calibration: one point per marker pinhole in the Reference frame (paper section 2.3).

Every probe sample is expressed in the Reference frame at its own moment (paper Eq. 3-5,
:func:`EMRegModule.core.tracking.probe_in_reference`), so a frame or transmitter moved between
dwells changes nothing. The dwells (probe held in a pinhole) come from the labels, or are
found automatically when the recording has none (:mod:`EMRegModule.core.dwell`). Each pinhole's
point is the robust average of its dwell samples (wild samples dropped), its direction the
robust mean of ``-(probe +X)``: the probe goes in tip first, so its +X points into the hole
and the marker's +Y (out of the hole) is its opposite.

With a tool (``tool``, :mod:`EMRegModule.core.tool`) every sample becomes the tip's position
(``TipToReference = ProbeToReference @ TipToProbe``) and a touch is the *tip* held still: the shaft may swing
(a pivot, as in PLUS's landmark recording) or rest; each point says which (``motion``). A pivoting touch's point is
the tip as placed, before the swing moves it (:func:`EMRegModule.core.tool.placement_samples`). Hand tremor moves a
held tip about 1 mm over a touch of several seconds, so the stillness radius is ``[tool] still_radius_mm``
(1 mm) instead of ``[calibration] still_radius_mm``. A tool lying still (on the table) is a touch too: an
extra point, which the pairing leaves out as it leaves out any point that matches no marker.

Revisits: two dwells at the same pinhole (the same label, or, without labels, averages
closer than ``merge_radius_mm``) are merged into one point (samples pooled); when the
visits disagree by more than ``revisit_tolerance_mm`` the point carries a warning. Labelled visits farther
apart than twice ``merge_radius_mm`` are several pinholes under one label (refused), and so is a labelled
dwell in which the probe moves (:func:`EMRegModule.core.dwell.refuse_moving_labels`).
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass, field, replace
from typing import Any

import numpy as np

from ..errors import EMRegError
from ..names import DEFAULT_PROBE_PORT, DEFAULT_REFERENCE_PORT
from ..settings import CalibrationSettings
from .dwell import Dwell, describe_still_periods, find_dwells, group_by_place, robust_mean, robust_mean_direction
from .probe_axis import ASSUMED_CONVENTION, check_probe_axis, marker_directions
from .tool import ToolCalibration, placement_samples, shaft_swing_deg, solve_tip_from_touches, tip_poses
from .tracking import ProbeInReference, TrackingRecording, invert_rigid_batch, probe_in_reference
from .transforms import mean_rigid

#: A touch of a tool whose shaft swung at least this much (degrees, :func:`EMRegModule.core.tool.shaft_swing_deg`)
#: about the still tip is a pivot; less is a rest (hand tremor of a held tool swings it by a degree or two).
PIVOT_TOUCH_SWING_DEG = 5.0


@dataclass
class CalibrationPoint:
    """One calibrated pinhole, in the Reference frame.

    ``position`` (3,) mm: the probe sensor's centre in the pinhole; ``direction`` (3,) unit:
    the marker's +Y (out of the hole), NaN when unknown; ``samples``: samples averaged;
    ``std_mm``: RMS 3D distance of those samples from ``position``; ``visits``: dwells merged;
    ``tracker_to_reference`` (4, 4): the transmitter's mean pose in the Reference frame over those samples
    (where the field came from: :mod:`EMRegModule.core.distortion`; None in older files).
    """

    label: str
    position: np.ndarray
    direction: np.ndarray
    samples: int
    std_mm: float
    visits: int = 1
    direction_std_deg: float = float("nan")
    start_s: float = float("nan")
    end_s: float = float("nan")
    warning: str = ""
    #: with a tool: ``pivot`` (the shaft swung about the still tip) or ``rest`` (the whole tool still); else empty
    motion: str = ""
    tracker_to_reference: np.ndarray | None = None

    def to_json(self) -> dict[str, Any]:
        out: dict[str, Any] = {
            "label": self.label, "position": [float(v) for v in self.position],
            "direction": [float(v) for v in self.direction] if np.all(np.isfinite(self.direction)) else None,
            "samples": int(self.samples),
            "std_mm": round(float(self.std_mm), 4), "visits": int(self.visits),
            "direction_std_deg": round(float(self.direction_std_deg), 3),
            "start_s": float(self.start_s), "end_s": float(self.end_s),
        }
        if self.warning:
            out["warning"] = self.warning
        if self.motion:
            out["motion"] = self.motion
        if self.tracker_to_reference is not None:
            out["TrackerToReference"] = np.asarray(self.tracker_to_reference, dtype=float).tolist()
        return out


@dataclass
class FrameCalibration:
    """The calibrated pinholes of a fiducial frame (Reference frame, mm) and how they were found."""

    points: list[CalibrationPoint]
    reference_sensor: int = DEFAULT_REFERENCE_PORT
    probe_sensor: int = DEFAULT_PROBE_PORT
    labelled: bool = True
    source: str = ""
    warnings: list[str] = field(default_factory=list)
    #: ``[sensors] probe_axis`` the calibration was made with, and the convention of ``direction``
    #: (``+x_in`` / ``+x_out``; ``none`` when no point has a direction).
    probe_axis: str = "auto"
    direction_convention: str = "+x_in"
    provenance: dict[str, Any] | None = None  # what it was made from (``EMRegModule.io.provenance``)
    #: the tool whose tip made the points (``{"TipToProbe": 4x4, "source": ..}``); None: the pinhole probe
    tool: dict[str, Any] | None = None
    #: the tool solved from this recording's touches (``--tool auto``), else None (not in the JSON: see ``tool``)
    solved_tool: ToolCalibration | None = field(default=None, repr=False)

    @property
    def labels(self) -> list[str]:
        return [p.label for p in self.points]

    @property
    def positions(self) -> np.ndarray:
        """Pinhole points (N, 3) in the Reference frame, mm."""
        return np.array([p.position for p in self.points], dtype=float).reshape(-1, 3)

    @property
    def directions(self) -> np.ndarray:
        """Unit marker +Y directions (N, 3) in the Reference frame (NaN rows when unknown)."""
        return np.array([p.direction for p in self.points], dtype=float).reshape(-1, 3)

    def to_json(self) -> dict[str, Any]:
        """The ``frame_calibration.json`` document (spec keys plus a few extra)."""
        document = {
            "reference_sensor": int(self.reference_sensor), "probe_sensor": int(self.probe_sensor),
            "points": [p.to_json() for p in self.points],
            "labelled": bool(self.labelled), "source": self.source, "warnings": list(self.warnings),
            "probe_axis": self.probe_axis_json(),
        }
        if self.provenance is not None:
            document["provenance"] = self.provenance
        if self.tool is not None:
            document["tool"] = self.tool
        return document

    def probe_axis_json(self) -> dict[str, Any]:
        """How the directions were made (the registration decides the sign under ``auto``)."""
        with_direction = int(np.count_nonzero(np.all(np.isfinite(self.directions), axis=1)))
        if with_direction == 0:
            note = "no probe orientation used (position-only probe rows or probe_axis = none)"
        elif self.probe_axis == "auto":
            note = ("directions stored assuming +X points into the pinhole; the registration checks the sign "
                    "against the CT's marker axes")
        else:
            note = f"directions stored for probe_axis = {self.probe_axis}"
        return {"setting": self.probe_axis, "direction_convention": self.direction_convention,
                "points_with_direction": with_direction, "note": note}

    @classmethod
    def from_json(cls, document: Mapping[str, Any], source: str = "frame calibration") -> FrameCalibration:
        """Parse a ``frame_calibration.json`` document; :class:`EMRegError` naming ``source`` if malformed."""
        try:
            points = []
            for i, item in enumerate(document["points"]):
                position = np.asarray(item["position"], dtype=float)
                direction = np.asarray(item.get("direction") or [np.nan] * 3, dtype=float)
                if position.shape != (3,) or not np.all(np.isfinite(position)):
                    raise EMRegError(f"{source}: point {i + 1} has no valid 3D position")
                if direction.shape != (3,):
                    raise EMRegError(f"{source}: point {i + 1} has a malformed direction")
                counts = (int(item.get("samples", 0)), int(item.get("visits", 1)))
                if counts[0] < 0 or counts[1] < 1 or float(item.get("std_mm", 0.0)) < 0:
                    raise EMRegError(f"{source}: point {i + 1} has a negative samples or std_mm, or no visit: a "
                                     "damaged or hand-edited file")
                norm = np.linalg.norm(direction)
                if np.isfinite(norm) and norm > 0:
                    direction = direction / norm
                else:
                    direction = np.full(3, np.nan)
                points.append(CalibrationPoint(
                    label=str(item.get("label") or f"P{i + 1:02d}"), position=position, direction=direction,
                    samples=int(item.get("samples", 0)), std_mm=float(item.get("std_mm", np.nan)),
                    visits=int(item.get("visits", 1)),
                    direction_std_deg=_float(item.get("direction_std_deg")),
                    start_s=_float(item.get("start_s")), end_s=_float(item.get("end_s")),
                    warning=str(item.get("warning", "")), motion=str(item.get("motion", "")),
                    tracker_to_reference=_pose_or_none(item.get("TrackerToReference"), f"{source}: point {i + 1}"),
                ))
            labels = [p.label for p in points]
            if len(set(labels)) != len(labels):
                raise EMRegError(f"{source}: point labels must be unique")
            axis = document.get("probe_axis") or {}
            setting = check_probe_axis(axis.get("setting", "auto"), source)
            convention = str(axis.get("direction_convention", "+x_in"))
            if convention not in ("+x_in", "+x_out", "none"):
                raise EMRegError(f"{source}: probe_axis direction_convention must be +x_in, +x_out or none")
            return cls(points, int(document.get("reference_sensor", 1)), int(document.get("probe_sensor", 2)),
                       bool(document.get("labelled", True)), str(document.get("source", "")),
                       [str(w) for w in document.get("warnings", [])], setting, convention,
                       _dict_or_none(document.get("provenance")), _dict_or_none(document.get("tool")))
        except (KeyError, TypeError, ValueError) as exc:
            raise EMRegError(f"{source}: not a frame calibration file ({exc!s:.100})") from None


def _pose_or_none(value: Any, source: str) -> np.ndarray | None:
    """A stored 4 x 4 pose (None when absent); a malformed one is an :class:`EMRegError`."""
    if value is None:
        return None
    pose = np.asarray(value, dtype=float)
    if pose.shape != (4, 4) or not np.all(np.isfinite(pose)):
        raise EMRegError(f"{source}: TrackerToReference must be a 4x4 matrix of finite numbers")
    return pose


def _dict_or_none(value: Any) -> dict[str, Any] | None:
    return value if isinstance(value, dict) else None


def _float(value: Any) -> float:
    return float("nan") if value is None else float(value)


def calibrate_frame(
    recording: TrackingRecording,
    reference_sensor: int = DEFAULT_REFERENCE_PORT,
    probe_sensor: int = DEFAULT_PROBE_PORT,
    settings: CalibrationSettings | None = None,
    probe_axis: str = "auto",
    tool: ToolCalibration | str | None = None,
    tool_still_radius_mm: float = 1.0,
) -> FrameCalibration:
    """One point per marker pinhole, in the Reference frame (mm), from a calibration recording.

    ``probe_axis``: ``[sensors] probe_axis`` (see :mod:`EMRegModule.core.probe_axis`); probe rows
    without angles (position only) give points without a direction.

    ``settings``: the ``[calibration]`` table (dwell keys and ``revisit_tolerance_mm``). Unlabelled
    dwells are named ``P01, P02, ...`` in time order of their first visit. Raises
    :class:`EMRegError` when no dwell is found.

    ``tool``: a tracked tool (:class:`~EMRegModule.core.tool.ToolCalibration`): the points are its tip's positions,
    a touch is the tip held still within ``tool_still_radius_mm`` (module docstring), and no direction is kept
    (a pivoting shaft has none). ``tool="auto"``: the tip is solved from the pivoting touches first
    (:func:`EMRegModule.core.tool.solve_tip_from_touches`); the result's ``solved_tool`` holds it.
    """
    dwell_settings = settings or CalibrationSettings()
    probe_axis = check_probe_axis(probe_axis)
    convention = ASSUMED_CONVENTION if probe_axis == "auto" else probe_axis
    samples = probe_in_reference(recording, reference_sensor, probe_sensor)
    position = samples.position_mm
    out_of_hole = marker_directions(samples.direction, convention)
    if tool == "auto":
        tool = _solve_tool(samples, dwell_settings, tool_still_radius_mm, recording.source)
    if tool is not None:
        position = tip_poses(samples.probe_to_reference, tool.tip_to_probe)[:, :3, 3]
        out_of_hole = np.full_like(position, np.nan)
        probe_axis, convention = "none", "none"
        dwell_settings = replace(dwell_settings, still_radius_mm=tool_still_radius_mm)
    dwells = _find_calibration_dwells(samples, position, dwell_settings, recording.source)
    labelled = bool(dwells[0].label)
    inlier_index, centres = _dwell_centres(dwells, samples, position, tool)
    group, order = _group_dwells(dwells, centres, labelled, dwell_settings.merge_radius_mm)
    points = [_pinhole_point(label, np.nonzero(group == g)[0], dwells, inlier_index, centres, samples, position,
                             out_of_hole, tool, labelled, dwell_settings, recording.source)
              for g, label in enumerate(order)]
    warnings = list(recording.warnings)  # time resets / gaps found on reading (kept, as separate segments)
    warnings += [f"{p.label}: {p.warning}" for p in points if p.warning]
    warnings += _close_point_warnings(points, 2.0 * dwell_settings.merge_radius_mm)
    has_direction = any(np.all(np.isfinite(p.direction)) for p in points)
    result = FrameCalibration(points, int(reference_sensor), int(probe_sensor), labelled, recording.source, warnings,
                              probe_axis, convention if has_direction else "none", tool=_tool_json(tool))
    result.solved_tool = tool if tool is not None and tool.method.startswith("auto") else None
    return result


def _solve_tool(samples: ProbeInReference, dwell_settings: CalibrationSettings, still_radius_mm: float,
                source: str) -> ToolCalibration:
    """``--tool auto``: the tip solved from the recording's pivoting touches (tip still within ``still_radius_mm``)."""
    touch_settings = replace(dwell_settings, still_radius_mm=still_radius_mm)

    def find_touches(tip_mm: np.ndarray) -> list[np.ndarray]:
        return [d.indices for d in find_dwells(samples.time_s, tip_mm, samples.label, samples.quality,
                                               touch_settings)]

    return solve_tip_from_touches(samples.probe_to_reference, samples.time_s, find_touches, source)


def _find_calibration_dwells(samples: ProbeInReference, position: np.ndarray, dwell_settings: CalibrationSettings,
                             source: str) -> list[Dwell]:
    """The dwells of the probe (or tool tip) positions (Reference frame, mm); refuses a recording with none."""
    dwells = find_dwells(samples.time_s, position, samples.label, samples.quality, dwell_settings, source=source)
    if not dwells:
        raise EMRegError(
            f"{source}: no dwell found (the probe never stayed still in a pinhole for "
            f"{dwell_settings.min_duration_s:g} s; check the sensor ports): "
            + describe_still_periods(samples.time_s, position, samples.quality, dwell_settings, section="calibration")
        )
    return dwells


def _dwell_centres(dwells: list[Dwell], samples: ProbeInReference, position: np.ndarray,
                   tool: ToolCalibration | None) -> tuple[list[np.ndarray], np.ndarray]:
    """Each dwell's inlier sample indices and robust centre (Reference mm); a tool's touch keeps the samples of
    the tip as placed (:func:`EMRegModule.core.tool.placement_samples`)."""
    inlier_index = []
    centres = []
    for dwell in dwells:
        indices = dwell.indices
        if tool is not None:  # a pivoting touch's point is the tip as placed (module docstring)
            indices = indices[placement_samples(samples.probe_to_reference[indices, :3, :3], tool.tip_mm)]
        average = robust_mean(position[indices])
        inlier_index.append(indices[average.inliers])
        centres.append(average.mean)
    return inlier_index, np.asarray(centres)


def _group_dwells(dwells: list[Dwell], centres: np.ndarray, labelled: bool,
                  merge_radius_mm: float) -> tuple[np.ndarray, list[str]]:
    """The pinhole (group index) of each dwell and the pinholes' labels: by label, else by place."""
    if labelled:
        names = [d.label for d in dwells]
        order = list(dict.fromkeys(names))
        return np.array([order.index(n) for n in names]), order
    group = group_by_place(centres, merge_radius_mm)
    return group, [f"P{g + 1:02d}" for g in range(int(group.max()) + 1)]


def _pinhole_point(label: str, members: np.ndarray, dwells: list[Dwell], inlier_index: list[np.ndarray],
                   centres: np.ndarray, samples: ProbeInReference, position: np.ndarray, out_of_hole: np.ndarray,
                   tool: ToolCalibration | None, labelled: bool, dwell_settings: CalibrationSettings,
                   source: str) -> CalibrationPoint:
    """One pinhole's point from the pooled inliers of its visits (``members``: dwell indices)."""
    pooled = np.concatenate([inlier_index[m] for m in members])
    average = robust_mean(position[pooled])
    used = pooled[average.inliers]
    if np.all(np.isfinite(out_of_hole[used])):
        direction, direction_std = robust_mean_direction(out_of_hole[used])
    else:  # position-only probe rows (or no convention): no direction
        direction, direction_std = np.full(3, np.nan), float("nan")
    warning = ""
    if len(members) > 1:
        visit_centres = centres[members]
        spread = float(np.max(np.linalg.norm(visit_centres[:, None] - visit_centres[None], axis=2)))
        if labelled and spread > 2.0 * dwell_settings.merge_radius_mm:
            raise EMRegError(
                f"{source}: the {len(members)} dwells labelled {label!r} lie up to {spread:.1f} mm "
                f"apart, farther than visits of one pinhole can (2 x [calibration] merge_radius_mm = "
                f"{2.0 * dwell_settings.merge_radius_mm:g} mm): one label given to several pinholes; "
                "check the labels")
        if spread > dwell_settings.revisit_tolerance_mm:
            warning = (f"{len(members)} visits disagree by up to {spread:.2f} mm "
                       f"(more than {dwell_settings.revisit_tolerance_mm:g} mm): check that the probe was fully "
                       "inserted")
    motion = ""
    if tool is not None:
        touched = np.concatenate([dwells[m].indices for m in members])
        swing = shaft_swing_deg(samples.probe_to_reference[touched, :3, :3], tool.tip_mm)
        motion = "pivot" if swing >= PIVOT_TOUCH_SWING_DEG else "rest"
    return CalibrationPoint(
        label=label, position=average.mean, direction=direction, samples=len(used), std_mm=average.std_mm,
        visits=len(members), direction_std_deg=direction_std,
        start_s=float(min(dwells[m].start_s for m in members)),
        end_s=float(max(dwells[m].end_s for m in members)), warning=warning, motion=motion,
        tracker_to_reference=mean_rigid(invert_rigid_batch(samples.reference_to_tracker[used])),
    )


def _tool_json(tool: ToolCalibration | None) -> dict[str, Any] | None:
    """``frame_calibration.json`` ``"tool"``: the tracked tool the points are its tip's (None: the pinhole probe)."""
    if tool is None:
        return None
    return {"TipToProbe": tool.tip_to_probe.tolist(), "tip_mm": tool.tip_mm.tolist(), "source": tool.source,
            "name": tool.name, "method": tool.method, "rms_mm": tool.rms_mm,
            "tip_std_mm": None if tool.tip_std_mm is None else tool.tip_std_mm.tolist()}


def _close_point_warnings(points: list[CalibrationPoint], radius_mm: float) -> list[str]:
    """Two points closer than any two pinholes can be: one pinhole under two labels, or visited
    twice with the probe at different depths."""
    warnings = []
    positions = np.array([p.position for p in points]).reshape(-1, 3)
    for i in range(len(points)):
        for k in range(i + 1, len(points)):
            distance = float(np.linalg.norm(positions[i] - positions[k]))
            if distance < radius_mm:
                warnings.append(f"{points[i].label} and {points[k].label} are only {distance:.2f} mm apart: "
                                "the same pinhole twice (another label, or the probe not fully inserted)?")
    return warnings


