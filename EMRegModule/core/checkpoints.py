"""Trust during navigation: checkpoints at the markers' pinholes, and jumps of the reference sensor.

**Checkpoints.** Whenever the probe rests in a marker's pinhole during navigation, EMReg knows where
it must be: the marker's pinhole at the solved sensor depth ``l`` in image space (``origin + l * axis``
of the detected marker, LPS mm). The probe's navigated position there (``ProbeToImage``, paper Eq. 12),
averaged robustly over the rest, minus that point is the registration's current error: the surgeon's
"touch a landmark to check", made automatic. No label is needed: a rest is found by the dwell finder's
stillness (:func:`EMRegModule.core.dwell.still_periods`, the ``[navigation]`` dwell keys) and recognised by
its proximity to a pinhole (``checkpoint_radius_mm``) and, when the probe has an orientation, by its
axis along the marker's (``checkpoint_angle_deg``).

**The decision.** With the registration's error model (:func:`pinholes_from_detection` given the
registration), each pinhole has a predicted checkpoint error when nothing changed: a 3D normal error of
covariance ``C`` (LPS mm^2), the registration's error at the pinhole plus the probe's per-dwell error and the
reference sensor's pose error (:class:`EMRegModule.core.error_model.ErrorModel`; the fitted field's term when a
distortion was found). A checkpoint fails when its error vector ``e`` is both beyond the user's limit
(``|e| > max_checkpoint_error_mm``) and beyond what the model explains at the false-alarm rate
``CHECKPOINT_FALSE_ALARM`` (``e^T C^-1 e > 3 F(1 - alpha; 3, dof)``, ``dof`` the degrees of freedom the
probe's error was estimated from; chi-square(3) when exact). Along ``e``'s direction that is one distance,
the checkpoint's ``threshold_mm``: ``max(limit, sqrt(q / u^T C^-1 u))``. So a noisier tracker does not fail
clean checkpoints (the threshold grows with its measured noise), and errors within the user's limit never
fail; ``expected_mm`` (``sqrt(tr C)``) says what a clean checkpoint shows there. Without an error model the
limit alone decides. A failed checkpoint makes every pose from its start ``INVALID`` until a later
checkpoint passes (or the user registers again).

**Reference jumps.** A slip of the reference sensor in its slot moves everything and shows at the next
checkpoint. Between checkpoints, a sudden step of the reference in the Tracker frame between two
samples, beyond the tracker's noise and the motion around it, that stays (not a lone wild sample) is
warned about: the frame was bumped or the reference slipped. The jump's measured step is then a hypothesis the
checkpoints after it test (:mod:`EMRegModule.core.slip`): a checkpoint whose error matches the slip's prediction
confirms it and fails when the slip's predicted error somewhere on the frame exceeds the limit, even if its own
error is within it; one that falls short of it rules the slip out (the frame moved as a whole).

The same code serves the offline ``emreg navigate`` / ``emreg run`` (whole recordings, vectorised) and
live navigation (:class:`TrustMonitor`, one sample at a time: a rest is judged when the probe leaves
the pinhole).
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Any

import numpy as np

from ..settings import NavigationSettings
from .dwell import good_quality_mask, robust_mean, still_periods
from .error_model import ErrorModel, pose_error_covariance
from .slip import SlipVerdict, SlipWatch, jump_transform
from .transforms import apply_transform, invert_rigid, rotation_angle_deg

if TYPE_CHECKING:
    from .registration import RegistrationResult

#: Pose status in ``navigation.csv`` and over OpenIGTLink (PLUS's ``TransformStatus`` names).
POSE_OK = "OK"
POSE_INVALID = "INVALID"
#: Samples on each side of a step that must agree for it to be a jump (not a lone wild sample).
JUMP_WINDOW = 8
#: A step counts as a jump when it exceeds this many robust sigmas of the sample-to-sample noise.
JUMP_NOISE_FACTOR = 8.0
#: Chance that a checkpoint fails although nothing changed (the error model's tail beyond the threshold): one
#: in 10^4 checkpoints, one false alarm in about 2000 sessions of 6 checkpoints.
CHECKPOINT_FALSE_ALARM = 1e-4


@dataclass
class Pinholes:
    """The detected markers' pinholes at the solved depth: ``ids`` (M,), ``position_image`` (M, 3, LPS mm,
    ``origin + l * axis``) and unit ``axis_image`` (M, 3, the marker's +Y, towards the opening);
    ``covariance_image`` (M, 3, 3, LPS mm^2): the error model's covariance of a checkpoint's error at each when
    nothing changed, estimated from ``dof`` degrees of freedom (None: no error model, the limit alone decides);
    ``reference_to_image`` (4x4): the registration they were judged with (None: no error model, no slip test)."""

    ids: list[str]
    position_image: np.ndarray
    axis_image: np.ndarray
    covariance_image: np.ndarray | None = None
    dof: float = float("inf")
    reference_to_image: np.ndarray | None = None

    def __len__(self) -> int:
        return len(self.ids)


def pinholes_from_detection(detection: Any, sensor_offset_l_mm: float,
                            registration: RegistrationResult | None = None) -> Pinholes:
    """The pinholes of every detected marker (paired or not: the CT alone places them) at depth ``l`` (mm)
    along its axis from its origin (bottom-face centre), in image space (LPS mm); with ``registration`` (its
    ``error``), the error model's covariance of a checkpoint there (:func:`checkpoint_covariance`)."""
    markers = list(getattr(detection, "markers", detection) or [])
    ids = [str(m.id) for m in markers]
    origin = np.array([m.origin for m in markers], dtype=float).reshape(-1, 3)
    axis = np.array([m.axis for m in markers], dtype=float).reshape(-1, 3)
    if len(axis):
        axis = axis / np.linalg.norm(axis, axis=1, keepdims=True)
    pinholes = Pinholes(ids, origin + float(sensor_offset_l_mm) * axis, axis)
    if registration is not None and getattr(registration, "error", None) is not None and len(ids):
        pinholes.covariance_image = checkpoint_covariance(registration.reference_to_image, registration.error,
                                                          pinholes.position_image)
        pinholes.dof = float(registration.error.probe_sigma_dof)
        pinholes.reference_to_image = np.asarray(registration.reference_to_image, dtype=float)
    return pinholes


def slip_watch(pinholes: Pinholes | None, settings: NavigationSettings) -> SlipWatch | None:
    """The slip test of the jumps (:mod:`EMRegModule.core.slip`) at these pinholes; None without an error model."""
    if pinholes is None or pinholes.covariance_image is None or pinholes.reference_to_image is None:
        return None
    return SlipWatch(pinholes.reference_to_image, pinholes.position_image, pinholes.ids,
                     settings.max_checkpoint_error_mm, pinholes.dof)


def judge_slip(watch: SlipWatch | None, checkpoint: Checkpoint, pinholes: Pinholes) -> None:
    """Judge ``checkpoint`` against the jumps before it (``watch``): it fails too when it confirms a slip, or a
    confirmed slip stands, whose predicted error on the frame exceeds the limit."""
    if watch is None:
        return
    k = pinholes.ids.index(checkpoint.image_marker)
    checkpoint.slip = watch.judge(np.asarray(checkpoint.offset_mm), pinholes.covariance_image[k], k)
    if checkpoint.slip is not None and checkpoint.slip.fails:
        checkpoint.ok = False


def checkpoint_covariance(reference_to_image: np.ndarray, error: Any, points_image: np.ndarray) -> np.ndarray:
    """Covariance (K, 3, 3, LPS mm^2) of a checkpoint's error at image points (K, 3) when nothing changed, from a
    registration's :class:`EMRegModule.core.error_model.RegistrationError`: the fit's error there, the probe's
    per-dwell error (isotropic), the reference sensor's pose error at calibration and now (the priors of
    :meth:`EMRegModule.core.error_model.ErrorModel.with_priors`, rotated into image space) and, when a field
    distortion was found, its term (isotropic). Infinite when the registration is undetermined."""
    model = ErrorModel.with_priors(reference_to_image, error)
    points = np.asarray(points_image, dtype=float).reshape(-1, 3)
    covariance = np.array(error.covariance.at(points), dtype=float)
    covariance += error.probe_sigma_mm ** 2 * np.eye(3)
    rotation = model.reference_to_image[:3, :3]
    lever_arms = apply_transform(invert_rigid(model.reference_to_image), points)
    reference = pose_error_covariance(lever_arms, model.reference_position_sigma_mm, model.reference_rotation_sigma_rad)
    covariance += 2.0 * rotation @ reference @ rotation.T
    distortion = error.distortion
    if distortion is not None and distortion.detected:
        covariance += (distortion.mean_square_at(lever_arms) / 3.0)[:, None, None] * np.eye(3)
    return covariance


def checkpoint_threshold(offset_mm: np.ndarray, covariance: np.ndarray | None, dof: float,
                         limit_mm: float) -> tuple[float, float | None]:
    """The distance (mm) a checkpoint's error along ``offset_mm`` (3,) must exceed to fail, and the expected error
    ``sqrt(tr C)`` (mm, None without ``covariance``): ``max(limit_mm, sqrt(q / u^T C^-1 u))`` with ``q`` the
    ``1 - CHECKPOINT_FALSE_ALARM`` quantile of ``e^T C^-1 e`` (3 F(3, dof); chi-square(3) for infinite dof)."""
    if covariance is None:
        return float(limit_mm), None
    covariance = np.asarray(covariance, dtype=float)
    expected = float(np.sqrt(np.trace(covariance)))
    if not np.all(np.isfinite(covariance)):
        return float("inf"), expected
    from scipy.special import fdtri, gammaincinv

    p = 1.0 - CHECKPOINT_FALSE_ALARM
    q = 2.0 * float(gammaincinv(1.5, p)) if not np.isfinite(dof) or dof > 1e6 else 3.0 * float(fdtri(3, dof, p))
    norm = float(np.linalg.norm(offset_mm))
    u = np.asarray(offset_mm, dtype=float) / norm if norm > 0 else np.array([1.0, 0.0, 0.0])
    along = float(u @ np.linalg.solve(covariance, u))
    return max(float(limit_mm), float(np.sqrt(q / along)) if along > 0 else float("inf")), expected


@dataclass
class Checkpoint:
    """One rest of the probe in a pinhole: its time span (s, the recording's clock), the marker, the error
    (mm: distance of the probe's robust mean position from the pinhole, image space), whether it passed,
    the samples it used and the error vector (probe minus pinhole, LPS mm)."""

    start_s: float
    end_s: float
    image_marker: str
    error_mm: float
    ok: bool
    samples: int = 0
    offset_mm: tuple[float, float, float] = (0.0, 0.0, 0.0)
    #: the error model's expected error there (mm, RMS) and the distance the error had to exceed (mm; see the
    #: module docstring); None without an error model (the limit alone decided)
    expected_mm: float | None = None
    threshold_mm: float | None = None
    #: what it says of the reference jumps before it (:mod:`EMRegModule.core.slip`), None when none was pending
    slip: SlipVerdict | None = None

    def to_json(self) -> dict[str, Any]:
        document = {"start_s": round(self.start_s, 4), "end_s": round(self.end_s, 4),
                    "image_marker": self.image_marker, "error_mm": round(self.error_mm, 4), "ok": bool(self.ok),
                    "samples": int(self.samples), "offset_mm": [round(float(v), 4) for v in self.offset_mm]}
        if self.threshold_mm is not None:
            document.update(expected_mm=None if self.expected_mm is None else round(self.expected_mm, 4),
                            threshold_mm=round(self.threshold_mm, 4) if np.isfinite(self.threshold_mm) else None)
        if self.slip is not None:
            document["slip"] = self.slip.to_json()
        return document

    def describe(self, limit_mm: float) -> str:
        verdict = "passed" if self.ok else "FAILED: poses are INVALID until a checkpoint passes"
        limit = f"limit {limit_mm:g} mm, [navigation] max_checkpoint_error_mm"
        if self.threshold_mm is not None and self.threshold_mm > limit_mm:
            limit += f"; {self.threshold_mm:.2f} mm at this tracker's noise, expected {self.expected_mm:.2f} mm"
        slip = "" if self.slip is None else f"; {self.slip.describe()}"
        return (f"checkpoint {self.image_marker} at {self.start_s:.2f}-{self.end_s:.2f} s: "
                f"error {self.error_mm:.2f} mm ({limit}{slip}) {verdict}")


@dataclass
class ReferenceJump:
    """A sudden step of the reference sensor at ``time_s``: ``jump_mm`` / ``jump_deg`` (the step beyond the
    motion around it) and the thresholds it exceeded."""

    time_s: float
    jump_mm: float
    jump_deg: float
    limit_mm: float
    limit_deg: float
    #: the measured step (4x4, mm): a point fixed in the Tracker frame, from the Reference frame before it into the
    #: one after it (:func:`EMRegModule.core.slip.jump_transform`); None when not measured
    reference_before_to_after: np.ndarray | None = None

    def to_json(self) -> dict[str, Any]:
        document = {"time_s": round(self.time_s, 4), "jump_mm": round(self.jump_mm, 4),
                    "jump_deg": round(self.jump_deg, 4), "limit_mm": round(self.limit_mm, 4),
                    "limit_deg": round(self.limit_deg, 4)}
        if self.reference_before_to_after is not None:
            document["ReferenceBeforeToReferenceAfter"] = np.round(self.reference_before_to_after, 6).tolist()
        return document

    def describe(self) -> str:
        return (f"the reference sensor jumped {self.jump_mm:.2f} mm / {self.jump_deg:.2f} deg at {self.time_s:.2f} s "
                f"(beyond the tracker's noise: limits {self.limit_mm:.2f} mm / {self.limit_deg:.2f} deg): "
                "the frame was bumped or the reference slipped in its slot; rest the probe in a marker's pinhole "
                "to check")


@dataclass
class CheckpointReport:
    """What ``checkpoints.json`` holds: the limit, every checkpoint and every reference jump, in time order."""

    max_error_mm: float
    checkpoints: list[Checkpoint] = field(default_factory=list)
    reference_jumps: list[ReferenceJump] = field(default_factory=list)
    radius_mm: float = 5.0
    invalid_poses: int = 0
    poses: int = 0
    provenance: dict[str, Any] | None = None
    #: why there are no checkpoints to look for (e.g. no detected markers beside the registration), or None
    note: str | None = None

    @property
    def failed(self) -> list[Checkpoint]:
        return [c for c in self.checkpoints if not c.ok]

    def to_json(self) -> dict[str, Any]:
        document: dict[str, Any] = {
            "max_error_mm": float(self.max_error_mm),
            "checkpoints": [c.to_json() for c in self.checkpoints],
            "reference_jumps": [j.to_json() for j in self.reference_jumps],
            "checkpoint_radius_mm": float(self.radius_mm),
            "poses": int(self.poses), "invalid_poses": int(self.invalid_poses),
        }
        if any(c.threshold_mm is not None for c in self.checkpoints):
            document["decision"] = ("fails when the error exceeds max_error_mm and the error model's prediction "
                                    "(expected_mm) at false-alarm rate false_alarm: threshold_mm along the error")
            document["false_alarm"] = CHECKPOINT_FALSE_ALARM
        if any(c.slip is not None for c in self.checkpoints):
            document["slip_test"] = ("after a reference jump: fails when the error matches the slip the jump would "
                                     "make (one-sided at slip.false_alarm) and the slip's predicted error on the frame "
                                     "exceeds max_error_mm (EMRegModule.core.slip)")
        if self.note:
            document["note"] = self.note
        if self.provenance is not None:
            document["provenance"] = self.provenance
        return document

    def warnings(self) -> list[str]:
        """One line per failed checkpoint and per reference jump."""
        lines = [c.describe(self.max_error_mm) for c in self.failed]
        noisy = [c for c in self.checkpoints if c.ok and c.error_mm > self.max_error_mm]
        if noisy:
            lines.append(f"{len(noisy)} checkpoint(s) passed with errors above the limit "
                         f"{self.max_error_mm:g} mm that the tracker's measured noise explains (largest "
                         f"{max(c.error_mm for c in noisy):.2f} mm, threshold {max(c.threshold_mm for c in noisy):.2f}"
                         " mm): at this noise a checkpoint cannot verify the limit")
        lines += [j.describe() for j in self.reference_jumps]
        return lines

    def summary(self) -> str:
        passed = len(self.checkpoints) - len(self.failed)
        worst = max((c.error_mm for c in self.checkpoints), default=float("nan"))
        text = f"{len(self.checkpoints)} checkpoint(s), {passed} passed"
        if self.note:
            text += f" ({self.note})"
        if self.checkpoints:
            text += f" (largest error {worst:.2f} mm, limit {self.max_error_mm:g} mm)"
        if self.reference_jumps:
            text += f", {len(self.reference_jumps)} reference jump(s)"
        if self.invalid_poses:
            text += f", {self.invalid_poses} of {self.poses} poses INVALID"
        return text


def find_checkpoints(time_s: np.ndarray, position_image: np.ndarray, direction_image: np.ndarray | None,
                     quality: np.ndarray | None, pinholes: Pinholes,
                     settings: NavigationSettings | None = None) -> list[Checkpoint]:
    """The checkpoints of one probe track: ``time_s`` (N,) sorted, ``position_image`` (N, 3, LPS mm: the navigated
    probe), ``direction_image`` (N, 3: the probe's +X in image space; None or NaN rows: position only),
    ``quality`` (N,) or None. Every still period (labels ignored) whose robust centre lies within
    ``checkpoint_radius_mm`` of a pinhole (and whose axis lies along the marker's) is a checkpoint."""
    settings = settings or NavigationSettings()
    time_s = np.asarray(time_s, dtype=float)
    position_image = np.asarray(position_image, dtype=float).reshape(-1, 3)
    if len(pinholes) == 0 or len(time_s) == 0:
        return []
    valid = np.all(np.isfinite(position_image), axis=1) & np.isfinite(time_s)
    if quality is not None:
        valid &= good_quality_mask(quality, settings.max_quality)
    # only samples near some pinhole can be part of a checkpoint (and the dwell finder's work shrinks)
    nearest, distance = _nearest_pinhole(position_image, pinholes)
    near = np.flatnonzero(valid & (distance <= settings.checkpoint_radius_mm + settings.still_radius_mm))
    if len(near) == 0:
        return []
    # one visit: near samples without a longer break than max_gap_s (two visits of one pinhole are two rests)
    breaks = np.flatnonzero(np.diff(time_s[near]) > settings.max_gap_s) + 1
    dwells = []
    for visit in np.split(near, breaks):
        mask = np.zeros(len(time_s), dtype=bool)
        mask[visit] = True
        dwells += still_periods(time_s, position_image, mask, settings)
    out = []
    for dwell in dwells:
        centre = robust_mean(position_image[dwell.indices])
        k = int(np.bincount(nearest[dwell.indices[centre.inliers]]).argmax())
        offset = centre.mean - pinholes.position_image[k]
        error = float(np.linalg.norm(offset))
        along = _along_axis(direction_image, dwell.indices, pinholes.axis_image[k], settings.checkpoint_angle_deg)
        if error > settings.checkpoint_radius_mm or not along:
            continue
        covariance = None if pinholes.covariance_image is None else pinholes.covariance_image[k]
        threshold, expected = checkpoint_threshold(offset, covariance, pinholes.dof,
                                                   settings.max_checkpoint_error_mm)
        out.append(Checkpoint(dwell.start_s, dwell.end_s, pinholes.ids[k], error, error <= threshold, centre.count,
                              tuple(float(v) for v in offset), expected,
                              None if covariance is None else threshold))
    return out


def _nearest_pinhole(position_image: np.ndarray, pinholes: Pinholes) -> tuple[np.ndarray, np.ndarray]:
    """Index of the nearest pinhole (N,) and the distance to it (N,, mm); NaN positions get an infinite distance.
    One matrix product per block of samples (``|p|^2 + |q|^2 - 2 p.q``), the chosen distance then exactly."""
    nearest = np.zeros(len(position_image), dtype=int)
    finite = np.all(np.isfinite(position_image), axis=1)
    points = pinholes.position_image
    squared = np.einsum("ij,ij->i", points, points)
    for start in range(0, len(position_image), 65536):
        block = np.where(finite[start:start + 65536, None], position_image[start:start + 65536], 0.0)
        nearest[start:start + len(block)] = np.argmin(squared[None, :] - 2.0 * block @ points.T, axis=1)
    distance = np.linalg.norm(position_image - points[nearest], axis=1)
    distance[~finite] = np.inf
    return nearest, distance


def _along_axis(direction_image: np.ndarray | None, indices: np.ndarray, axis: np.ndarray,
                max_angle_deg: float) -> bool:
    """True when the probe's mean axis over ``indices`` lies within ``max_angle_deg`` of ``axis`` (either sign:
    +X into or out of the hole), or when the probe has no orientation."""
    if direction_image is None:
        return True
    directions = np.asarray(direction_image, dtype=float)[indices]
    directions = directions[np.all(np.isfinite(directions), axis=1)]
    if len(directions) == 0:
        return True
    signs = np.sign(directions @ axis)
    signs[signs == 0] = 1.0
    mean = (directions * signs[:, None]).mean(axis=0)
    norm = float(np.linalg.norm(mean))
    return norm > 0 and abs(float(mean @ axis)) / norm >= np.cos(np.radians(max_angle_deg))


def pose_status(time_s: np.ndarray, quality: np.ndarray | None, checkpoints: list[Checkpoint],
                max_quality: float | None = None) -> np.ndarray:
    """``OK`` / ``INVALID`` per pose (N,): INVALID from the start of a failed checkpoint until the start of the next
    one that passes, and wherever the quality number is worse than ``max_quality`` (None: not checked)."""
    time_s = np.asarray(time_s, dtype=float)
    invalid = np.zeros(len(time_s), dtype=bool)
    if quality is not None and max_quality is not None:
        invalid |= ~good_quality_mask(quality, max_quality)
    failing_since: float | None = None
    for checkpoint in sorted(checkpoints, key=lambda c: c.start_s):
        if not checkpoint.ok and failing_since is None:
            failing_since = checkpoint.start_s
        elif checkpoint.ok and failing_since is not None:
            invalid |= (time_s >= failing_since) & (time_s < checkpoint.start_s)
            failing_since = None
    if failing_since is not None:
        invalid |= time_s >= failing_since
    return np.where(invalid, POSE_INVALID, POSE_OK).astype(object)


# --- reference jumps -----------------------------------------------------------------------------


def _step_excess(position_mm: np.ndarray, rotation: np.ndarray,
                 steps: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """For each of ``steps`` (step k: sample k -> k + 1, with ``JUMP_WINDOW`` steps before it): how far the step
    departs from the motion just before (mm: the step vector minus the componentwise median of the previous
    steps' vectors; degrees: the step's angle minus the previous steps' median angle), and that motion vector
    (mm per step)."""
    w = JUMP_WINDOW
    before = steps[:, None] + np.arange(-w, 0)  # (m, w) the previous steps
    step = position_mm[steps + 1] - position_mm[steps]
    motion = np.median(position_mm[before + 1] - position_mm[before], axis=1)
    angle = rotation_angle_deg(rotation[steps], rotation[steps + 1])
    turning = np.median(rotation_angle_deg(rotation[before], rotation[before + 1]), axis=1)
    return np.linalg.norm(step - motion, axis=1), angle - turning, motion


#: Steps :func:`step_noise` looks at, at most (evenly spread): the median of a few thousand is as good as all.
NOISE_STEPS = 4000


def step_noise(position_mm: np.ndarray, rotation: np.ndarray) -> tuple[float, float]:
    """The tracker's noise as a sensor's steps show it (mm, degrees): the median departure of a step from the
    motion just before it (:func:`_step_excess`, at most ``NOISE_STEPS`` steps; smooth motion cancels)."""
    position_mm = np.asarray(position_mm, dtype=float).reshape(-1, 3)
    if len(position_mm) < JUMP_WINDOW + 2:
        return 0.0, 0.0
    steps = np.arange(JUMP_WINDOW, len(position_mm) - 1)
    steps = steps[::max(1, len(steps) // NOISE_STEPS)]
    excess_mm, excess_deg, _ = _step_excess(position_mm, np.asarray(rotation, dtype=float).reshape(-1, 3, 3), steps)
    return float(np.median(excess_mm)), float(np.median(np.abs(excess_deg)))


def reference_jumps(time_s: np.ndarray, position_mm: np.ndarray, rotation: np.ndarray,
                    settings: NavigationSettings | None = None,
                    noise: tuple[float, float] | None = None) -> list[ReferenceJump]:
    """Sudden steps of one sensor (the reference: ``time_s`` (N,), ``position_mm`` (N, 3) and ``rotation``
    (N, 3, 3) in the Tracker frame, good samples only, time order). A jump at sample i: the step from i - 1
    to i departs from the motion of the ``JUMP_WINDOW`` steps before it by more than the limit
    (``reference_jump_mm`` / ``_deg``, and at least ``JUMP_NOISE_FACTOR`` times ``noise``, default
    :func:`step_noise` of these samples), and the pose after it stays there (the medians of the windows before
    and after, the motion taken out, differ by at least half of it: a lone wild sample does not)."""
    settings = settings or NavigationSettings()
    time_s = np.asarray(time_s, dtype=float)
    position_mm = np.asarray(position_mm, dtype=float).reshape(-1, 3)
    rotation = np.asarray(rotation, dtype=float).reshape(-1, 3, 3)
    w = JUMP_WINDOW
    if len(time_s) < 2 * w + 1:
        return []
    noise_mm, noise_deg = step_noise(position_mm, rotation) if noise is None else noise
    limit_mm = max(settings.reference_jump_mm, JUMP_NOISE_FACTOR * noise_mm)
    limit_deg = max(settings.reference_jump_deg, JUMP_NOISE_FACTOR * noise_deg)
    # candidates: a step, or its change from the step before, beyond half the floor (a jump changes the step by
    # its size whatever the motion); only they are measured against the motion before them
    step = np.diff(position_mm, axis=0)
    angle = rotation_angle_deg(rotation[:-1], rotation[1:])
    change = np.linalg.norm(np.diff(step, axis=0), axis=1)
    steps = np.arange(w, len(position_mm) - w)  # w steps before, a window of w samples after
    loose_mm, loose_deg = 0.5 * settings.reference_jump_mm, 0.5 * settings.reference_jump_deg
    steps = steps[(np.linalg.norm(step[steps], axis=1) > loose_mm) | (change[steps - 1] > loose_mm)
                  | (angle[steps] > loose_deg) | (np.abs(angle[steps] - angle[steps - 1]) > loose_deg)]
    if len(steps) == 0:
        return []
    parts = [_step_excess(position_mm, rotation, steps[k:k + 16384]) for k in range(0, len(steps), 16384)]
    excess_mm, excess_deg, motion = (np.concatenate(values) for values in zip(*parts, strict=True))
    candidates = np.flatnonzero((excess_mm > limit_mm) | (excess_deg > limit_deg))
    jumps: list[ReferenceJump] = []
    for j in candidates.tolist():
        i = int(steps[j]) + 1  # the first sample after the step
        before, after = slice(i - w, i), slice(i, i + w)
        moved = np.median(position_mm[after], axis=0) - np.median(position_mm[before], axis=0) - w * motion[j]
        turned = float(rotation_angle_deg(rotation[i - 1 - w // 2], rotation[i + w // 2 - 1]))
        e_mm, e_deg = float(excess_mm[j]), float(excess_deg[j])
        # a steady turn before the step (beyond the angles' own noise, which is never negative) is taken out
        turning = max(float(np.median(angle[i - 1 - w:i - 1])) - 2.0 * noise_deg, 0.0)
        stays = ((e_mm > limit_mm and float(np.linalg.norm(moved)) >= 0.5 * e_mm)
                 or (e_deg > limit_deg and turned - w * turning >= 0.5 * e_deg))
        if not stays:
            continue
        jump = ReferenceJump(float(time_s[i]), max(e_mm, 0.0), max(e_deg, 0.0), limit_mm, limit_deg,
                             jump_transform(position_mm, rotation, before, after, motion[j]))
        if jumps and i - np.searchsorted(time_s, jumps[-1].time_s) <= w:  # one slip over a few samples: one jump
            if e_mm > jumps[-1].jump_mm:
                jumps[-1] = jump
            continue
        jumps.append(jump)
    return jumps


# --- offline: a whole navigation -----------------------------------------------------------------


def check_navigation(navigation: Any, recording: Any, pinholes: Pinholes | None, reference_sensor: int,
                     settings: NavigationSettings | None = None) -> CheckpointReport:
    """Checkpoints and reference jumps of a navigated recording, and the pose status they give.

    ``navigation``: a :class:`EMRegModule.core.navigation.NavigationResult` (its ``status`` is set here);
    ``recording``: the tracking recording it was made from (the reference sensor's samples are judged for
    jumps); ``pinholes``: where the probe must be in each pinhole (None: no checkpoints, jumps only).
    """
    settings = settings or NavigationSettings()
    checkpoints = [] if pinholes is None else find_checkpoints(
        navigation.time_s, navigation.position_mm, navigation.direction, navigation.quality, pinholes, settings)
    reference = recording.for_sensor(reference_sensor)
    good = (np.all(np.isfinite(reference.position_mm), axis=1) & np.all(np.isfinite(reference.rotation), axis=(1, 2))
            & good_quality_mask(reference.quality, settings.max_quality))
    jumps = reference_jumps(reference.time_s[good], reference.position_mm[good], reference.rotation[good], settings)
    judge_slips(checkpoints, jumps, pinholes, settings)
    navigation.status = pose_status(navigation.time_s, navigation.quality, checkpoints, settings.max_quality)
    invalid = int(np.count_nonzero(navigation.status == POSE_INVALID))
    return CheckpointReport(settings.max_checkpoint_error_mm, checkpoints, jumps, settings.checkpoint_radius_mm,
                            invalid, len(navigation.time_s))


def judge_slips(checkpoints: list[Checkpoint], jumps: list[ReferenceJump], pinholes: Pinholes | None,
                settings: NavigationSettings) -> None:
    """Judge each checkpoint against the jumps before its end, in time order (:func:`judge_slip`)."""
    watch = slip_watch(pinholes, settings)
    if watch is None or not jumps:
        return
    events = sorted([(j.time_s, 0, j) for j in jumps] + [(c.end_s, 1, c) for c in checkpoints], key=lambda e: e[:2])
    for _, kind, event in events:
        if kind == 0:
            watch.add_jump(event.time_s, event.reference_before_to_after)
        else:
            judge_slip(watch, event, pinholes)


# --- live: one sample at a time ------------------------------------------------------------------


class TrustMonitor:
    """Checkpoints and reference jumps during live navigation, one measurement cycle at a time.

    :meth:`observe` takes each cycle's navigated probe pose and reference pose and returns the events it
    completed (:class:`Checkpoint`, :class:`ReferenceJump`). A rest near a pinhole is collected while the
    probe stays within ``checkpoint_radius_mm`` of it and judged by :func:`find_checkpoints` when it leaves
    (or after ``max_visit_s``). :attr:`valid` is False from a failed checkpoint until one passes. The work
    per cycle away from the pinholes is one distance to each pinhole and one reference step.
    """

    def __init__(self, pinholes: Pinholes | None, settings: NavigationSettings | None = None,
                 max_visit_s: float = 30.0, noise_samples: int = 400) -> None:
        self.pinholes = pinholes
        self.settings = settings or NavigationSettings()
        self.max_visit_s = max_visit_s
        self.report = CheckpointReport(self.settings.max_checkpoint_error_mm,
                                       radius_mm=self.settings.checkpoint_radius_mm)
        self.valid = True
        self.watch = slip_watch(pinholes, self.settings)
        self._visit: list[tuple[float, np.ndarray, np.ndarray, float]] = []
        # the reference's recent samples in a ring (no allocation per cycle); a step above the floors (squared:
        # mm^2, and the rotation's |R1 - R0|_F^2 = 8 sin^2(angle / 2)) is a candidate, judged by reference_jumps
        # once its window after it has arrived, against the noise of the ring's samples
        self._ring = max(int(noise_samples), 4 * JUMP_WINDOW)
        self._times = np.empty(self._ring)
        self._positions = np.empty((self._ring, 3))
        self._rotations = np.empty((self._ring, 3, 3))
        self._count = 0
        self._floor_mm2 = self.settings.reference_jump_mm ** 2
        self._floor_rot2 = 8.0 * np.sin(np.radians(self.settings.reference_jump_deg) / 2.0) ** 2
        self._pending: int | None = None  # samples until a candidate step has its window after it

    def observe(self, time_s: float, probe_to_image: np.ndarray | None, reference_to_tracker: np.ndarray | None,
                quality: float = float("nan")) -> list[Checkpoint | ReferenceJump]:
        """One cycle: ``probe_to_image`` (4x4, LPS mm; None when no valid pose), ``reference_to_tracker`` (4x4;
        None when the reference sample is not valid), the worse quality number of the two sensors."""
        events: list[Checkpoint | ReferenceJump] = []
        if probe_to_image is not None:  # this pose went out with the status :attr:`valid` gave it
            self.report.poses += 1
            self.report.invalid_poses += not self.valid
        if reference_to_tracker is not None:
            jump = self._observe_reference(time_s, reference_to_tracker)
            if jump is not None:
                self.report.reference_jumps.append(jump)
                if self.watch is not None:
                    self.watch.add_jump(jump.time_s, jump.reference_before_to_after)
                events.append(jump)
        if probe_to_image is not None and self.pinholes is not None and len(self.pinholes):
            position = probe_to_image[:3, 3]
            offset = self.pinholes.position_image - position
            near = float(np.min(np.einsum("ij,ij->i", offset, offset))) ** 0.5
            limit = self.settings.checkpoint_radius_mm + self.settings.still_radius_mm
            if self._visit and (time_s - self._visit[0][0] > self.max_visit_s or
                                (near > limit and time_s - self._visit[-1][0] > self.settings.max_gap_s)):
                events += self._judge_visit()  # left the pinhole (longer than a wild sample's break), or a long rest
            if near <= limit:
                self._visit.append((time_s, position.copy(), probe_to_image[:3, 0].copy(), quality))
        return events

    def flush(self) -> list[Checkpoint]:
        """Judge the visit in progress (the stream ended while the probe rested in a pinhole)."""
        return self._judge_visit() if self._visit else []

    def _judge_visit(self) -> list[Checkpoint]:
        time_s, position, direction, quality = (np.array(v) for v in zip(*self._visit, strict=True))
        self._visit = []
        found = find_checkpoints(time_s, position, direction, quality.astype(float), self.pinholes, self.settings)
        for checkpoint in found:
            judge_slip(self.watch, checkpoint, self.pinholes)
            self.report.checkpoints.append(checkpoint)
            self.valid = checkpoint.ok
        return found

    def _observe_reference(self, time_s: float, reference_to_tracker: np.ndarray) -> ReferenceJump | None:
        position, rotation = reference_to_tracker[:3, 3], reference_to_tracker[:3, :3]
        k = self._count % self._ring
        if self._count and self._pending is None:
            j = (self._count - 1) % self._ring
            step = position - self._positions[j]
            turn = rotation - self._rotations[j]
            if float(step @ step) > self._floor_mm2 or float(np.vdot(turn, turn)) > self._floor_rot2:
                self._pending = JUMP_WINDOW
        self._times[k], self._positions[k], self._rotations[k] = time_s, position, rotation
        self._count += 1
        if self._pending is None:
            return None
        self._pending -= 1
        if self._pending > 0:
            return None
        self._pending = None
        order = np.arange(max(0, self._count - self._ring), self._count) % self._ring
        positions, rotations = self._positions[order], self._rotations[order]
        window = slice(max(0, len(order) - (2 * JUMP_WINDOW + 2)), None)
        jumps = reference_jumps(self._times[order][window], positions[window], rotations[window], self.settings,
                                step_noise(positions, rotations))
        return jumps[-1] if jumps else None
