"""NDI Aurora driver on ndicapi, and the live sample source behind ``aurora:///dev/ttyUSB0[?baud=...]``.

What ndicapi does (the C library shipped in the ``ndicapi`` wheel, the one PLUS and
scikit-surgerynditracker use): opening and probing the serial port (``ndiSerialProbe``: INIT at 9600
baud, break + RESET if the device runs at another speed, GETINFO / VER), framing every command with
its CRC16, reading replies (ASCII up to CR, BX by its length header), checking every reply's CRC,
switching the host's line speed after COMM, turning ``ERRORxx`` into error codes, and parsing
PHSR / PHINF / TX / BX replies into per-handle transforms, port status and frame numbers.

What EMReg adds: the start-up sequence (INIT, COMM to the URL's baud, VER to choose BX or TX the way
scikit-surgerynditracker does, free stale handles, PINIT every tool - a tool without SROM is an
error naming its port -, PENA dynamic), the port-handle -> sensor mapping (a tool's sensor number is
its physical port 1..4 read from PHINF's port location, +4 for channel 1 of a 5-DOF splitter, so the
spec's defaults reference = 1, probe = 2 mean ports 1 and 2), the polling loop (a new sample only
for a new frame number; a reply ndicapi rejects - bad CRC, timeout - gives no sample at all), the
mapping of NDI states to EMReg's (MISSING -> out of range, port unoccupied or DISABLED -> not
attached, out-of-volume or partially-out-of-volume bit -> out of range, which of them in the sample's
``extra["flag"]``, its ``transform_status``; the RMS error -> ``quality``),
a tool plugged in during tracking (system status ``SYSTEM_PORT_OCCUPIED``: a replugged tool has a new
handle) initialised and tracked again under its port's sensor number, and counters.

ndicapi is called through ``ctypes`` on the very library the ``ndicapy`` module is built from, not
through ``ndicapy``'s Python functions: ``ndicapy.ndiCommand`` returns every reply as a ``str``, and a
binary BX reply whose length byte is not valid UTF-8 (three or more tools: e.g. 171 = 0xAB bytes for
four) raises ``UnicodeDecodeError`` there (ndicapi 3.7.6), and such a reply with a bad CRC makes the
wrapper release a NULL object. ``ctypes`` also releases the GIL during the blocking serial reads.
"""

from __future__ import annotations

import ctypes
import importlib.util
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from ...core.transforms import quaternion_to_rotation
from ...errors import EMRegError
from ..samples import (
    FLAG_MISSING,
    FLAG_OUT_OF_VOLUME,
    FLAG_PARTLY_OUT_OF_VOLUME,
    STATUS_NOT_ATTACHED,
    STATUS_OK,
    STATUS_OUT_OF_RANGE,
    SensorSample,
)
from . import protocol as ndi

SampleCallback = Callable[[SensorSample], None]

#: Pause after a poll that returned a frame number already seen (choice: short, so that a poll starts in
#: every measuring period even when the host is busy; the line itself paces the polls, ~10 ms each).
IDLE_POLL_S = 0.001
#: Rotation from EMReg's 5-DOF sensor frame to NDI's: a 5-DOF sensor measures only its coil axis, which
#: NDI reports as the sensor's +Z (choice: taken as the coil axis); EMReg's probe axis is the sensor's +X
#: (``probe_axis.py``: ``+x_in`` / ``+x_out``, the trakSTAR Model 90's), so 5-DOF poses are turned by this
#: fixed cyclic permutation (+X -> NDI +Z, det +1) and the coil axis is the probe axis. Roll stays
#: meaningless; nothing in calibration or pairing uses it.
FIVE_DOF_X_TO_NDI = np.array([[0.0, 1.0, 0.0], [0.0, 0.0, 1.0], [1.0, 0.0, 0.0]])
#: Start-up attempts when the line garbles a reply (choice): each attempt starts again from the probe,
#: whose break resets a device a garbled COMM may have left at another speed.
OPEN_ATTEMPTS = 3
#: ndicapi codes of a damaged line rather than a device's answer ([CAPI] ndicapi.h: bad CRC, write
#: error, read error, timeout).
LINE_ERRORS = (ndi.NDI_BAD_CRC, ndi.NDI_TIMEOUT, ndi.NDI_WRITE_ERROR, ndi.NDI_READ_ERROR)
#: The Aurora's measuring rate, at which its frame counter advances (choice: 40 Hz, the Aurora's nominal
#: update rate; ``?rate=`` in the URL overrides it). Sample times come from frame numbers at this rate,
#: not from when a poll happened to be answered: polling jitter would otherwise look like motion.
DEFAULT_RATE_HZ = 40.0
#: Times a start-up command is sent when the line damages its reply (choice).
COMMAND_ATTEMPTS = 3
#: ndiSerialProbe results that mean a device answered but the reply was damaged ([CAPI] ndicapi.h:
#: NDI_PROBE_FAIL, NDI_BAD_REPLY, NDI_NO_FEATURES_FIRMWARE, NDI_COMMAND_VER_FAILED); an open error is not
#: retried.
PROBE_GARBLED = (0x0107, 0x0201, 0x0202, 0x0203)
#: A probe timeout is retried too (choice): ndicapi gives INIT only 0.1 s (after a 0.1 s pause) before it
#: falls back to a break, which a device that answered INIT just late may not follow with RESET; the next
#: probe finds it initialised. A port where nothing answers costs ``OPEN_ATTEMPTS`` probes (~7 s each).
PROBE_RETRIED = (*PROBE_GARBLED, ndi.NDI_TIMEOUT)
#: BX/TX reply option: transforms + out-of-volume ones too ([CAPI] 0x0001 | 0x0800; what [SKS] sends).
REPLY_OPTION = ndi.REPLY_TRANSFORMS | ndi.REPLY_NOT_NORMALLY_REPORTED


class NdicapiLibrary:
    """The ndicapi C functions EMReg uses, from the ``ndicapy`` extension module of the ``ndicapi`` wheel."""

    _instance: NdicapiLibrary | None = None

    def __init__(self) -> None:
        spec = importlib.util.find_spec("ndicapy")
        if spec is None or not spec.origin:
            raise EMRegError("the Aurora needs ndicapi: pip install 'emreg[aurora]' (or pip install ndicapi)")
        lib = ctypes.CDLL(spec.origin)
        vp, i, c = ctypes.c_void_p, ctypes.c_int, ctypes.c_char_p
        sig = {
            "ndiSerialProbe": (i, [c, ctypes.c_bool]), "ndiOpenSerial": (vp, [c]), "ndiCloseSerial": (None, [vp]),
            "ndiGetError": (i, [vp]), "ndiErrorString": (c, [i]),
            "ndiGetPHSRNumberOfHandles": (i, [vp]), "ndiGetPHSRHandle": (i, [vp, i]),
            "ndiGetPHINFPortLocation": (i, [vp, c]), "ndiGetPHINFPartNumber": (i, [vp, c]),
            "ndiGetPHINFPortStatus": (i, [vp]),
            "ndiGetBXTransform": (i, [vp, i, ctypes.POINTER(ctypes.c_float)]), "ndiGetBXPortStatus": (i, [vp, i]),
            "ndiGetBXFrame": (ctypes.c_ulong, [vp, i]), "ndiGetBXSystemStatus": (i, [vp]),
            "ndiGetTXTransform": (i, [vp, i, ctypes.POINTER(ctypes.c_double)]), "ndiGetTXPortStatus": (i, [vp, i]),
            "ndiGetTXFrame": (ctypes.c_ulong, [vp, i]), "ndiGetTXSystemStatus": (i, [vp]),
        }
        for name, (restype, argtypes) in sig.items():
            fn = getattr(lib, name)
            fn.restype, fn.argtypes = restype, argtypes
        lib.ndiCommand.restype = ctypes.c_char_p  # variadic: called as ndiCommand(pol, "%s", text)
        self.lib = lib

    @classmethod
    def get(cls) -> NdicapiLibrary:
        if cls._instance is None:
            cls._instance = cls()
        return cls._instance

    def error_string(self, code: int) -> str:
        return self.lib.ndiErrorString(code).decode("latin-1")


class _LineError(EMRegError):
    """A reply damaged on the line (ndicapi: bad CRC, timeout, read/write error)."""


class _ProbeTimeoutError(_LineError):
    """Nothing answered the probe in time (tried again: see ``PROBE_RETRIED``)."""


@dataclass
class AuroraTool:
    """An enabled tool: its port handle and where it is plugged in."""

    handle: int
    port: int
    channel: int
    sensor: int
    dof: int = 6
    part_number: str = ""


@dataclass
class AuroraStats:
    """What the polling loop saw."""

    polls: int = 0
    frames: int = 0  # replies with a new frame number
    repeated: int = 0  # replies with the frame number already seen
    missed_frames: int = 0  # gaps in the frame numbers
    crc_errors: int = 0
    timeouts: int = 0
    other_errors: int = 0
    replugs: int = 0  # times tracking stopped to initialise a tool plugged in meanwhile

    @property
    def rejected(self) -> int:
        return self.crc_errors + self.timeouts + self.other_errors


class AuroraDriver:
    """An Aurora on a serial port, through ndicapi. ``open()``, ``start(callback)``, ``stop()``, ``close()``.

    ``reply``: ``auto`` (BX unless the firmware is one scikit-surgerynditracker knows needs TX),
    ``bx`` or ``tx``. ``five_dof``: sensor numbers of 5-DOF sensors (their roll is meaningless;
    samples carry ``extra["dof"] = 5`` and the coil axis as the rotation's +X, see ``FIVE_DOF_X_TO_NDI``).
    """

    def __init__(self, port: str, baud: int = ndi.DEFAULT_BAUD, reply: str = "auto",
                 five_dof: tuple[int, ...] = (), rate_hz: float = DEFAULT_RATE_HZ) -> None:
        if baud not in ndi.BAUD_RATES:
            raise EMRegError(f"Aurora baud {baud}: use one of {', '.join(map(str, ndi.BAUD_RATES))}")
        if reply not in ("auto", "bx", "tx"):
            raise EMRegError(f"Aurora reply {reply!r}: use auto, bx or tx")
        self.port = port
        self.baud = baud
        self.reply = reply
        self.five_dof = tuple(five_dof)
        if not rate_hz > 0:
            raise EMRegError(f"Aurora rate {rate_hz}: must be a positive number of Hz")
        self.rate_hz = float(rate_hz)
        self.api = NdicapiLibrary.get()
        self.pol: int | None = None
        self.freeze_tag = ""
        self.use_bx = True
        self.tools: list[AuroraTool] = []
        self.stats = AuroraStats()
        self.error: str | None = None
        self._reader: threading.Thread | None = None
        self._stop = threading.Event()
        self._lock = threading.Lock()

    # -- commands -------------------------------------------------------------------------------------
    def command(self, text: str) -> str:
        """Send one command through ndicapi; its reply without CRC, or EMRegError with ndicapi's error.
        A reply the line damaged is asked for again (``COMMAND_ATTEMPTS``), except after COMM, whose
        damaged OKAY may already have changed the device's speed (the start-up then begins anew)."""
        for _ in range(1 if text.startswith("COMM") else COMMAND_ATTEMPTS):
            reply, code = self._command(text)
            if code not in LINE_ERRORS:
                break
        if code:
            error = _LineError if code in LINE_ERRORS else EMRegError
            raise error(f"Aurora on {self.port}: {text} failed: {self.api.error_string(code)} "
                        f"(ndicapi error {code:#04x})")
        return reply

    def _command(self, text: str) -> tuple[str, int]:
        if self.pol is None:
            raise EMRegError(f"Aurora port {self.port} is not open")
        with self._lock:
            raw = self.api.lib.ndiCommand(ctypes.c_void_p(self.pol), b"%s", text.encode("ascii"))
            code = self.api.lib.ndiGetError(self.pol)
        return (raw or b"").decode("latin-1"), code

    # -- start-up ---------------------------------------------------------------------------------------
    def open(self) -> AuroraDriver:
        """Probe, open, INIT, COMM to ``baud``, VER; then initialise and enable every tool. A reply the
        line garbled (bad CRC, timeout) restarts the sequence, up to ``OPEN_ATTEMPTS`` times."""
        for attempt in range(1, OPEN_ATTEMPTS + 1):
            try:
                return self._open_once()
            except _LineError as exc:
                if attempt == OPEN_ATTEMPTS:
                    why = "" if isinstance(exc, _ProbeTimeoutError) else \
                        "; the serial line garbles replies - check the cable and the baud rate"
                    raise EMRegError(f"{exc} ({attempt} attempts{why})") from None
        raise AssertionError("unreachable")

    def _open_once(self) -> AuroraDriver:
        lib = self.api.lib
        code = lib.ndiSerialProbe(self.port.encode(), False)
        if code != ndi.NDI_OKAY:
            # something answered, but garbled (a bad reply to INIT, GETINFO or VER), or nothing in time: try again
            error = _LineError if code in PROBE_RETRIED else EMRegError
            if code == ndi.NDI_TIMEOUT:
                error = _ProbeTimeoutError
            raise error(f"Aurora on {self.port}: no NDI device answered ({self.api.error_string(code)}); "
                             "check the path, power, cable and permissions (dialout group)")
        pol = lib.ndiOpenSerial(self.port.encode())
        if not pol:
            raise EMRegError(f"Aurora on {self.port}: cannot open the serial port")
        self.pol = pol
        try:
            self.command("INIT:")
            code_digit = next(k for k, v in ndi.COMM_BAUD.items() if v == self.baud)
            self.command(f"COMM:{code_digit}0000")  # 8N1, no handshake; ndicapi follows on the host side
            self.freeze_tag = ndi.freeze_tag_of(self.command("VER:4"))
            self.use_bx = self.reply == "bx" or (self.reply == "auto" and ndi.supports_bx(self.freeze_tag))
            self._initialise_tools()
        except BaseException:
            self.close()
            raise
        return self

    def _handles(self, mode: int) -> list[int]:
        self.command(f"PHSR:{mode:02X}")
        n = self.api.lib.ndiGetPHSRNumberOfHandles(self.pol)
        return [self.api.lib.ndiGetPHSRHandle(self.pol, k) for k in range(n)]

    def _tool_info(self, handle: int) -> tuple[int, int, str]:
        self.command(f"PHINF:{handle:02X}0025")  # basic + part number + port location
        location = ctypes.create_string_buffer(15)
        part = ctypes.create_string_buffer(21)
        self.api.lib.ndiGetPHINFPortLocation(self.pol, location)
        self.api.lib.ndiGetPHINFPartNumber(self.pol, part)
        try:
            port, channel = ndi.parse_port_location(location.raw[:14].decode("latin-1"))
        except ValueError:
            port, channel = 0, 0
        return port, channel, part.raw[:20].decode("latin-1").strip()

    def _initialise_tools(self) -> None:
        for handle in self._handles(ndi.PHSR_STALE):  # handles of tools unplugged earlier
            self.command(f"PHF:{handle:02X}")
        info: dict[int, tuple[int, int, str]] = {}
        for _ in range(8):  # as scikit-surgerynditracker: initialise until no handle waits for it
            waiting = self._handles(ndi.PHSR_UNINITIALIZED)
            if not waiting:
                break
            for handle in waiting:
                info[handle] = self._tool_info(handle)
                for _ in range(COMMAND_ATTEMPTS):
                    reply, code = self._command(f"PINIT:{handle:02X}")
                    if code not in LINE_ERRORS:
                        break
                if code in LINE_ERRORS:
                    raise _LineError(f"Aurora on {self.port}: PINIT:{handle:02X} failed: "
                                     f"{self.api.error_string(code)}")
                if code:
                    port, channel, _ = info[handle]
                    where = f"port {port}" + (f" channel {channel}" if channel else "")
                    hint = (" - the tool has no SROM (NDI 'Unable to initialize Tool-in-Port'); program it "
                            "(NDI Cygna-6D) or unplug it" if code == ndi.ERROR_PINIT_FAIL else "")
                    raise EMRegError(f"Aurora on {self.port}: the tool on {where} (handle {handle:02X}) cannot be "
                                     f"initialised: {self.api.error_string(code)}{hint}")
        for handle in self._handles(ndi.PHSR_UNENABLED):
            if handle not in info:
                info[handle] = self._tool_info(handle)
            self.command(f"PENA:{handle:02X}D")
        self.tools = []
        for handle in self._handles(ndi.PHSR_ENABLED):
            port, channel, part = info.get(handle) or self._tool_info(handle)
            sensor = port + 4 * channel if port else handle
            dof = 5 if sensor in self.five_dof else 6
            self.tools.append(AuroraTool(handle, port, channel, sensor, dof, part))
        if not self.tools:
            raise EMRegError(f"Aurora on {self.port}: no tool is plugged in (no port handle could be enabled)")

    # -- tracking -----------------------------------------------------------------------------------------
    @property
    def streaming(self) -> bool:
        return self._reader is not None

    def start(self, callback: SampleCallback) -> None:
        """TSTART, then poll BX (or TX) in a thread; ``callback(sample)`` per tool for every new frame."""
        if self.streaming:
            raise EMRegError("the Aurora is already tracking")
        self.command("TSTART:")
        self._stop.clear()
        self.error = None
        self._reader = threading.Thread(target=self._poll, args=(callback,), name="aurora-reader", daemon=True)
        self._reader.start()

    def stop(self) -> None:
        """Stop polling and TSTOP (idempotent)."""
        if self._reader is None:
            return
        self._stop.set()
        self._reader.join(timeout=10.0)
        self._reader = None
        if self.pol is not None:
            self._command("TSTOP:")

    def close(self) -> None:
        """Stop and close the port (idempotent)."""
        self.stop()
        if self.pol is not None:
            self.api.lib.ndiCloseSerial(self.pol)
            self.pol = None

    def __enter__(self) -> AuroraDriver:
        return self.open() if self.pol is None else self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def _poll(self, callback: SampleCallback) -> None:
        text = f"{'BX' if self.use_bx else 'TX'}:{REPLY_OPTION:04X}"
        last_frame: int | None = None  # the device's frame number of the last reply used
        first_frame: int | None = None
        last_out: int | None = None  # frame number (and its arrival) of the last samples given out
        last_out_ns = 0
        frame_offset = 0  # added to the device's frame numbers after a restart, so that they keep increasing
        plug_handled = False  # the 'tool plugged in' bit was acted on and has not cleared since (choice: one
        # restart per rise of the bit, so a device that kept it set could not make every poll a restart)
        st = self.stats
        errors_in_row = 0
        try:
            while not self._stop.is_set():
                _, code = self._command(text)
                t_ns = time.monotonic_ns()
                st.polls += 1
                if code:
                    if code == ndi.NDI_BAD_CRC:
                        st.crc_errors += 1
                    elif code == ndi.NDI_TIMEOUT:
                        st.timeouts += 1
                    else:
                        st.other_errors += 1
                    errors_in_row += 1
                    if errors_in_row >= 20:
                        self.error = (f"Aurora on {self.port}: {errors_in_row} replies in a row rejected "
                                      f"({self.api.error_string(code)})")
                        return
                    continue
                errors_in_row = 0
                samples = self._decode(t_ns)
                frame = samples[0].frame if samples else None
                new_frame = frame is not None and frame != last_frame
                if new_frame:
                    if last_frame is not None and frame > last_frame + 1:
                        st.missed_frames += frame - last_frame - 1
                    if last_frame is None and last_out is not None:  # the first frame after a restart
                        gap = max(1, round((t_ns - last_out_ns) * self.rate_hz / 1e9))
                        frame_offset = last_out + gap - frame
                    last_frame = frame
                    st.frames += 1
                    out_frame = frame + frame_offset  # the device's clock: its frame counter, kept increasing
                    if first_frame is None:
                        first_frame = out_frame
                    for sample in samples:
                        sample.extra["device_frame"] = frame
                        sample.frame = out_frame
                        sample.time_s = (out_frame - first_frame) / self.rate_hz
                        callback(sample)
                    last_out, last_out_ns = out_frame, t_ns
                else:
                    st.repeated += 1
                plugged = bool(self._system_status() & ndi.SYSTEM_PORT_OCCUPIED)
                if plugged and not plug_handled:
                    self._reinitialise()
                    last_frame = None  # the device may count its frames anew from TSTART
                    plug_handled = True
                    continue
                plug_handled = plugged
                if not new_frame:
                    self._stop.wait(IDLE_POLL_S)
        except EMRegError as exc:  # a tool plugged in cannot be initialised, or the line failed meanwhile
            self.error = str(exc)
        except Exception as exc:  # pragma: no cover - the callback or the library failed
            self.error = f"Aurora on {self.port}: {exc}"

    def _system_status(self) -> int:
        """System status of the last BX/TX reply ndicapi accepted."""
        lib = self.api.lib
        return int((lib.ndiGetBXSystemStatus if self.use_bx else lib.ndiGetTXSystemStatus)(self.pol))

    def _reinitialise(self) -> None:
        """A tool was plugged in (system status ``SYSTEM_PORT_OCCUPIED``): an unplugged tool's handle is
        stale and a replugged one comes back under a new handle that waits for PINIT / PENA, which the Aurora
        takes only outside tracking. So: TSTOP, free stale handles, initialise and enable the new ones (the
        tool keeps its sensor number: its port), TSTART."""
        self._command("TSTOP:")
        self._initialise_tools()
        self.command("TSTART:")
        self.stats.replugs += 1

    def _decode(self, t_ns: int) -> list[SensorSample]:
        """Samples of every enabled tool from the last BX/TX reply ndicapi accepted."""
        lib, pol = self.api.lib, self.pol
        out = []
        for tool in self.tools:
            if self.use_bx:
                values = (ctypes.c_float * 8)()
                result = lib.ndiGetBXTransform(pol, tool.handle, values)
                port_status = lib.ndiGetBXPortStatus(pol, tool.handle)
                frame = int(lib.ndiGetBXFrame(pol, tool.handle))
            else:
                values = (ctypes.c_double * 8)()
                result = lib.ndiGetTXTransform(pol, tool.handle, values)
                port_status = lib.ndiGetTXPortStatus(pol, tool.handle)
                frame = int(lib.ndiGetTXFrame(pol, tool.handle))
            out.append(self._sample(tool, result, list(values), port_status, frame, t_ns))
        return out

    @staticmethod
    def _sample(tool: AuroraTool, result: int, values: list[float], port_status: int, frame: int,
                t_ns: int) -> SensorSample:
        nan3 = np.full(3, np.nan)
        status, flag = STATUS_OK, None
        if result == 1 or not port_status & ndi.PORT_OCCUPIED:  # NDI_DISABLED, or the tool was unplugged
            status = STATUS_NOT_ATTACHED
        elif result == 2 or port_status & (ndi.PORT_OUT_OF_VOLUME | ndi.PORT_PARTIALLY_IN_VOLUME):
            # NDI_MISSING, or (partly) outside the characterised volume: a transform without its accuracy
            status = STATUS_OUT_OF_RANGE
            flag = (FLAG_PARTLY_OUT_OF_VOLUME if port_status & ndi.PORT_PARTIALLY_IN_VOLUME else
                    FLAG_OUT_OF_VOLUME if port_status & ndi.PORT_OUT_OF_VOLUME else FLAG_MISSING)
        if result == 0:
            quaternion = np.asarray(values[:4], dtype=float)
            position, rotation, error = np.asarray(values[4:7], dtype=float), quaternion_to_rotation(quaternion), \
                float(values[7])
            if tool.dof == 5:
                rotation = rotation @ FIVE_DOF_X_TO_NDI
        else:
            quaternion, position, rotation, error = None, nan3, np.full((3, 3), np.nan), float("nan")
        sample = SensorSample(tool.sensor, 0.0, position, rotation, error, status, frame=frame,
                              received_ns=t_ns)
        sample.extra.update(handle=tool.handle, port_status=port_status, dof=tool.dof, quaternion=quaternion)
        if flag is not None:
            sample.extra["flag"] = flag  # which of the handle's states: the recordings' and clients' TransformStatus
        return sample


def sensors_from_text(text: str | None) -> tuple[int, ...]:
    """'2,3' -> (2, 3) (sensor numbers 1..8)."""
    if not text:
        return ()
    try:
        values = tuple(int(v) for v in text.split(","))
    except ValueError:
        raise EMRegError(f"sensor list {text!r}: use numbers like 2,3") from None
    if any(not 1 <= v <= 8 for v in values):
        raise EMRegError(f"sensor list {text!r}: Aurora sensors are 1..4 (+4 for channel 1 of a splitter)")
    return values
