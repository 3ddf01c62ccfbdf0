"""The live checks on real tracking (issue 37): no false alarm on undisturbed data, and the registration's
prediction_trust reaching the live stream.

The real data (``Testing/Data/PlusLibData``, BSD-3, see its README): PLUS's
``WaterTankBottomTranslationTrackerBuffer`` (Probe and Reference of an EM tracker, 5,000 frames at 46 Hz, 125 s; the
reference lies still in a water tank until 123.5 s, when it was moved about 3 mm in 0.3 s: the control) and
``EightLandmarkPointsTrackedForPhantomRegistration`` (a stylus and a reference moved by hand, 1,000 frames at 15 Hz,
67 s: the watchdog's only, since a reference moved by hand jumps). Replayed through the live navigator on the
recordings' own clocks (:func:`EMRegModule.live.false_alarms.replay_false_alarms`).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from EMRegModule.devices.igtl_status import StatusMessage
from EMRegModule.io.recording import read_recording
from EMRegModule.live.false_alarms import replay_false_alarms
from EMRegModule.live.navigator import TRUST_STATUS_NAME, LiveNavigator

PLUS_DATA = Path(__file__).resolve().parents[1] / "Data" / "PlusLibData"
WATER_TANK = PLUS_DATA / "WaterTankBottomTranslationTrackerBuffer.igs.mha"
LANDMARKS = PLUS_DATA / "EightLandmarkPointsTrackedForPhantomRegistration.igs.mha"
#: Where the water tank's reference was moved (s after the first frame): the undisturbed part ends before it.
WATER_TANK_MOVED_S = 123.4


@pytest.fixture(scope="module")
def water_tank():
    return read_recording(WATER_TANK)


def test_no_false_alarm_on_the_still_reference(water_tank):
    """The undisturbed 123 s: no watchdog alarm (the real tracker's late frames included) and no reference jump."""
    still = water_tank.select(water_tank.time_s < water_tank.time_s.min() + WATER_TANK_MOVED_S)
    alarms = replay_false_alarms(still, 1, 2)
    assert alarms.hours * 3600 > 120 and alarms.frames > 4900
    assert alarms.watchdog == [] and alarms.jumps == []


def test_the_real_reference_move_is_a_jump(water_tank):
    """The control: the same replay sees the reference moved at the end of the recording (true, not false)."""
    alarms = replay_false_alarms(water_tank, 1, 2)
    assert alarms.watchdog == []
    assert len(alarms.jumps) >= 1
    assert all("jumped" in j for j in alarms.jumps)


def test_no_watchdog_alarm_on_the_hand_held_recording():
    """15 Hz real tracking with its own gaps: the watchdog (stale, missing sensor) stays silent."""
    alarms = replay_false_alarms(read_recording(LANDMARKS), 1, 2)
    assert alarms.frames == 1000
    assert alarms.watchdog == []


class _Server:
    """The messages a navigator sends (an IGTLServer's ``send`` / ``send_transform``)."""

    def __init__(self) -> None:
        self.statuses: list[StatusMessage] = []

    def send(self, message) -> None:
        if isinstance(message, StatusMessage):
            self.statuses.append(message)

    def send_transform(self, *args, **kwargs) -> int:
        return 0


@pytest.mark.parametrize("trusted", [True, False])
def test_prediction_trust_reaches_the_live_stream(trusted):
    """A registration whose prediction is not trusted says why in a STATUS ``PredictionTrust`` at the start and
    again each second; a trusted one sends none."""
    server, now = _Server(), [100.0]
    block = {"trusted": trusted, "reasons": [] if trusted else ["field distortion measured at the pinholes"]}
    navigator = LiveNavigator(np.eye(4), server=server, out=None, prediction_trust=block, clock=lambda: now[0])
    for step in range(30):  # 3 s of ticks
        now[0] = 100.0 + 0.1 * (step + 1)
        navigator.tick()
    sent = [m for m in server.statuses if m.device_name == TRUST_STATUS_NAME]
    if trusted:
        assert sent == [] and navigator.untrusted == ""
    else:
        assert 3 <= len(sent) <= 5
        assert all("field distortion measured" in m.status_message for m in sent)
