"""Live navigation: every tracker frame -> ``ProbeToImage`` over OpenIGTLink, guarded by a watchdog.

For each measurement cycle with both sensors (paper Eq. 12)::

    ProbeToImage = ReferenceToImage @ inv(ReferenceToTracker) @ ProbeToTracker

``ProbeToImage`` maps probe-sensor coordinates into the CT's LPS space. 3D Slicer's OpenIGTLinkIF
applies a received TRANSFORM as is, in Slicer's RAS world, so the message carries
``ProbeToRAS = LPS_TO_RAS @ ProbeToImage`` (only the image side changes: the probe frame is the
sensor's own frame, not an LPS one, so conjugating both sides would mirror the tool's own axes;
the position - the last column - is the same either way). ``navigation.csv`` keeps LPS, as the
offline ``emreg navigate`` writes it.

The :class:`Watchdog` withholds poses - and says why, in an OpenIGTLink STATUS message (device
name ``Navigation``; a name of its own, because pyigtl clients keep one message per device name
and a STATUS named ``ProbeToImage`` would displace the pose) and on the terminal - when data
are stale (no sample within ``stale_periods`` sample periods), when the reference or probe
sensor is missing, out of range or of bad quality; it resumes by itself when good data return.
Poses come only from samples that passed the driver's framing checks.
"""

from __future__ import annotations

import dataclasses
import sys
import threading
import time
from collections import deque
from collections.abc import Callable
from dataclasses import dataclass
from typing import TextIO

import numpy as np

from ..core.checkpoints import Checkpoint
from ..core.frames import LPS_TO_RAS
from ..core.navigation import probe_to_image as probe_to_image_pose
from ..devices import igtl_status as st
from ..devices.igtl_server import TRANSFORM_INVALID, TRANSFORM_OK
from ..devices.igtl_status import StatusMessage
from ..devices.port_check import PORT_REASONS, PortRoleCheck
from ..devices.samples import (
    FLAG_MISSING,
    FLAG_OUT_OF_VOLUME,
    FLAG_PARTLY_OUT_OF_VOLUME,
    STATUS_NOT_ATTACHED,
    STATUS_OUT_OF_RANGE,
    SensorSample,
)
from ..names import DEFAULT_PROBE_PORT, DEFAULT_REFERENCE_PORT

#: Device name of the STATUS messages that carry checkpoint results and reference jumps (live navigation).
CHECKPOINT_STATUS_NAME = "Checkpoint"
#: Device name of the STATUS that says the registration's predicted error is not to be trusted, and why (its
#: ``prediction_trust`` reasons), sent at the start and once a second (a client that connects later learns it).
TRUST_STATUS_NAME = "PredictionTrust"

#: Status of a sample whose pose the link guard's jump test refused (moved faster than a hand can).
STATUS_REJECTED = "rejected"

#: Default worst acceptable quality number (0 = best). The trakSTAR's METAL byte runs 0..127 and a
#: clean field reads a few units; the simulated recordings mark wild samples with 40..250 (choice).
DEFAULT_MAX_QUALITY = 20.0


@dataclass(frozen=True)
class Verdict:
    """The watchdog's judgement: publish (``ok``) or not, and why."""

    ok: bool
    reason: str  # ok, no_data, stale, reference_missing, probe_missing, out_of_range, bad_quality
    message: str
    code: int  # OpenIGTLink status code
    error_name: str

    @property
    def key(self) -> tuple[str, str]:
        return (self.reason, self.error_name)


OK = Verdict(True, "ok", "tracking data good", st.STATUS_OK, "OK")

#: How an out-of-range sensor is named (terminal line, STATUS message and error name) by its tracker's flag.
_OUT_OF_RANGE = {
    None: ("out of the tracker's range", "OutOfRange"),
    FLAG_MISSING: ("missing: the tracker found no solution (MISSING)", "ToolMissing"),
    FLAG_OUT_OF_VOLUME: ("out of the tracker's measurement volume", "OutOfVolume"),
    FLAG_PARTLY_OUT_OF_VOLUME: ("partly out of the tracker's measurement volume: accuracy not vouched for",
                                "PartlyOutOfVolume"),
}


class Watchdog:
    """Decides from the latest samples whether a pose may be published (times in monotonic seconds).

    ``period_s``: nominal time between samples of a sensor; None estimates it from the arrivals.
    ``max_quality``: worst acceptable quality number (None: not checked; NaN quality passes).
    """

    def __init__(self, reference_sensor: int = DEFAULT_REFERENCE_PORT, probe_sensor: int = DEFAULT_PROBE_PORT,
                 period_s: float | None = None, stale_periods: float = 3.0,
                 max_quality: float | None = DEFAULT_MAX_QUALITY, link=None) -> None:
        self.reference_sensor = reference_sensor
        self.link = link  # a link_quality.LinkGuard for a raw tracker link, or None
        self.lost: str | None = None  # set when the device is gone (no more samples will come)
        self.port_check = None  # a port_check.PortRoleCheck while the sensor ports are judged, or None
        self.probe_sensor = probe_sensor
        self.nominal_period_s = period_s
        self.stale_periods = stale_periods
        self.max_quality = max_quality
        self._last: dict[int, tuple[SensorSample, float]] = {}
        self._estimate: float | None = None
        self._first_s: float | None = None

    @property
    def period_s(self) -> float:
        """The sample period used for staleness (nominal, else estimated, else 50 ms)."""
        return self.nominal_period_s or self._estimate or 0.05

    @property
    def stale_after_s(self) -> float:
        return self.stale_periods * self.period_s

    def observe(self, sample: SensorSample, now_s: float) -> None:
        """Record that ``sample`` arrived at ``now_s``."""
        previous = self._last.get(sample.sensor)
        if previous is not None and self.nominal_period_s is None and sample.frame != previous[0].frame:
            step = now_s - previous[1]
            if step > 0:
                self._estimate = step if self._estimate is None else 0.9 * self._estimate + 0.1 * step
        self._last[sample.sensor] = (sample, now_s)
        if self._first_s is None:
            self._first_s = now_s

    def evaluate(self, now_s: float) -> Verdict:
        """The verdict at ``now_s``."""
        if self.lost is not None:
            return Verdict(False, "lost", self.lost, st.STATUS_TIME_OUT, "TrackerLost")
        if not self._last:
            return Verdict(False, "no_data", "no tracker data yet", st.STATUS_NOT_READY, "NoData")
        if self.link is not None:
            link = self.link.state()
            if not link.ok:
                judging = link.judged < self.link.monitor.min_records
                return Verdict(False, "no_data" if judging else "link", link.message,
                               st.STATUS_NOT_READY if judging else st.STATUS_CHECKSUM_ERROR,
                               "NoData" if judging else "LinkCorrupt")
        limit = self.stale_after_s
        newest = max(t for _, t in self._last.values())
        if now_s - newest > limit:
            return Verdict(False, "stale", f"no tracker sample for {1000 * (now_s - newest):.0f} ms "
                           f"(limit {self.stale_periods:g} sample periods = {1000 * limit:.0f} ms)",
                           st.STATUS_TIME_OUT, "Stale")
        for role, sensor, reason in (("reference", self.reference_sensor, "reference_missing"),
                                     ("probe", self.probe_sensor, "probe_missing")):
            entry = self._last.get(sensor)
            name = f"{role.capitalize()}Missing"
            if entry is None:
                if now_s - self._first_s <= limit:  # start-up: the other sensor's first record is on its way
                    return Verdict(False, "no_data", "waiting for both sensors", st.STATUS_NOT_READY, "NoData")
                return Verdict(False, reason, f"{role} sensor (port {sensor}) missing: no sample from it",
                               st.STATUS_NOT_PRESENT, name)
            sample, t = entry
            if now_s - t > limit:
                return Verdict(False, reason, f"{role} sensor (port {sensor}) missing: no sample for "
                               f"{1000 * (now_s - t):.0f} ms", st.STATUS_NOT_PRESENT, name)
            if sample.status == STATUS_NOT_ATTACHED:
                return Verdict(False, reason, f"{role} sensor (port {sensor}) missing: not attached",
                               st.STATUS_NOT_PRESENT, name)
        for role, sensor in (("reference", self.reference_sensor), ("probe", self.probe_sensor)):
            sample = self._last[sensor][0]
            if sample.status == STATUS_OUT_OF_RANGE:
                what, name = _OUT_OF_RANGE.get(sample.extra.get("flag"), _OUT_OF_RANGE[None])
                return Verdict(False, "out_of_range", f"{role} sensor (port {sensor}) {what}", st.STATUS_OVERFLOW, name)
        if self.max_quality is not None:
            for role, sensor in (("reference", self.reference_sensor), ("probe", self.probe_sensor)):
                quality = self._last[sensor][0].quality
                if not np.isnan(quality) and quality > self.max_quality:
                    return Verdict(False, "bad_quality", f"{role} sensor (port {sensor}) quality {quality:g} "
                                   f"worse than {self.max_quality:g}", st.STATUS_UNKNOWN_ERROR, "BadQuality")
        ports = None if self.port_check is None else self.port_check.verdict()
        if ports is not None:  # last: the ports are judged only from cycles every other check passed
            return Verdict(False, ports.reason, ports.message, ports.code, ports.error_name)
        return OK


class _Announcer:
    """Sends a STATUS and prints one terminal line when the verdict changes (and re-sends STATUS each second)."""

    def __init__(self, server, device_name: str, out: TextIO | None, what: str,
                 on_paused: Callable[[Verdict], None] | None = None) -> None:
        self.server = server
        self.device_name = device_name
        self.what = what
        self.out = out
        self.current: Verdict | None = None
        self._last_sent = 0.0
        self.changes: list[Verdict] = []
        #: called with a not-OK verdict when it starts and with each STATUS re-sent (the transforms' INVALID)
        self.on_paused = on_paused

    def update(self, verdict: Verdict, now_s: float) -> None:
        changed = self.current is None or verdict.key != self.current.key
        if changed:
            self.changes.append(verdict)
            quiet = verdict.reason == "no_data" or (verdict.ok and (self.current is None or
                                                                    self.current.reason == "no_data"))
            if self.out is not None and not quiet:
                if verdict.ok:
                    line = f"[emreg] watchdog: publishing {self.what} again ({verdict.message})"
                else:
                    line = f"[emreg] watchdog: not publishing {self.what}: {verdict.message}"
                print(line, file=self.out, flush=True)
            self.current = verdict
        if self.server is not None and (changed or now_s - self._last_sent >= 1.0):
            self._last_sent = now_s
            self.server.send(StatusMessage(verdict.code, 0, verdict.error_name, verdict.message,
                                           device_name=self.device_name))
            if not verdict.ok and self.on_paused is not None:
                self.on_paused(verdict)


class _WatchedPublisher:
    """What a publisher guarded by a :class:`Watchdog` shares: re-evaluation between samples.

    Subclasses set ``watchdog``, ``announcer`` and ``_lock``.
    """

    watchdog: Watchdog
    announcer: _Announcer
    _lock: threading.Lock
    #: the clock samples are judged by (monotonic seconds); a replay on the recording's own clock sets another
    clock: Callable[[], float] = staticmethod(time.monotonic)

    def tick(self) -> Verdict:
        """Re-evaluate without a new sample (staleness); returns the verdict."""
        now = self.clock()
        with self._lock:
            verdict = self.watchdog.evaluate(now)
            self.announcer.update(verdict, now)
            return verdict

    def device_lost(self, message: str) -> Verdict:
        """The device is gone: publish a not-OK STATUS now (clients must not keep the last OK)."""
        now = self.clock()
        with self._lock:
            self.watchdog.lost = message
            verdict = self.watchdog.evaluate(now)
            self.announcer.update(verdict, now)
            return verdict

    def device_back(self, link=None) -> None:
        """A new connection to the device: a fresh link guard, the watchdog judges again from scratch."""
        with self._lock:
            self.watchdog.lost = None
            self.watchdog.link = link
            self.watchdog._last.clear()
            self.watchdog._first_s = None

    def _admit(self, sample: SensorSample) -> SensorSample:
        """The sample, or a copy marked rejected when the link guard's jump test refuses its pose."""
        link = self.watchdog.link
        if link is None or link.admit(sample):
            return sample
        self.jump_rejected += 1
        return dataclasses.replace(sample, status=STATUS_REJECTED)


class LiveNavigator(_WatchedPublisher):
    """Turns sensor samples into published ``ProbeToImage`` poses (see module docstring).

    Feed it with ``on_sample`` (any thread) and call ``tick()`` regularly (it notices staleness
    when no samples come at all). ``server``: an :class:`~.igtl_server.IGTLServer` or None;
    ``writer``: a :class:`~.writers.NavigationWriter` or None. ``check_ports``: judge the sensor ports
    from the first cycles before publishing (:mod:`.port_check`; for raw tracker links). ``tip_to_probe`` (4x4, mm):
    a tool on the probe port, whose tip is then published (``TipToImage = ProbeToImage @ TipToProbe``, under
    ``device_name``) and written; the checkpoints (``trust``) still watch the sensor's own pose. ``guide``: a
    :class:`~.guide.LiveGuide` (a plan): each pose's guidance numbers go into ``navigation.csv`` and, at most 20 times
    a second, into a STRING ``Guidance``, and the plan is published once a second. ``prediction_trust``: the
    registration's ``prediction_trust`` block; when it is not trusted, its reasons go out in a STATUS
    ``PredictionTrust`` (at the start and once a second) and on the terminal. ``clock``: what samples are judged by
    (monotonic seconds; a replay on a recording's own clock gives another).
    """

    def __init__(self, reference_to_image: np.ndarray, reference_sensor: int = DEFAULT_REFERENCE_PORT,
                 probe_sensor: int = DEFAULT_PROBE_PORT, server=None, writer=None, period_s: float | None = None,
                 stale_periods: float = 3.0, max_quality: float | None = DEFAULT_MAX_QUALITY,
                 out: TextIO | None = sys.stderr, device_name: str = "ProbeToImage", status_name: str = "Navigation",
                 link=None, check_ports: bool = False, trust=None, tip_to_probe: np.ndarray | None = None,
                 guide=None, prediction_trust: dict | None = None,
                 clock: Callable[[], float] = time.monotonic) -> None:
        self.clock = clock
        self.reference_to_image = np.asarray(reference_to_image, dtype=float)
        self.tip_to_probe = None if tip_to_probe is None else np.asarray(tip_to_probe, dtype=float)
        self.guide = guide
        self.reference_sensor = reference_sensor
        self.probe_sensor = probe_sensor
        self.server = server
        self.writer = writer
        self.device_name = device_name
        self.watchdog = Watchdog(reference_sensor, probe_sensor, period_s, stale_periods, max_quality, link)
        if check_ports:
            self.watchdog.port_check = PortRoleCheck(reference_sensor, probe_sensor)
        #: why the ports are wrong (the port check's latched verdict): live navigation ends with exit 2
        self.fatal: str | None = None
        self.announcer = _Announcer(server, status_name, out, device_name, on_paused=self._send_invalid)
        self.jump_rejected = 0
        self._latest: dict[int, SensorSample] = {}
        self._done_frame: int | None = None
        self._lock = threading.Lock()
        self.published = 0
        self.withheld = 0
        self.frames = 0
        #: (frame, received_ns of the frame's later sensor record, send-complete ns) per published pose
        self.latencies: deque[tuple[int, int, int]] = deque(maxlen=200_000)
        self.last_probe_to_image: np.ndarray | None = None
        self.invalid_sent = 0  # TRANSFORMs sent with TransformStatus INVALID (poses withheld)
        #: frames handled at most (``--max-samples``); later samples are ignored (None: no limit)
        self.max_frames: int | None = None
        #: checkpoints and reference jumps (a :class:`EMRegModule.core.checkpoints.TrustMonitor`, or None): after a
        # failed
        #: checkpoint the poses go out with TransformStatus INVALID until one passes; each result is a STATUS
        #: ``Checkpoint`` (sticky: a client that connects later learns it) and one terminal line
        self.trust = trust
        self.out = out
        reasons = [] if prediction_trust is None or prediction_trust.get("trusted", True) else \
            [str(r) for r in prediction_trust.get("reasons", [])]
        #: why the registration's predicted error is not to be trusted (empty: it is, or nothing says otherwise)
        self.untrusted = "; ".join(reasons or ([] if prediction_trust is None or prediction_trust.get("trusted", True)
                                               else ["the registration says its predicted error is not trusted"]))
        self._trust_sent: float | None = None
        if self.untrusted and out is not None:
            print(f"[emreg] warning: the predicted error is not to be trusted: {self.untrusted}", file=out, flush=True)
        self._send_prediction_trust(self.clock())

    @property
    def verdict(self) -> Verdict | None:
        return self.announcer.current

    def tick(self) -> Verdict:
        """The watchdog's re-evaluation, and the plan published again when it is due (clients that connect later)."""
        verdict = super().tick()
        with self._lock:
            if self.guide is not None and self.server is not None:
                self.guide.keep_plan_published(self.server)
            self._send_prediction_trust(self.clock())
        return verdict

    def _send_prediction_trust(self, now_s: float) -> None:
        """The STATUS ``PredictionTrust`` with the reasons, when not trusted: now, and again each second."""
        if not self.untrusted or self.server is None:
            return
        if self._trust_sent is None or now_s - self._trust_sent >= 1.0:
            self._trust_sent = now_s
            self.server.send(StatusMessage(st.STATUS_UNKNOWN_ERROR, 0, "PredictionNotTrusted", self.untrusted,
                                           device_name=TRUST_STATUS_NAME))

    def device_back(self, link=None) -> None:
        super().device_back(link)
        with self._lock:  # the new connection numbers its frames from 0 again
            self._latest.clear()
            self._done_frame = None
            if self.watchdog.port_check is not None:  # the sensors may have been plugged anew: judged afresh
                self.watchdog.port_check = PortRoleCheck(self.reference_sensor, self.probe_sensor)

    def on_sample(self, sample: SensorSample) -> None:
        now = self.clock()
        with self._lock:
            if sample.sensor not in (self.reference_sensor, self.probe_sensor):
                self.watchdog.observe(sample, now)
                self.announcer.update(self.watchdog.evaluate(now), now)
                return
            sample = self._admit(sample)
            self.watchdog.observe(sample, now)
            verdict = self.watchdog.evaluate(now)
            self.announcer.update(verdict, now)
            self._latest[sample.sensor] = sample
            reference = self._latest.get(self.reference_sensor)
            probe = self._latest.get(self.probe_sensor)
            if reference is None or probe is None or reference.frame != probe.frame or probe.frame == self._done_frame:
                return
            if self.max_frames is not None and self.frames >= self.max_frames:
                return  # --max-samples reached: the reader may deliver more before the command loop stops it
            self._done_frame = probe.frame
            self.frames += 1
            check = self.watchdog.port_check
            if check is not None and verdict.reason in PORT_REASONS and reference.valid and probe.valid:
                check.add(reference.transform(), probe.transform())  # a cycle every other check passed
                verdict = self.watchdog.evaluate(now)
                self.announcer.update(verdict, now)
                self.fatal = check.fatal
            if not (verdict.ok and reference.valid and probe.valid):
                self.withheld += 1
                self._send_invalid(verdict)
                return
            reference_to_tracker = reference.transform()
            probe_to_image = probe_to_image_pose(self.reference_to_image, reference_to_tracker, probe.transform())
            pose = probe_to_image if self.tip_to_probe is None else probe_to_image @ self.tip_to_probe
            self.last_probe_to_image = pose
            received_ns = max(reference.received_ns, probe.received_ns)
            status = TRANSFORM_OK if self.trust is None or self.trust.valid else TRANSFORM_INVALID
            if self.server is not None:
                stamp = time.time() - (time.monotonic_ns() - received_ns) / 1e9
                sent_ns = self.server.send_transform(self.device_name, LPS_TO_RAS @ pose, stamp, status)
                self.latencies.append((probe.frame, received_ns, sent_ns))
            numbers = None if self.guide is None else self.guide.numbers(pose)
            if self.writer is not None:
                self.writer.write_position(probe.time_s, pose[:3, 3], probe.label, status, numbers)
            self.published += 1
            if self.guide is not None:  # after the send: off the latency path
                if status == TRANSFORM_OK:
                    self.guide.observe(probe.time_s, pose[:3, 3], numbers)
                if self.server is not None:
                    self.guide.publish(self.server, numbers, now)
            if self.trust is not None:  # after the send: off the latency path
                quality = float(np.fmax(reference.quality, probe.quality))
                self._announce_trust(self.trust.observe(probe.time_s, probe_to_image, reference_to_tracker, quality))

    def finish_trust(self) -> None:
        """The stream ended: judge a rest in a pinhole still in progress and announce it."""
        if self.trust is not None:
            with self._lock:
                self._announce_trust(self.trust.flush())

    def _announce_trust(self, events: list) -> None:
        """A STATUS ``Checkpoint`` and a terminal line per checkpoint result or reference jump."""
        for event in events:
            if isinstance(event, Checkpoint):
                text = event.describe(self.trust.settings.max_checkpoint_error_mm)
                code, name = ((st.STATUS_OK, "CheckpointOK") if event.ok else
                              (st.STATUS_UNKNOWN_ERROR, "CheckpointFailed"))
            else:
                text, code, name = event.describe(), st.STATUS_UNKNOWN_ERROR, "ReferenceJump"
            if self.out is not None:
                print(f"[emreg] {text}", file=self.out, flush=True)
            if self.server is not None:
                self.server.send(StatusMessage(code, 0, name, text, device_name=CHECKPOINT_STATUS_NAME))


    def _send_invalid(self, verdict: Verdict) -> None:
        """Tell the clients on the transform itself that no valid pose is published now (PLUS habit:
        ``TransformStatus = INVALID`` with the last published pose), besides the STATUS. Nothing before
        the first pose: there is nothing to invalidate, and a client ignoring the status would show a
        made-up pose."""
        if self.server is None or self.last_probe_to_image is None:
            return
        self.server.send_transform(self.device_name, LPS_TO_RAS @ self.last_probe_to_image, time.time(),
                                   TRANSFORM_INVALID)
        self.invalid_sent += 1


class TrackerPublisher(_WatchedPublisher):
    """``emreg serve``: every sensor sample as a TRANSFORM ``<Name>ToTracker`` (tracker frame, mm,
    sent as measured; a sensor without a usable pose - not attached, out of range - is not sent),
    plus a STATUS named ``Tracker`` from the watchdog. Names: the reference port
    is ``ReferenceToTracker``, the probe port ``ProbeToTracker``, others ``Sensor<N>ToTracker``.
    Samples of one cycle share one timestamp."""

    def __init__(self, server, reference_sensor: int = DEFAULT_REFERENCE_PORT,
                 probe_sensor: int = DEFAULT_PROBE_PORT, period_s: float | None = None, stale_periods: float = 3.0,
                 max_quality: float | None = DEFAULT_MAX_QUALITY, out: TextIO | None = sys.stderr,
                 link=None) -> None:
        self.server = server
        self.reference_sensor = reference_sensor
        self.probe_sensor = probe_sensor
        self.watchdog = Watchdog(reference_sensor, probe_sensor, period_s, stale_periods, max_quality, link)
        self.announcer = _Announcer(server, "Tracker", out, "tracker transforms")
        self.jump_rejected = 0
        self._frame: int | None = None
        self._stamp = 0.0
        self._lock = threading.Lock()
        self.published = 0
        self.samples = 0
        self.invalid_sent = 0  # TRANSFORMs sent with TransformStatus INVALID
        self._last_pose: dict[str, np.ndarray] = {}
        self.latencies: deque[tuple[int, int, int]] = deque(maxlen=200_000)
        #: samples handled at most (``--max-samples``); later samples are ignored (None: no limit)
        self.max_samples: int | None = None

    def name(self, sensor: int) -> str:
        if sensor == self.reference_sensor:
            return "ReferenceToTracker"
        if sensor == self.probe_sensor:
            return "ProbeToTracker"
        return f"Sensor{sensor}ToTracker"

    def on_sample(self, sample: SensorSample) -> None:
        now = time.monotonic()
        with self._lock:
            if self.max_samples is not None and self.samples >= self.max_samples:
                return
            self.samples += 1
            sample = self._admit(sample)
            self.watchdog.observe(sample, now)
            verdict = self.watchdog.evaluate(now)
            self.announcer.update(verdict, now)
            if sample.frame != self._frame:
                self._frame = sample.frame
                self._stamp = time.time() - (time.monotonic_ns() - sample.received_ns) / 1e9
            name = self.name(sample.sensor)
            guarded = self.watchdog.link is not None
            paused = verdict.reason in ("link", "lost") or (guarded and verdict.reason == "no_data")
            if sample.valid and not paused:
                sent_ns = self.server.send_transform(name, sample.transform(), self._stamp, TRANSFORM_OK)
                self.latencies.append((sample.frame, sample.received_ns, sent_ns))
                self._last_pose[name] = sample.transform()
                self.published += 1
            elif name in self._last_pose:  # PLUS habit: the transform goes out with TransformStatus INVALID
                status = TRANSFORM_INVALID if sample.valid else sample.transform_status  # or the tracker's reason
                self.server.send_transform(name, self._last_pose[name], self._stamp, status)
                self.invalid_sent += 1
