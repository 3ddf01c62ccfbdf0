"""False alarms of the live checks on real, undisturbed tracking (issue 37).

A recording made without any fault (the reference sensor stays where it was put, the tracker delivers every cycle)
is replayed through :class:`~.navigator.LiveNavigator` with its watchdog and the checkpoints' reference-jump watch
(:class:`EMRegModule.core.checkpoints.TrustMonitor`), on the recording's own clock: each frame arrives at its time
stamp, and the navigator is ticked every ``tick_s`` between frames as the live command's loop does (10 ms), so a
late frame of the real tracker counts as the watchdog sees it. Every not-OK verdict the watchdog starts (stale,
a sensor missing, out of range, bad quality) and every reference jump is a false alarm: nothing happened.
Frames: the Tracker frame of the recording; ``ReferenceToImage`` is the identity (the checks do not depend on it).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..core.checkpoints import TrustMonitor
from ..core.tracking import TrackingRecording
from ..devices.samples import SensorSample
from ..settings import NavigationSettings
from .navigator import LiveNavigator

#: The live command's loop ticks the navigator this often (s).
TICK_S = 0.01


@dataclass(frozen=True)
class FalseAlarms:
    """What the live checks raised on a replayed recording: ``hours`` of tracking, the watchdog's not-OK verdicts
    (``watchdog``: their messages) and the reference jumps (``jumps``: their descriptions), and the frames."""

    hours: float
    frames: int
    watchdog: list[str]
    jumps: list[str]

    @property
    def count(self) -> int:
        return len(self.watchdog) + len(self.jumps)

    @property
    def per_hour(self) -> float:
        return self.count / self.hours if self.hours > 0 else float("nan")


class _Clock:
    """The recording's time (s), set as the replay advances."""

    def __init__(self) -> None:
        self.now_s = 0.0

    def __call__(self) -> float:
        return self.now_s


def replay_false_alarms(recording: TrackingRecording, reference_sensor: int, probe_sensor: int,
                        settings: NavigationSettings | None = None, tick_s: float = TICK_S) -> FalseAlarms:
    """Replay ``recording`` (frames: samples within 1 ms) through the live path on its own clock; the alarms raised
    (see the module docstring). The sample period is the watchdog's own estimate, as for a live tracker."""
    times = np.asarray(recording.time_s, dtype=float)
    order = np.argsort(times, kind="stable")
    starts = np.flatnonzero(np.concatenate([[True], np.diff(times[order]) > 1e-3]))
    frames = [order[a:b] for a, b in zip(starts, [*starts[1:], len(order)], strict=True)]
    trust = TrustMonitor(None, settings)
    clock = _Clock()
    navigator = LiveNavigator(np.eye(4), reference_sensor, probe_sensor, out=None, trust=trust, clock=clock)
    previous = None
    for index, rows in enumerate(frames):
        t = float(times[rows[0]])
        if previous is not None:
            for between in np.arange(previous + tick_s, t, tick_s):
                clock.now_s = float(between)
                navigator.tick()
        clock.now_s = t
        for i in rows:
            navigator.on_sample(SensorSample(int(recording.sensor[i]), float(times[i]), recording.position_mm[i],
                                             recording.rotation[i], float(recording.quality[i]),
                                             label=str(recording.label[i] or ""), frame=index))
        previous = t
    navigator.finish_trust()
    watchdog = [v.message for v in navigator.announcer.changes if not v.ok and v.reason != "no_data"]
    span = float(times[order[-1]] - times[order[0]]) if len(times) else 0.0
    return FalseAlarms(span / 3600.0, len(frames), watchdog, [j.describe() for j in trust.report.reference_jumps])
