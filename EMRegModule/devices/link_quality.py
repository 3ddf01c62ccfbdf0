"""Tracker-agnostic guards of the live path: a link-quality monitor and a jump test.

A serial line without checksums (the trakSTAR's RS-232 protocol; the Aurora's CRC catches more, but not
everything) lets some corrupted records through framing. Two guards sit between any tracker driver and
what EMReg publishes or records:

- :class:`LinkQualityMonitor`: the fraction of records that failed (framing, value plausibility, the
  jump test) over a sliding window of the last ``window`` records. Above ``threshold`` it raises an
  alarm: the watchdog stops publishing (STATUS not OK) until the fraction has fallen to
  ``clear_fraction`` over a full window again (hysteresis, so a flaky link does not flicker). Until
  ``min_records`` records have been judged the link counts as not yet known (nothing is published):
  a bad line is caught before its first pose goes out. A driver reports its cumulative counts of
  accepted and rejected records (``update(accepted, rejected)``); the jump test adds its own
  rejections (``reject_accepted()``).
- :class:`JumpFilter`: per sensor, a pose that moved further than a hand can move it since the last
  accepted pose of that sensor (``max_speed_mm_s`` x elapsed time + ``noise_mm``; rotations likewise
  with ``max_angular_speed_deg_s`` + ``noise_deg``) is rejected as a corrupted record that passed
  framing. A sensor's first pose - and the first after a rejection streak - is only accepted when the
  next one agrees with it (``confirm``), so a single corrupted record can never become the anchor.

The defaults come from measurements on the simulator (``scripts/measure_link_quality.py``, real pty,
real driver, 80 Hz, four ports in group mode; the table is on the manual's page docs/guide/live.md): on a clean
link no record failed and the built-in scene's probe moved at most 0.42 m/s and deviated at most 0.7 mm
from the constant-velocity prediction; data-bit corruption of 0.2 % / 1 % / 5 % of the bytes made 0.6 % /
4.5 % / 22 % of the records fail (dropped bytes: 3 % / 12 % / 51 % at 0.2 % / 1 % / 5 %). A threshold of
1 % therefore never fires on a clean link, fires at once at 1 % corruption and intermittently at 0.2 %.
Below it, single corrupted records whose error stays under the jump limit (about 5 mm at 80 Hz) can
pass: a protocol without checksums cannot do better per record.
"""

from __future__ import annotations

from collections import deque
from dataclasses import dataclass

import numpy as np

#: Fraction of failed records (over the window) above which publishing pauses.
DEFAULT_THRESHOLD = 0.01
#: The alarm clears when the fraction over a full window is at most this (one record in 500).
DEFAULT_CLEAR_FRACTION = 0.002
#: Records in the sliding window (about 1.6 s of four ports at 80 Hz).
DEFAULT_WINDOW = 500
#: Records judged before the link is trusted at all (ten cycles of four ports: 0.125 s at 80 Hz).
DEFAULT_MIN_RECORDS = 40

#: Fastest credible hand motion of a sensor (mm/s), and the noise allowance per step (mm).
DEFAULT_MAX_SPEED_MM_S = 2000.0
DEFAULT_NOISE_MM = 2.0
#: Largest credible acceleration of a hand-held sensor (mm/s^2): a pose may deviate from the one
#: predicted at constant velocity by ``noise_mm + max_accel * dt^2`` (5.1 mm at 80 Hz).
DEFAULT_MAX_ACCEL_MM_S2 = 20000.0
#: Fastest credible rotation (degrees/s), and the noise allowance per step (degrees).
DEFAULT_MAX_ANGULAR_SPEED_DEG_S = 1500.0
DEFAULT_NOISE_DEG = 5.0


@dataclass(frozen=True)
class LinkState:
    """What the monitor says: ``ok`` (publish) or not, the failed fraction and a one-line reason."""

    ok: bool
    fraction: float
    judged: int
    message: str


class LinkQualityMonitor:
    """Sliding-window rejection rate of a tracker link with an alarm and hysteresis (see module docstring)."""

    def __init__(self, threshold: float = DEFAULT_THRESHOLD, clear_fraction: float = DEFAULT_CLEAR_FRACTION,
                 window: int = DEFAULT_WINDOW, min_records: int = DEFAULT_MIN_RECORDS) -> None:
        if not 0 <= clear_fraction <= threshold < 1:
            raise ValueError("need 0 <= clear_fraction <= threshold < 1")
        self.threshold = threshold
        self.clear_fraction = clear_fraction
        self.window = int(window)
        self.min_records = min(int(min_records), self.window)
        self._outcomes: deque[bool] = deque(maxlen=self.window)  # True = failed
        self._failed_in_window = 0
        self._accepted_total = 0
        self._rejected_total = 0
        self.alarm = False
        self.alarms = 0  # times the alarm was raised
        self.max_fraction = 0.0

    def _push(self, failed: bool) -> None:
        if len(self._outcomes) == self._outcomes.maxlen and self._outcomes[0]:
            self._failed_in_window -= 1
        self._outcomes.append(failed)
        self._failed_in_window += int(failed)

    def update(self, accepted_total: int, rejected_total: int) -> None:
        """Take a driver's cumulative counts of accepted and rejected records (new ones enter the window)."""
        new_accepted = max(0, int(accepted_total) - self._accepted_total)
        new_rejected = max(0, int(rejected_total) - self._rejected_total)
        self._accepted_total = max(self._accepted_total, int(accepted_total))
        self._rejected_total = max(self._rejected_total, int(rejected_total))
        # interleave, so that a burst read in one chunk does not sort good and bad records
        total = new_accepted + new_rejected
        if total > self.window:
            scale = self.window / total
            new_accepted, new_rejected = round(new_accepted * scale), round(new_rejected * scale)
            total = new_accepted + new_rejected
        for k in range(total):
            self._push(k * new_rejected // max(total, 1) != (k + 1) * new_rejected // max(total, 1))
        self._judge()

    def record(self, failed: bool) -> None:
        """One record's outcome, for drivers that report record by record."""
        self._push(bool(failed))
        self._judge()

    def reject_accepted(self) -> None:
        """A record the driver accepted was rejected later (the jump test): count it as failed."""
        for k in range(len(self._outcomes) - 1, -1, -1):
            if not self._outcomes[k]:
                self._outcomes[k] = True
                self._failed_in_window += 1
                break
        else:
            self._push(True)
        self._judge()

    @property
    def fraction(self) -> float:
        return self._failed_in_window / len(self._outcomes) if self._outcomes else 0.0

    def _judge(self) -> None:
        fraction = self.fraction
        if len(self._outcomes) >= self.min_records:
            self.max_fraction = max(self.max_fraction, fraction)
        if not self.alarm and len(self._outcomes) >= self.min_records and fraction > self.threshold:
            self.alarm = True
            self.alarms += 1
        elif self.alarm and len(self._outcomes) == self.window and fraction <= self.clear_fraction:
            self.alarm = False

    def state(self) -> LinkState:
        """The monitor's verdict now."""
        judged = len(self._outcomes)
        fraction = self.fraction
        if judged < self.min_records:
            return LinkState(False, fraction, judged, f"judging the tracker link ({judged} of {self.min_records} "
                                                      "records)")
        if self.alarm:
            return LinkState(False, fraction, judged,
                             f"tracker link corrupt: {100 * fraction:.0f} % of the last {judged} records failed "
                             f"(limit {100 * self.threshold:g} %; publishing resumes at {100 * self.clear_fraction:g}"
                             " %)")
        return LinkState(True, fraction, judged, f"tracker link good ({100 * fraction:.1f} % of records failed)")


#: :attr:`JumpFilter.outcome` of the last :meth:`JumpFilter.check`: the pose follows the sensor's anchor (a
#: candidate waiting for confirmation, if any, was an outlier); it confirmed the waiting candidate (whose poses
#: are therefore genuine too); it starts a new candidate (an earlier one, if any, is given up); it adds to the
#: waiting candidate (``confirm`` > 1); its numbers are not finite.
ANCHORED, CONFIRMED, NEW_CANDIDATE, MORE_CANDIDATE, NOT_FINITE = "anchored", "confirmed", "new", "more", "not finite"


class JumpFilter:
    """Rejects poses that move faster than a hand can (per sensor; see module docstring).

    ``check(sensor, time_s, position_mm, rotation)`` returns True when the pose may be used; ``outcome`` then
    says why (one of :data:`ANCHORED`, :data:`CONFIRMED`, :data:`NEW_CANDIDATE`, :data:`MORE_CANDIDATE`,
    :data:`NOT_FINITE`).
    """

    def __init__(self, max_speed_mm_s: float = DEFAULT_MAX_SPEED_MM_S, noise_mm: float = DEFAULT_NOISE_MM,
                 max_angular_speed_deg_s: float = DEFAULT_MAX_ANGULAR_SPEED_DEG_S,
                 noise_deg: float = DEFAULT_NOISE_DEG, confirm: int = 1,
                 max_accel_mm_s2: float = DEFAULT_MAX_ACCEL_MM_S2) -> None:
        self.max_speed_mm_s = max_speed_mm_s
        self.max_accel_mm_s2 = max_accel_mm_s2
        self._velocity: dict[int, np.ndarray] = {}
        self.max_deviation_seen_mm = 0.0  # largest accepted deviation from the constant-velocity prediction
        self.noise_mm = noise_mm
        self.max_angular_speed_deg_s = max_angular_speed_deg_s
        self.noise_deg = noise_deg
        self.confirm = confirm
        self._anchor: dict[int, tuple[float, np.ndarray, np.ndarray]] = {}
        self._candidate: dict[int, tuple[float, np.ndarray, np.ndarray, int]] = {}
        self.rejected = 0
        self.accepted = 0
        self.max_speed_seen_mm_s = 0.0
        self.outcome = NOT_FINITE

    def anchored(self, sensor: int) -> bool:
        """True when the sensor has an accepted pose to compare the next one with."""
        return sensor in self._anchor

    def reset(self, sensor: int | None = None) -> None:
        """Forget the anchors (all sensors, or one): the next poses must confirm each other again."""
        if sensor is None:
            self._anchor.clear()
            self._candidate.clear()
            self._velocity.clear()
        else:
            self._anchor.pop(sensor, None)
            self._candidate.pop(sensor, None)
            self._velocity.pop(sensor, None)

    def _close(self, a: tuple, time_s: float, position: np.ndarray, rotation: np.ndarray,
               velocity: np.ndarray | None = None) -> bool:
        dt = abs(time_s - a[0])
        distance = float(np.linalg.norm(position - a[1]))
        if distance > self.noise_mm + self.max_speed_mm_s * dt:
            return False
        if velocity is not None:
            deviation = float(np.linalg.norm(position - (a[1] + velocity * (time_s - a[0]))))
            if deviation > self.noise_mm + self.max_accel_mm_s2 * dt * dt:
                return False
            self._last_deviation = deviation
        if rotation is not None and a[2] is not None and np.all(np.isfinite(rotation)) and np.all(np.isfinite(a[2])):
            cos_angle = (np.trace(a[2].T @ rotation) - 1.0) / 2.0
            angle = float(np.degrees(np.arccos(np.clip(cos_angle, -1.0, 1.0))))
            if angle > self.noise_deg + self.max_angular_speed_deg_s * dt:
                return False
        return True

    def check(self, sensor: int, time_s: float, position_mm: np.ndarray, rotation: np.ndarray | None) -> bool:
        """True when the pose is credible after the sensor's last accepted one (then it becomes the anchor)."""
        position = np.asarray(position_mm, dtype=float)
        self.outcome = NOT_FINITE
        if not np.all(np.isfinite(position)):
            return False
        anchor = self._anchor.get(sensor)
        self._last_deviation = 0.0
        if anchor is not None and self._close(anchor, time_s, position, rotation, self._velocity.get(sensor)):
            self.max_deviation_seen_mm = max(self.max_deviation_seen_mm, self._last_deviation)
            if time_s > anchor[0]:
                velocity = (position - anchor[1]) / (time_s - anchor[0])
                self.max_speed_seen_mm_s = max(self.max_speed_seen_mm_s, float(np.linalg.norm(velocity)))
                self._velocity[sensor] = velocity
            self._anchor[sensor] = (time_s, position, rotation)
            self._candidate.pop(sensor, None)
            self.accepted += 1
            self.outcome = ANCHORED
            return True
        # no anchor, or a jump: accept only once ``confirm`` later poses agree with this new place
        candidate = self._candidate.get(sensor)
        if candidate is not None and self._close(candidate, time_s, position, rotation):
            count = candidate[3] + 1
            if count >= self.confirm:
                self._anchor[sensor] = (time_s, position, rotation)
                self._velocity.pop(sensor, None)  # a new anchor: no velocity to predict with yet
                self._candidate.pop(sensor, None)
                self.accepted += 1
                self.outcome = CONFIRMED
                return True
            self._candidate[sensor] = (time_s, position, rotation, count)
            self.outcome = MORE_CANDIDATE
        else:
            self._candidate[sensor] = (time_s, position, rotation, 0)
            self.outcome = NEW_CANDIDATE
        if anchor is not None:
            self.rejected += 1
        return False


class LinkGuard:
    """The monitor and the jump test for one tracker link (one per opened device).

    ``counts``: a callable giving the driver's cumulative (accepted, rejected) record counts. Use
    :meth:`admit` on every sample before it is published or recorded and :meth:`state` for the
    watchdog.
    """

    def __init__(self, counts, monitor: LinkQualityMonitor | None = None, jump: JumpFilter | None = None,
                 period_s: float | None = None) -> None:
        self.counts = counts
        self.monitor = monitor or LinkQualityMonitor()
        self.jump = jump or JumpFilter()
        #: the tracker's nominal sample period: the jump test times poses by their measurement cycle
        #: (``frame`` x period), not by when the bytes were read (reads jitter by milliseconds)
        self.period_s = period_s

    def refresh(self) -> None:
        """Take the driver's newest counts into the window."""
        accepted, rejected = self.counts()
        self.monitor.update(accepted, rejected)

    def admit(self, sample) -> bool:
        """True when a sample (``SensorSample``) may be used: counts refreshed, its pose credible."""
        self.refresh()
        if not sample.valid:
            return True  # the watchdog deals with missing / out-of-range sensors
        anchored = self.jump.anchored(sample.sensor)
        moment = sample.frame * self.period_s if self.period_s and sample.frame >= 0 else sample.time_s
        if self.jump.check(sample.sensor, moment, sample.position_mm, sample.rotation):
            return True
        if anchored:  # a jump (not a first pose waiting for confirmation): a corrupted record
            self.monitor.reject_accepted()
        return False

    def state(self) -> LinkState:
        self.refresh()
        return self.monitor.state()

    def summary(self) -> str:
        """The guard's figures in one line: its verdict now, the worst failed share of a window, the alarms and
        the poses the jump test refused."""
        monitor = self.monitor
        return (f"link guard: {self.state().message}; at worst {100 * monitor.max_fraction:.0f} % of "
                f"{monitor.window} records failed, {monitor.alarms} alarm(s), {self.jump.rejected} pose(s) "
                "refused by the jump test")


class HoldBack:
    """Samples passed on in arrival order once a :class:`LinkGuard` has judged them, for a recording that must
    not lose what a clean link delivered.

    Publishing live, a pose the guard cannot judge yet is withheld for good; a recording can wait for the
    verdict instead. So samples are held, in order, while the link is still being judged (its first
    ``min_records`` records) and while a pose waits for the jump test's confirmation (a sensor's first pose,
    the first after a jump); they are passed on (``emit(sample)``) once the link is judged good and the next
    pose of that sensor confirmed them, and dropped when the jump test gives them up (the next pose agrees with
    the old place: an outlier), when the next sample of the sensor has no pose or ``max_queued`` samples of
    other sensors queue behind it (its sensor stopped sending), or when the link alarm goes off (everything
    held then is dropped too). Samples without a pose (sensor not attached, out of range) pass as
    they are, for the writer to judge. Nothing the guard refuses is ever passed on; what is still held at
    :meth:`close` is dropped.
    """

    def __init__(self, guard: LinkGuard, emit) -> None:
        self.guard = guard
        self.emit = emit
        self._queue: deque[list] = deque()  # [sample, ready, dropped] in arrival order
        self._held: dict[int, list[list]] = {}  # sensor -> its entries waiting for the jump test
        self.dropped = 0
        #: samples queued behind a pose waiting for confirmation before it is given up: twice the records
        #: the link needs to be judged
        self.max_queued = 2 * guard.monitor.min_records

    def push(self, sample) -> LinkState:
        """Judge one sample, pass on what is ready; returns the link's state after it."""
        admitted = self.guard.admit(sample)
        state = self.guard.state()
        if self.guard.monitor.alarm:  # a corrupt link: nothing held, nothing new
            self._drop_all()
            return state
        entry = [sample, True, False]
        if sample.valid:
            outcome = self.guard.jump.outcome
            held = self._held.pop(sample.sensor, [])
            if outcome == MORE_CANDIDATE:
                self._held[sample.sensor] = held
            else:
                for waiting in held:
                    waiting[1 if outcome == CONFIRMED else 2] = True
                self.dropped += 0 if outcome == CONFIRMED else len(held)
            if outcome in (NEW_CANDIDATE, MORE_CANDIDATE):
                entry[1] = False
                self._held.setdefault(sample.sensor, []).append(entry)
            elif not admitted:
                return state
        else:
            for waiting in self._held.pop(sample.sensor, []):
                waiting[2] = True
                self.dropped += 1
        self._queue.append(entry)
        self._pop_dropped()
        while len(self._queue) > self.max_queued and not self._queue[0][1]:  # a held pose blocks the queue
            for waiting in self._held.pop(self._queue[0][0].sensor, []):  # its sensor has sent nothing since
                waiting[2] = True
                self.dropped += 1
            self._pop_dropped()
        if state.ok:
            self._flush()
        return state

    def _pop_dropped(self) -> None:
        while self._queue and self._queue[0][2]:
            self._queue.popleft()

    def _flush(self) -> None:
        while self._queue and (self._queue[0][1] or self._queue[0][2]):
            sample, _, dropped = self._queue.popleft()
            if not dropped:
                self.emit(sample)

    def _drop_all(self) -> None:
        self.dropped += sum(1 for entry in self._queue if not entry[2])
        self._queue.clear()
        self._held.clear()

    def close(self) -> None:
        """Pass on what is ready (the link judged good), drop what still waits."""
        if self.guard.state().ok:
            self._flush()
        self._drop_all()


def guard_for(source) -> LinkGuard | None:
    """A :class:`LinkGuard` for sources with a raw tracker link (``source.link_counts``), else None.

    Replays and OpenIGTLink (TCP, checksummed) deliver what was recorded or served: no guard.
    """
    counts = getattr(source, "link_counts", None)
    return LinkGuard(counts, period_s=getattr(source, "period_s", None)) if callable(counts) else None
