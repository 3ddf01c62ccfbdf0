"""Device URLs of live sources.

- ``trakstar:///dev/ttyUSB0?baud=115200`` (also ``trakstar:/dev/pts/7``): a trakSTAR (or the
  simulator's pty) on a serial port. Query options: ``baud`` (default 115200), ``format``
  (record format, default ``POSITION/ANGLES``, ``_`` for ``/``), ``rate`` (measurement rate, Hz),
  ``metal`` (1/0: quality byte, default 1), ``scale`` (36 or 72 inches), ``gap_ms`` (max silence
  inside a record, default 50).
- ``aurora:///dev/ttyUSB0?baud=115200``: an NDI Aurora (or ``emreg sim-tracker --model aurora``) through
  ndicapi. Options: ``baud`` (set with COMM after the 9600-baud start; default 115200), ``reply``
  (``auto``: BX unless the firmware needs TX; ``bx``, ``tx``), ``five_dof`` (sensors with 5-DOF
  sensors, e.g. ``2``), ``rate`` (Hz at which its frame counter runs: sample times and the
  watchdog's period; default 40). A tool's sensor number is
  its port 1..4 (+4 for channel 1 of a splitter).
- ``igtl://HOST:PORT``: another EMReg (``emreg serve``) or PLUS server; options ``reference`` and
  ``probe``: the TRANSFORM device names to consume (default ``ReferenceToTracker``,
  ``ProbeToTracker``).
- ``replay:FILE.csv``: a tracking recording (spec CSV).
"""

from __future__ import annotations

from dataclasses import dataclass, field
from urllib.parse import SplitResult, parse_qs, urlsplit

from ..errors import EMRegError
from .aurora import protocol as ndi
from .trakstar import protocol as tp

SCHEMES = ("trakstar", "aurora", "igtl", "replay")


@dataclass
class DeviceURL:
    """A parsed device URL: ``kind`` is ``trakstar``, ``aurora``, ``igtl`` or ``replay``."""

    kind: str
    path: str = ""
    host: str = ""
    port: int = 0
    options: dict[str, str] = field(default_factory=dict)
    text: str = ""

    @property
    def baud(self) -> int:
        return int(self.options.get("baud", ndi.DEFAULT_BAUD if self.kind == "aurora" else tp.DEFAULT_BAUD))


def parse_device_url(text: str) -> DeviceURL:
    """Parse a device URL; a malformed one raises :class:`EMRegError` saying what is expected."""
    text = text.strip()
    scheme, sep, rest = text.partition(":")
    scheme = scheme.lower()
    if not sep or scheme not in SCHEMES:
        raise EMRegError(f"device {text!r}: use trakstar:///dev/ttyUSB0?baud=115200, aurora:///dev/ttyUSB0, "
                         "igtl://HOST:PORT or replay:FILE.csv")
    if scheme == "replay":
        path = rest[2:] if rest.startswith("//") else rest
        if not path:
            raise EMRegError(f"device {text!r}: replay: needs a file, e.g. replay:navigation.csv")
        return DeviceURL("replay", path=path, text=text)
    parts = urlsplit(text)
    options = {k: v[-1] for k, v in parse_qs(parts.query).items()}
    if scheme == "aurora":
        url = _serial_url("aurora", text, parts, options, ndi.BAUD_RATES, "use")
        if options.get("reply", "auto") not in ("auto", "bx", "tx"):
            raise EMRegError(f"device {text!r}: reply must be auto, bx or tx")
        return url
    if scheme == "trakstar":
        url = _serial_url("trakstar", text, parts, options, tp.BAUD_RATES, "the trakSTAR supports")
        if "format" in options:
            try:
                tp.get_format(options["format"])
            except ValueError as exc:
                raise EMRegError(f"device {text!r}: {exc}") from None
        return url
    try:
        port = parts.port
    except ValueError:
        port = None
    if not parts.hostname or port is None:
        raise EMRegError(f"device {text!r}: igtl: needs a host and port, e.g. igtl://127.0.0.1:18944")
    return DeviceURL("igtl", host=parts.hostname, port=port, options=options, text=text)


def _serial_url(kind: str, text: str, parts: SplitResult, options: dict[str, str], baud_rates: tuple[int, ...],
                rates_said: str) -> DeviceURL:
    """A serial tracker's URL (``kind:///dev/ttyUSB0?baud=N``), its device path and baud rate checked against the
    device's ``baud_rates`` (refused naming them after ``rates_said``)."""
    path = parts.path or parts.netloc
    if parts.netloc and parts.path:  # kind://dev/ttyUSB0 (two slashes): netloc holds the first part
        path = "/" + parts.netloc + parts.path
    if not path:
        raise EMRegError(f"device {text!r}: {kind}: needs a serial device, e.g. {kind}:///dev/ttyUSB0")
    url = DeviceURL(kind, path=path, options=options, text=text)
    try:
        baud = url.baud
    except ValueError:
        raise EMRegError(f"device {text!r}: baud must be a number") from None
    if baud not in baud_rates:
        raise EMRegError(f"device {text!r}: baud={baud}; {rates_said} {', '.join(map(str, baud_rates))}")
    return url
