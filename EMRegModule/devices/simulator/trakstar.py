"""A trakSTAR that lives on a pseudo-terminal: it answers the RS-232 protocol byte for byte.

It serves a pty (:mod:`.pty`): any RS-232 client (EMReg's driver, or another trakSTAR program) opens
the slave path (e.g. ``/dev/pts/7``) exactly as it would open ``/dev/ttyUSB0``. What it emulates (see
:mod:`..trakstar.protocol` for the sources):

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
- faults on demand (:mod:`.faults`): dropped bytes, flipped phasing bits, stalls, a sensor unplugged (all-zero
  records, sensor serial 0, error code 5) or out of range (saturated position, worst METAL byte).

Every record sent can be logged with the truth it encodes (``keep_truth``), which is what the
tests compare the driver's output with.
"""

from __future__ import annotations

import os
import time
from collections import deque
from collections.abc import Iterable
from dataclasses import dataclass

import numpy as np

from ...errors import EMRegError
from ..trakstar import protocol as tp
from ..trakstar.protocol import Pose, RecordFormat
from .faults import FaultPlan
from .pty import PtyDevice
from .scene import BuiltinScene, ReplayScene, Scene
from .tracker_flags import trakstar_metal

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


class TrackerSimulator(PtyDevice):
    """A trakSTAR on a pseudo-terminal. Use ``start()`` (background thread) or ``run()`` (foreground).

    ``path`` is the slave device to open (e.g. with ``trakstar://<path>``); ``link`` makes a
    symbolic link to it. Stop with ``stop()``; the pty is closed and the link removed.
    """

    thread_name = "trakstar-simulator"
    #: A distortion model (``distortion_mm(position_mm) -> mm`` at a sensor in the Tracker frame; see
    #: :mod:`.tracker_flags`) or None: with METAL on, each record's METAL byte is the worse of
    #: the scene's quality and the distortion there (``trakstar_metal``).
    distortion = None

    def __init__(self, scene: Scene | None = None, baud: int = tp.DEFAULT_BAUD,
                 faults: FaultPlan | None = None, seed: int = 0, link: str | os.PathLike[str] | None = None,
                 fast: bool = False, keep_truth: bool = False, max_records: int | None = None,
                 duration_s: float | None = None, attached: Iterable[int] | None = None) -> None:
        if baud not in tp.BAUD_RATES:
            raise EMRegError(f"baud rate {baud} is not one the trakSTAR supports ({tp.BAUD_RATES})")
        self.scene = scene or BuiltinScene(seed)
        self.baud = baud
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
        super().__init__(faults or FaultPlan(), link)
        if attached is not None:
            self._manual["unplug"] = set(self.sensors) - set(attached)
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
        self.set_state("unplug", sensor, unplugged)

    def set_out_of_range(self, sensor: int, out: bool = True) -> None:
        """Move a sensor out of the position range (or back) now."""
        self.set_state("out-of-range", sensor, out)

    def set_distorted(self, sensor: int, distorted: bool = True) -> None:
        """Metal distortion at a sensor now (or gone): its METAL byte reads ``DISTORTED_METAL``."""
        self.set_state("distort", sensor, distorted)

    @property
    def finished(self) -> bool:
        """True once ``max_records`` or ``duration_s`` is reached (the loop then ends)."""
        return self._stop.is_set()

    # -- main loop (:meth:`PtyDevice.run`) ------------------------------------------------
    def _done(self) -> bool:
        return self.max_records is not None and self.records_sent >= self.max_records and not self._queue

    def _tick(self, now: int) -> None:
        if self.streaming and now >= self._next_tick_ns:
            self._stream_tick(now)

    def _wake_ns(self, wake: int) -> int:
        if self._queue:
            wake = min(wake, self._queue[0].due_ns)
        if self.streaming:
            wake = min(wake, self._next_tick_ns)
        return wake

    def _receive(self, data: bytes) -> None:
        self._rx.extend(data)
        self._handle_commands()

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

    def _sensor_state(self, sensor: int, t_s: float) -> str:
        if sensor not in self.sensors or self._active("unplug", sensor, t_s):
            return "not_attached"
        if self._active("out-of-range", sensor, t_s):
            return "out_of_range"
        if self._active("distort", sensor, t_s):
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

