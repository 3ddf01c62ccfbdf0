"""An NDI Aurora on a pseudo-terminal: it answers NDI's serial command API byte for byte.

Like :mod:`.trakstar`, it serves the master side of a pty (:mod:`.pty`) and a client opens
the slave path (``/dev/pts/N`` or the ``--link`` symlink) exactly as it would open ``/dev/ttyUSB0``.
How ndicapi opens ports: ``ndiSerialOpen`` / ``ndiSerialProbe`` / ``ndiOpenSerial`` take any path
(``open(2)`` with O_NOCTTY, an advisory ``F_SETLK`` lock, termios), so a pty path or a symlink to it
works as given; only ndicapi's own enumeration (``ndiSerialDeviceName(i)``: on Linux the fixed names
``/dev/ttyS0``, ``/dev/ttyS1``, ``/dev/ttyUSB0`` .. ``/dev/ttyUSB5``) and scikit-surgerynditracker's
auto-probe (pyserial's ``list_ports.comports()``, which lists no ptys) cannot find it - so clients are
given the path: ``aurora://PATH`` for EMReg, ``{"serial port": PATH}`` for scikit-surgerynditracker,
``ndiProbe(PATH)`` / ``ndiOpen(PATH)`` for ndicapi. What it emulates (formats and constants in
:mod:`..aurora.protocol`, with their sources):

- commands ``INIT``, ``COMM`` (baud change after the OKAY, as ndicapi expects), ``VER`` (3 is
  ``ERROR23`` as on a real Aurora; 0, 1, 2, 4, 5 give the same text: choice), ``GETINFO``
  (``ERROR01``: this firmware has none, so ndicapi's probe falls back to ``VER``; choice), ``BEEP``
  (answers ``1``: choice), ``PHSR`` (all five modes), ``PHINF`` (every field; tool type ``0B``
  catheter, manufacturer, serial and part number are choices), ``PHF``, ``PINIT`` (``ERROR13`` for a
  tool without SROM), ``PENA`` / ``PDIS``, ``TSTART`` / ``TSTOP``, ``BX`` and ``TX`` (reply modes
  0x0001 and 0x0800; BX/TX list every initialised handle, DISABLED when not enabled: choice), every
  reply with its CRC16; a command with a wrong CRC gets ``ERROR04``, an unknown one ``ERROR01``,
  BX/TX outside tracking and PHSR/PHINF/PINIT/PENA during tracking ``ERROR0C``, anything but INIT,
  COMM, VER, BEEP before INIT ``ERROR10`` (which code a real Aurora sends there: choice);
- the line: replies leave no faster than the current baud allows (start + data + parity + stop
  bits per byte) and are written when their last byte would have arrived; the device reads the
  host's line speed from the pty (Linux reports the slave's termios on the master), so a client
  talking at the wrong speed is ignored (its bytes are line noise to the device) and hears noise;
- the break: a pty cannot carry a serial break. ndicapi always flushes both directions right
  before it sends one (``ndiSerialBreak`` = ``tcflush(TCIOFLUSH)`` + ``tcsendbreak``), so the
  simulator, reading the pty in packet mode, takes a full flush by a host at 9600 baud after the
  device received noise (bytes sent at another speed) as the break: it resets to 9600 baud and
  answers ``RESET`` + CRC, as the Aurora does - which is how ndicapi's probe recovers a device left
  at another speed by a previous program (choice, documented; a break without preceding noise, as
  ``ndiCommand(NULL)`` sends, is not seen);
- tools on ports 1..4 (6-DOF, 5-DOF, or without SROM), port handles allocated at power-on from
  0x0A (choice), frame numbers counting from 0 at TSTART at the measuring rate (40 Hz by default,
  choice; a replay uses its recording's rate), BX/TX answering the newest measured frame;
- states on demand (``--fault`` windows in seconds after start, or the ``set_*`` methods): a tool
  ``missing`` (no solution: MISSING), ``out-of-range`` (outside the characterised volume: port
  status bit 0x40, reported MISSING unless the reply mode has 0x0800), ``partly-out`` (partially
  outside it: port status bit 0x80 on a transform reported as valid), ``unplug`` (MISSING, port no
  longer occupied, system status 0x0080; its handle stays unoccupied - listed by PHSR:01 until PHF
  frees it - and, plugged back in, the tool gets a new handle waiting for PINIT / PENA while BX/TX
  replies carry system status 0x0040, as on the Aurora: [CAPI] ``NDI_PORT_OCCUPIED``), ``distort``
  (RMS error 2.5 mm, choice); line faults ``drop=P`` (bytes lost),
  ``flip=P`` (a bit flipped in a byte), ``crc=P`` (a reply's CRC field wrong), ``stall=EVERY:S``.

Tests compare what a client reads with :meth:`AuroraSimulator.truth_for_frame` (the pose the
simulator encoded for a frame number).
"""

from __future__ import annotations

import contextlib
import fcntl
import os
import struct
import termios
import time
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from ...core.transforms import rotation_to_quaternion
from ...errors import EMRegError
from ..aurora import protocol as ndi
from .faults import AuroraFaults
from .pty import PtyDevice
from .scene import BuiltinScene, ReplayScene, Scene, pose_at
from .tracker_flags import aurora_error_mm

#: Measuring rate of the simulated Aurora (choice: 40 Hz, the Aurora's nominal update rate).
DEFAULT_RATE_HZ = 40.0
#: RMS error reported for a clean 6-DOF / 5-DOF solution and for a distorted one (mm; choice).
CLEAN_ERROR = 0.05
DISTORTED_ERROR = 2.5
#: Termios speed constants -> baud (what the host set on its end of the line).
_TERMIOS_BAUD = {getattr(termios, f"B{b}"): b for b in (1200, 2400, 4800, 9600, 19200, 38400, 57600, 115200, 230400)}
_PKT_FLUSHREAD, _PKT_FLUSHWRITE = 0x01, 0x02  # TIOCPKT control bits (linux/tty.h)
#: Replies are written in pieces of this much line time, at least CHUNK_MIN_BYTES each (choice: well under
#: the 0.1 s ndicapi waits for the next byte while probing; a BX reply at 115200 baud is one piece).
CHUNK_NS = 20_000_000
CHUNK_MIN_BYTES = 8


@dataclass
class AuroraTool:
    """A tool plugged into ``port`` (1..4), ``channel`` 0/1 (two 5-DOF sensors share a port via a
    splitter). ``dof`` 6 or 5; ``srom`` False: a sensor without SROM (PINIT fails with ERROR13)."""

    port: int
    channel: int = 0
    dof: int = 6
    srom: bool = True

    @property
    def sensor(self) -> int:
        """EMReg's sensor number for this tool: the port, +4 for channel 1 (see :mod:`..aurora.driver`)."""
        return self.port + 4 * self.channel


@dataclass
class _Handle:
    handle: int
    tool: AuroraTool
    initialized: bool = False
    enabled: bool = False
    mode: str = "D"
    freed: bool = False
    #: the tool was unplugged from this handle: it stays unoccupied, a replugged tool gets a new handle
    stale: bool = False


def parse_tools(text: str) -> list[AuroraTool]:
    """``1:6dof,2:5dof,3:nosrom,4:none`` (port:kind; ``5dof2`` adds a channel-1 5-DOF sensor)."""
    tools = []
    for item in filter(None, (s.strip() for s in text.split(","))):
        port_text, _, kind = item.partition(":")
        try:
            port = int(port_text)
        except ValueError:
            port = 0
        kind = (kind or "6dof").lower()
        if port not in ndi.AURORA_PORTS or kind not in ("6dof", "5dof", "5dof2", "nosrom", "none"):
            raise EMRegError(f"--tools {text!r}: use PORT:KIND with PORT 1..4 and KIND 6dof, 5dof, 5dof2, "
                             "nosrom or none")
        if kind == "none":
            continue
        if kind == "5dof2":
            tools += [AuroraTool(port, 0, 5), AuroraTool(port, 1, 5)]
        else:
            tools.append(AuroraTool(port, 0, 5 if kind == "5dof" else 6, kind != "nosrom"))
    return tools


@dataclass
class EmittedFrame:
    """One BX/TX reply sent: its frame number, when its last byte left, and whether it was damaged."""

    frame: int
    command: str
    emit_ns: int = 0
    corrupted: bool = False


@dataclass
class _Pending:
    due_ns: int
    data: bytes
    frame: EmittedFrame | None = None
    after: Callable[[], None] | None = None  # run once written (the COMM baud switch)


class AuroraSimulator(PtyDevice):
    """An Aurora System Control Unit on a pty. ``start()`` (thread) or ``run()`` (foreground), ``stop()``."""

    thread_name = "aurora-simulator"
    #: A distortion model (``distortion_mm(position_mm) -> mm``, :mod:`.tracker_flags`) or
    #: None: a tool's RMS error grows by the distortion at it (``aurora_error_mm``).
    distortion = None
    #: The characterised volume (``state(position_mm) -> "in" | "partly" | "out"``, ``MeasurementVolume``) or
    #: None: a tool outside it is out of volume (port status 0x40, MISSING unless the reply mode has 0x0800),
    #: near its faces partly out (0x80).
    volume = None

    def __init__(self, scene: Scene | None = None, tools: list[AuroraTool] | None = None,
                 rate_hz: float | None = None, faults: AuroraFaults | None = None, seed: int = 0,
                 link: str | os.PathLike[str] | None = None, duration_s: float | None = None,
                 freeze_tag: str = ndi.DEFAULT_FREEZE_TAG, keep_log: bool = False) -> None:
        self.scene = scene or BuiltinScene(seed)
        if tools is None:
            ports = [s for s in self.scene.sensors if s in ndi.AURORA_PORTS]
            tools = [AuroraTool(p) for p in ports]
        self.tools = tools
        replay_rate = 1.0 / self.scene.period_s if getattr(self.scene, "period_s", None) else None
        self.rate_hz = float(rate_hz or replay_rate or DEFAULT_RATE_HZ)
        self.rng = np.random.default_rng(seed)
        self.duration_s = duration_s
        self.freeze_tag = freeze_tag
        self.keep_log = keep_log
        self.log: list[EmittedFrame] = []
        self.frames_sent = 0
        self.commands: list[str] = []
        self.line_noise_bytes = 0
        self._corrupt_next = 0
        self._drop_next = False
        super().__init__(faults or AuroraFaults(), link)
        self._power_on()

    # -- device state -------------------------------------------------------------------------
    def _power_on(self) -> None:
        """Power-on / after-break state: 9600 8N1, not initialised, handles for every tool present."""
        self.baud = ndi.POWER_ON_BAUD
        self.bits_per_byte = 10
        self.initialized = False
        self.tracking = False
        self._rx = bytearray()
        self._queue: list[_Pending] = []
        self._line_free_ns = 0
        self._garbled = False
        self._tstart_ns = 0
        order = sorted(self.tools, key=lambda t: (t.channel, t.port))
        self.handles = {ndi.FIRST_HANDLE + i: _Handle(ndi.FIRST_HANDLE + i, tool) for i, tool in enumerate(order)}

    @property
    def byte_ns(self) -> float:
        return self.bits_per_byte * 1e9 / self.baud

    # -- public controls (also :meth:`PtyDevice.set_state`, :meth:`PtyDevice.stall`) ------------------------
    def corrupt_next_replies(self, n: int = 1) -> None:
        """Send the next ``n`` BX/TX replies with a wrong CRC."""
        self._corrupt_next += n

    def drop_byte_of_next_reply(self) -> None:
        """Lose one byte (in the middle) of the next BX/TX reply on the line."""
        self._drop_next = True

    def _configure_pty(self) -> None:
        """The line starts at 9600 baud (the Aurora's power-on speed) and the master side sees the host's
        flushes (packet mode: a break is emulated from them)."""
        attrs = termios.tcgetattr(self.slave_fd)
        attrs[4] = attrs[5] = termios.B9600
        termios.tcsetattr(self.slave_fd, termios.TCSANOW, attrs)
        fcntl.ioctl(self.master_fd, termios.TIOCPKT, struct.pack("i", 1))

    # -- truth ------------------------------------------------------------------------------------
    def frame_time_s(self, frame: int) -> float:
        """Scene time of frame number ``frame`` (frames count from 0 at TSTART)."""
        if isinstance(self.scene, ReplayScene):
            return self.scene.frame_offset_s(frame)
        return frame / self.rate_hz

    def truth_for_frame(self, sensor: int, frame: int) -> tuple[np.ndarray, np.ndarray] | None:
        """(quaternion w,x,y,z with w >= 0, position mm) the simulator encodes for ``sensor`` at
        ``frame`` (5-DOF tools: the zero-roll quaternion of the sensor axis), or None if it has none."""
        tool = next((t for t in self.tools if t.sensor == sensor), None)
        if tool is None:
            return None
        pose = pose_at(self.scene, sensor, self.frame_time_s(frame), frame)
        if pose is None:
            return None
        rotation = pose.rotation
        if tool.dof == 5:
            rotation = _zero_roll(rotation[:, 2])
        return rotation_to_quaternion(rotation), np.asarray(pose.position_mm, dtype=float)

    def _quality(self, sensor: int, frame: int) -> float:
        if isinstance(self.scene, ReplayScene):
            pose = self.scene.frame(frame).get(sensor)
            if pose is not None and np.isfinite(pose.quality) and pose.quality > 0:
                return float(pose.quality)
        return CLEAN_ERROR

    # -- main loop (:meth:`PtyDevice.run`) ---------------------------------------------------------
    def _wake_ns(self, wake: int) -> int:
        return min(wake, self._queue[0].due_ns) if self._queue else wake

    def _host_baud(self) -> int | None:
        try:
            return _TERMIOS_BAUD.get(termios.tcgetattr(self.master_fd)[4])
        except termios.error:
            return None

    def _receive(self, packet: bytes) -> None:
        """A packet-mode read: a control byte (0: data follows; else the host's flush) and the data."""
        control, data = packet[0], packet[1:]
        if control != 0:  # TIOCPKT status byte: the host flushed its buffers
            if control & _PKT_FLUSHREAD and control & _PKT_FLUSHWRITE:
                host = self._host_baud()
                if host == ndi.POWER_ON_BAUD and self._garbled:
                    self._break()
            return
        if self._host_baud() != self.baud:
            self.line_noise_bytes += len(data)  # framing errors at the device: nothing it can read
            self._garbled = True
            return
        self._rx.extend(data)
        while b"\r" in self._rx:
            line, _, rest = bytes(self._rx).partition(b"\r")
            self._rx = bytearray(rest)
            self._execute(line)

    def _break(self) -> None:
        """A serial break: reset to the power-on state and say RESET at 9600 baud."""
        self._power_on()
        self._send(ndi.frame_reply("RESET"))

    def _flush_due(self, now: int) -> None:
        while self._queue and self._queue[0].due_ns <= now:
            item = self._queue.pop(0)
            data = item.data
            if self._host_baud() != self.baud:  # the host listens at another speed: it hears noise
                data = self.rng.integers(0, 256, len(data), dtype=np.uint8).tobytes()
            with contextlib.suppress(BlockingIOError, OSError):
                os.write(self.master_fd, data)
            if item.frame is not None:
                item.frame.emit_ns = time.monotonic_ns()
                self.frames_sent += 1
            if item.after is not None:
                item.after()

    # -- output --------------------------------------------------------------------------------------
    def _send(self, data: bytes, frame: EmittedFrame | None = None, after: Callable[[], None] | None = None,
              command_bytes: int = 0) -> None:
        """Queue a reply: written when its last byte would have arrived (after the command's own bytes)."""
        now = time.monotonic_ns()
        start = max(now + int(command_bytes * self.byte_ns), self._line_free_ns, self._stall_until_ns)
        if self._stall_active(now):
            start = max(start, self._stall_until_ns)
        self._line_free_ns = int(start + len(data) * self.byte_ns)
        data = self._line_faults(data)
        # bytes reach the host as they cross the line (ndicapi's reads time out after 0.1 s of silence
        # while probing, so a long reply must not arrive in one piece at its end): chunks of 20 ms, at
        # least 8 bytes (so a BX header arrives whole)
        step = max(CHUNK_MIN_BYTES, int(CHUNK_NS / self.byte_ns))
        for i in range(0, max(len(data), 1), step):
            last = i + step >= len(data)
            self._queue.append(_Pending(int(start + min(i + step, len(data)) * self.byte_ns), data[i:i + step],
                                        frame if last else None, after if last else None))

    def _line_faults(self, data: bytes) -> bytes:
        f = self.faults
        if f.drop <= 0 and f.flip <= 0:
            return data
        arr = np.frombuffer(data, dtype=np.uint8).copy()
        if f.flip > 0:
            hits = self.rng.random(len(arr)) < f.flip
            arr[hits] ^= (1 << self.rng.integers(0, 8, int(hits.sum()))).astype(np.uint8)
        if f.drop > 0:
            arr = arr[self.rng.random(len(arr)) >= f.drop]
        return arr.tobytes()

    def _reply(self, text: str, command_bytes: int, after: Callable[[], None] | None = None) -> None:
        self._send(ndi.frame_reply(text), after=after, command_bytes=command_bytes)

    def _error(self, code: int, command_bytes: int) -> None:
        self._reply(f"ERROR{code:02X}", command_bytes)

    # -- commands ------------------------------------------------------------------------------------
    def _present(self, h: _Handle, t_s: float) -> bool:
        return not h.stale and not self._active("unplug", h.tool.sensor, t_s)

    def _refresh_handles(self) -> None:
        """Plugging: a handle whose tool was unplugged turns stale; a tool present without a live handle
        (plugged back in) gets a new handle, not yet initialised."""
        t_s = self._elapsed_s()
        for h in self.handles.values():
            if not h.freed and not h.stale and self._active("unplug", h.tool.sensor, t_s):
                h.stale = True
        for tool in self.tools:
            if self._active("unplug", tool.sensor, t_s):
                continue
            if not any(h.tool is tool and not h.freed and not h.stale for h in self.handles.values()):
                new = max(self.handles) + 1
                self.handles[new] = _Handle(new, tool)

    def _execute(self, line: bytes) -> None:
        n = len(line) + 1
        self._refresh_handles()
        self._garbled = False
        cmd = ndi.parse_command(line)
        self.commands.append(cmd.name)
        if not cmd.crc_ok:
            self._error(ndi.ERROR_BAD_COMMAND_CRC, n)
            return
        name, args = cmd.name, cmd.args
        if name == "INIT":
            self.initialized = True
            self.tracking = False
            self._reply("OKAY", n)
        elif name == "COMM":
            self._comm(args, n)
        elif name == "VER":
            if args.strip() == "3":
                self._error(ndi.ERROR_VER, n)
            elif args.strip() in ("0", "1", "2", "4", "5"):
                self._reply(ndi.ver_reply(self.freeze_tag), n)
            else:
                self._error(ndi.ERROR_PARAMETERS, n)
        elif name == "BEEP":
            self._reply("1", n)
        elif name == "RESET":
            self._power_on()
            self._reply("RESET", n)
        elif not self.initialized:
            self._error(ndi.ERROR_INITIALIZATION, n)
        elif name in ("BX", "TX"):
            self._frame_reply(name, args, n)
        elif self.tracking and name in ("PHSR", "PHINF", "PINIT", "PENA", "PDIS", "PHF"):
            self._error(ndi.ERROR_BAD_MODE, n)  # "not available during tracking mode" ([CAPI] ndicapi.h)
        elif name == "PHSR":
            self._phsr(args, n)
        elif name == "PHINF":
            self._phinf(args, n)
        elif name in ("PINIT", "PENA", "PDIS", "PHF"):
            self._handle_command(name, args, n)
        elif name == "TSTART":
            self.tracking = True
            self._tstart_ns = time.monotonic_ns()
            self._reply("OKAY", n)
        elif name == "TSTOP":
            self.tracking = False
            self._reply("OKAY", n)
        else:  # GETINFO and everything this firmware does not know
            self._error(ndi.ERROR_INVALID, n)

    def _comm(self, args: str, n: int) -> None:
        if len(args) != 5 or args[0] not in ndi.COMM_BAUD or args[1] not in "01" or args[2] not in "012" \
                or args[3] not in "01" or args[4] not in "01":
            self._error(ndi.ERROR_PARAMETERS, n)
            return
        baud = ndi.COMM_BAUD[args[0]]
        bits = 1 + (8 if args[1] == "0" else 7) + (0 if args[2] == "0" else 1) + (1 if args[3] == "0" else 2)

        def switch() -> None:  # after the OKAY has left at the old speed ([CAPI] ndiCOMMHelper waits 100 ms)
            self.baud, self.bits_per_byte = baud, bits

        self._reply("OKAY", n, after=switch)

    def _handle_status(self, h: _Handle) -> int:
        t_s = self._elapsed_s()
        status = ndi.PORT_OCCUPIED if self._present(h, t_s) else 0
        status |= ndi.PORT_INITIALIZED if h.initialized else 0
        status |= ndi.PORT_ENABLED if h.enabled else 0
        return status

    def _phsr(self, args: str, n: int) -> None:
        try:
            mode = int(args or "0", 16)
        except ValueError:
            mode = -1
        if mode not in range(5):
            self._error(ndi.ERROR_PARAMETERS, n)
            return
        t_s = self._elapsed_s()
        entries = []
        for h in self.handles.values():
            if h.freed:
                continue
            present = self._present(h, t_s)
            keep = {ndi.PHSR_ALL: True, ndi.PHSR_STALE: not present,
                    ndi.PHSR_UNINITIALIZED: present and not h.initialized,
                    ndi.PHSR_UNENABLED: present and h.initialized and not h.enabled,
                    ndi.PHSR_ENABLED: h.enabled}[mode]
            if keep:
                entries.append((h.handle, self._handle_status(h)))
        self._reply(ndi.phsr_reply_text(entries), n)

    def _lookup(self, text: str) -> _Handle | None:
        try:
            h = self.handles.get(int(text[:2], 16))
        except ValueError:
            return None
        return None if h is None or h.freed else h

    def _phinf(self, args: str, n: int) -> None:
        h = self._lookup(args)
        if h is None:
            self._error(ndi.ERROR_HANDLE_NOT_ALLOC, n)
            return
        try:
            mode = int(args[2:6] or "0001", 16)
        except ValueError:
            self._error(ndi.ERROR_PARAMETERS, n)
            return
        status = self._handle_status(h)
        if not status & ndi.PORT_OCCUPIED:
            self._reply("UNOCCUPIED", n)
            return
        tool = h.tool
        fields = {
            # tool type (8), manufacturer (12), revision (3), serial (8), port status (2); [CAPI] ndiPHINFHelper
            # reads the status at offset 31. Type 0B = catheter ([CAPI] NDI_TYPE_CATHETER), the rest (choice).
            "basic": f"0B000000{'NDI':<12}000{0x3A000000 + h.handle:08X}{status & 0xFF:02X}",
            "testing": "00000000",
            "part_number": f"{f'EMREG-SIM-{tool.dof}DOF' if tool.srom else '':<20}",
            "accessories": "00",
            "marker_type": "00",
            "port_location": ndi.port_location(tool.port, tool.channel),
            "gpio": "00",
        }
        self._reply("".join(fields[name] for bit, name, _ in ndi.PHINF_FIELDS if mode & bit), n)

    def _handle_command(self, name: str, args: str, n: int) -> None:
        h = self._lookup(args)
        if h is None:
            self._error(ndi.ERROR_HANDLE_NOT_ALLOC, n)
            return
        if name == "PHF":
            h.freed = True
        elif name == "PINIT":
            if not self._handle_status(h) & ndi.PORT_OCCUPIED:
                self._error(ndi.ERROR_NO_TOOL, n)
                return
            if not h.tool.srom:
                self._error(ndi.ERROR_PINIT_FAIL, n)
                return
            h.initialized = True
        elif name == "PENA":
            mode = args[2:3]
            if not h.initialized:
                self._error(ndi.ERROR_PORT_NOT_INIT, n)
                return
            if mode not in ndi.PENA_MODES:
                self._error(ndi.ERROR_INVALID_MODE, n)
                return
            h.enabled, h.mode = True, mode
        elif name == "PDIS":
            h.enabled = False
        self._reply("OKAY", n)

    def _frame_reply(self, name: str, args: str, n: int) -> None:
        if not self.tracking:
            self._error(ndi.ERROR_BAD_MODE, n)
            return
        try:
            mode = int(args or "0001", 16)
        except ValueError:
            self._error(ndi.ERROR_PARAMETERS, n)
            return
        now = time.monotonic_ns()
        frame = max(0, int((now - self._tstart_ns) * self.rate_hz / 1e9))
        t_s = self._elapsed_s(now)
        reports = []
        system_status = 0
        for h in sorted(self.handles.values(), key=lambda x: x.handle):
            if h.freed:
                continue
            if not h.initialized:
                if self._present(h, t_s):
                    system_status |= ndi.SYSTEM_PORT_OCCUPIED  # a tool plugged in waits for PINIT
                continue
            if not h.enabled:
                reports.append(ndi.ToolReport(h.handle, "disabled", port_status=self._handle_status(h), frame=frame))
                continue
            sensor = h.tool.sensor
            status = self._handle_status(h)
            truth = self.truth_for_frame(sensor, frame)
            where = "in" if self.volume is None or truth is None else self.volume.state(truth[1])
            state = "valid"
            if not status & ndi.PORT_OCCUPIED:
                system_status |= ndi.SYSTEM_PORT_UNOCCUPIED
                state = "missing"
            elif truth is None or self._active("missing", sensor, t_s):
                state = "missing"
            elif self._active("out-of-range", sensor, t_s) or where == "out":
                status |= ndi.PORT_OUT_OF_VOLUME
                if not mode & ndi.REPLY_NOT_NORMALLY_REPORTED:
                    state = "missing"
            elif self._active("partly-out", sensor, t_s) or where == "partly":
                status |= ndi.PORT_PARTIALLY_IN_VOLUME  # a transform, of accuracy the Aurora does not vouch for
            report = ndi.ToolReport(h.handle, state, port_status=status, frame=frame)
            if state == "valid":
                report.quaternion, report.position_mm = truth
                report.error = DISTORTED_ERROR if self._active("distort", sensor, t_s) else self._quality(sensor, frame)
                if self.distortion is not None:

                    report.error = aurora_error_mm(self.distortion.distortion_mm(truth[1]), report.error)
            reports.append(report)
        if name == "BX":
            data = ndi.bx_reply(reports, system_status)
        else:
            data = ndi.frame_reply(ndi.tx_reply_text(reports, system_status))
        emitted = EmittedFrame(frame, name)
        if self._corrupt_next > 0 or (self.faults.crc > 0 and self.rng.random() < self.faults.crc):
            self._corrupt_next = max(0, self._corrupt_next - 1)
            emitted.corrupted = True
            data = _break_crc(data, binary=name == "BX")
        if self._drop_next:
            self._drop_next = False
            emitted.corrupted = True
            data = data[:len(data) // 2] + data[len(data) // 2 + 1:]
        if self.keep_log:
            self.log.append(emitted)
        self._send(data, frame=emitted, command_bytes=n)


def _break_crc(data: bytes, binary: bool) -> bytes:
    """The same reply with a wrong CRC field (binary: the last two bytes; text: the 4 hex digits)."""
    if binary:
        return data[:-2] + bytes([data[-2] ^ 0x5A, data[-1]])
    crc = int(data[-5:-1], 16) ^ 0x1111
    return data[:-5] + f"{crc:04X}\r".encode("ascii")


def _zero_roll(axis: np.ndarray) -> np.ndarray:
    """The rotation taking +Z to ``axis`` by the shortest arc: how a 5-DOF sensor's orientation is
    reported here, its roll being unmeasurable (choice)."""
    z = np.array([0.0, 0.0, 1.0])
    a = np.asarray(axis, dtype=float) / np.linalg.norm(axis)
    v = np.cross(z, a)
    c = float(np.dot(z, a))
    if c < -1 + 1e-12:
        return np.diag([1.0, -1.0, -1.0])
    vx = np.array([[0, -v[2], v[1]], [v[2], 0, -v[0]], [-v[1], v[0], 0]])
    return np.eye(3) + vx + vx @ vx / (1 + c)
