"""Tracked tools: a sensor plus a tip, ``TipToProbe`` (4x4, mm: the tip frame into the probe sensor's frame).

PLUS calls it ``StylusTipToStylus`` (``<Transform From="StylusTip" To="Stylus">`` in a device-set file);
SlicerIGT's pivot calibration writes it as a linear transform. Without a tool EMReg uses the paper's pinhole
probe (the sensor on the pinhole axis at an unknown depth l); with one, every probe sample is turned into the
tip's pose (``TipToReference = ProbeToReference @ TipToProbe``), so the touched points are tip positions and
there is no unknown depth.

Its files (the tool file, ``emreg pivot``'s outputs, the pivot recording) are :mod:`EMRegModule.io.tool_files`'s.

Pivot calibration (:func:`pivot_calibration`): the tip rests in a divot while the tool swings, so for every
sample ``R_i @ tip + p_i = pivot`` (``R_i``, ``p_i``: ``ProbeToReference``). The six unknowns (the tip in the
probe frame, the pivot point in the Reference frame) are solved by linear least squares over all samples, then
refitted without the outliers (samples whose residual exceeds three times the robust RMS residual, as PLUS's
``vtkIGSIOPivotCalibrationAlgo`` and scikit-surgerycalibration reject them) until the inliers stop changing.
The tip frame is oriented as PLUS orients it: +Z from the sensor's origin towards the tip (along the shaft), +X
the sensor's +X made perpendicular to it.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

import numpy as np

from ..errors import EMRegError, NoSafeAnswerError
from .transforms import check_rigid

#: The shaft must swing over at least this cone (degrees, twice the 95th percentile angle of the shaft from its
#: mean direction) for the tip to be pinned down along the shaft: with the simulator's per-sample tracker noise,
#: 640 samples (8 s at 80 Hz) of a 150 mm tip swung over 12 / 20 / 30 degrees put it within 0.45 / 0.26 / 0.17 mm
#: (10 seeds, worst).
MIN_PIVOT_ROTATION_DEG = 20.0

#: A pivot fit whose inliers' RMS residual exceeds this (mm) did not pivot about one point (PLUS reports 0.3 to
#: 0.6 mm for hand-held pivots; a recording of touches at several places fits tens of millimetres).
MAX_PIVOT_RMS_MM = 1.5

#: Fewest samples of a pivot calibration.
MIN_PIVOT_SAMPLES = 10

#: Residuals above this many robust RMS residuals are outliers (PLUS: three standard deviations).
OUTLIER_FACTOR = 3.0

#: The outlier cut is never below this (mm): a perfect synthetic pivot keeps its samples.
MIN_OUTLIER_CUT_MM = 0.05


@dataclass
class ToolCalibration:
    """A tool: ``tip_to_probe`` (4x4, mm), where it came from, and (from a pivot calibration) how well it fits.

    ``name``: the tool's transform name (``Stylus`` for ``StylusToTracker``), None when the file does not say;
    ``pivot_point_mm``: the divot in the Reference frame (Tracker when the recording has no reference);
    ``rms_mm``: RMS distance of the inlier samples' tip from the pivot point; ``rotation_range_deg``: the
    shaft's swing (:data:`MIN_PIVOT_ROTATION_DEG`); ``samples``: inliers used of ``samples_total``."""

    tip_to_probe: np.ndarray
    source: str = ""
    name: str | None = None
    method: str = "file"
    pivot_point_mm: np.ndarray | None = None
    rms_mm: float | None = None
    rotation_range_deg: float | None = None
    samples: int | None = None
    samples_total: int | None = None
    pivot_frame: str | None = None
    warnings: list[str] = field(default_factory=list)
    #: the tip's standard deviation per probe axis (mm), from the residuals (a tip solved from the touches)
    tip_std_mm: np.ndarray | None = None
    #: touches the tip was solved from (``--tool auto``)
    touches: int | None = None

    @property
    def tip_mm(self) -> np.ndarray:
        """The tip in the probe sensor's frame (3,), mm."""
        return self.tip_to_probe[:3, 3].copy()

    def to_json(self) -> dict[str, Any]:
        """The ``tool_calibration.json`` document."""
        document: dict[str, Any] = {
            "TipToProbe": [[float(v) for v in row] for row in self.tip_to_probe],
            "tip_mm": [round(float(v), 4) for v in self.tip_mm],
            "method": self.method, "source": self.source,
        }
        if self.name:
            document["tool"] = self.name
        if self.pivot_point_mm is not None:
            document["pivot_point_mm"] = [round(float(v), 4) for v in self.pivot_point_mm]
            document["pivot_point_frame"] = self.pivot_frame or "Reference"
        for key in ("rms_mm", "rotation_range_deg"):
            value = getattr(self, key)
            if value is not None:
                document[key] = round(float(value), 4)
        if self.samples is not None:
            document["samples"] = int(self.samples)
            document["samples_total"] = int(self.samples_total or self.samples)
        if self.tip_std_mm is not None:
            document["tip_std_mm"] = [round(float(v), 4) for v in self.tip_std_mm]
        if self.touches is not None:
            document["touches"] = int(self.touches)
        if self.warnings:
            document["warnings"] = list(self.warnings)
        return document


# --- the tip transform ------------------------------------------------------------------------


def check_tip_to_probe(matrix: Any, where: str) -> np.ndarray:
    """``TipToProbe`` as a 4x4 float array, or :class:`EMRegError` (one line naming ``where``) when it is not
    a finite rigid transform (:func:`~EMRegModule.core.transforms.check_rigid`)."""
    try:
        matrix = np.asarray(matrix, dtype=float)
    except (TypeError, ValueError):
        raise EMRegError(f"{where}: TipToProbe is not a 4x4 matrix of numbers") from None
    if matrix.shape != (4, 4) or not np.all(np.isfinite(matrix)):
        raise EMRegError(f"{where}: TipToProbe must be a 4x4 matrix of finite numbers, got shape {matrix.shape}")
    check_rigid(matrix, f"{where}: TipToProbe (a tool's tip transform is a rotation and a translation)")
    return matrix


def tip_poses(sensor_to_frame: np.ndarray, tip_to_probe: np.ndarray) -> np.ndarray:
    """``TipToFrame`` (N, 4, 4) of a tool from its sensor's poses ``ProbeToFrame`` (N, 4, 4) in any frame."""
    return np.asarray(sensor_to_frame, dtype=float) @ np.asarray(tip_to_probe, dtype=float)


# --- pivot calibration -------------------------------------------------------------------------


@dataclass
class PivotFit:
    """A pivot fit: ``tip_mm`` (3,) in the probe frame, ``pivot_mm`` (3,) in the samples' frame, the
    ``inliers`` mask (N,), the per-sample ``residual_mm`` (N,) and the RMS of the inliers' residuals."""

    tip_mm: np.ndarray
    pivot_mm: np.ndarray
    inliers: np.ndarray
    residual_mm: np.ndarray
    rms_mm: float


def _solve_pivot(rotation: np.ndarray, position: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Least squares of ``R_i @ tip - pivot = -p_i`` over the samples (a (3N, 6) system)."""
    n = len(rotation)
    system = np.zeros((3 * n, 6))
    system[:, :3] = rotation.reshape(3 * n, 3)
    system[:, 3:] = -np.tile(np.eye(3), (n, 1))
    solution = np.linalg.lstsq(system, -position.reshape(3 * n), rcond=None)[0]
    return solution[:3], solution[3:]


def fit_pivot(probe_to_frame: np.ndarray, max_iterations: int = 10) -> PivotFit:
    """Tip (probe frame) and pivot point (the poses' frame) from sensor poses ``ProbeToFrame`` (N, 4, 4, mm):
    algebraic least squares, then refits without the outliers (module docstring)."""
    poses = np.asarray(probe_to_frame, dtype=float)
    rotation, position = poses[:, :3, :3], poses[:, :3, 3]
    inliers = np.ones(len(poses), dtype=bool)
    for _ in range(max_iterations):
        tip, pivot = _solve_pivot(rotation[inliers], position[inliers])
        residual = np.linalg.norm(np.einsum("nij,j->ni", rotation, tip) + position - pivot, axis=1)
        # robust RMS of a 3D residual: the median of a chi-3 distance is about 1.538 sigma, the RMS sqrt(3) sigma
        robust_rms = float(np.median(residual[inliers])) * np.sqrt(3.0) / 1.5382
        cut = max(OUTLIER_FACTOR * robust_rms, MIN_OUTLIER_CUT_MM)
        new_inliers = residual <= cut
        if np.count_nonzero(new_inliers) < max(MIN_PIVOT_SAMPLES, len(poses) // 2):
            break  # never reject most of the samples: the fit stays with the previous inliers
        if np.array_equal(new_inliers, inliers):
            break
        inliers = new_inliers
    tip, pivot = _solve_pivot(rotation[inliers], position[inliers])
    residual = np.linalg.norm(np.einsum("nij,j->ni", rotation, tip) + position - pivot, axis=1)
    rms = float(np.sqrt(np.mean(residual[inliers] ** 2)))
    return PivotFit(tip, pivot, inliers, residual, rms)


def shaft_swing_deg(rotation: np.ndarray, tip_mm: np.ndarray) -> float:
    """How far the shaft swung (degrees): the 95th percentile of the angle between a sample's shaft direction
    (``R_i @ tip``, the sensor-to-tip line in the poses' frame) and the mean direction, doubled (a cone's full
    angle). Zero when the tip is at the sensor's origin (no shaft)."""
    length = float(np.linalg.norm(tip_mm))
    if length < 1e-6:
        return 0.0
    directions = np.einsum("nij,j->ni", np.asarray(rotation, dtype=float), np.asarray(tip_mm) / length)
    mean = directions.mean(axis=0)
    mean /= max(float(np.linalg.norm(mean)), 1e-12)
    angles = np.degrees(np.arccos(np.clip(directions @ mean, -1.0, 1.0)))
    return float(2.0 * np.percentile(angles, 95))


#: A pivoting touch's point is the tip *as placed*: its samples from the touch's start until the shaft first turns
#: more than this (degrees) from its direction at the start (:func:`placement_samples`). Twice the swing that
#: makes a touch a pivot (hand tremor turns a held tool by a degree or two).
PLACEMENT_SWING_DEG = 10.0

#: A placement is never fewer samples than this (PLUS's landmark detection averages 4), nor more than the touch.
MIN_PLACEMENT_SAMPLES = 5


def placement_samples(rotation: np.ndarray, tip_mm: np.ndarray) -> np.ndarray:
    """The samples of one touch (``rotation``: (N, 3, 3) ``ProbeToFrame`` rotations, in time order) where the tip
    is *as placed*: a boolean mask (N,) of the leading samples until the shaft (``R_i @ tip``) first turns more than
    :data:`PLACEMENT_SWING_DEG` from its direction at the start (the median of the first three), at least
    :data:`MIN_PLACEMENT_SAMPLES`. A touch that never turns that far (a rest) keeps all its samples.

    Why: a hand-held pivot does not turn about the calibrated tip exactly (the tip slides and rolls in the
    landmark, and the tip calibration's error ``e`` shows as ``R_i @ e``), so the tip drifts as the shaft swings,
    by an amount that depends on how each touch was swung. On PLUS's real landmark recording the tip moves up to
    about 1 mm through a touch, and the 8 touched points fit the phantom's landmarks best at the start: 0.20 mm
    RMS for each touch's first second against 0.32-0.60 mm for any later second and 0.30 mm for the whole touch.
    PLUS's landmark detection takes the same moment (the mean of 4 samples once the tip has settled; pivoting only
    tells it that the tip is held on purpose)."""
    rotation = np.asarray(rotation, dtype=float)
    keep = np.ones(len(rotation), dtype=bool)
    length = float(np.linalg.norm(tip_mm))
    if length < 1e-6 or len(rotation) <= MIN_PLACEMENT_SAMPLES:
        return keep
    directions = np.einsum("nij,j->ni", rotation, np.asarray(tip_mm, dtype=float) / length)
    start = np.median(directions[:3], axis=0)
    start /= max(float(np.linalg.norm(start)), 1e-12)
    turned = np.degrees(np.arccos(np.clip(directions @ start, -1.0, 1.0))) > PLACEMENT_SWING_DEG
    if turned.any():
        keep[max(int(np.argmax(turned)), MIN_PLACEMENT_SAMPLES):] = False
    return keep


def tip_frame_rotation(tip_mm: np.ndarray) -> np.ndarray:
    """The tip frame's axes in the probe frame (3x3, columns X, Y, Z), as PLUS orients a pivot-calibrated tip:
    +Z along the shaft (from the sensor's origin towards the tip), +X the sensor's +X made perpendicular to it
    (its +Y when the shaft lies along +X), +Y = Z x X."""
    z_axis = np.asarray(tip_mm, dtype=float)
    length = float(np.linalg.norm(z_axis))
    if length < 1e-9:
        return np.eye(3)
    z_axis = z_axis / length
    seed = np.array([1.0, 0.0, 0.0]) if abs(z_axis[0]) < 0.9 else np.array([0.0, 1.0, 0.0])
    x_axis = seed - (seed @ z_axis) * z_axis
    x_axis /= np.linalg.norm(x_axis)
    return np.column_stack([x_axis, np.cross(z_axis, x_axis), z_axis])


def pivot_calibration(probe_to_frame: np.ndarray, source: str = "recording", frame: str = "Reference",
                      name: str | None = None, min_rotation_deg: float = MIN_PIVOT_ROTATION_DEG) -> ToolCalibration:
    """Pivot calibration from sensor poses ``ProbeToFrame`` (N, 4, 4, mm) taken while the tip rests in one divot.

    ``frame``: the poses' frame (``Reference``; ``Tracker`` when the recording has no reference), where the
    pivot point is given. Raises :class:`NoSafeAnswerError` (exit 3) when the shaft swung less than
    ``min_rotation_deg`` (saying how much it swung and how much is needed), the tip did not stay at one point
    (:data:`MAX_PIVOT_RMS_MM`) or there are too few samples."""
    poses = np.asarray(probe_to_frame, dtype=float).reshape(-1, 4, 4)
    finite = np.all(np.isfinite(poses.reshape(len(poses), -1)), axis=1)
    poses = poses[finite]
    if len(poses) < MIN_PIVOT_SAMPLES:
        raise NoSafeAnswerError(f"{source}: {len(poses)} samples with a full pose; a pivot calibration needs at "
                                f"least {MIN_PIVOT_SAMPLES}")
    rotation = poses[:, :3, :3]
    fit = fit_pivot(poses)
    swing = shaft_swing_deg(rotation[fit.inliers], fit.tip_mm)
    if swing < min_rotation_deg:
        raise NoSafeAnswerError(
            f"{source}: the tool swung only {swing:.1f} degrees about its tip; a pivot calibration needs at least "
            f"{min_rotation_deg:g} degrees of swing to pin the tip down (rest the tip in a divot and swing the "
            "shaft in a cone, 20-30 degrees each way)")
    if fit.rms_mm > MAX_PIVOT_RMS_MM:
        raise NoSafeAnswerError(
            f"{source}: the tip did not stay at one point: the pivot fit leaves {fit.rms_mm:.1f} mm RMS (at most "
            f"{MAX_PIVOT_RMS_MM:g} mm); record one divot per pivot recording, the tip resting in it throughout")
    tip_to_probe = make_tip_to_probe(fit.tip_mm)
    warnings = []
    dropped = len(poses) - int(np.count_nonzero(fit.inliers))
    if dropped:
        warnings.append(f"{source}: {dropped} of {len(poses)} samples left out of the pivot fit as outliers "
                        f"(residual above {OUTLIER_FACTOR:g} x the robust RMS)")
    return ToolCalibration(tip_to_probe, source, name, "pivot: least squares, then refit without outliers "
                           f"(> {OUTLIER_FACTOR:g} x robust RMS residual)", fit.pivot_mm, fit.rms_mm, swing,
                           int(np.count_nonzero(fit.inliers)), len(poses), frame, warnings)


# --- the tip solved from the touches (--tool auto) ---------------------------------------------------

#: Windows of this length (s) are pivot-fitted to find where the tool pivots before its tip is known.
AUTO_WINDOW_S = 1.0

#: A window pivots when its fit leaves at most this RMS (mm) over at least ``AUTO_WINDOW_MIN_SWING_DEG``.
AUTO_WINDOW_MAX_RMS_MM = 0.7
AUTO_WINDOW_MIN_SWING_DEG = 10.0

#: Fewest pivoting touches that pin the tip down (each pins it along the directions its swing spans).
AUTO_MIN_TOUCHES = 3


def fit_multi_pivot(poses: list[np.ndarray]) -> tuple[np.ndarray, np.ndarray, float, np.ndarray]:
    """One tip (probe frame) and one pivot point per group of sensor poses ``ProbeToReference`` (each (N_k, 4,
    4)): least squares of ``R_i @ tip - pivot_k = -p_i`` over every sample. Returns the tip (3,), the pivot
    points (K, 3), the RMS residual (mm) and the tip's covariance (3x3, mm^2) from the residuals."""
    k_groups = len(poses)
    rows = sum(len(p) for p in poses)
    system = np.zeros((3 * rows, 3 + 3 * k_groups))
    rhs = np.zeros(3 * rows)
    start = 0
    for k, group in enumerate(poses):
        n = len(group)
        block = slice(3 * start, 3 * (start + n))
        system[block, :3] = group[:, :3, :3].reshape(3 * n, 3)
        system[block, 3 + 3 * k:6 + 3 * k] = -np.tile(np.eye(3), (n, 1))
        rhs[block] = -group[:, :3, 3].reshape(3 * n)
        start += n
    solution, *_ = np.linalg.lstsq(system, rhs, rcond=None)
    residual = (system @ solution - rhs).reshape(-1, 3)
    distances = np.linalg.norm(residual, axis=1)
    rms = float(np.sqrt(np.mean(distances**2)))
    dof = max(3 * rows - len(solution), 1)
    sigma2 = float(np.sum(residual**2)) / dof
    normal = system.T @ system
    covariance = sigma2 * np.linalg.pinv(normal)[:3, :3]
    return solution[:3], solution[3:].reshape(k_groups, 3), rms, covariance


def pivoting_windows_tip(probe_to_reference: np.ndarray, time_s: np.ndarray) -> np.ndarray | None:
    """A first tip (probe frame, mm) before any is known: the median tip of the 1 s windows (half a window apart)
    that pivot (:data:`AUTO_WINDOW_MAX_RMS_MM`, :data:`AUTO_WINDOW_MIN_SWING_DEG`); None when none does."""
    time_s = np.asarray(time_s, dtype=float)
    if len(time_s) == 0:
        return None
    tips = []
    for start_s in np.arange(time_s[0], time_s[-1], AUTO_WINDOW_S / 2):
        first, last = np.searchsorted(time_s, [start_s, start_s + AUTO_WINDOW_S])
        if last - first < MIN_PIVOT_SAMPLES:
            continue
        window = probe_to_reference[first:last]
        fit = fit_pivot(window, max_iterations=2)
        if (fit.rms_mm <= AUTO_WINDOW_MAX_RMS_MM
                and shaft_swing_deg(window[:, :3, :3], fit.tip_mm) >= AUTO_WINDOW_MIN_SWING_DEG):
            tips.append(fit.tip_mm)
    return np.median(np.asarray(tips), axis=0) if tips else None


def solve_tip_from_touches(probe_to_reference: np.ndarray, time_s: np.ndarray, find_touches: Any,
                           source: str = "recording", iterations: int = 3) -> ToolCalibration:
    """``--tool auto``: the tip (probe frame) solved from a recording whose touches pivot about the tip.

    ``find_touches(tip_positions) -> list of index arrays``: the touches of a tip track (the calibration's dwell
    finder). A first tip from the pivoting 1 s windows (:func:`pivoting_windows_tip`) gives the tip track; its
    touches that swing (:data:`AUTO_WINDOW_MIN_SWING_DEG`) are fitted jointly (:func:`fit_multi_pivot`: one tip,
    one point per touch), and the touches are found again with the new tip, ``iterations`` times. Raises
    :class:`NoSafeAnswerError` when nothing pivots or fewer than :data:`AUTO_MIN_TOUCHES` touches do."""
    poses = np.asarray(probe_to_reference, dtype=float)
    tip = pivoting_windows_tip(poses, time_s)
    if tip is None:
        raise NoSafeAnswerError(
            f"{source}: --tool auto: the tool never pivots about its tip (no {AUTO_WINDOW_S:g} s window swings "
            f"{AUTO_WINDOW_MIN_SWING_DEG:g} degrees about a still point within {AUTO_WINDOW_MAX_RMS_MM:g} mm RMS); "
            "pivot the tool at each touch, or give its tip with --tool FILE (emreg pivot)")
    for _ in range(iterations):
        touches = find_touches(tip_poses(poses, make_tip_to_probe(tip))[:, :3, 3])
        pivoting = [t for t in touches if shaft_swing_deg(poses[t, :3, :3], tip) >= AUTO_WINDOW_MIN_SWING_DEG]
        if len(pivoting) < AUTO_MIN_TOUCHES:
            raise NoSafeAnswerError(
                f"{source}: --tool auto: {len(pivoting)} touch(es) pivot about the tip (of {len(touches)} found); at "
                f"least {AUTO_MIN_TOUCHES} are needed to solve the tip; pivot the tool at each touch, or give its "
                "tip with --tool FILE")
        tip, _, rms, covariance = fit_multi_pivot([poses[t] for t in pivoting])
    swing = min(shaft_swing_deg(poses[t, :3, :3], tip) for t in pivoting)
    tool = ToolCalibration(make_tip_to_probe(tip), source, None,
                           f"auto: one tip and one point per touch fitted to {len(pivoting)} pivoting touches",
                           rms_mm=rms, rotation_range_deg=swing, samples=int(sum(len(t) for t in pivoting)),
                           samples_total=len(poses), pivot_frame="Reference",
                           tip_std_mm=np.sqrt(np.clip(np.diag(covariance), 0.0, None)), touches=len(pivoting))
    return tool


def make_tip_to_probe(tip_mm: np.ndarray) -> np.ndarray:
    """``TipToProbe`` (4x4) for a tip (probe frame, mm), its axes as PLUS orients them (:func:`tip_frame_rotation`)."""
    tip_to_probe = np.eye(4)
    tip_to_probe[:3, :3] = tip_frame_rotation(tip_mm)
    tip_to_probe[:3, 3] = tip_mm
    return tip_to_probe
