"""Did the reference sensor slip in its slot, or did the frame move as a whole? A jump tested at the checkpoints.

A sudden step of the reference sensor (:func:`EMRegModule.core.checkpoints.reference_jumps`) has two causes the tracker
cannot tell apart: the frame was bumped (the reference moved with the pinholes and the patient: the registration
still holds), or the reference slipped in its slot (the patient stayed: every navigated point is now off). The
step is measured: ``ReferenceBeforeToReferenceAfter`` (4x4, mm), the coordinates of a point fixed in the Tracker
frame before and after it (:func:`jump_transform`). Were it a slip, a point ``x`` of image space (LPS, mm) would now
be navigated to ``ReferenceToImage @ S @ inv(ReferenceToImage) @ x``, with ``S`` the product of the steps since the
registration that are not ruled out: a predicted error ``d(x)`` everywhere, largest at the pinholes far from the
reference when the step turned it.

At a checkpoint at pinhole ``k`` with error ``e`` (probe minus pinhole, LPS mm) and the error model's covariance
``C`` of that error when nothing changed (:func:`EMRegModule.core.checkpoints.checkpoint_covariance`), the two
hypotheses differ along ``d = d(x_k)``: ``s = d^T C^-1 e / |d|_C`` (``|d|_C = sqrt(d^T C^-1 d)``, the separation)
is N(0, 1) when the frame moved as a whole and N(``|d|_C``, 1) when the reference slipped (the most powerful test
of one against the other, Neyman-Pearson). ``C``'s scale is estimated (the probe's error from ``dof`` degrees of
freedom, as for the checkpoint's own threshold), so ``z`` is the ``1 - SLIP_FALSE_ALARM`` quantile of Student's t
with ``dof`` degrees of freedom (the normal one for infinite ``dof``):

- ``s > z`` (and ``e`` not as far short of ``d``, below): the slip is **confirmed**. The checkpoint fails when the
  slip's predicted error at some pinhole of the frame exceeds ``[navigation] max_checkpoint_error_mm`` although its
  own error may be within it: the slip's rotation moves the pinholes far from the checked one more (a 2 mm /
  0.5 degree slip: 0.7-4 mm over a frame);
- ``|d|_C - s > z`` (``e`` falls as far short of ``d``): the step was **ruled out** as a slip and is forgotten;
  when ``s > z`` as well, **neither** fits (the error lies between none and the slip's: the frame moved and the
  reference shifted in it by part of the step, or the noise's tails): the slip test is dropped too, and the
  checkpoint's own error decides;
- otherwise the question stays **open**: a confirmed slip stands (the checkpoint fails: it cannot show the
  registration good again where the slip is small; a checkpoint that rules the slip out, or registering again,
  can), an unconfirmed one waits for the next checkpoint.

A frame that was bumped fails its next checkpoint by this test once in ``1 / SLIP_FALSE_ALARM``; the test only
runs after a jump was warned about. (Simulated clean checkpoints at the tracker's usual noise: ``s`` beyond the
0.999 quantile in 0.06-0.3 % of random directions, its tails a little heavier than the model's; 1e-2 would be
0.5-1.6 %.) The step's own measurement error (window medians of the reference's samples,
a few hundredths of a mm) is left out of ``C``.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np

from .transforms import apply_transform, invert_rigid, quaternion_to_rotation, rotation_to_quaternion

#: Chance that the checkpoint after a jump of a frame bumped as a whole fails by the slip test (the rate of the
#: one-sided test along the slip's predicted error).
SLIP_FALSE_ALARM = 1e-3
CONFIRMED, OPEN, RULED_OUT, NEITHER = "confirmed", "open", "ruled_out", "neither"


def robust_pose(position_mm: np.ndarray, rotation: np.ndarray) -> np.ndarray:
    """One pose (4x4) for samples of a still sensor: the median position (mm) and the normalised componentwise
    median of the quaternions (signs aligned with the first), so a wild sample does not move it."""
    quaternions = rotation_to_quaternion(np.asarray(rotation, dtype=float).reshape(-1, 3, 3))
    quaternions *= np.where(quaternions @ quaternions[0] < 0, -1.0, 1.0)[:, None]
    pose = np.eye(4)
    pose[:3, :3] = quaternion_to_rotation(np.median(quaternions, axis=0))  # normalised there
    pose[:3, 3] = np.median(np.asarray(position_mm, dtype=float).reshape(-1, 3), axis=0)
    return pose


def jump_transform(position_mm: np.ndarray, rotation: np.ndarray, before: slice, after: slice,
                   motion_mm: np.ndarray | None = None) -> np.ndarray:
    """``ReferenceBeforeToReferenceAfter`` (4x4, mm) of a step of one sensor (samples ``position_mm`` (N, 3) and
    ``rotation`` (N, 3, 3) in the Tracker frame): ``inv(after) @ before`` of the robust poses (:func:`robust_pose`)
    of the samples ``before`` and ``after`` it, the steady motion ``motion_mm`` (mm per sample) over the windows'
    distance taken out of the after side."""
    pose_before = robust_pose(position_mm[before], rotation[before])
    pose_after = robust_pose(position_mm[after], rotation[after])
    if motion_mm is not None:
        centre_before = 0.5 * (before.start + before.stop - 1)
        centre_after = 0.5 * (after.start + after.stop - 1)
        pose_after[:3, 3] -= (centre_after - centre_before) * np.asarray(motion_mm, dtype=float)
    return invert_rigid(pose_after) @ pose_before


@dataclass
class SlipVerdict:
    """What one checkpoint says of the jumps before it: ``predicted_mm`` (the slip's error at this pinhole, mm),
    ``largest_mm`` and ``largest_at`` (its largest error over the frame's pinholes, and where), ``statistic``
    (``s``) and ``separation`` (``|d|_C``) of the test, ``verdict`` (``confirmed``, ``open``, ``ruled_out``,
    ``neither``),
    ``fails`` (the checkpoint fails by it) and ``since_s`` (the first jump's time, s)."""

    predicted_mm: float
    largest_mm: float
    largest_at: str
    statistic: float
    separation: float
    verdict: str
    fails: bool
    since_s: float

    def to_json(self) -> dict[str, Any]:
        return {"since_s": round(self.since_s, 4), "predicted_mm": round(self.predicted_mm, 4),
                "largest_mm": round(self.largest_mm, 4), "largest_at": self.largest_at,
                "statistic": round(self.statistic, 3), "separation": round(self.separation, 3),
                "verdict": self.verdict, "fails": bool(self.fails), "false_alarm": SLIP_FALSE_ALARM}

    def describe(self) -> str:
        if self.verdict == RULED_OUT:
            return f"the reference jump at {self.since_s:.2f} s was not a slip (the frame moved as a whole)"
        if self.verdict == NEITHER:
            return (f"the error here lies between none and the {self.predicted_mm:.2f} mm a slip of the reference at "
                    f"{self.since_s:.2f} s would make: neither fits, the slip test is dropped")
        if self.verdict == CONFIRMED:
            what = "this checkpoint confirms a slip of the reference"
        elif self.fails:
            what = "a slip of the reference confirmed before stands (this checkpoint does not rule it out)"
        else:
            what = "this checkpoint leaves open a slip of the reference"
        text = (f"{what} at {self.since_s:.2f} s (predicted error {self.predicted_mm:.2f} mm here, up to "
                f"{self.largest_mm:.2f} mm at {self.largest_at})")
        return text + (": register again, or rest the probe where the slip would show" if self.fails else "")


class SlipWatch:
    """The jumps since the registration as a slip hypothesis, judged checkpoint by checkpoint (module docstring).

    ``reference_to_image`` (4x4): the registration; ``pinholes_image`` (M, 3, LPS mm) and ``ids`` (M,): the
    frame's pinholes, where the slip's largest error is looked for; ``limit_mm``: the checkpoint limit; ``dof``: the
    degrees of freedom the checkpoints' covariance was estimated from."""

    def __init__(self, reference_to_image: np.ndarray, pinholes_image: np.ndarray, ids: list[str],
                 limit_mm: float, dof: float = float("inf"), false_alarm: float = SLIP_FALSE_ALARM) -> None:
        from scipy.special import ndtri, stdtrit

        self.reference_to_image = np.asarray(reference_to_image, dtype=float)
        self.pinholes_image = np.asarray(pinholes_image, dtype=float).reshape(-1, 3)
        self.ids = list(ids)
        self.limit_mm = float(limit_mm)
        self.z = float(ndtri(1.0 - false_alarm) if not np.isfinite(dof) or dof > 1e6
                       else stdtrit(dof, 1.0 - false_alarm))
        self.suspect: np.ndarray | None = None  # ImageToImage: where a point is navigated to if the jumps slipped
        self.since_s = float("nan")
        self.confirmed = False

    def add_jump(self, time_s: float, reference_before_to_after: np.ndarray | None) -> None:
        """A jump of the reference at ``time_s`` (s) with its ``ReferenceBeforeToReferenceAfter`` (4x4)."""
        if reference_before_to_after is None:
            return
        step = self.reference_to_image @ np.asarray(reference_before_to_after, dtype=float) \
            @ invert_rigid(self.reference_to_image)
        if self.suspect is None:
            self.suspect, self.since_s = step, float(time_s)
        else:
            self.suspect = step @ self.suspect

    def judge(self, offset_mm: np.ndarray, covariance: np.ndarray, index: int) -> SlipVerdict | None:
        """The verdict of a checkpoint at pinhole ``index`` with error ``offset_mm`` (3,, LPS mm) and covariance
        (3, 3, LPS mm^2) when nothing changed; None when no jump is pending or the covariance is not finite."""
        covariance = np.asarray(covariance, dtype=float)
        if self.suspect is None or not np.all(np.isfinite(covariance)):
            return None
        moved = apply_transform(self.suspect, self.pinholes_image) - self.pinholes_image
        sizes = np.linalg.norm(moved, axis=1)
        d = moved[index]
        weighted = np.linalg.solve(covariance, d)
        separation = float(np.sqrt(max(float(d @ weighted), 0.0)))
        statistic = float(weighted @ np.asarray(offset_mm, dtype=float)) / separation if separation > 0 else 0.0
        confirms, rules_out = statistic > self.z, separation - statistic > self.z
        if rules_out:
            verdict = NEITHER if confirms else RULED_OUT
        elif confirms:
            verdict = CONFIRMED
            self.confirmed = True
        else:
            verdict = OPEN
        largest = int(np.argmax(sizes))
        result = SlipVerdict(float(sizes[index]), float(sizes[largest]), self.ids[largest], statistic, separation,
                             verdict, self.confirmed and not rules_out and float(sizes[largest]) > self.limit_mm,
                             self.since_s)
        if rules_out:
            self.suspect, self.confirmed, self.since_s = None, False, float("nan")
        return result
