"""Robot URLs, as the trackers have device URLs, and :func:`open_robot`, which connects to the robot behind one.

- ``franka://HOST``: a Franka FR3 or Panda (or a simulator speaking its protocol, e.g. ``franky-sim``) at HOST,
  through franky-control (libfranka's protocol: TCP 1337 and UDP). The port is the protocol's own and cannot be
  given. Needs the optional extra ``robot`` (``pip install emreg[robot]``).
"""

from __future__ import annotations

from dataclasses import dataclass
from urllib.parse import parse_qs, urlsplit

from ...errors import EMRegError
from .driver import RobotDriver
from .franka import FrankaRobot

ROBOT_SCHEMES = ("franka",)


@dataclass(frozen=True)
class RobotURL:
    """A parsed robot URL: ``kind`` (``franka``), ``host`` and the query options."""

    kind: str
    host: str
    options: dict[str, str]
    text: str


def parse_robot_url(text: str) -> RobotURL:
    """Parse a robot URL; a malformed one raises :class:`EMRegError` (exit 2) saying what is expected."""
    text = str(text).strip()
    scheme = text.partition(":")[0].lower()
    if scheme not in ROBOT_SCHEMES or "://" not in text:
        raise EMRegError(f"robot {text!r}: use franka://HOST (a Franka FR3/Panda, or a simulator speaking its "
                         "protocol, e.g. franka://127.0.0.1)")
    parts = urlsplit(text)
    try:
        port = parts.port
    except ValueError:
        port = -1
    if not parts.hostname:
        raise EMRegError(f"robot {text!r}: no host; e.g. franka://172.16.0.2")
    if port is not None:
        raise EMRegError(f"robot {text!r}: libfranka's protocol uses its own ports (TCP 1337); give the host alone")
    return RobotURL(scheme, parts.hostname, {k: v[-1] for k, v in parse_qs(parts.query).items()}, text)


def open_robot(url: str | RobotURL) -> RobotDriver:
    """Connect to the robot behind a URL (:class:`EMRegError` with one line when it cannot)."""
    parsed = parse_robot_url(url) if isinstance(url, str) else url
    return FrankaRobot(parsed.host, parsed.options)
