"""The simulators' one ``--fault`` grammar: ``KIND=VALUE`` items, parsed once into a :class:`FaultPlan`.

Every name means the same on both simulated devices where both have it; each device honours the names
its protocol can show (a name of the other device is refused, listing the device's own). Seconds count
from the simulator's start; P is a probability 0..1 (per byte for ``drop`` / ``flip`` / ``corrupt``, per
reply for ``crc`` / ``late``); SENSOR is the sensor number (trakSTAR 1..4; Aurora 1..8: port 1..4, +4 for
channel 1 of a splitter); a window ``SENSOR@START-END`` without END lasts to the end.

==================  ====================  ==========================================  ===========================
name                value                 trakSTAR                                    Aurora
==================  ====================  ==========================================  ===========================
``drop``            P                     a byte is lost                              the same
``flip``            P                     a byte's phasing bit (bit 7) is inverted    one bit of a byte inverted
``corrupt``         P                     a byte's 7 data bits replaced at random     -
``crc``             P                     -                                           a BX/TX reply's CRC wrong
``stall``           EVERY_S[:DURATION_S]  silent DURATION_S (0.2) every EVERY_S       the same
``late``            P[:DELAY_S]           a POINT reply DELAY_S (0.2) late            -
``unplug``          SENSOR@START-END      all-zero records, serial 0, error code 5    MISSING, port unoccupied
``out-of-range``    SENSOR@START-END      saturated position, worst METAL byte        port status 0x40
``distort``         SENSOR@START-END      METAL byte ``DISTORTED_METAL``              RMS error 2.5 mm
``missing``         SENSOR@START-END      -                                           no solution: MISSING
``partly-out``      SENSOR@START-END      -                                           port status 0x80
==================  ====================  ==========================================  ===========================

``_`` in a name is read as ``-`` (``out_of_range``), and names are case-blind.
"""

from __future__ import annotations

from collections.abc import Iterable
from dataclasses import dataclass, field
from typing import ClassVar

from ...errors import EMRegError
from ..aurora import protocol as ndi
from ..trakstar import protocol as tp

#: ``(sensor, start_s, end_s)``: a sensor's state from START to END seconds after the start.
Window = tuple[int, float, float]

#: The value each name takes, as the refusal message spells it.
FORMS = {"drop": "P", "flip": "P", "corrupt": "P", "crc": "P", "stall": "EVERY_S:DURATION_S", "late": "P:DELAY_S",
         "unplug": "SENSOR@START-END", "out-of-range": "SENSOR@START-END", "distort": "SENSOR@START-END",
         "missing": "SENSOR@START-END", "partly-out": "SENSOR@START-END"}
#: The per-byte / per-reply probabilities.
PROBABILITIES = ("drop", "flip", "corrupt", "crc")
#: The sensor states, switched on by windows (or by hand: ``set_state``).
WINDOW_KINDS = ("missing", "out-of-range", "partly-out", "unplug", "distort")
#: Names each simulated device honours.
TRAKSTAR_NAMES = ("drop", "flip", "corrupt", "stall", "late", "unplug", "out-of-range", "distort")
AURORA_NAMES = ("drop", "flip", "crc", "stall", "missing", "out-of-range", "partly-out", "unplug", "distort")
#: DURATION_S of ``stall`` and DELAY_S of ``late`` when not given (s).
DEFAULT_STALL_S = 0.2
DEFAULT_LATE_S = 0.2


def fault_probability(value: str) -> float:
    """A ``--fault`` probability (per byte or per reply): a number in 0..1, else ValueError."""
    probability = float(value)
    if not 0.0 <= probability <= 1.0:
        raise ValueError(value)
    return probability


def fault_stall(value: str) -> tuple[float, float]:
    """``EVERY_S:DURATION_S`` of ``stall=`` (s): both positive and finite (DURATION_S default 0.2), else
    ValueError."""
    every, _, duration = value.partition(":")
    every_s, stall_s = float(every), float(duration or DEFAULT_STALL_S)
    if not (0.0 < every_s < float("inf") and 0.0 < stall_s < float("inf")):
        raise ValueError(value)
    return every_s, stall_s


def fault_late(value: str) -> tuple[float, float]:
    """``P:DELAY_S`` of ``late=``: a probability and a finite delay >= 0 s (default 0.2), else ValueError."""
    probability, _, delay = value.partition(":")
    late, late_s = fault_probability(probability), float(delay or DEFAULT_LATE_S)
    if not 0.0 <= late_s < float("inf"):
        raise ValueError(value)
    return late, late_s


def fault_window(value: str, max_sensor: int) -> Window:
    """``SENSOR@START-END`` (seconds after start; no END: to the end) as ``(sensor, start_s, end_s)``;
    ValueError unless 1 <= SENSOR <= ``max_sensor`` and 0 <= START < END."""
    sensor, _, window = value.partition("@")
    start, _, end = window.partition("-")
    entry = (int(sensor), float(start or 0.0), float(end) if end else float("inf"))
    if not (1 <= entry[0] <= max_sensor and 0.0 <= entry[1] < entry[2]):
        raise ValueError(value)
    return entry


@dataclass
class FaultPlan:
    """Faults to inject into the trakSTAR simulator (:class:`AuroraFaults`: the Aurora's): the values of the
    table above. Probabilities per byte sent (``crc``, ``late``: per reply); ``stall_every_s`` /
    ``stall_s``: silent for ``stall_s`` every ``stall_every_s`` seconds; ``late_s``: the delay of a late
    POINT reply (s); ``windows``: state name -> its :data:`Window` s."""

    drop: float = 0.0
    flip: float = 0.0
    corrupt: float = 0.0
    crc: float = 0.0
    stall_every_s: float = 0.0
    stall_s: float = 0.0
    late: float = 0.0
    late_s: float = 0.0
    windows: dict[str, list[Window]] = field(default_factory=dict)

    #: The device named in a refusal, the names it honours and its highest sensor number.
    device: ClassVar[str] = "trakSTAR"
    names: ClassVar[tuple[str, ...]] = TRAKSTAR_NAMES
    max_sensor: ClassVar[int] = tp.MAX_SENSORS

    @classmethod
    def parse(cls, items: Iterable[str]) -> FaultPlan:
        """The plan of ``--fault KIND=VALUE`` strings (the table above); :class:`EMRegError` naming the item,
        and what the device takes, for anything else."""
        plan = cls()
        for item in items:
            kind, _, value = item.partition("=")
            kind = kind.strip().lower().replace("_", "-")
            try:
                if kind not in cls.names:
                    raise ValueError(kind)
                plan._add(kind, value)
            except ValueError:
                raise EMRegError(cls._refusal(item)) from None
        return plan

    def _add(self, kind: str, value: str) -> None:
        if kind in PROBABILITIES:
            setattr(self, kind, fault_probability(value))
        elif kind == "stall":
            self.stall_every_s, self.stall_s = fault_stall(value)
        elif kind == "late":
            self.late, self.late_s = fault_late(value)
        else:
            self.windows.setdefault(kind, []).append(fault_window(value, self.max_sensor))

    @classmethod
    def _refusal(cls, item: str) -> str:
        *first, last = [f"{name}={FORMS[name]}" for name in cls.names]
        return (f"--fault {item!r}: for the {cls.device} use {', '.join(first)} or {last} (P a probability 0..1, "
                f"seconds positive, SENSOR 1..{cls.max_sensor}, 0 <= START < END)")

    def active(self, kind: str, sensor: int, t_s: float) -> bool:
        """Whether a window of state ``kind`` holds ``sensor`` at ``t_s`` seconds after the start."""
        return any(s == sensor and a <= t_s < b for s, a, b in self.windows.get(kind, ()))


class AuroraFaults(FaultPlan):
    """The same plan for the Aurora simulator: the Aurora's names, sensors 1..8."""

    device: ClassVar[str] = "Aurora"
    names: ClassVar[tuple[str, ...]] = AURORA_NAMES
    max_sensor: ClassVar[int] = 2 * len(ndi.AURORA_PORTS)
