"""Live check of the sensor ports: the offline rule (:func:`EMRegModule.core.tracking.role_problem`) applied online.

Offline, a recording whose probe never moves relative to the reference, or whose "reference" moves like a
hand-held probe while the "probe" stays still, is refused (exit 2). Live navigation from a tracker
(trakSTAR, Aurora) judges the paired poses of its first moments with the same rule and the same limits
before it publishes a pose:

- the probe has not moved ``MIN_PROBE_SPREAD_MM`` (2 mm) relative to the reference yet: paused,
  ``ProbeNotMoving``. A probe resting on the table and a second sensor on the frame look the same, so this
  only pauses: moving the probe clears it, a port mistake never does;
- neither sensor has moved ``SWAP_MIN_SPREAD_MM`` (10 mm) in the Tracker frame yet (too little motion to
  tell which sensor is in the hand): paused, ``PortCheck``;
- then the "reference" moved more than ``SWAP_SPREAD_FACTOR`` (3) times the "probe": the ports are swapped,
  ``PortsSwapped``: fatal (:class:`SensorPortsError`, exit 2). It must not clear by itself: with swapped
  ports a hand at rest hides the mistake while every pose is still wrong, so only a restart with the
  right ports (or a reconnection, judged afresh) can resume;
- otherwise the check has passed and is not applied again on this connection (a probe put down, or a
  frame moved with the table, later on is normal).

Poses are ``SensorToTracker`` 4x4 matrices (mm); spreads are 95th-percentile distances from the median (mm).
"""

from __future__ import annotations

from collections import deque
from dataclasses import dataclass

import numpy as np

from ..core.tracking import MIN_PROBE_SPREAD_MM, SWAP_MIN_SPREAD_MM, role_problem, role_spreads
from ..errors import EMRegError
from . import igtl_status as st

#: Pairs needed before the check may pass or call the ports swapped (one corrupted pose that slipped
#: through the jump test must not decide).
MIN_PAIRS = 20
#: Pairs kept (the most recent ones) while the check is pending.
MAX_PAIRS = 2000
#: Judge every this many pairs once ``MIN_PAIRS`` are in (the percentiles cost O(pairs)).
JUDGE_EVERY = 4

#: Watchdog reasons the port check gives (publishing paused for them).
REASON_STILL = "probe_not_moving"
REASON_PENDING = "port_check"
REASON_SWAPPED = "ports_swapped"
PORT_REASONS = (REASON_STILL, REASON_PENDING, REASON_SWAPPED)


class SensorPortsError(EMRegError):
    """The sensor ports are wrong (live): ends live navigation with exit 2."""


@dataclass(frozen=True)
class PortVerdict:
    reason: str
    error_name: str  # OpenIGTLink STATUS name (at most 20 bytes)
    message: str
    code: int


class PortRoleCheck:
    """Collects ``(ReferenceToTracker, ProbeToTracker)`` of the first measurement cycles and judges the ports."""

    def __init__(self, reference_port: int, probe_port: int) -> None:
        self.reference_port = reference_port
        self.probe_port = probe_port
        self._reference: deque[np.ndarray] = deque(maxlen=MAX_PAIRS)
        self._probe_position: deque[np.ndarray] = deque(maxlen=MAX_PAIRS)
        self.pairs = 0
        self.passed = False
        #: set (latched) when the ports look swapped
        self.fatal: str | None = None
        self.spreads: tuple[float, float, float] = (0.0, 0.0, 0.0)
        self._verdict: PortVerdict | None = self._still(0.0)

    def add(self, reference_to_tracker: np.ndarray, probe_to_tracker: np.ndarray) -> None:
        """One measurement cycle with valid poses of both sensors."""
        if self.passed or self.fatal is not None:
            return
        self._reference.append(np.asarray(reference_to_tracker, dtype=float)[:3, :4].copy())
        self._probe_position.append(np.asarray(probe_to_tracker, dtype=float)[:3, 3].copy())
        self.pairs += 1
        if self.pairs < MIN_PAIRS or self.pairs % JUDGE_EVERY == 0:
            self._judge()

    def verdict(self) -> PortVerdict | None:
        """Why publishing must wait (or stop), or None once the check has passed."""
        return None if self.passed else self._verdict

    def _judge(self) -> None:
        reference = np.array(self._reference)
        self.spreads = role_spreads(reference[:, :, 3], reference[:, :, :3], np.array(self._probe_position))
        problem = role_problem(self.spreads, self.reference_port, self.probe_port)
        relative, reference_spread, probe_spread = self.spreads
        if problem is not None and problem[0] == "still":
            self._verdict = self._still(relative)
        elif self.pairs < MIN_PAIRS or max(reference_spread, probe_spread) < SWAP_MIN_SPREAD_MM:
            self._verdict = PortVerdict(
                REASON_PENDING, "PortCheck",
                f"checking the sensor ports: move the probe (port {self.probe_port}) further; publishing starts "
                f"when a sensor has moved {SWAP_MIN_SPREAD_MM:g} mm "
                f"(so far {max(reference_spread, probe_spread):.1f} mm)",
                st.STATUS_NOT_READY)
        elif problem is not None:  # swapped: latched
            self.fatal = f"sensor ports: {problem[1]}"
            self._verdict = PortVerdict(REASON_SWAPPED, "PortsSwapped", self.fatal, st.STATUS_CONFIG_ERROR)
        else:
            self.passed = True
            self._verdict = None
            self._reference.clear()
            self._probe_position.clear()

    def _still(self, relative_mm: float) -> PortVerdict:
        return PortVerdict(
            REASON_STILL, "ProbeNotMoving",
            f"the probe (port {self.probe_port}) has not moved relative to the reference "
            f"(port {self.reference_port}) yet ({relative_mm:.2f} mm of {MIN_PROBE_SPREAD_MM:g} mm): "
            "move the probe to start; if it moves, check the sensor ports",
            st.STATUS_NOT_READY)
