"""The trakSTAR RS-232 binary protocol: command bytes, record formats, word coding, record framing.

The 3D Guidance trakSTAR speaks, on its RS-232 port, the binary command set of Ascension's Flock of
Birds (FOB). Sources, cited constant by constant below:

- [TSG] "3D Guidance trakSTAR Installation and Operation Guide" (Ascension / NDI), chapter "RS-232
  Commands". The guide itself was not among the documents reachable while this was written; every
  fact taken from it was checked against [FOB] and [IGSTK] / [LTS], and where only the guide could
  settle a point the choice made is marked "(choice)".
- [FOB] "Flock of Birds Installation and Operation Guide" (Ascension), the ancestor command set the
  trakSTAR keeps: command bytes, CHANGE/EXAMINE VALUE parameter numbers, status bits, error codes.
- [IGSTK] Kitware's IGSTK ``igstkAscensionCommandInterpreter`` and D. Gobbi's ``flock.h``: the same
  byte values, the examine/change data lengths, the phase-error recovery.
- [LTS] the public-domain ``trakstar/PointATC3DG`` driver (S. Yun, SRI), which sends the very same
  bytes to a trakSTAR over USB: sensor addressing ``0xF1 + i``, POINT replies, position scale,
  measurement rate coding, the error-code table.

Data words (all three sources agree): a word is two bytes, least significant first; only 7 bits of
each byte carry data, bit 7 is the *phasing* bit, set on the first byte of a record and clear on
every other byte, so a receiver can find where records start. The 14 data bits form a signed
number ``value = ((msb << 7) | (lsb & 0x7F)) << 2`` read as a signed 16-bit integer. Positions are
``value * scale / 32768`` inches (scale 36 or 72), angles ``value * 180 / 32768`` degrees, matrix
and quaternion elements ``value / 32768``. EXAMINE VALUE replies are plain bytes (no phasing).
"""

from __future__ import annotations

from collections.abc import Iterable
from dataclasses import dataclass, field

import numpy as np

from ...core.transforms import angles_to_rotation, quaternion_to_rotation, rotation_to_angles, rotation_to_quaternion
from ...names import DEFAULT_TRAKSTAR_BAUD

# --- serial line -------------------------------------------------------------------------------

#: Baud rates the trakSTAR RS-232 port supports ([TSG] rear-panel dip switches; [FOB] 2400..115200).
BAUD_RATES = (2400, 4800, 9600, 19200, 38400, 57600, 115200)
#: Default line speed used by EMReg (the fastest; [TSG] factory setting is also 115200 (choice)).
DEFAULT_BAUD = DEFAULT_TRAKSTAR_BAUD
#: 8 data bits, no parity, 1 stop bit, no handshake ([FOB] "RS232 interface"; [IGSTK] opens 8N1):
#: one start + 8 data + one stop bit = 10 bit times on the line per byte.
BITS_PER_BYTE = 10
#: Inches to millimetres.
MM_PER_INCH = 25.4

# --- command bytes ([FOB] RS232 command table; [IGSTK] flock.h; [LTS]) -----------------------------

POINT = 0x42  # 'B': one record (one per sensor in group mode); also ends STREAM mode
STREAM = 0x40  # '@': records continuously at the measurement rate until a POINT ('B') arrives
RUN = 0x46  # 'F'
SLEEP = 0x47  # 'G'
EXAMINE_VALUE = 0x4F  # 'O' + PARAMETERnumber -> reply bytes
CHANGE_VALUE = 0x50  # 'P' + PARAMETERnumber + PARAMETERdata
HEMISPHERE = 0x4C  # 'L' + 2 bytes ([IGSTK] SendCommandWords FB_HEMISPHERE, 1 word)
FBB_RESET = 0x2F  # '/'
RESET = 0x62  # 'b' ([LTS] RESET 0x62; software reset to the power-on state)
METAL = 0x73  # 's' + flag byte + data byte ([LTS] defines METAL 0x73; [TSG] metal error reporting) (choice: 2 bytes)
XON = 0x11
XOFF = 0x13
#: RS232 TO FBB: ``0xF0 + address`` sends the next command to FBB address 1..14 ([FOB], [IGSTK]);
#: on the trakSTAR the four sensor ports are addresses 1..4, i.e. sensor port p -> ``0xF0 + p``
#: (= ``0xF1 + i`` for i = 0..3 in [LTS]).
ADDRESS_BASE = 0xF0
MAX_SENSORS = 4


def address_byte(sensor: int) -> int:
    """The RS232-TO-FBB prefix byte that sends the next command to sensor port 1..4."""
    if not 1 <= sensor <= MAX_SENSORS:
        raise ValueError(f"trakSTAR sensor ports are 1..{MAX_SENSORS}, got {sensor}")
    return ADDRESS_BASE + sensor


# --- CHANGE / EXAMINE VALUE parameters ([FOB] table; numbers and lengths as in [IGSTK]) -----------

PARAM_STATUS = 0  # 2 bytes: bird status word (bits below)
PARAM_REVISION = 1  # 2 bytes: software revision (integer part, fraction)
PARAM_SPEED = 2  # 2 bytes: crystal speed
PARAM_POSITION_SCALING = 3  # 2 bytes: 0 -> 36 inch full scale, 1 -> 72 inch ([LTS]: reply byte 0 == 1 -> 72)
PARAM_FILTER = 4  # 2 bytes
PARAM_RATE_COUNT = 6  # 2 bytes
PARAM_MEASUREMENT_RATE = 7  # 2 bytes: rate in Hz x 256 ([LTS] setMeasurementRate; [FOB])
PARAM_ERROR_CODE = 10  # 1 byte: last error (table below), cleared by reading ([FOB])
PARAM_ERROR_BEHAVIOR = 11  # 1 byte
PARAM_SUDDEN_OUTPUT_CHANGE_LOCK = 14  # 1 byte ([LTS])
PARAM_SYSTEM_MODEL = 15  # 10 bytes: model identification string
PARAM_EXPANDED_ERROR_CODE = 16  # 2 bytes: error code, address
PARAM_BIRD_SERIAL = 25  # 2 bytes
PARAM_SENSOR_SERIAL = 26  # 2 bytes: 0 when no sensor is plugged into the port ([LTS] sensorAttached)
PARAM_TRANSMITTER_SERIAL = 27  # 2 bytes: 0 when no transmitter ([LTS] transmitterAttached)
PARAM_GROUP_MODE = 35  # 1 byte: 1 = POINT/STREAM answer for every sensor, each record + address byte
PARAM_FBB_STATUS = 36  # 14 bytes (normal addressing): one status byte per FBB address 1..14
PARAM_FBB_AUTOCONFIG = 50  # change: 1 byte (number of units); examine: 5 bytes ([IGSTK])

#: EXAMINE VALUE reply length in bytes per parameter ([IGSTK] examine_change_len_table).
EXAMINE_LENGTH = {
    PARAM_STATUS: 2, PARAM_REVISION: 2, PARAM_SPEED: 2, PARAM_POSITION_SCALING: 2, PARAM_FILTER: 2,
    PARAM_RATE_COUNT: 2, PARAM_MEASUREMENT_RATE: 2, 8: 1, 9: 1, PARAM_ERROR_CODE: 1,
    PARAM_ERROR_BEHAVIOR: 1, PARAM_SUDDEN_OUTPUT_CHANGE_LOCK: 1, PARAM_SYSTEM_MODEL: 10,
    PARAM_EXPANDED_ERROR_CODE: 2, 17: 1, 18: 1, 19: 1, 20: 1, 21: 1, 22: 2,
    PARAM_BIRD_SERIAL: 2, PARAM_SENSOR_SERIAL: 2, PARAM_TRANSMITTER_SERIAL: 2, 32: 2,
    PARAM_GROUP_MODE: 1, PARAM_FBB_STATUS: 14, PARAM_FBB_AUTOCONFIG: 5,
}
#: CHANGE VALUE data length in bytes per parameter ([IGSTK] ChangeValue). Position scaling takes a
#: 2-byte word as [FOB]/[IGSTK] send it ([LTS] sends a single byte; a trailing 0x00 is harmless on a
#: device that expects one byte, a missing byte is not, so EMReg sends two) (choice).
CHANGE_LENGTH = {
    PARAM_POSITION_SCALING: 2, PARAM_FILTER: 2, PARAM_MEASUREMENT_RATE: 2, 8: 1, 9: 1,
    PARAM_ERROR_BEHAVIOR: 1, PARAM_SUDDEN_OUTPUT_CHANGE_LOCK: 1, 17: 1, 18: 1, 20: 1, 22: 2, 32: 2,
    PARAM_GROUP_MODE: 1, PARAM_FBB_AUTOCONFIG: 1,
}

# Bird status word bits (EXAMINE VALUE parameter 0; [FOB], [IGSTK] flock.h).
STATUS_STREAMING = 0x0001
STATUS_FORMAT_MASK = 0x001E  # (format command byte - 'V' + 1) << 1
STATUS_SLEEPING = 0x0020
STATUS_RUNNING = 0x1000
STATUS_ERROR = 0x2000
STATUS_INITIALIZED = 0x4000
STATUS_MASTER = 0x8000
# FBB status byte bits (parameter 36; [FOB], [IGSTK]).
FBB_STATUS_SENSOR = 0x20  # a sensor is attached to this unit
FBB_STATUS_RUNNING = 0x40
FBB_STATUS_ACCESSIBLE = 0x80

#: Power-on state ([TSG]: 36-inch position scale, POSITION/ANGLES records, point mode, group mode
#: off). Measurement rate 80 Hz (the 3D Guidance default; range 20..255 Hz) (choice, from the
#: 3D Guidance API's documented default as PLUS uses it).
POWER_ON_SCALE_INCHES = 36
POWER_ON_RATE_HZ = 80.0
MIN_RATE_HZ, MAX_RATE_HZ = 20.0, 255.0

#: Error codes returned by EXAMINE VALUE ERROR CODE ([FOB] error code table, as listed in [LTS]).
ERROR_CODES = {
    0: "no error", 1: "system RAM failure", 2: "non-volatile storage write failure",
    3: "PCB configuration data corrupt", 4: "transmitter calibration data corrupt or not connected",
    5: "sensor calibration data corrupt or not connected", 6: "invalid RS232 command",
    7: "not an FBB master", 8: "no birds accessible in device list", 9: "bird is not initialized",
    10: "FBB serial port receive error (intra bird bus)", 11: "RS232 serial port receive error",
    12: "FBB serial port receive error", 13: "no FBB command response", 14: "invalid FBB host command",
    15: "FBB run time error", 16: "invalid CPU speed", 17: "no FBB data", 18: "illegal baud rate",
    19: "slave acknowledge error", 28: "CRT synchronization", 29: "transmitter not accessible",
    30: "extended range transmitter not attached", 32: "sensor saturated", 33: "slave configuration",
    34: "watch dog timer", 35: "over temperature",
}
ERROR_INVALID_COMMAND = 6
ERROR_SENSOR_NOT_CONNECTED = 5
ERROR_SENSOR_SATURATED = 32
#: Largest METAL (quality) byte: 7 data bits ([TSG] metal error 0..127, 0 = no distortion).
METAL_MAX = 127

# --- record formats ---------------------------------------------------------------------------


@dataclass(frozen=True)
class RecordFormat:
    """One trakSTAR record format: its command byte and what its words hold.

    ``parts`` lists (kind, word count) in record order; kinds are ``position`` (x, y, z),
    ``angles`` (azimuth, elevation, roll), ``matrix`` (9 elements, see :func:`encode_record`) and
    ``quaternion`` (q0 = w, q1, q2, q3).
    """

    name: str
    command: int
    parts: tuple[tuple[str, int], ...]

    @property
    def words(self) -> int:
        """Data words in one record."""
        return sum(n for _, n in self.parts)

    def has(self, kind: str) -> bool:
        """True when the record carries ``kind`` (position, angles, matrix, quaternion)."""
        return any(k == kind for k, _ in self.parts)

    @property
    def status_code(self) -> int:
        """The format's code in bits 1..4 of the bird status word ([FOB])."""
        return self.command - ord("V") + 1


#: The seven record formats ([FOB] command table; word counts 3, 3, 9, 6, 12, 4, 7 as in [IGSTK]).
FORMATS: dict[str, RecordFormat] = {
    "POSITION": RecordFormat("POSITION", ord("V"), (("position", 3),)),
    "ANGLES": RecordFormat("ANGLES", ord("W"), (("angles", 3),)),
    "MATRIX": RecordFormat("MATRIX", ord("X"), (("matrix", 9),)),
    "POSITION/ANGLES": RecordFormat("POSITION/ANGLES", ord("Y"), (("position", 3), ("angles", 3))),
    "POSITION/MATRIX": RecordFormat("POSITION/MATRIX", ord("Z"), (("position", 3), ("matrix", 9))),
    "QUATERNION": RecordFormat("QUATERNION", ord("\\"), (("quaternion", 4),)),
    "POSITION/QUATERNION": RecordFormat("POSITION/QUATERNION", ord("]"), (("position", 3), ("quaternion", 4))),
}
FORMAT_BY_COMMAND = {f.command: f for f in FORMATS.values()}
#: Power-on record format ([TSG]).
POWER_ON_FORMAT = FORMATS["POSITION/ANGLES"]


def get_format(name: str) -> RecordFormat:
    """A record format by name (case-insensitive; ``_`` or ``-`` may replace ``/``)."""
    key = name.strip().upper().replace("_", "/").replace("-", "/")
    if key not in FORMATS:
        raise ValueError(f"unknown trakSTAR record format {name!r}; use one of {', '.join(FORMATS)}")
    return FORMATS[key]


def record_length(fmt: RecordFormat, metal: bool = False, group: bool = False) -> int:
    """Bytes in one record: 2 per word, + 1 METAL byte if enabled, + 1 address byte in group mode.

    [FOB]/[IGSTK]: in group mode the FBB address of the sensor follows the data (and the button
    byte, which the trakSTAR has not); [TSG]: the METAL byte follows the data words (choice: the
    METAL byte comes before the group address byte).
    """
    return 2 * fmt.words + int(metal) + int(group)


def bytes_per_second(baud: int) -> float:
    """Bytes per second an 8N1 line carries at ``baud``."""
    return baud / BITS_PER_BYTE


def max_stream_rate_hz(fmt: RecordFormat, sensors: int, baud: int = DEFAULT_BAUD, metal: bool = False,
                       group: bool = True) -> float:
    """The highest measurement rate whose records for ``sensors`` sensors fit on the line."""
    return bytes_per_second(baud) / (sensors * record_length(fmt, metal, group))


# --- words ------------------------------------------------------------------------------------

#: A data word holds 14 significant bits: raw values -8192..8191, i.e. 16-bit values in steps of 4.
RAW_MIN, RAW_MAX = -8192, 8191
WORD_STEP = 4
FULL_SCALE_COUNTS = 32768.0


def quantise(values: Iterable[float] | np.ndarray, full_scale: float) -> np.ndarray:
    """Raw 14-bit numbers for physical values (``value / full_scale * 32768`` rounded to steps of 4).

    Values beyond full scale saturate at the largest raw number of their sign (the device's own
    behaviour when a sensor leaves the position range).
    """
    counts = np.asarray(values, dtype=float) / full_scale * FULL_SCALE_COUNTS / WORD_STEP
    return np.clip(np.rint(counts), RAW_MIN, RAW_MAX).astype(np.int64)


def raw_to_value(raw: np.ndarray, full_scale: float) -> np.ndarray:
    """Physical values from raw 14-bit numbers (inverse of :func:`quantise` up to rounding)."""
    return np.asarray(raw, dtype=float) * WORD_STEP * full_scale / FULL_SCALE_COUNTS


def encode_words(raw: np.ndarray) -> bytes:
    """Bytes (LSB first, 7 data bits each, phasing bit clear) of raw 14-bit numbers."""
    u = np.asarray(raw, dtype=np.int64) & 0x3FFF
    out = np.empty(2 * len(u), dtype=np.uint8)
    out[0::2] = u & 0x7F
    out[1::2] = (u >> 7) & 0x7F
    return out.tobytes()


def decode_words(data: bytes | bytearray | memoryview) -> np.ndarray:
    """Raw 14-bit numbers (signed) of consecutive words; the phasing bit is ignored.

    Equivalent to the vendor formula ``((msb << 7) | (lsb & 0x7F)) << 2`` read as int16, divided
    by 4.
    """
    b = np.frombuffer(bytes(data), dtype=np.uint8).astype(np.int64)
    u = ((b[1::2] & 0x7F) << 7) | (b[0::2] & 0x7F)
    return np.where(u >= 0x2000, u - 0x4000, u)


def word_value(lsb: int, msb: int) -> int:
    """The signed 16-bit value of one word exactly as the vendor writes it (for documentation/tests)."""
    value = (((msb & 0x7F) << 7) | (lsb & 0x7F)) << 2
    return value - 0x10000 if value & 0x8000 else value


# --- records ----------------------------------------------------------------------------------


@dataclass
class Pose:
    """A sensor pose as the tracker measures it: position (mm) and angles (deg) in the Tracker frame.

    ``rotation`` (SensorToTracker, ``Rz(az) @ Ry(el) @ Rx(roll)``) and ``quaternion`` (w, x, y, z,
    w >= 0) are derived on demand.
    """

    position_mm: np.ndarray
    angles_deg: np.ndarray
    quality: float = 0.0  # what the METAL byte reports for this pose (0 = clean), when enabled

    @property
    def rotation(self) -> np.ndarray:
        a = self.angles_deg
        return angles_to_rotation(a[0], a[1], a[2])

    @property
    def quaternion(self) -> np.ndarray:
        return rotation_to_quaternion(self.rotation)


def encode_record(fmt: RecordFormat, pose: Pose, scale_inches: float, metal: int | None = None,
                  address: int | None = None) -> bytes:
    """The bytes the tracker sends for one sensor record (phasing bit set on the first byte).

    MATRIX words are the rotation ``SensorToTracker`` in row-major order: [FOB] sends
    M(1,1), M(2,1), M(3,1), M(1,2)... of a matrix M whose first row is (cos E cos A, cos E sin A,
    -sin E), i.e. M = R transposed, so the stream is R row by row ([IGSTK] GetMatrix agrees).
    QUATERNION words are (w, x, y, z) of the same rotation with w >= 0 (choice: [TSG] gives q0 as
    the scalar part; its sign convention could not be re-checked).
    """
    raw: list[np.ndarray] = []
    for kind, _ in fmt.parts:
        if kind == "position":
            raw.append(quantise(np.asarray(pose.position_mm) / MM_PER_INCH, scale_inches))
        elif kind == "angles":
            raw.append(quantise(_wrap_angles(pose.angles_deg), 180.0))
        elif kind == "matrix":
            raw.append(quantise(pose.rotation.reshape(9), 1.0))
        else:
            raw.append(quantise(pose.quaternion, 1.0))
    data = bytearray(encode_words(np.concatenate(raw)))
    data[0] |= 0x80
    if metal is not None:
        data.append(int(min(max(metal, 0), METAL_MAX)))
    if address is not None:
        data.append(address & 0x7F)
    return bytes(data)


def zero_record(fmt: RecordFormat, metal: bool = False, address: int | None = None) -> bytes:
    """An all-zero record: what the tracker sends for a port without a sensor (choice, see driver)."""
    data = bytearray(2 * fmt.words)
    data[0] = 0x80
    if metal:
        data.append(0)
    if address is not None:
        data.append(address & 0x7F)
    return bytes(data)


@dataclass
class DecodedRecord:
    """One record decoded: values in mm / degrees / unit elements, plus flags.

    ``raw`` holds the 14-bit numbers. ``saturated``: a position word sits at the end of its range
    (the sensor is out of the position range). ``all_zero``: every data word is zero, which no real
    sensor produces (position zero is the transmitter's centre): the port has no sensor.
    """

    fmt: RecordFormat
    raw: np.ndarray
    position_mm: np.ndarray | None = None
    angles_deg: np.ndarray | None = None
    matrix: np.ndarray | None = None
    quaternion: np.ndarray | None = None
    metal: int | None = None
    address: int | None = None
    saturated: bool = False
    all_zero: bool = False

    def rotation(self) -> np.ndarray | None:
        """``SensorToTracker`` rotation from whatever orientation the record carries (None if none)."""
        if self.angles_deg is not None:
            return angles_to_rotation(*self.angles_deg)
        if self.matrix is not None:
            u, _, vt = np.linalg.svd(self.matrix)  # nearest rotation to the quantised matrix
            return u @ vt
        if self.quaternion is not None:
            return quaternion_to_rotation(self.quaternion)
        return None

    def angles(self) -> np.ndarray | None:
        """(azimuth, elevation, roll) in degrees, from the record's orientation."""
        if self.angles_deg is not None:
            return self.angles_deg
        rotation = self.rotation()
        return None if rotation is None else rotation_to_angles(rotation)


#: Tolerances of the value checks on a decoded record: a record whose orientation is not a
#: rotation within the quantisation (plus margin) failed in transit.
UNIT_TOLERANCE = 2e-3


def decode_record(fmt: RecordFormat, data: bytes | bytearray, scale_inches: float, metal: bool = False,
                  group: bool = False) -> DecodedRecord:
    """Decode one complete record (length as :func:`record_length`); no framing checks here."""
    n = 2 * fmt.words
    raw = decode_words(data[:n])
    out = DecodedRecord(fmt, raw)
    i = 0
    for kind, count in fmt.parts:
        part = raw[i:i + count]
        i += count
        if kind == "position":
            out.position_mm = raw_to_value(part, scale_inches) * MM_PER_INCH
            out.saturated = bool(np.any((part >= RAW_MAX) | (part <= RAW_MIN)))
        elif kind == "angles":
            out.angles_deg = raw_to_value(part, 180.0)
        elif kind == "matrix":
            out.matrix = raw_to_value(part, 1.0).reshape(3, 3)
        else:
            out.quaternion = raw_to_value(part, 1.0)
    out.all_zero = not np.any(raw)
    j = n
    if metal:
        out.metal = int(data[j]) & 0x7F
        j += 1
    if group:
        out.address = int(data[j]) & 0x7F
    return out


def record_values_plausible(record: DecodedRecord) -> bool:
    """Value checks that a bit error in transit can fail: elevation within +-90 degrees,
    a unit quaternion, an orthonormal right-handed matrix (within quantisation). An all-zero
    record (no sensor) is accepted here and flagged by the caller."""
    if record.all_zero:
        return True
    if record.angles_deg is not None and abs(record.angles_deg[1]) > 90.0 + 180.0 * WORD_STEP / FULL_SCALE_COUNTS:
        return False
    if record.quaternion is not None and abs(np.linalg.norm(record.quaternion) - 1.0) > UNIT_TOLERANCE:
        return False
    if record.matrix is not None:
        m = record.matrix
        if np.max(np.abs(m @ m.T - np.eye(3))) > 2 * UNIT_TOLERANCE or np.linalg.det(m) < 0.9:
            return False
    return True


def _wrap_angles(angles_deg: np.ndarray) -> np.ndarray:
    """Angles into [-180, 180) (the range a word can hold)."""
    return (np.asarray(angles_deg, dtype=float) + 180.0) % 360.0 - 180.0


# --- record framing ---------------------------------------------------------------------------


@dataclass
class FramingStats:
    """Counters of what the record parser accepted and rejected."""

    records: int = 0
    phase_errors: int = 0  # a record start (bit 7 set) arrived before the record was complete
    stray_bytes: int = 0  # bytes without a record start to belong to (discarded while resynchronising)
    address_errors: int = 0  # group-mode address byte not one of the expected sensors
    follow_errors: int = 0  # the byte right after a complete record was not a record start
    gap_errors: int = 0  # a record's bytes were interrupted by a silence longer than the gap limit
    value_errors: int = 0  # decoded values impossible (see record_values_plausible), set by the driver

    @property
    def rejected(self) -> int:
        return (self.phase_errors + self.address_errors + self.follow_errors + self.gap_errors
                + self.value_errors)


@dataclass
class RecordParser:
    """Finds complete, well-framed records in a byte stream (resynchronising on the phasing bit).

    After each :meth:`feed`, ``ends`` holds where each returned record ended in the byte stream
    (``offset`` counts every byte fed, good or bad), so a caller can tell how many bytes lay between
    two accepted records.

    ``length`` is the record length in bytes (:func:`record_length`); ``addresses`` the group-mode
    sensor addresses accepted in the last byte (None: not group mode). A record is accepted when it
    starts with the phasing bit, has no phasing bit in any other byte, has the right length, ends
    with an expected address (group mode), and - if the byte after it has already arrived - is
    followed by a record start. A record whose bytes are interrupted by more than ``max_gap_ns`` of
    silence is dropped (a real tracker sends a record's bytes back to back).
    """

    length: int
    addresses: frozenset[int] | None = None
    max_gap_ns: int = 50_000_000
    stats: FramingStats = field(default_factory=FramingStats)

    def __post_init__(self) -> None:
        self._current = bytearray()
        self._last_byte_ns = 0
        #: bytes consumed so far (the stream offset of the next byte fed)
        self.offset = 0
        #: stream offsets just past the last byte of each record the last :meth:`feed` returned
        self.ends: list[int] = []

    def reset(self) -> None:
        """Forget any partial record (after a flush of the serial input)."""
        self._current = bytearray()

    def configure(self, length: int, addresses: Iterable[int] | None = None) -> None:
        """Change the record length / group addresses (drops a partial record)."""
        self.length = length
        self.addresses = None if addresses is None else frozenset(addresses)
        self.reset()

    def feed(self, data: bytes, t_ns: int, timed: bool = True) -> list[bytes]:
        """Consume bytes received at ``t_ns`` (monotonic); return the complete valid records.

        ``timed=False``: the bytes had been waiting in the input buffer before the read began, so the
        host's clock says nothing about a silence on the line before them (a late reader is not a
        silent line): the gap check is not applied to them."""
        out: list[bytes] = []
        ends: list[int] = []
        base = self.offset
        self.offset += len(data)
        self.ends = ends
        current = self._current
        if current and timed and t_ns - self._last_byte_ns > self.max_gap_ns:
            self.stats.gap_errors += 1
            current.clear()
        self._last_byte_ns = t_ns
        n = len(data)
        for i in range(n):
            b = data[i]
            if b & 0x80:
                if current:
                    self.stats.phase_errors += 1
                    current.clear()
                current.append(b)
            elif current:
                current.append(b)
            else:
                self.stats.stray_bytes += 1
                continue
            if len(current) == self.length:
                if i + 1 < n and not data[i + 1] & 0x80:
                    self.stats.follow_errors += 1
                elif self.addresses is not None and current[-1] not in self.addresses:
                    self.stats.address_errors += 1
                else:
                    self.stats.records += 1
                    out.append(bytes(current))
                    ends.append(base + i + 1)
                current.clear()
        return out

