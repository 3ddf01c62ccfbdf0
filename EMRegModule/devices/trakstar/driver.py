"""A trakSTAR RS-232 client over pyserial: POINT and STREAM, record formats, examine / change value.

Protocol facts and their sources are in :mod:`.protocol`. What the driver adds:

- Framing: records are found by the phasing bit; a record is used only if it passes every check of
  :class:`~.protocol.RecordParser` (start byte, no stray phasing bit, exact length,
  group-mode address, followed by a record start when that byte is already there, no long silence
  inside it while the reader was waiting on the line: bytes found already waiting say nothing about
  silences) *and* its values are possible (:func:`~.protocol.record_values_plausible`).
  Anything else is dropped and counted; the parser resynchronises on the next record start. No
  pose is ever made from a record that failed these checks.
- Limits of the protocol: records carry no checksum, so a flipped *data* bit (bits 0..6) that keeps
  the framing intact cannot be detected by any trakSTAR RS-232 client; the value checks catch the
  large ones in orientation, none in position. Use a shielded cable; the watchdog in
  :mod:`..navigator` adds staleness and quality checks on top.
- Sensor status: the RS-232 records carry no status bits. A port without a sensor answers with an
  all-zero record (position zero is the transmitter's centre, where no sensor can be) and sensor
  serial number 0 ([LTS] ``sensorAttached``); a sensor beyond the position range answers with
  saturated position words ([FOB]: the output saturates at full scale). The driver reports these as
  ``not_attached`` and ``out_of_range`` (choice, documented in the simulator too).
- Quality: with METAL enabled each record ends with a METAL byte, 0 (no distortion) .. 127, reported
  as ``quality``.
- Line settings: 8 data bits, no parity, 1 stop bit, no flow control; RTS left low (RTS high holds
  the unit in reset: [FOB], [IGSTK] Reset()).
"""

from __future__ import annotations

import contextlib
import select
import threading
import time
from collections.abc import Callable, Iterable, Sequence

import numpy as np
import serial

from ...errors import EMRegError
from ..samples import STATUS_NOT_ATTACHED, STATUS_OK, STATUS_OUT_OF_RANGE, SensorSample
from . import protocol as tp
from .protocol import DecodedRecord, FramingStats, RecordFormat, RecordParser

SampleCallback = Callable[[SensorSample], None]


class TrakstarDriver:
    """Talks to a trakSTAR (or the simulator) on a serial port.

    >>> driver = TrakstarDriver("/dev/ttyUSB0").open()          # doctest: +SKIP
    >>> driver.configure(record_format="POSITION/ANGLES")       # doctest: +SKIP
    >>> sample = driver.point(2)                                # doctest: +SKIP
    """

    def __init__(self, port: str, baud: int = tp.DEFAULT_BAUD, timeout_s: float = 0.5,
                 max_gap_ms: float = 50.0) -> None:
        if baud not in tp.BAUD_RATES:
            raise EMRegError(f"baud={baud}: the trakSTAR supports {', '.join(map(str, tp.BAUD_RATES))}")
        self.port = port
        self.baud = baud
        self.timeout_s = timeout_s
        self.serial = None
        self.scale_inches: float = tp.POWER_ON_SCALE_INCHES
        self.rate_hz: float = tp.POWER_ON_RATE_HZ
        self.formats: dict[int, RecordFormat] = dict.fromkeys(range(1, tp.MAX_SENSORS + 1), tp.POWER_ON_FORMAT)
        self.metal: dict[int, bool] = dict.fromkeys(range(1, tp.MAX_SENSORS + 1), False)
        self.group_mode = False
        self.group_sensors: tuple[int, ...] = tuple(range(1, tp.MAX_SENSORS + 1))
        self.parser = RecordParser(tp.record_length(tp.POWER_ON_FORMAT), None, int(max_gap_ms * 1e6))
        self._reader: threading.Thread | None = None
        self._stop_reader = threading.Event()
        self._lock = threading.Lock()
        self._t0_ns = time.monotonic_ns()
        self._frame = -1
        self._frame_time_s = 0.0
        self._last_address = 99
        self._last_end: int | None = None
        self._last_arrival_end: tuple[int, int] | None = None
        self.error: str | None = None
        #: POINT replies discarded because the line carried more or less than one clean reply (see ``_request``)
        self.discarded_replies = 0
        #: ports with a sensor when the stream started; samples of other ports are always "not attached"
        self.attached: frozenset[int] | None = None

    # -- connection ----------------------------------------------------------------------
    def open(self) -> TrakstarDriver:
        """Open the port (8N1, no flow control), stop any stream left running, read the scale."""
        try:
            self.serial = serial.Serial(self.port, self.baud, bytesize=serial.EIGHTBITS, parity=serial.PARITY_NONE,
                                        stopbits=serial.STOPBITS_ONE, timeout=self.timeout_s, xonxoff=False,
                                        rtscts=False, dsrdtr=False)
        except (serial.SerialException, OSError, ValueError) as exc:
            raise EMRegError(f"trakSTAR port {self.port}: cannot open it ({exc}); check the device path "
                             "and permissions (dialout group)") from None
        with contextlib.suppress(Exception):
            self.serial.rts = False
        self._write(bytes([tp.POINT]))  # ends a stream left running by a previous program
        # its reply (or the stream's last records) must not be read as the reply to EXAMINE VALUE:
        # wait until the line is silent, not a fixed time
        self._drain_until_silent(max(0.05, min(self.timeout_s, 0.2)))
        self.scale_inches = 72 if self.examine_word(tp.PARAM_POSITION_SCALING) == 1 else 36
        self.rate_hz = self.examine_word(tp.PARAM_MEASUREMENT_RATE) / 256.0 or tp.POWER_ON_RATE_HZ
        return self

    def close(self) -> None:
        """Stop streaming and close the port (idempotent)."""
        if self.serial is None:
            return
        with contextlib.suppress(Exception):
            self.stop_stream()
        with contextlib.suppress(Exception):
            self.serial.close()
        self.serial = None

    def __enter__(self) -> TrakstarDriver:
        return self.open() if self.serial is None else self

    def __exit__(self, *exc: object) -> None:
        self.close()

    @property
    def stats(self) -> FramingStats:
        """Counters of accepted and rejected records."""
        return self.parser.stats

    # -- low level -----------------------------------------------------------------------
    def _write(self, data: bytes) -> None:
        if self.serial is None:
            raise EMRegError(f"trakSTAR port {self.port} is not open")
        try:
            self.serial.write(data)
            self.serial.flush()
        except Exception as exc:  # serial.SerialException, OSError
            raise EMRegError(f"trakSTAR port {self.port}: write failed ({exc})") from None

    def _read_exact(self, n: int, what: str) -> bytes:
        data = self.serial.read(n)
        if len(data) < n:
            raise EMRegError(f"trakSTAR on {self.port}: no reply to {what} within {self.timeout_s:g} s "
                             f"(got {len(data)} of {n} bytes); check power, cable and baud rate ({self.baud})")
        return data

    def _purge(self) -> None:
        time.sleep(0.002)
        self.serial.reset_input_buffer()
        self.parser.reset()

    @staticmethod
    def _prefix(sensor: int | None) -> bytes:
        return b"" if sensor is None else bytes([tp.address_byte(sensor)])

    # -- examine / change value ----------------------------------------------------------
    def examine(self, param: int, sensor: int | None = None) -> bytes:
        """EXAMINE VALUE: the parameter's reply bytes (plain bytes, no phasing)."""
        if param not in tp.EXAMINE_LENGTH:
            raise ValueError(f"unknown EXAMINE VALUE parameter {param}")
        self._ensure_not_streaming()
        self._write(self._prefix(sensor) + bytes([tp.EXAMINE_VALUE, param]))
        return self._read_exact(tp.EXAMINE_LENGTH[param], f"EXAMINE VALUE {param}")

    def examine_word(self, param: int, sensor: int | None = None) -> int:
        """EXAMINE VALUE of a 1- or 2-byte parameter as an unsigned number (LSB first)."""
        return int.from_bytes(self.examine(param, sensor), "little")

    def change(self, param: int, data: bytes, sensor: int | None = None) -> None:
        """CHANGE VALUE with raw parameter data (length as the protocol wants it)."""
        if tp.CHANGE_LENGTH.get(param) != len(data):
            raise ValueError(f"CHANGE VALUE {param} takes {tp.CHANGE_LENGTH.get(param)} data bytes, got {len(data)}")
        self._ensure_not_streaming()
        self._write(self._prefix(sensor) + bytes([tp.CHANGE_VALUE, param]) + data)

    def error_code(self) -> int:
        """The tracker's last error code (reading clears it); see ``protocol.ERROR_CODES``."""
        return self.examine_word(tp.PARAM_ERROR_CODE)

    def sensor_attached(self, sensor: int) -> bool:
        """True when a sensor is plugged into the port (its serial number is non-zero; [LTS])."""
        return self.examine_word(tp.PARAM_SENSOR_SERIAL, sensor) != 0

    def set_position_scale(self, inches: int) -> None:
        """36- or 72-inch full scale (CHANGE VALUE 3: word 0 or 1)."""
        if inches not in (36, 72):
            raise ValueError("the position scale is 36 or 72 inches")
        self.change(tp.PARAM_POSITION_SCALING, (0 if inches == 36 else 1).to_bytes(2, "little"))
        self.scale_inches = inches

    def set_measurement_rate(self, rate_hz: float) -> None:
        """Measurement rate in Hz (CHANGE VALUE 7: rate x 256 as a word; 20..255 Hz)."""
        if not tp.MIN_RATE_HZ <= rate_hz <= tp.MAX_RATE_HZ:
            raise EMRegError(f"measurement rate {rate_hz:g} Hz: the trakSTAR allows "
                             f"{tp.MIN_RATE_HZ:g}..{tp.MAX_RATE_HZ:g} Hz")
        self.change(tp.PARAM_MEASUREMENT_RATE, round(rate_hz * 256).to_bytes(2, "little"))
        self.rate_hz = rate_hz

    def set_group_mode(self, on: bool) -> None:
        """Group mode: POINT / STREAM answer for every sensor, each record followed by its address."""
        self.change(tp.PARAM_GROUP_MODE, bytes([int(on)]))
        self.group_mode = on

    def set_format(self, record_format: str | RecordFormat, sensors: Iterable[int] = (1, 2, 3, 4)) -> None:
        """Select the record format of each sensor (address prefix + format command byte)."""
        fmt = record_format if isinstance(record_format, RecordFormat) else tp.get_format(record_format)
        self._ensure_not_streaming()
        for sensor in sensors:
            self._write(self._prefix(sensor) + bytes([fmt.command]))
            self.formats[sensor] = fmt

    def set_metal(self, on: bool, sensors: Iterable[int] = (1, 2, 3, 4), sensitivity: int = 32) -> None:
        """METAL: append a quality byte (0 best .. 127) to each record of these sensors."""
        self._ensure_not_streaming()
        for sensor in sensors:
            self._write(self._prefix(sensor) + bytes([tp.METAL, int(on), sensitivity & 0x7F]))
            self.metal[sensor] = on

    def configure(self, record_format: str | RecordFormat = "POSITION/ANGLES", metal: bool = True,
                  group: bool = True, rate_hz: float | None = None, scale_inches: int | None = None) -> None:
        """The usual set-up: one format for all four ports, METAL on or off, group mode."""
        if scale_inches is not None:
            self.set_position_scale(scale_inches)
        if rate_hz is not None:
            self.set_measurement_rate(rate_hz)
        self.set_format(record_format)
        self.set_metal(metal)
        self.set_group_mode(group)

    # -- data ----------------------------------------------------------------------------
    def record_length(self, sensor: int) -> int:
        return tp.record_length(self.formats[sensor], self.metal[sensor], self.group_mode)

    def point(self, sensor: int | None = None) -> SensorSample | None:
        """POINT: one record of ``sensor`` (group mode off), or None if it failed framing / timed out."""
        if self.group_mode:
            raise EMRegError("point(sensor) needs group mode off; use point_all() in group mode")
        sensor = sensor or 1
        self._ensure_not_streaming()
        self.parser.configure(self.record_length(sensor), None)
        records = self._request(self._prefix(sensor) + bytes([tp.POINT]), 1, self.record_length(sensor))
        if not records:
            return None
        data, t_ns = records[0]
        return self._sample(data, sensor, t_ns, new_frame=True)

    def point_all(self) -> list[SensorSample]:
        """POINT in group mode: one record per sensor of the flock (those that passed framing)."""
        if not self.group_mode:
            raise EMRegError("point_all() needs group mode (set_group_mode(True))")
        self._ensure_not_streaming()
        length = self._group_length()
        self.parser.configure(length, self.group_sensors)
        samples = []
        first = True
        for data, t_ns in self._request(bytes([tp.POINT]), len(self.group_sensors), length):
            sample = self._sample(data, None, t_ns, new_frame=first)
            first = False
            if sample is not None:
                samples.append(sample)
        return samples

    def _request(self, command: bytes, count: int, length: int) -> list[tuple[bytes, int]]:
        """Send a POINT request and read the ``count`` records of ``length`` bytes that answer it.

        The protocol has no request id: a record is only known to answer this request when nothing
        else can be on the line. So the bytes already waiting are discarded before the request; after
        a reply that timed out, came short or failed framing, the line is drained until it has been
        silent for ``timeout_s`` (a late reply to this request arrives meanwhile and is thrown away,
        never taken as the reply to the next request); and a reply followed by more bytes within two
        record times is discarded whole (its first records may have been a late reply to an earlier
        request, the rest this one's), then the line is drained. Counted in ``discarded_replies``.
        """
        self.serial.reset_input_buffer()
        self.parser.reset()
        stats = self.parser.stats
        failed_before = stats.rejected + stats.stray_bytes
        self._write(command)
        records = self._read_records(count, length)
        clean = len(records) == count and stats.rejected + stats.stray_bytes == failed_before
        if clean and self._more_bytes_within(max(0.002, 2 * length * tp.BITS_PER_BYTE / self.baud)):
            records, clean = [], False  # more than one reply on the line: none of it can be trusted
        if not clean:
            self.discarded_replies += 1
            self._drain_until_silent(self.timeout_s)
        return records

    def _more_bytes_within(self, seconds: float) -> bool:
        """True when a byte arrives (or is already waiting) within ``seconds``."""
        return bool(self.serial.in_waiting) or self._readable_within(seconds)

    def _readable_within(self, seconds: float) -> bool:
        try:
            readable, _, _ = select.select([self.serial.fileno()], [], [], seconds)
        except (OSError, ValueError):
            return False
        return bool(readable)

    def _drain_until_silent(self, quiet_s: float, max_s: float | None = None) -> None:
        """Read and discard until the line has been silent for ``quiet_s`` (at most ``max_s``,
        default 10 x ``quiet_s``: a device that never stops talking is left to the next request's
        framing)."""
        deadline = time.monotonic() + (10 * quiet_s if max_s is None else max_s)
        while time.monotonic() < deadline and self._more_bytes_within(quiet_s):
            self.serial.read(max(1, min(self.serial.in_waiting, 4096)))
        self.serial.reset_input_buffer()
        self.parser.reset()

    def _read_records(self, count: int, length: int) -> list[tuple[bytes, int]]:
        deadline = time.monotonic() + self.timeout_s
        out: list[tuple[bytes, int]] = []
        while len(out) < count and time.monotonic() < deadline:
            need = max(1, min(self.serial.in_waiting, 4096))
            chunk = self.serial.read(need)
            if not chunk:
                continue
            t_ns = time.monotonic_ns()
            out.extend((r, t_ns) for r in self.parser.feed(chunk, t_ns))
        return out

    def _group_length(self) -> int:
        lengths = {tp.record_length(self.formats[s], self.metal[s], True) for s in self.group_sensors}
        if len(lengths) != 1:
            raise EMRegError("group mode needs the same record format and METAL setting on every sensor; "
                             "use configure()")
        return lengths.pop()

    def _sample(self, data: bytes, sensor: int | None, t_ns: int, new_frame: bool = False,
                received_ns: int | None = None) -> SensorSample | None:
        """Decode a framed record into a sample; None (and counted) when its values are impossible.

        ``t_ns``: when the record arrived (a new frame takes its time from it); ``received_ns``: when
        the reader got it (default ``t_ns``)."""
        if sensor is None:
            sensor = data[-1] & 0x7F
        fmt = self.formats[sensor]
        record = tp.decode_record(fmt, data, self.scale_inches, self.metal[sensor], self.group_mode)
        if new_frame:  # a cycle starts even when its first record is then refused
            self._frame += 1
            self._frame_time_s = (t_ns - self._t0_ns) / 1e9
        if not tp.record_values_plausible(record):
            self.parser.stats.value_errors += 1
            self.parser.stats.records -= 1
            return None
        return record_to_sample(record, sensor, self._frame_time_s, self._frame,
                                t_ns if received_ns is None else received_ns)

    # -- streaming -----------------------------------------------------------------------
    @property
    def streaming(self) -> bool:
        return self._reader is not None

    def start_stream(self, callback: SampleCallback, group: bool = True) -> None:
        """STREAM: records of every sensor at the measurement rate; ``callback(sample)`` runs in the
        reader thread for each accepted record (keep it short: it is on the latency path)."""
        if self.streaming:
            raise EMRegError("the trakSTAR is already streaming")
        if group and not self.group_mode:
            self.set_group_mode(True)
        length = self._group_length() if self.group_mode else self.record_length(1)
        if self.group_mode:  # a corrupted record of an empty port would look like a pose: it stays "not attached"
            self.attached = frozenset(s for s in self.group_sensors if self.sensor_attached(s))
        self.parser.configure(length, self.group_sensors if self.group_mode else None)
        self.serial.reset_input_buffer()
        self._t0_ns = time.monotonic_ns()
        self._frame = -1
        self._last_address = 99
        self._last_end = None
        self._last_arrival_end = None
        self._stop_reader.clear()
        self.error = None
        self._write(bytes([tp.STREAM]))
        self._reader = threading.Thread(target=self._read_stream, args=(callback,), name="trakstar-reader",
                                        daemon=True)
        self._reader.start()

    def stop_stream(self) -> None:
        """End STREAM mode (POINT byte), stop the reader thread and discard what is still in flight (records
        already read but not yet handed to the callback included: it is not called again)."""
        if self._reader is None:
            return
        self._stop_reader.set()
        with contextlib.suppress(EMRegError):
            self._write(bytes([tp.POINT]))
        self._reader.join(timeout=2.0)
        self._reader = None
        time.sleep(0.02)
        with contextlib.suppress(Exception):
            self._purge()

    def _ensure_not_streaming(self) -> None:
        if self.streaming:
            self.stop_stream()
        if self.serial is None:
            raise EMRegError(f"trakSTAR port {self.port} is not open")

    def _read_stream(self, callback: SampleCallback) -> None:
        ser = self.serial
        try:
            while not self._stop_reader.is_set():
                # bytes already waiting: the reader is late, and how late says nothing about the line
                late = ser.in_waiting > 0
                chunk = ser.read(1)
                if not chunk:
                    continue
                waiting = ser.in_waiting
                if waiting:
                    chunk += ser.read(waiting)
                t_ns = time.monotonic_ns()
                records = self.parser.feed(chunk, t_ns, timed=not late)
                for data, end in zip(records, self.parser.ends, strict=True):
                    if self._stop_reader.is_set():
                        # stop_stream() discards what is still in flight: a late reader may hold a whole input
                        # buffer of records (4 KB, ~70 cycles), and delivering them all to a slow callback would
                        # outlast the join; the callback is never called once stop_stream() has returned
                        break
                    address = data[-1] & 0x7F if self.group_mode else 1
                    new_frame = self._starts_cycle(address, end, len(data))
                    arrival_ns = self._arrival_ns(t_ns, end)
                    sample = self._sample(data, address, arrival_ns, new_frame, received_ns=t_ns)
                    if sample is not None:
                        if self.attached is not None and sample.sensor not in self.attached:
                            sample.status = STATUS_NOT_ATTACHED  # whatever a corrupted record of it says
                        callback(sample)
        except Exception as exc:  # the port vanished (cable pulled, simulator stopped)
            if not self._stop_reader.is_set():
                self.error = f"trakSTAR port {self.port}: read failed ({exc})"

    def _starts_cycle(self, address: int, end: int, length: int) -> bool:
        """True when an accepted stream record begins a new measurement cycle (decided by the data only).

        In group mode every port of the unit answers each cycle, one record of ``length`` bytes per
        port, in port order, back to back ([FOB] group mode); outside group mode each record is a
        cycle. So a record starts a new cycle when its port does not come after the previous record's
        port, or when more bytes lie between the two records than the ports skipped between them
        could fill (records of a later cycle were lost in between). A dropped byte only shortens that
        gap, so lost bytes never merge two cycles unless at least a whole cycle's bytes vanished.
        When the reader is late (a loaded host) the bytes wait in the input buffer: the host time
        between records says nothing about the cycle and is not used.
        """
        previous_address, previous_end = self._last_address, self._last_end
        self._last_address, self._last_end = address, end
        if not self.group_mode or previous_end is None or address not in self.group_sensors \
                or previous_address not in self.group_sensors:
            return True
        skipped_ports = self.group_sensors.index(address) - self.group_sensors.index(previous_address) - 1
        if skipped_ports < 0:
            return True
        bytes_between = end - length - previous_end
        return bytes_between > skipped_ports * length

    def _arrival_ns(self, read_ns: int, end: int) -> int:
        """When a record's last byte reached the host (monotonic ns), estimated from the line rate.

        A read returns every byte waiting, so a record followed by ``k`` more bytes of the same read
        was complete at least ``k`` byte times (10 bits at the baud rate) before the read. Two
        records cannot arrive closer than the line time of the bytes between their ends, which also
        keeps the estimate strictly increasing when a late reader collects several cycles at once.
        """
        byte_ns = tp.BITS_PER_BYTE * 1e9 / self.baud
        arrival = read_ns - int((self.parser.offset - end) * byte_ns)
        if self._last_arrival_end is not None:
            previous_ns, previous_end = self._last_arrival_end
            arrival = max(arrival, previous_ns + int((end - previous_end) * byte_ns))
        self._last_arrival_end = (arrival, end)
        return arrival


def record_to_sample(record: DecodedRecord, sensor: int, time_s: float, frame: int, received_ns: int) -> SensorSample:
    """A :class:`SensorSample` from a decoded record (missing parts NaN; status from the record)."""
    position = record.position_mm if record.position_mm is not None else np.full(3, np.nan)
    rotation = record.rotation()
    if rotation is None:
        rotation = np.full((3, 3), np.nan)
    status = STATUS_OK
    if record.all_zero:
        status = STATUS_NOT_ATTACHED
    elif record.saturated:
        status = STATUS_OUT_OF_RANGE
    quality = float(record.metal) if record.metal is not None else float("nan")
    sample = SensorSample(sensor, time_s, np.asarray(position, dtype=float), rotation, quality, status,
                          frame=frame, received_ns=received_ns, angles_deg=record.angles())
    sample.extra["record"] = record
    return sample


def sensors_from_list(text: str | Sequence[int] | None) -> tuple[int, ...]:
    """Sensor ports from '1,2,3' (or a sequence); each 1..4."""
    if text is None:
        return tuple(range(1, tp.MAX_SENSORS + 1))
    values = [int(v) for v in text.split(",")] if isinstance(text, str) else [int(v) for v in text]
    if not values or any(not 1 <= v <= tp.MAX_SENSORS for v in values):
        raise EMRegError(f"sensor ports must be 1..{tp.MAX_SENSORS}, got {text}")
    return tuple(values)
