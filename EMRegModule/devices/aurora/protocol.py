"""NDI's serial command API as the Aurora speaks it: framing, CRC16, reply formats, with their sources.

The Aurora's System Control Unit speaks NDI's "Combined API" over RS-232: ASCII commands
``NAME:ARGS`` + CRC16 (4 upper-case hex digits) + CR, ASCII replies ``TEXT`` + CRC16 + CR, and for
BX one binary reply. Sources, cited constant by constant:

- [CAPI] ndicapi (PlusToolkit/ndicapi, MIT; the library behind PLUS and scikit-surgerynditracker,
  PyPI ``ndicapi``, module ``ndicapy``): ``ndicapi.cxx`` (``CalcCRC16``, ``ndiCommandVA``,
  ``ndiSerialProbe``, the ``ndiTXHelper`` / ``ndiBXHelper`` / ``ndiPHSRHelper`` / ``ndiPHINFHelper`` /
  ``ndiCOMMHelper`` reply parsers), ``ndicapi.h`` (command macros, reply-mode bits, status bits,
  error codes), ``ndicapi_serial_unix.cxx`` (``ndiSerialRead``: how a reply's end is found).
- [SKS] scikit-surgerynditracker (``nditracker.py``): the Aurora start-up sequence and the
  firmware check that chooses BX or TX.
- [SAW] a real Aurora's ``VER`` replies quoted in the public issue jhu-saw/sawNDITracker#6, and
  ``ERROR13`` on ``PINIT`` of a tool without an SROM, quoted in PlusToolkit/ndicapi#40 and
  SciKit-Surgery/scikit-surgerynditracker#79.

Where none of them settles a point the choice is marked "(choice)".
"""

from __future__ import annotations

import struct
from dataclasses import dataclass

import numpy as np

# --- line ------------------------------------------------------------------------------------------

#: Power-on / after-break line speed: 9600 8N1, no handshake ([CAPI] ``ndiSerialProbe`` and
#: ``ndiOpenSerial`` talk at 9600 "8N1" before any COMM).
POWER_ON_BAUD = 9600
#: COMM baud-rate digit -> baud ([CAPI] ``ndiCOMMHelper`` ``convert_baud`` and ``'A'`` -> 230400;
#: ``ndicapi.h`` ``NDI_9600`` .. ``NDI_230400``).
COMM_BAUD = {"0": 9600, "1": 14400, "2": 19200, "3": 38400, "4": 57600, "5": 115200, "6": 921600,
             "7": 1228739, "A": 230400}
#: Rates a Linux host can set ([CAPI] ``ndiSerialComm``: 14400 is refused on Linux; 921600 and
#: 1228739 are not in its table either).
HOST_BAUD = (9600, 19200, 38400, 57600, 115200, 230400)
#: Baud rates EMReg's URL accepts (those both ends can do).
BAUD_RATES = HOST_BAUD
DEFAULT_BAUD = 115200  # (choice) the fastest rate every host serial port has; what [SKS] selects

# --- CRC16 ([CAPI] CalcCRC16: "polynomial X^16 + X^15 + X^2 + 1", reflected, initial value 0) --------


def _crc_table() -> list[int]:
    table = []
    for byte in range(256):
        crc = byte
        for _ in range(8):
            crc = (crc >> 1) ^ 0xA001 if crc & 1 else crc >> 1  # 0xA001: 0x8005 bit-reversed
        table.append(crc)
    return table


_CRC_TABLE = _crc_table()


def crc16(data: bytes | str, crc: int = 0) -> int:
    """NDI's CRC16 of ``data`` (the CRC-16/ARC parameters: poly 0x8005 reflected, init 0, no xorout).

    Published values to check it against (ndicapi's hard-coded command strings): ``INIT:`` -> E3A5,
    ``OKAY`` -> A896, ``RESET`` -> BE6F, ``VER:0`` -> 65EE, ``GETINFO:Features.Firmware.Version`` -> 0492.
    """
    if isinstance(data, str):
        data = data.encode("latin-1")
    for b in data:
        crc = (crc >> 8) ^ _CRC_TABLE[(crc ^ b) & 0xFF]
    return crc


def frame_command(text: str) -> bytes:
    """A host command as ndicapi sends it: ``text`` + CRC (only when the name ends with ':') + CR."""
    name_end = next((i for i, c in enumerate(text) if not (c.isupper() or c.isdigit())), len(text))
    with_crc = name_end < len(text) and text[name_end] == ":"
    return (text + (f"{crc16(text):04X}" if with_crc else "") + "\r").encode("latin-1")


def frame_reply(text: str | bytes) -> bytes:
    """An ASCII reply: text + its CRC16 as 4 upper-case hex digits + CR ([CAPI] ``ndiCommandVA``)."""
    data = text.encode("latin-1") if isinstance(text, str) else text
    return data + f"{crc16(data):04X}\r".encode("ascii")


@dataclass(frozen=True)
class Command:
    """A parsed host command: ``name`` (``BX``), ``args`` (``0801``), whether its CRC was right."""

    name: str
    args: str
    crc_ok: bool


def parse_command(line: bytes) -> Command:
    """Split one command line (without the CR). ``NAME:ARGS`` + 4-hex CRC, or ``NAME ARGS`` without a
    CRC (the space form NDI allows; [CAPI] ``ndiTXHelper`` reads a reply mode after ':' or ' ')."""
    text = line.decode("latin-1")
    name_end = next((i for i, c in enumerate(text) if not (c.isupper() or c.isdigit())), len(text))
    name = text[:name_end]
    rest = text[name_end:]
    if rest.startswith(":"):
        if len(rest) < 5:
            return Command(name, "", False)
        body, crc_text = text[:-4], text[-4:]
        try:
            ok = int(crc_text, 16) == crc16(body)
        except ValueError:
            ok = False
        return Command(name, body[name_end + 1:], ok)
    return Command(name, rest[1:] if rest.startswith(" ") else rest, True)


# --- error codes ([CAPI] ndicapi.h NDI_INVALID ..) -----------------------------------------------------

ERROR_INVALID = 0x01  # invalid command
ERROR_TOO_LONG = 0x02
ERROR_BAD_COMMAND_CRC = 0x04
ERROR_PARAMETERS = 0x07  # incorrect number of command parameters
ERROR_INVALID_PORT = 0x08  # (Aurora: invalid port handle)
ERROR_INVALID_MODE = 0x09
ERROR_BAD_MODE = 0x0C  # command invalid in the current mode (e.g. BX before TSTART)
ERROR_NO_TOOL = 0x0D
ERROR_PORT_NOT_INIT = 0x0E
ERROR_PORT_DISABLED = 0x0F
ERROR_INITIALIZATION = 0x10  # system not initialised (a command before INIT)
ERROR_PINIT_FAIL = 0x13  # "Unable to initialize Tool-in-Port": a tool without SROM ([SAW] ndicapi#40)
ERROR_VER = 0x23  # what a real Aurora answers to "VER:3" ([SAW]: "command VER 3 returned: ERROR23")
ERROR_HANDLE_NOT_ALLOC = 0x2B

# host-side codes ndicapi sets itself ([CAPI] ndicapi.h)
NDI_OKAY = 0x00
NDI_BAD_CRC = 0x0100
NDI_TIMEOUT = 0x0103
NDI_WRITE_ERROR = 0x0104
NDI_READ_ERROR = 0x0105

# --- port handles ------------------------------------------------------------------------------------

#: PHSR reply-mode argument ([CAPI] ndicapi.h ``NDI_ALL_HANDLES`` ..).
PHSR_ALL, PHSR_STALE, PHSR_UNINITIALIZED, PHSR_UNENABLED, PHSR_ENABLED = 0, 1, 2, 3, 4
#: Port status bits (PHSR information, PHINF, TX/BX port status; [CAPI] ndicapi.h
#: ``NDI_TOOL_IN_PORT`` .. ``NDI_PARTIALLY_IN_VOLUME``).
PORT_OCCUPIED = 0x01
PORT_SWITCH_1, PORT_SWITCH_2, PORT_SWITCH_3 = 0x02, 0x04, 0x08
PORT_INITIALIZED = 0x10
PORT_ENABLED = 0x20
PORT_OUT_OF_VOLUME = 0x40
PORT_PARTIALLY_IN_VOLUME = 0x80
#: Handle status byte of a BX reply ([CAPI] ``NDI_HANDLE_VALID / MISSING / DISABLED``).
HANDLE_VALID, HANDLE_MISSING, HANDLE_DISABLED = 0x01, 0x02, 0x04
#: System status bits of TX/BX replies ([CAPI] ndicapi.h, ``ndiGetTXSystemStatus``).
SYSTEM_COMM_SYNC_ERROR = 0x0001
SYSTEM_COMM_CRC_ERROR = 0x0004
SYSTEM_PORT_OCCUPIED = 0x0040
SYSTEM_PORT_UNOCCUPIED = 0x0080
#: Wired tool ports of the simulated System Control Unit: 1..4 (choice: the four-port SCU); a port with a
#: splitter carries two 5-DOF sensors on channels 0 and 1 ([CAPI] ndicapi.h ``ndiPHRQ``: "AURORA tool
#: channel 00 or 01").
AURORA_PORTS = (1, 2, 3, 4)
#: First handle the simulated Aurora assigns; handles follow in port order, channel-1 tools after all
#: channel-0 tools (choice).
FIRST_HANDLE = 0x0A
#: PENA tracking priorities ([CAPI] ndicapi.h ``NDI_STATIC`` 'S', ``NDI_DYNAMIC`` 'D', ``NDI_BUTTON_BOX`` 'B').
PENA_MODES = ("S", "D", "B")

# --- reply modes ([CAPI] ndicapi.h) ------------------------------------------------------------------

REPLY_TRANSFORMS = 0x0001  # NDI_XFORMS_AND_STATUS
REPLY_ADDITIONAL_INFO = 0x0002
REPLY_SINGLE_STRAY = 0x0004
REPLY_FRAME_NUMBER = 0x0008  # (GX only; TX/BX always carry the frame number)
REPLY_NOT_NORMALLY_REPORTED = 0x0800  # BX/TX: also report out-of-volume transforms
#: PHINF reply-format bits ([CAPI] ``NDI_BASIC`` .. ``NDI_GPIO_STATUS``) and their field widths
#: ([CAPI] ``ndiPHINFHelper``: 33, 8, 20, 2, 2, 14, 2 characters).
PHINF_FIELDS = ((0x0001, "basic", 33), (0x0002, "testing", 8), (0x0004, "part_number", 20),
                (0x0008, "accessories", 2), (0x0010, "marker_type", 2), (0x0020, "port_location", 14),
                (0x0040, "gpio", 2))

# --- firmware ------------------------------------------------------------------------------------------

#: Firmware revisions for which [SKS] falls back from BX to TX (``_set_use_bx_transforms``).
TX_ONLY_FREEZE_TAGS = ("AURORA Rev 007", "AURORA Rev 008")
#: Default freeze tag of the simulated Aurora: a revision newer than those (choice).
DEFAULT_FREEZE_TAG = "AURORA Rev 013"


def ver_reply(freeze_tag: str = DEFAULT_FREEZE_TAG, serial: str = "D4-00000") -> str:
    """``VER:0`` / ``VER:4`` reply text, line by line as a real Aurora's ([SAW]; the serial number and
    dates are (choice))."""
    return ("Aurora Control Firmware\n"
            f"NDI S/N: {serial}\n"
            "Characterization Date: 2026-01-01\n"
            f"Freeze Tag: {freeze_tag}\n"
            "Freeze Date: 2013-07-25\n"
            "(C) Northern Digital Inc.\n")


def freeze_tag_of(ver_text: str) -> str:
    """The ``Freeze Tag:`` of a VER reply ('' when absent)."""
    for line in ver_text.splitlines():
        if line.startswith("Freeze Tag:"):
            return line.split(":", 1)[1].strip()
    return ""


def supports_bx(freeze_tag: str) -> bool:
    """BX for every firmware but those [SKS] knows to need TX (compares the tag's first 3 words)."""
    return " ".join(freeze_tag.split()[:3]) not in TX_ONLY_FREEZE_TAGS


# --- transforms in replies --------------------------------------------------------------------------------


@dataclass
class ToolReport:
    """What one port handle reports in one TX/BX frame.

    ``state``: ``valid``, ``missing`` or ``disabled``. ``quaternion`` (w, x, y, z) and ``position_mm``
    give ``ToolToTracker``; ``error`` is the tool's RMS fit error; ``port_status`` the bits above.
    """

    handle: int
    state: str
    quaternion: np.ndarray | None = None
    position_mm: np.ndarray | None = None
    error: float = 0.0
    port_status: int = PORT_OCCUPIED | PORT_INITIALIZED | PORT_ENABLED
    frame: int = 0


def _signed(value: float, width: int, scale: float) -> str:
    """``+dddd`` fixed-point text: sign + (width-1) digits of ``round(value * scale)`` ([CAPI]
    ``ndiSignedToLong`` reads it back). Values beyond the field are clamped (choice)."""
    limit = 10 ** (width - 1) - 1
    n = int(np.clip(round(value * scale), -limit, limit))
    return f"{'-' if n < 0 else '+'}{abs(n):0{width - 1}d}"


def tx_transform_text(report: ToolReport) -> str:
    """The 51 characters of a TX transform ([CAPI] ``ndiGetTXTransform``: four quaternion fields of
    6 characters, 1e-4 units; three position fields of 7 characters, 0.01 mm; the error, 6
    characters, 1e-4 units)."""
    q, p = report.quaternion, report.position_mm
    return ("".join(_signed(v, 6, 1e4) for v in q) + "".join(_signed(v, 7, 100.0) for v in p)
            + _signed(report.error, 6, 1e4))


def tx_reply_text(reports: list[ToolReport], system_status: int = 0) -> str:
    """TX reply (mode 0x0001 / 0x0801) text before its CRC ([CAPI] ``ndiTXHelper``): handle count
    (2 hex), then per handle: handle (2 hex), the transform or ``MISSING`` / ``DISABLED``, port
    status (8 hex), frame number (8 hex), LF; then the system status (4 hex)."""
    out = [f"{len(reports):02X}"]
    for r in reports:
        if r.state == "disabled":
            out.append(f"{r.handle:02X}DISABLED{r.port_status:08X}{r.frame & 0xFFFFFFFF:08X}\n")
            continue
        body = tx_transform_text(r) if r.state == "valid" else "MISSING"
        out.append(f"{r.handle:02X}{body}{r.port_status:08X}{r.frame & 0xFFFFFFFF:08X}\n")
    out.append(f"{system_status:04X}")
    return "".join(out)


BX_START = 0xA5C4  # start sequence, sent little-endian: C4 A5 ([CAPI] ``ndiBXHelper``, ``ndiSerialRead``)
BX_HEADER_BYTES = 6  # start (2) + reply length (2) + header CRC (2)


def bx_reply(reports: list[ToolReport], system_status: int = 0) -> bytes:
    """Binary BX reply ([CAPI] ``ndiBXHelper``): header ``C4 A5``, body length (uint16 LE), header
    CRC16 (LE, over those 4 bytes); body: handle count (1 byte), per handle: handle (1), handle status
    (1), for a valid one 8 float32 LE (q0 qx qy qz tx ty tz error), unless disabled the port status
    (uint32 LE) and frame number (uint32 LE); system status (uint16 LE); then the body's CRC16 (LE).

    ndicapi checks one CRC over header + header CRC + body; because a CRC16 of data followed by its
    own little-endian CRC is 0, that equals the body's CRC, so both CRCs here are the ones NDI
    documents (header CRC over the header, reply CRC over the body).
    """
    body = bytearray([len(reports)])
    for r in reports:
        status = {"valid": HANDLE_VALID, "missing": HANDLE_MISSING, "disabled": HANDLE_DISABLED}[r.state]
        body += bytes([r.handle & 0xFF, status])
        if r.state == "disabled":
            continue
        if r.state == "valid":
            body += struct.pack("<8f", *r.quaternion, *r.position_mm, r.error)
        body += struct.pack("<II", r.port_status & 0xFFFFFFFF, r.frame & 0xFFFFFFFF)
    body += struct.pack("<H", system_status & 0xFFFF)
    header = struct.pack("<HH", BX_START, len(body))
    return header + struct.pack("<H", crc16(header)) + bytes(body) + struct.pack("<H", crc16(bytes(body)))


def parse_bx_reply(data: bytes) -> tuple[list[ToolReport], int]:
    """Decode a BX reply (mode 0x0001/0x0801) checking both CRCs; raises ValueError when it is not one.
    An independent reader for tests (EMReg's driver reads BX through ndicapi)."""
    if len(data) < BX_HEADER_BYTES + 3:
        raise ValueError("BX reply too short")
    start, length, header_crc = struct.unpack_from("<HHH", data)
    if start != BX_START:
        raise ValueError(f"BX start sequence {start:04X}, expected A5C4")
    if header_crc != crc16(data[:4]):
        raise ValueError("BX header CRC mismatch")
    body = data[BX_HEADER_BYTES:BX_HEADER_BYTES + length]
    if len(body) != length or len(data) < BX_HEADER_BYTES + length + 2:
        raise ValueError("BX reply truncated")
    (body_crc,) = struct.unpack_from("<H", data, BX_HEADER_BYTES + length)
    if body_crc != crc16(body):
        raise ValueError("BX body CRC mismatch")
    count, i, reports = body[0], 1, []
    for _ in range(count):
        handle, status = body[i], body[i + 1]
        i += 2
        if status == HANDLE_DISABLED:
            reports.append(ToolReport(handle, "disabled", port_status=0))
            continue
        q = p = None
        error = float("nan")
        if status == HANDLE_VALID:
            values = struct.unpack_from("<8f", body, i)
            q, p, error = np.array(values[:4]), np.array(values[4:7]), values[7]
            i += 32
        port_status, frame = struct.unpack_from("<II", body, i)
        i += 8
        reports.append(ToolReport(handle, "valid" if status == HANDLE_VALID else "missing", q, p, error,
                                  port_status, frame))
    (system_status,) = struct.unpack_from("<H", body, i)
    return reports, system_status


def phsr_reply_text(entries: list[tuple[int, int]]) -> str:
    """PHSR reply: count (2 hex), per handle: handle (2 hex) + status (3 hex) ([CAPI] ``ndiGetPHSRHandle``
    steps 5 characters, ``ndiGetPHSRInformation`` reads 3 hex after the handle)."""
    return f"{len(entries):02X}" + "".join(f"{h:02X}{s & 0xFFF:03X}" for h, s in entries)


def port_location(port: int, channel: int = 0) -> str:
    """PHINF port-location field, 14 characters laid out as PHRQ's criteria ([CAPI] ``ndiPHRQ``: device
    number (8), system type "1" = AURORA SCU, tool type "0" = wired, port (2), channel (2)); the device
    number ``00000000`` is (choice)."""
    return f"0000000010{port:02d}{channel:02d}"


def parse_port_location(text: str) -> tuple[int, int]:
    """(port, channel) from a 14-character PHINF port location."""
    return int(text[10:12]), int(text[12:14])
