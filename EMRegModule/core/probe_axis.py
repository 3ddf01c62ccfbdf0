"""Which probe axis lies along the pinhole: optional evidence for pairing, never a reason to fail.

The paper's method pairs from distances alone; the probe's orientation in the pinhole is extra
evidence whose sign depends on how the sensor sits in its holder (and on the sensor model):

- ``+x_in``: the probe sensor's +X points into the pinhole (tip first): marker +Y = -X;
- ``+x_out``: +X points out of the pinhole: marker +Y = +X;
- ``none``: no usable direction (a recording without probe angles, or +X not along the hole).

``[sensors] probe_axis = "auto" | "+x_in" | "+x_out" | "none"`` (default ``auto``). The frame
calibration stores each pinhole's direction under the convention it was made with; the
registration (:func:`pair_with_probe_axis`) decides against the CT's marker axes:

- ``auto``: pairing with the directions known up to a common sign (the pairwise angles are
  sign-invariant; a mapped direction may lie along or against the marker axis), then the sign
  read off the paired points; when the directions do not agree with the marker axes (or the
  direction-aided pairing finds nothing), the paper's distance-only pairing decides alone;
- a forced sign: pairing with signed directions; when that finds no safe pairing, or fewer pairs
  than the distances alone (a wrong sign can fit the few markers of one face, mirrored), the
  distance-only pairing is the fallback (with a warning saying what the data show);
- ``none``: distance-only pairing.

A wrong sign therefore never turns a good case into a refusal; a layout that distances cannot
tell apart is refused by the distance-only pairing as before.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

import numpy as np

from ..errors import EMRegError, NoSafeAnswerError
from .pairing import PairingResult, PairingSettings, pair_markers

PROBE_AXIS_CHOICES = ("auto", "+x_in", "+x_out", "none")
DEFAULT_PROBE_AXIS = "auto"
#: The convention assumed for stored directions when the calibration could not know it.
ASSUMED_CONVENTION = "+x_in"


def check_probe_axis(value: Any, source: str = "case.toml [sensors]") -> str:
    """A valid ``probe_axis`` setting (``auto``, ``+x_in``, ``+x_out``, ``none``) or an :class:`EMRegError`."""
    if value is None:
        return DEFAULT_PROBE_AXIS
    text = str(value).strip().lower().replace(" ", "")
    aliases = {"x_in": "+x_in", "x_out": "+x_out", "in": "+x_in", "out": "+x_out"}
    text = aliases.get(text, text)
    if not isinstance(value, str) or text not in PROBE_AXIS_CHOICES:
        raise EMRegError(f"{source}: probe_axis must be one of {', '.join(repr(c) for c in PROBE_AXIS_CHOICES)}, "
                         f"got {value!r}")
    return text


def marker_directions(probe_x: np.ndarray, convention: str) -> np.ndarray:
    """Marker +Y directions (N, 3) from the probe's +X axes (N, 3) under a convention
    (``+x_in``: -X; ``+x_out``: +X; ``none``: NaN)."""
    probe_x = np.asarray(probe_x, dtype=float).reshape(-1, 3)
    if convention == "+x_in":
        return -probe_x
    if convention == "+x_out":
        return probe_x.copy()
    return np.full_like(probe_x, np.nan)


def _other(convention: str) -> str:
    return "+x_out" if convention == "+x_in" else "+x_in"


@dataclass
class ProbeAxisReport:
    """What the registration found about the probe's axis (``registration.json`` ``probe_axis``).

    ``setting``: what was asked; ``detected``: ``+x_in``, ``+x_out`` or ``none``;
    ``pairing``: ``directions`` (signed), ``directions up to sign`` or ``distances only``;
    ``median_angle_deg``: median angle between the paired probe axes and the marker axes
    (the better of along / against); ``agreeing``: paired points whose direction agrees with
    the detected sign; ``note``: one sentence for the report.
    """

    setting: str
    detected: str
    pairing: str
    median_angle_deg: float = float("nan")
    agreeing: int = 0
    paired: int = 0
    note: str = ""
    warnings: list[str] = field(default_factory=list)

    def to_json(self) -> dict[str, Any]:
        return {"setting": self.setting, "detected": self.detected, "pairing": self.pairing,
                "median_angle_deg": None if not np.isfinite(self.median_angle_deg)
                else round(float(self.median_angle_deg), 2),
                "agreeing_points": int(self.agreeing), "paired_points": int(self.paired), "note": self.note}


def _signed_cosines(result: PairingResult, directions: np.ndarray, axes: np.ndarray) -> np.ndarray:
    """Cosine between each paired calibration direction mapped into the image and its marker axis."""
    rotation = result.reference_to_image[:3, :3]
    return np.array([float((rotation @ directions[i]) @ axes[j]) for j, i in result.pairs])


def _verdict(cosines: np.ndarray, convention: str, cos_limit: float) -> tuple[str, int, float]:
    """(detected convention or 'none', points agreeing, median angle in degrees) from the cosines
    of directions stored under ``convention``."""
    finite = cosines[np.isfinite(cosines)]
    if len(finite) == 0:
        return "none", 0, float("nan")
    along = int(np.count_nonzero(finite >= cos_limit))
    against = int(np.count_nonzero(finite <= -cos_limit))
    sign = 1.0 if along >= against else -1.0
    agreeing = max(along, against)
    median_angle = float(np.degrees(np.median(np.arccos(np.clip(sign * finite, -1.0, 1.0)))))
    # The directions are usable when nearly every paired point agrees (one stray dwell allowed per ten).
    if agreeing >= 3 and agreeing >= len(finite) - max(1, len(finite) // 10):
        return (convention if sign > 0 else _other(convention)), agreeing, median_angle
    return "none", agreeing, median_angle


def pair_with_probe_axis(
    origins_image: np.ndarray,
    axes_image: np.ndarray,
    points_reference: np.ndarray,
    directions_reference: np.ndarray | None,
    l_range_mm: tuple[float, float],
    settings: PairingSettings,
    setting: str = DEFAULT_PROBE_AXIS,
    stored_convention: str = ASSUMED_CONVENTION,
) -> tuple[PairingResult, ProbeAxisReport]:
    """Pair image markers with calibration points using the probe directions as far as they help.

    ``directions_reference`` (N, 3): marker +Y per calibration point (Reference frame) as the
    calibration stored them under ``stored_convention`` (NaN rows: unknown). ``setting``: the
    ``[sensors] probe_axis`` value. Raises :class:`NoSafeAnswerError` only when the
    distance-only pairing (the paper's CSP) refuses too.
    """
    setting = check_probe_axis(setting)
    points, directions = _points_and_directions(points_reference, directions_reference)
    present = np.all(np.isfinite(directions), axis=1)
    has_directions = bool(np.count_nonzero(present) >= max(3, len(points) // 2))
    cos_limit = float(np.cos(np.radians(min(settings.angle_tolerance_deg, 45.0))))
    axes = np.asarray(axes_image, dtype=float)

    def distance_only(reason: str, extra_warning: str = "") -> tuple[PairingResult, ProbeAxisReport]:
        result = pair_markers(origins_image, axes_image, points, None, l_range_mm, settings)
        detected, agreeing, angle = "none", 0, float("nan")
        if has_directions:
            detected, agreeing, angle = _verdict(_signed_cosines(result, directions, axes), stored_convention,
                                                 cos_limit)
        report = ProbeAxisReport(setting, detected, "distances only", angle, agreeing, result.support,
                                 note=reason)
        if extra_warning:
            report.warnings.append(extra_warning)
        return result, report

    if setting == "none":
        return distance_only("probe_axis = none: paired from distances only")
    if not has_directions:
        return distance_only("the calibration has no probe orientation (position-only probe rows): "
                             "paired from distances only")
    if setting == "auto":
        try:
            result = pair_markers(origins_image, axes_image, points, directions, l_range_mm, settings,
                                  unsigned_directions=True)
        except NoSafeAnswerError as exc:
            return distance_only(f"the probe directions did not give a safe pairing ({_short(exc)}): "
                                 "paired from distances only")
        detected, agreeing, angle = _verdict(_signed_cosines(result, directions, axes), stored_convention, cos_limit)
        if detected == "none":
            return distance_only(f"the probe's +X axis is not consistently along the pinholes ({agreeing} of "
                                 f"{result.support} paired points agree): paired from distances only")
        where = "into" if detected == "+x_in" else "out of"
        return result, ProbeAxisReport(
            setting, detected, "directions up to sign", angle, agreeing, result.support,
            note=f"detected: the probe's +X points {where} the pinhole ({agreeing} of {result.support} paired "
                 f"points, median angle {angle:.1f} deg)")
    # a forced sign
    def contradicted(reason: str) -> tuple[PairingResult, ProbeAxisReport]:
        result, report = distance_only(reason)
        if report.detected not in ("none", setting):
            report.warnings.append(f"probe_axis = {setting} is set, but the data show the probe's +X pointing "
                                   f"{'into' if report.detected == '+x_in' else 'out of'} the pinhole "
                                   f"(probe_axis = {report.detected}); paired from distances only")
        else:
            report.warnings.append(f"probe_axis = {setting}: the probe directions do not match the marker axes; "
                                   "paired from distances only")
        return result, report

    signed = directions if setting == stored_convention else -directions
    try:
        result = pair_markers(origins_image, axes_image, points, signed, l_range_mm, settings)
    except NoSafeAnswerError as exc:
        return contradicted(f"probe_axis = {setting} gave no safe pairing ({_short(exc)}): paired from distances "
                            "only")
    # A wrong sign can still fit a few markers whose flipped directions agree (one face of the frame, mirrored):
    # the distances, which pair every marker, then pair more, and they decide.
    try:
        by_distances = pair_markers(origins_image, axes_image, points, None, l_range_mm, settings)
    except NoSafeAnswerError:
        by_distances = None
    if by_distances is not None and by_distances.support > result.support:
        return contradicted(f"probe_axis = {setting} paired {result.support} points, the distances alone "
                            f"{by_distances.support}: paired from distances only")
    _, agreeing, angle = _verdict(_signed_cosines(result, signed, axes), setting, cos_limit)
    return result, ProbeAxisReport(setting, setting, "directions", angle, agreeing, result.support,
                                   note=f"probe_axis = {setting} (forced); {agreeing} of {result.support} paired "
                                        f"points agree")


def _points_and_directions(points_reference: np.ndarray,
                           directions_reference: np.ndarray | None) -> tuple[np.ndarray, np.ndarray]:
    """(N, 3) points and (N, 3) directions (NaN rows where unknown; all NaN when the calibration has none)."""
    points = np.asarray(points_reference, dtype=float).reshape(-1, 3)
    if directions_reference is None:
        return points, np.full_like(points, np.nan)
    return points, np.asarray(directions_reference, dtype=float).reshape(-1, 3)


def _short(exc: Exception) -> str:
    text = str(exc)
    return text.split(";")[0][:120]
