"""A trakSTAR that lives on a pseudo-terminal: it answers the RS-232 protocol byte for byte.

The simulator opens a pty pair (``os.openpty``), puts it in raw mode and serves the master side;
any RS-232 client (EMReg's driver, or another trakSTAR program) opens the slave path (e.g.
``/dev/pts/7``) through the operating system's serial stack, exactly as it would open
``/dev/ttyUSB0``. What it emulates (see :mod:`.trakstar_protocol` for the sources):

- commands: sensor addressing (``0xF0 + port``), POINT, STREAM (ended by POINT), the seven record
  formats, CHANGE / EXAMINE VALUE (position scale, measurement rate, group mode, error code, status,
  sensor and transmitter serial numbers, FBB status, model), METAL (quality byte), RUN, SLEEP,
  HEMISPHERE, RESET; anything else sets error code 6 ("invalid RS232 command");
- the power-on state: 36-inch scale, POSITION/ANGLES, point mode, group mode off, 80 Hz;
- the line speed: bytes leave no faster than the baud rate allows (10 bit times per byte), so a
  STREAM of four sensors is limited as on the real cable; a measurement that finds the line still
  busy is skipped, as the device does;
- sources: a built-in scene (frame at rest on port 1, a probe moving between waypoints on port 2,
  two slowly moving tools on ports 3 and 4) or a replayed tracking CSV (successive POINT requests
  for a sensor return that sensor's successive samples; STREAM sends them in order at the
  recording's rate, or as fast as the line allows with ``fast``; the recording's quality numbers
  become the METAL bytes, capped at 127);
- faults on demand: dropped bytes, flipped phasing bits, stalls, a sensor unplugged (all-zero
  records, sensor serial 0, error code 5) or out of range (saturated position, worst METAL byte).

Every record sent can be logged with the truth it encodes (``keep_truth``), which is what the
tests compare the driver's output with.
"""

from __future__ import annotations

import contextlib
import errno
import fcntl
import os
import select
import threading
import time
import tty
from collections import deque
from collections.abc import Iterable
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from ..errors import EMRegError
from . import trakstar_protocol as tp
from .trakstar_protocol import Pose, RecordFormat

# --- pose sources ---------------------------------------------------------------------------


class BuiltinScene:
    """A deterministic scene in the Tracker frame (mm, degrees), a function of time.

    Port 1: the reference sensor of the fiducial frame, at rest. Port 2: the probe, dwelling at
    six waypoints around the frame and moving between them. Ports 3 and 4: tools moving slowly on
    circles. Everything stays inside the 36-inch position range.
    """

    sensors = (1, 2, 3, 4)
    period_s: float | None = None

    def __init__(self, seed: int = 0) -> None:
        rng = np.random.default_rng(seed)
        self.reference_position = np.array([300.0, 40.0, 120.0])
        self.reference_angles = np.array([20.0, -10.0, 5.0])
        self.waypoints = self.reference_position + rng.uniform(-60.0, 60.0, size=(6, 3))
        self.dwell_s = 0.6
        self.move_s = 0.4

    def pose(self, sensor: int, t_s: float) -> Pose:
        """Truth pose of ``sensor`` at ``t_s`` seconds after start."""
        if sensor == 1:
            return Pose(self.reference_position.copy(), self.reference_angles.copy())
        if sensor == 2:
            cycle = self.dwell_s + self.move_s
            k = int(t_s // cycle)
            phase = t_s - k * cycle
            a = self.waypoints[k % len(self.waypoints)]
            b = self.waypoints[(k + 1) % len(self.waypoints)]
            s = 0.0 if phase < self.dwell_s else (phase - self.dwell_s) / self.move_s
            s = s * s * (3.0 - 2.0 * s)
            position = a + s * (b - a)
            angles = np.array([40.0 * np.sin(0.7 * t_s), 30.0 * np.sin(0.5 * t_s + 1.0), 60.0 * np.sin(0.3 * t_s)])
            return Pose(position, angles)
        w = 0.8 if sensor == 3 else -0.5
        centre = np.array([200.0, -150.0, 50.0]) if sensor == 3 else np.array([-250.0, 100.0, -80.0])
        position = centre + 80.0 * np.array([np.cos(w * t_s), np.sin(w * t_s), 0.3 * np.sin(2 * w * t_s)])
        azimuth = ((100.0 * w * t_s + 180.0) % 360.0) - 180.0
        angles = np.array([azimuth, 45.0 * np.sin(w * t_s), -170.0 + (20.0 * t_s) % 340.0])
        return Pose(position, angles)


class ReplayScene:
    """Poses from a tracking recording (``SensorToTracker`` rows), frame by frame.

    Rows of one moment (same ``time_s`` within 1 ms) form one frame. ``next_point(sensor)`` returns
    the sensor's samples one after another (cycling), ``frame(k)`` the k-th frame (cycling).
    """

    def __init__(self, recording) -> None:
        from ..transforms import rotation_to_angles

        order = np.argsort(recording.time_s, kind="stable")
        times = recording.time_s[order]
        sensors = recording.sensor[order]
        positions = recording.position_mm[order]
        angles = rotation_to_angles(recording.rotation[order])
        quality = np.nan_to_num(recording.quality[order], nan=0.0)
        self.sensors = tuple(sorted(int(s) for s in np.unique(sensors)))
        if any(not 1 <= s <= tp.MAX_SENSORS for s in self.sensors):
            raise EMRegError(f"{recording.source}: the simulator has sensor ports 1..4, "
                             f"the recording uses {self.sensors}")
        self.frames: list[tuple[float, dict[int, Pose]]] = []
        for i in range(len(times)):
            if not self.frames or times[i] - self.frames[-1][0] > 1e-3:
                self.frames.append((float(times[i]), {}))
            self.frames[-1][1][int(sensors[i])] = Pose(positions[i].copy(), angles[i].copy(), float(quality[i]))
        self.per_sensor = {s: [p[s] for _, p in self.frames if s in p] for s in self.sensors}
        self._cursor = dict.fromkeys(self.sensors, 0)
        frame_times = np.array([t for t, _ in self.frames])
        steps = np.diff(frame_times)
        self.period_s = float(np.median(steps)) if len(steps) else 1.0 / tp.POWER_ON_RATE_HZ
        self.duration_s = float(frame_times[-1] - frame_times[0]) + self.period_s

    def next_point(self, sensor: int) -> Pose | None:
        samples = self.per_sensor.get(sensor)
        if not samples:
            return None
        i = self._cursor[sensor]
        self._cursor[sensor] = (i + 1) % len(samples)
        return samples[i]

    def frame_offset_s(self, k: int) -> float:
        """Time of frame ``k`` (cycling) from the first frame, in seconds."""
        n = len(self.frames)
        loops, i = divmod(k, n)
        return loops * self.duration_s + self.frames[i][0] - self.frames[0][0]

    def frame(self, k: int) -> dict[int, Pose]:
        return self.frames[k % len(self.frames)][1]


# --- faults ---------------------------------------------------------------------------------


def fault_probability(value: str) -> float:
    """A ``--fault`` probability (per byte or per reply): a number in 0..1, else ValueError."""
    probability = float(value)
    if not 0.0 <= probability <= 1.0:
        raise ValueError(value)
    return probability


def fault_stall(value: str) -> tuple[float, float]:
    """``EVERY_S:DURATION_S`` of a ``--fault stall=``: both positive and finite (DURATION_S default 0.2), else
    ValueError."""
    every, _, duration = value.partition(":")
    every_s, stall_s = float(every), float(duration or 0.2)
    if not (0.0 < every_s < float("inf") and 0.0 < stall_s < float("inf")):
        raise ValueError(value)
    return every_s, stall_s


def fault_window(value: str, max_sensor: int) -> tuple[int, float, float]:
    """``SENSOR@START-END`` of a ``--fault`` (seconds after start; no END: to the end) as ``(sensor, start_s, end_s)``;
    ValueError unless 1 <= SENSOR <= ``max_sensor`` and 0 <= START < END."""
    sensor, _, window = value.partition("@")
    start, _, end = window.partition("-")
    entry = (int(sensor), float(start or 0.0), float(end) if end else float("inf"))
    if not (1 <= entry[0] <= max_sensor and 0.0 <= entry[1] < entry[2]):
        raise ValueError(value)
    return entry


@dataclass
class FaultPlan:
    """Faults to inject. Probabilities are per byte sent; windows are seconds after start.

    ``drop``: a byte is lost. ``flip``: a byte's phasing bit (bit 7) is inverted - the corruption
    the protocol's framing can detect. ``corrupt``: a byte's seven data bits are replaced by random
    ones - line noise that this checksum-free protocol's framing cannot detect at all (the link
    guard's jump test and value checks catch what they can). ``stall_every_s`` / ``stall_s``: the tracker
    falls silent for ``stall_s`` every ``stall_every_s`` seconds. ``unplugged`` / ``out_of_range``:
    ``(sensor, start_s, end_s)`` windows. ``late`` / ``late_s``: a POINT request is answered ``late_s``
    seconds late with probability ``late`` (a tracker busy with something else, or a host that missed
    its reply): the reply is the same bytes, only later, and the replies to later requests queue behind
    it on the line, as on the real cable (the protocol has no request id).
    """

    drop: float = 0.0
    flip: float = 0.0
    corrupt: float = 0.0
    stall_every_s: float = 0.0
    stall_s: float = 0.0
    late: float = 0.0
    late_s: float = 0.0
    unplugged: list[tuple[int, float, float]] = field(default_factory=list)
    out_of_range: list[tuple[int, float, float]] = field(default_factory=list)
    distorted: list[tuple[int, float, float]] = field(default_factory=list)

    @classmethod
    def parse(cls, items: Iterable[str]) -> FaultPlan:
        """From ``KIND=VALUE`` strings: ``drop=0.001``, ``flip=0.001``, ``corrupt=0.01``, ``stall=EVERY_S:DURATION_S``,
        ``late=P:DELAY_S`` (a POINT reply comes DELAY_S late with probability P),
        ``unplug=SENSOR@START-END``, ``out-of-range=SENSOR@START-END``, ``distort=SENSOR@START-END``
        (metal distortion: bad METAL byte, pose still sent) (seconds after start)."""
        plan = cls()
        for item in items:
            kind, _, value = item.partition("=")
            kind = kind.strip().lower().replace("_", "-")
            try:
                if kind in ("drop", "flip", "corrupt"):
                    setattr(plan, kind, fault_probability(value))
                elif kind == "stall":
                    plan.stall_every_s, plan.stall_s = fault_stall(value)
                elif kind == "late":
                    probability, _, delay = value.partition(":")
                    plan.late, plan.late_s = fault_probability(probability), float(delay or 0.2)
                    if not 0.0 <= plan.late_s < float("inf"):
                        raise ValueError(kind)
                elif kind in ("unplug", "out-of-range", "distort"):
                    {"unplug": plan.unplugged, "out-of-range": plan.out_of_range,
                     "distort": plan.distorted}[kind].append(fault_window(value, tp.MAX_SENSORS))
                else:
                    raise ValueError(kind)
            except ValueError:
                raise EMRegError(
                    f"--fault {item!r}: use drop=P, flip=P, corrupt=P, stall=EVERY_S:DURATION_S, late=P:DELAY_S, "
                    "unplug=SENSOR@START-END, out-of-range=SENSOR@START-END or distort=SENSOR@START-END "
                    f"(P a probability 0..1, seconds positive, SENSOR 1..{tp.MAX_SENSORS}, 0 <= START < END)") from None
        return plan


#: Longest delay (s) of a descheduled simulator whose STREAM cycles are still sent late; older ones are skipped.
MAX_CATCH_UP_S = 1.0

#: METAL byte the simulator sends for a distorted sensor (the scale runs 0 = clean .. 127).
DISTORTED_METAL = 90


@dataclass
class EmittedRecord:
    """One record the simulator sent: the truth it encodes and what happened to it on the way."""

    sensor: int
    seq: int
    time_s: float
    pose: Pose
    fmt: str
    status: str  # "ok", "not_attached", "out_of_range", "distorted"
    corrupted: bool
    emit_ns: int = 0  # time.monotonic_ns() when its last byte was written to the pty


@dataclass
class _Pending:
    due_ns: int
    data: bytes
    record: EmittedRecord | None


# --- the simulator ----------------------------------------------------------------------------


class PtyDevice:
    """A simulated serial device serving the master side of a pseudo-terminal in raw mode.

    Clients open ``path`` (the slave side) or ``link``, a symbolic link to it. Subclasses call
    :meth:`_open_pty` in their constructor, implement ``run()`` (ending when ``_stop`` is set) and may
    configure the line in :meth:`_configure_pty`.
    """

    thread_name = "pty-device"

    def _open_pty(self, link: str | os.PathLike[str] | None) -> None:
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None
        self.master_fd, self.slave_fd = os.openpty()
        tty.setraw(self.slave_fd)
        self._configure_pty()
        flags = fcntl.fcntl(self.master_fd, fcntl.F_GETFL)
        fcntl.fcntl(self.master_fd, fcntl.F_SETFL, flags | os.O_NONBLOCK)
        self.path = os.ttyname(self.slave_fd)
        self.link = Path(link) if link else None
        if self.link is not None:
            self._make_link()
        self._closed = False

    def _configure_pty(self) -> None:
        """Line settings beyond raw mode (none by default)."""

    def _make_link(self) -> None:
        assert self.link is not None
        if self.link.is_symlink():
            self.link.unlink()
        elif self.link.exists():
            self._close_fds()
            raise EMRegError(f"--link {self.link}: a file of that name exists and is not a symbolic link; "
                             "choose another path")
        folder = self.link.parent
        if not folder.is_dir():
            self._close_fds()
            raise EMRegError(f"--link {self.link}: the folder {folder} does not exist; make it or choose another path")
        try:
            os.symlink(self.path, self.link)
        except OSError as exc:  # named after the link, never the pty it points to
            self._close_fds()
            raise EMRegError(f"--link {self.link}: cannot make the link ({exc.strerror or exc})") from None

    def _close_fds(self) -> None:
        for fd in (self.master_fd, self.slave_fd):
            with contextlib.suppress(OSError):
                os.close(fd)

    def run(self) -> None:
        raise NotImplementedError

    def start(self) -> PtyDevice:
        """Serve in a background thread (daemon; stops with ``stop()``)."""
        self._thread = threading.Thread(target=self.run, name=self.thread_name, daemon=True)
        self._thread.start()
        return self

    def stop(self) -> None:
        """Stop serving, close the pty and remove the link (idempotent)."""
        self._stop.set()
        if self._thread is not None and self._thread is not threading.current_thread():
            self._thread.join(timeout=5.0)
        self.close()

    def __enter__(self) -> PtyDevice:
        return self.start()

    def __exit__(self, *exc: object) -> None:
        self.stop()

    def close(self) -> None:
        if self._closed:
            return
        self._closed = True
        self._close_fds()
        if self.link is not None and self.link.is_symlink():
            with contextlib.suppress(OSError):
                self.link.unlink()


class TrackerSimulator(PtyDevice):
    """A trakSTAR on a pseudo-terminal. Use ``start()`` (background thread) or ``run()`` (foreground).

    ``path`` is the slave device to open (e.g. with ``trakstar://<path>``); ``link`` makes a
    symbolic link to it. Stop with ``stop()``; the pty is closed and the link removed.
    """

    thread_name = "trakstar-simulator"
    #: A distortion model (``distortion_mm(position_mm) -> mm`` at a sensor in the Tracker frame; see
    #: :mod:`EMRegModule.simulation.tracker_flags`) or None: with METAL on, each record's METAL byte is the worse of
    #: the scene's quality and the distortion there (``trakstar_metal``).
    distortion = None

    def __init__(self, scene: BuiltinScene | ReplayScene | None = None, baud: int = tp.DEFAULT_BAUD,
                 faults: FaultPlan | None = None, seed: int = 0, link: str | os.PathLike[str] | None = None,
                 fast: bool = False, keep_truth: bool = False, max_records: int | None = None,
                 duration_s: float | None = None, attached: Iterable[int] | None = None) -> None:
        if baud not in tp.BAUD_RATES:
            raise EMRegError(f"baud rate {baud} is not one the trakSTAR supports ({tp.BAUD_RATES})")
        self.scene = scene or BuiltinScene(seed)
        self.baud = baud
        self.faults = faults or FaultPlan()
        self.fast = fast
        self.keep_truth = keep_truth
        self.max_records = max_records
        self.duration_s = duration_s
        self.rng = np.random.default_rng(seed)
        self.byte_ns = tp.BITS_PER_BYTE * 1e9 / baud
        self.truth: list[EmittedRecord] = []
        self.records_sent = 0
        self.skipped_measurements = 0
        self.dropped_writes = 0
        self.late_replies = 0  # POINT replies sent late (fault ``late``)
        self.sensors = tuple(self.scene.sensors)
        self._manual_unplugged: set[int] = set() if attached is None else set(self.sensors) - set(attached)
        self._manual_out_of_range: set[int] = set()
        self._manual_distorted: set[int] = set()
        self._stall_until_ns = 0
        self._open_pty(link)
        self._reset_state()

    # -- device state --------------------------------------------------------------------
    def _reset_state(self) -> None:
        """The power-on state ([TSG]): 36-inch scale, POSITION/ANGLES, point mode, 80 Hz."""
        self.scale_inches = tp.POWER_ON_SCALE_INCHES
        self.formats: dict[int, RecordFormat] = dict.fromkeys(range(1, tp.MAX_SENSORS + 1), tp.POWER_ON_FORMAT)
        self.metal: dict[int, bool] = dict.fromkeys(range(1, tp.MAX_SENSORS + 1), False)
        self.group_mode = False
        self.streaming = False
        self.sleeping = False
        self.rate_hz = self.scene.period_s and 1.0 / self.scene.period_s or tp.POWER_ON_RATE_HZ
        self.error_code = 0
        self._rx = bytearray()
        self._target: int | None = None
        self._queue: deque[_Pending] = deque()
        self._line_free_ns = 0
        self._seq = 0
        self._stream_k = 0
        self._stream_sensor = 1
        self._stream_t0_ns = 0
        self._next_tick_ns = 0

    # -- public controls -----------------------------------------------------------------
    def set_unplugged(self, sensor: int, unplugged: bool = True) -> None:
        """Unplug (or plug back) a sensor now."""
        (self._manual_unplugged.add if unplugged else self._manual_unplugged.discard)(sensor)

    def set_out_of_range(self, sensor: int, out: bool = True) -> None:
        """Move a sensor out of the position range (or back) now."""
        (self._manual_out_of_range.add if out else self._manual_out_of_range.discard)(sensor)

    def set_distorted(self, sensor: int, distorted: bool = True) -> None:
        """Metal distortion at a sensor now (or gone): its METAL byte reads ``DISTORTED_METAL``."""
        (self._manual_distorted.add if distorted else self._manual_distorted.discard)(sensor)

    def stall(self, seconds: float) -> None:
        """Fall silent for ``seconds`` from now (records due meanwhile are skipped or delayed)."""
        self._stall_until_ns = time.monotonic_ns() + int(seconds * 1e9)

    @property
    def finished(self) -> bool:
        """True once ``max_records`` or ``duration_s`` is reached (the loop then ends)."""
        return self._stop.is_set()

    # -- main loop -----------------------------------------------------------------------
    def run(self) -> None:
        """Serve until ``stop()`` (or the record / duration limit)."""
        self._start_ns = time.monotonic_ns()
        deadline = None if self.duration_s is None else self._start_ns + int(self.duration_s * 1e9)
        try:
            while not self._stop.is_set():
                now = time.monotonic_ns()
                if deadline is not None and now >= deadline:
                    break
                if self.max_records is not None and self.records_sent >= self.max_records and not self._queue:
                    break
                self._flush_due(now)
                if self.streaming and now >= self._next_tick_ns:
                    self._stream_tick(now)
                wake = now + 50_000_000
                if self._queue:
                    wake = min(wake, self._queue[0].due_ns)
                if self.streaming:
                    wake = min(wake, self._next_tick_ns)
                if deadline is not None:
                    wake = min(wake, deadline)
                timeout = max(0.0, (wake - time.monotonic_ns()) / 1e9)
                try:
                    readable, _, _ = select.select([self.master_fd], [], [], timeout)
                except (OSError, ValueError):
                    break
                if readable:
                    try:
                        data = os.read(self.master_fd, 4096)
                    except BlockingIOError:
                        continue
                    except OSError as exc:
                        if exc.errno == errno.EIO:
                            time.sleep(0.01)
                            continue
                        raise
                    self._rx.extend(data)
                    self._handle_commands()
        finally:
            self._stop.set()
            self.close()

    def _flush_due(self, now: int) -> None:
        while self._queue and self._queue[0].due_ns <= now:
            item = self._queue.popleft()
            if item.data:
                try:
                    written = os.write(self.master_fd, item.data)
                    if written < len(item.data):
                        self.dropped_writes += 1
                except BlockingIOError:
                    self.dropped_writes += 1  # nobody reads the port: the bytes go nowhere, as on a cable
                except OSError:
                    self.dropped_writes += 1
            if item.record is not None:
                item.record.emit_ns = time.monotonic_ns()
                self.records_sent += 1

    # -- output --------------------------------------------------------------------------
    def _send(self, data: bytes, record: EmittedRecord | None = None, after_ns: int = 0) -> None:
        """Queue bytes for the line: they are written when their last bit would have arrived."""
        now = time.monotonic_ns()
        # a STREAM cycle is scheduled at its planned time (a late loop must not stretch the line);
        # a reply starts when the command has arrived
        start = max(after_ns or now, self._line_free_ns, self._stall_until_ns)
        done = int(start + len(data) * self.byte_ns)
        self._line_free_ns = done
        self._queue.append(_Pending(done, data, record))

    def _corrupt(self, data: bytes) -> tuple[bytes, bool]:
        f = self.faults
        if f.drop <= 0 and f.flip <= 0 and f.corrupt <= 0:
            return data, False
        arr = np.frombuffer(data, dtype=np.uint8).copy()
        corrupted = False
        if f.corrupt > 0:  # line noise in the data bits: invisible to the framing
            hit = self.rng.random(len(arr)) < f.corrupt
            if hit.any():
                noise = self.rng.integers(0, 128, int(hit.sum()), dtype=np.uint8)
                changed = (arr[hit] & 0x80) | noise
                corrupted = corrupted or bool(np.any(changed != arr[hit]))
                arr[hit] = changed
        if f.flip > 0:
            flips = self.rng.random(len(arr)) < f.flip
            if flips.any():
                arr[flips] ^= 0x80
                corrupted = True
        if f.drop > 0:
            keep = self.rng.random(len(arr)) >= f.drop
            if not keep.all():
                arr = arr[keep]
                corrupted = True
        return arr.tobytes(), corrupted

    def _elapsed_s(self, now_ns: int | None = None) -> float:
        return ((now_ns or time.monotonic_ns()) - self._start_ns) / 1e9

    def _sensor_state(self, sensor: int, t_s: float) -> str:
        if sensor not in self.sensors or sensor in self._manual_unplugged or any(
                s == sensor and a <= t_s < b for s, a, b in self.faults.unplugged):
            return "not_attached"
        if sensor in self._manual_out_of_range or any(
                s == sensor and a <= t_s < b for s, a, b in self.faults.out_of_range):
            return "out_of_range"
        if sensor in self._manual_distorted or any(s == sensor and a <= t_s < b for s, a, b in self.faults.distorted):
            return "distorted"
        return "ok"

    def _record(self, sensor: int, pose: Pose | None, t_s: float, group: bool, after_ns: int = 0) -> None:
        fmt = self.formats[sensor]
        metal = self.metal[sensor]
        state = self._sensor_state(sensor, t_s) if pose is not None else "not_attached"
        address = sensor if group else None
        if state == "not_attached":
            data = tp.zero_record(fmt, metal, address)
            pose = pose or Pose(np.zeros(3), np.zeros(3))
            self.error_code = tp.ERROR_SENSOR_NOT_CONNECTED
        else:
            sent_pose = pose
            clean = int(min(max(pose.quality, 0.0), tp.METAL_MAX))  # a replay carries its recording's quality
            if self.distortion is not None and metal:
                from ..simulation.tracker_flags import trakstar_metal  # only with a model (a heavy package)

                clean = trakstar_metal(self.distortion.distortion_mm(pose.position_mm), clean)
            quality = (DISTORTED_METAL if state == "distorted" else clean) if metal else None
            if state == "out_of_range":
                full_scale_mm = self.scale_inches * tp.MM_PER_INCH
                position = np.array(pose.position_mm, dtype=float)
                position[0] = 1.5 * full_scale_mm * (1.0 if position[0] >= 0 else -1.0)
                sent_pose = Pose(position, pose.angles_deg)
                quality = tp.METAL_MAX if metal else None
                pose = sent_pose
            data = tp.encode_record(fmt, sent_pose, self.scale_inches, quality, address)
        data, corrupted = self._corrupt(data)
        record = EmittedRecord(sensor, self._seq, t_s, pose, fmt.name, state, corrupted)
        self._seq += 1
        if self.keep_truth:
            self.truth.append(record)
        self._send(data, record, after_ns)

    def _stall_active(self, now: int) -> bool:
        f = self.faults
        if now < self._stall_until_ns:
            return True
        if f.stall_every_s > 0 and f.stall_s > 0:
            t = self._elapsed_s(now)
            phase = t % f.stall_every_s
            if t >= f.stall_every_s and phase < f.stall_s:
                self._stall_until_ns = now + int((f.stall_s - phase) * 1e9)
                return True
        return False

    def _tick_sensors(self) -> list[int]:
        # In group mode every port of the unit answers; an empty port answers an all-zero record (choice).
        if self.group_mode:
            return list(range(1, tp.MAX_SENSORS + 1))
        return [self._stream_sensor]

    def _stream_tick(self, now: int) -> None:
        if isinstance(self.scene, ReplayScene):
            self._replay_tick(now)
            return
        period_ns = int(1e9 / self.rate_hz)
        tick_ns = self._next_tick_ns
        self._stream_k += 1
        sensors = self._tick_sensors()
        if self.fast:  # cycles back to back: the next one starts when this one's last byte is out
            frame_bytes = sum(tp.record_length(self.formats[s], self.metal[s], self.group_mode) for s in sensors)
            period_ns = int(frame_bytes * self.byte_ns)
            tick_ns = max(tick_ns, self._line_free_ns)
        self._next_tick_ns = tick_ns + period_ns
        # the device measures on its own clock whatever the host does: the cycles a descheduled simulator owes
        # are sent late, in order, each with the pose of its own time (to the client, a reader that was late);
        # only beyond MAX_CATCH_UP_S are they given up, and counted
        behind = (now - self._next_tick_ns) // period_ns
        if behind > MAX_CATCH_UP_S * 1e9 // period_ns:
            self.skipped_measurements += int(behind) + 1
            self._next_tick_ns = now + period_ns
            tick_ns = now
        if self.sleeping or self._stall_active(now) or self._line_free_ns > tick_ns + period_ns // 2:
            self.skipped_measurements += 1
            return
        t_s = self._elapsed_s(tick_ns)
        for sensor in sensors:
            pose = self.scene.pose(sensor, t_s) if sensor in self.sensors else None
            self._record(sensor, pose, t_s, self.group_mode, after_ns=tick_ns)

    def _replay_tick(self, now: int) -> None:
        scene: ReplayScene = self.scene  # type: ignore[assignment]
        k = self._stream_k
        self._stream_k += 1
        frame = scene.frame(k)
        t_s = scene.frame_offset_s(k)
        sensors = self._tick_sensors()
        if self.sleeping or self._stall_active(now):
            self._next_tick_ns = max(now, self._stall_until_ns)
            self._stream_k -= 1
            return
        for sensor in sensors:
            if sensor in frame or self.group_mode:
                self._record(sensor, frame.get(sensor), t_s, self.group_mode)
        if self.fast:
            self._next_tick_ns = self._line_free_ns
        else:
            self._next_tick_ns = max(self._stream_t0_ns + int(scene.frame_offset_s(self._stream_k) * 1e9),
                                     self._line_free_ns - int(0.5 * scene.period_s * 1e9))

    def _point(self) -> None:
        sensors = list(range(1, tp.MAX_SENSORS + 1)) if self.group_mode else [self._target or 1]
        t_s = self._elapsed_s()
        after_ns = 0
        if self.faults.late > 0 and self.rng.random() < self.faults.late:
            after_ns = time.monotonic_ns() + int(self.faults.late_s * 1e9)  # the whole reply comes late
            self.late_replies += 1
        for sensor in sensors:
            if isinstance(self.scene, ReplayScene):
                pose = self.scene.next_point(sensor)
            else:
                pose = self.scene.pose(sensor, t_s) if sensor in self.sensors else None
            if self.sleeping:
                continue
            self._record(sensor, pose, t_s, self.group_mode, after_ns=after_ns)

    # -- commands ------------------------------------------------------------------------
    def _handle_commands(self) -> None:
        rx = self._rx
        while rx:
            b = rx[0]
            if tp.ADDRESS_BASE < b <= tp.ADDRESS_BASE + 14:
                self._target = b - tp.ADDRESS_BASE
                del rx[0]
                continue
            need = self._command_length(b, rx)
            if need is None or len(rx) < need:
                return  # wait for the rest of the command
            command = bytes(rx[:need])
            del rx[:need]
            self._execute(command)
            self._target = None

    @staticmethod
    def _command_length(b: int, rx: bytearray) -> int | None:
        if b == tp.CHANGE_VALUE:
            if len(rx) < 2:
                return None
            return 2 + tp.CHANGE_LENGTH.get(rx[1], 0)
        if b == tp.EXAMINE_VALUE:
            return 2
        if b == tp.METAL or b == tp.HEMISPHERE:
            return 3
        return 1

    def _execute(self, command: bytes) -> None:
        c = command[0]
        target = self._target or 1
        if c == tp.POINT:
            was_streaming = self.streaming
            self.streaming = False
            if not was_streaming:
                self._point()
        elif c == tp.STREAM:
            self.streaming = True
            self._stream_sensor = target
            self._stream_k = 0
            self._stream_t0_ns = max(time.monotonic_ns(), self._line_free_ns)
            self._next_tick_ns = self._stream_t0_ns
        elif c in tp.FORMAT_BY_COMMAND:
            self.streaming = False
            self.formats[target] = tp.FORMAT_BY_COMMAND[c]
        elif c == tp.EXAMINE_VALUE:
            self.streaming = False
            reply = self._examine(command[1], target)
            if reply is not None:
                self._send(reply)
        elif c == tp.CHANGE_VALUE:
            self._change(command[1], command[2:], target)
        elif c == tp.METAL:
            self.metal[target] = bool(command[1])
        elif c == tp.RUN:
            self.sleeping = False
        elif c == tp.SLEEP:
            self.sleeping = True
            self.streaming = False
        elif c == tp.RESET:
            self._reset_state()
        elif c in (tp.HEMISPHERE, tp.FBB_RESET, tp.XON, tp.XOFF):
            pass
        else:
            self.error_code = tp.ERROR_INVALID_COMMAND

    def _examine(self, param: int, target: int) -> bytes | None:
        word = lambda v: int(v & 0xFFFF).to_bytes(2, "little")  # noqa: E731
        t_s = self._elapsed_s()
        if param == tp.PARAM_STATUS:
            status = tp.STATUS_MASTER | tp.STATUS_INITIALIZED | (self.formats[target].status_code << 1)
            status |= tp.STATUS_STREAMING if self.streaming else 0
            status |= tp.STATUS_SLEEPING if self.sleeping else tp.STATUS_RUNNING
            status |= tp.STATUS_ERROR if self.error_code else 0
            return word(status)
        if param == tp.PARAM_REVISION:
            return bytes([3, 67])
        if param == tp.PARAM_SPEED:
            return word(25)
        if param == tp.PARAM_POSITION_SCALING:
            return word(0 if self.scale_inches == 36 else 1)
        if param == tp.PARAM_MEASUREMENT_RATE:
            return word(round(self.rate_hz * 256))
        if param == tp.PARAM_ERROR_CODE:
            code, self.error_code = self.error_code, 0
            return bytes([code])
        if param == tp.PARAM_EXPANDED_ERROR_CODE:
            code, self.error_code = self.error_code, 0
            return bytes([code, target])
        if param == tp.PARAM_SYSTEM_MODEL:
            return b"trakSTAR  "
        if param == tp.PARAM_BIRD_SERIAL:
            return word(1000 + target)
        if param == tp.PARAM_SENSOR_SERIAL:
            attached = self._sensor_state(target, t_s) != "not_attached"
            return word(2000 + target if attached else 0)
        if param == tp.PARAM_TRANSMITTER_SERIAL:
            return word(3001)
        if param == tp.PARAM_GROUP_MODE:
            return bytes([int(self.group_mode)])
        if param == tp.PARAM_FBB_STATUS:
            out = bytearray(14)
            for s in range(1, tp.MAX_SENSORS + 1):
                out[s - 1] = tp.FBB_STATUS_ACCESSIBLE | tp.FBB_STATUS_RUNNING
                if self._sensor_state(s, t_s) != "not_attached":
                    out[s - 1] |= tp.FBB_STATUS_SENSOR
            return bytes(out)
        if param == tp.PARAM_FBB_AUTOCONFIG:
            return bytes([len(self.sensors), 0, 0, 0, 0])
        if param in tp.EXAMINE_LENGTH:
            return bytes(tp.EXAMINE_LENGTH[param])
        self.error_code = tp.ERROR_INVALID_COMMAND
        return None

    def _change(self, param: int, data: bytes, target: int) -> None:
        if param == tp.PARAM_POSITION_SCALING:
            self.scale_inches = 72 if int.from_bytes(data[:2], "little") == 1 else 36
        elif param == tp.PARAM_MEASUREMENT_RATE:
            rate = int.from_bytes(data[:2], "little") / 256.0
            if tp.MIN_RATE_HZ <= rate <= tp.MAX_RATE_HZ:
                self.rate_hz = rate
            else:
                self.error_code = tp.ERROR_INVALID_COMMAND
        elif param == tp.PARAM_GROUP_MODE:
            self.group_mode = bool(data[0])
        elif param not in tp.CHANGE_LENGTH:
            self.error_code = tp.ERROR_INVALID_COMMAND

