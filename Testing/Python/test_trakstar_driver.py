"""The trakSTAR driver against the simulator over a real pseudo-terminal (pyserial on /dev/pts/N).

Every decoded pose is compared with the truth the simulator encoded, within the protocol's
quantisation (half a 14-bit step; one step for unit elements, which saturate at 1 - 2^-13).
"""

from __future__ import annotations

import time

import numpy as np
import pytest
from polling import wait_for

from EMRegModule.core.tracking import TrackingRecording
from EMRegModule.core.transforms import make_transform, random_rotation, rotation_to_angles
from EMRegModule.devices.samples import STATUS_NOT_ATTACHED, STATUS_OK, STATUS_OUT_OF_RANGE
from EMRegModule.devices.simulator.faults import FaultPlan
from EMRegModule.devices.simulator.scene import ReplayScene
from EMRegModule.devices.simulator.trakstar import DISTORTED_METAL, EmittedRecord, TrackerSimulator
from EMRegModule.devices.trakstar import protocol as tp
from EMRegModule.devices.trakstar.driver import TrakstarDriver
from EMRegModule.errors import EMRegError

EPS = 1e-9


def _step_mm(scale: float) -> float:
    return 4 * scale / 32768 * 25.4


def matches(sample, truth: EmittedRecord, scale: float) -> bool:
    """True when the sample's record encodes ``truth`` within the quantisation."""
    record = sample.extra["record"]
    pose = truth.pose
    if record.position_mm is not None and np.max(np.abs(record.position_mm - pose.position_mm)) > \
            0.5 * _step_mm(scale) + EPS:
        return False
    if record.angles_deg is not None:
        diff = (record.angles_deg - pose.angles_deg + 180.0) % 360.0 - 180.0
        if np.max(np.abs(diff)) > 0.5 * 4 * 180 / 32768 + EPS:
            return False
    if record.matrix is not None and np.max(np.abs(record.matrix - pose.rotation)) > 4 / 32768 + EPS:
        return False
    return not (record.quaternion is not None and np.max(np.abs(record.quaternion - pose.quaternion)) > 4 / 32768 + EPS)


def assert_subsequence_of_truth(samples, truth: list[EmittedRecord], scale: float,
                                matched: list[EmittedRecord] | None = None) -> int:
    """Each sensor's decoded samples must be, in order, uncorrupted records the simulator sent (each one's record
    appended to ``matched`` when given)."""
    checked = 0
    for sensor in {s.sensor for s in samples}:
        sent = [t for t in truth if t.sensor == sensor]
        i = 0
        for sample in (s for s in samples if s.sensor == sensor):
            # the next record sent intact whose truth the sample encodes (a static sensor repeats its pose,
            # so an identical pose of a corrupted record is skipped over, never counted as the match)
            while i < len(sent) and (sent[i].corrupted or not matches(sample, sent[i], scale)):
                i += 1
            assert i < len(sent), f"sensor {sensor}: decoded pose {sample.position_mm} matches no intact record sent"
            assert sample.status == ("ok" if sent[i].status in ("ok", "distorted") else sent[i].status)
            if matched is not None:
                matched.append(sent[i])
            i += 1
            checked += 1
    return checked


@pytest.fixture()
def sim():
    simulator = TrackerSimulator(keep_truth=True, seed=1).start()
    yield simulator
    simulator.stop()


@pytest.fixture()
def driver(sim):
    d = TrakstarDriver(sim.path).open()
    yield d
    d.close()


def test_power_on_state_and_examine(sim, driver):
    assert driver.scale_inches == 36 and driver.rate_hz == pytest.approx(80.0)
    status = driver.examine_word(tp.PARAM_STATUS)
    assert (status & tp.STATUS_FORMAT_MASK) >> 1 == tp.POWER_ON_FORMAT.status_code
    assert not status & tp.STATUS_STREAMING
    assert all(driver.sensor_attached(s) for s in (1, 2, 3, 4))
    assert driver.examine(tp.PARAM_SYSTEM_MODEL).startswith(b"trakSTAR")
    assert driver.error_code() == 0
    sample = driver.point(2)  # power-on format: POSITION/ANGLES, no METAL byte
    assert sample is not None and sample.extra["record"].fmt.name == "POSITION/ANGLES"
    assert matches(sample, sim.truth[-1], 36)


@pytest.mark.parametrize("name", list(tp.FORMATS))
def test_point_every_format_four_sensors(sim, driver, name):
    driver.set_format(name)
    for sensor in (1, 2, 3, 4):
        for _ in range(3):
            sample = driver.point(sensor)
            assert sample is not None and sample.sensor == sensor and sample.status == STATUS_OK
            truth = sim.truth[-1]
            assert truth.sensor == sensor and truth.fmt == name
            assert matches(sample, truth, 36), (name, sensor)
    assert driver.stats.rejected == 0


def test_scale_rate_and_group_point(sim, driver):
    driver.set_position_scale(72)
    assert driver.examine_word(tp.PARAM_POSITION_SCALING) == 1
    driver.set_measurement_rate(150.0)
    assert driver.examine_word(tp.PARAM_MEASUREMENT_RATE) / 256 == pytest.approx(150.0)
    driver.configure("POSITION/MATRIX", metal=True, group=True)
    for _ in range(5):
        samples = driver.point_all()
        assert [s.sensor for s in samples] == [1, 2, 3, 4]
        assert len({s.frame for s in samples}) == 1 and all(s.quality == 0 for s in samples)
        for sample, truth in zip(samples, sim.truth[-4:], strict=True):
            assert matches(sample, truth, 72)
    with pytest.raises(EMRegError):
        driver.set_measurement_rate(400.0)


@pytest.mark.parametrize("name", ["POSITION/ANGLES", "POSITION/QUATERNION", "POSITION/MATRIX"])
def test_stream_four_sensors_every_pose_matches_truth(sim, driver, name):
    driver.configure(name, metal=True, group=True, rate_hz=200.0)
    got = []
    rate = min(200.0, tp.max_stream_rate_hz(tp.get_format(name), 4, metal=True))  # the line limits MATRIX
    driver.start_stream(got.append)
    assert wait_for(lambda: len(got) >= 0.6 * 4 * 0.6 * rate)  # about 0.4 s of the stream
    driver.stop_stream()
    assert {s.sensor for s in got} == {1, 2, 3, 4}
    checked = assert_subsequence_of_truth(got, sim.truth, 36)
    assert checked == len(got) and driver.stats.rejected == 0
    assert_whole_cycles(got)


def assert_whole_cycles(samples) -> None:
    """On a clean link every frame is one whole measurement cycle (ports 1..4 in order, one time),
    except the last (the stream may stop inside a cycle); frame times strictly increase."""
    by_frame = {}
    for s in samples:
        by_frame.setdefault(s.frame, []).append(s)
    frames = [by_frame[k] for k in sorted(by_frame)]
    assert len(frames) >= 10
    assert sorted(by_frame) == list(range(frames[0][0].frame, frames[0][0].frame + len(frames)))
    split = [[s.sensor for s in v] for v in frames[:-1] if [s.sensor for s in v] != [1, 2, 3, 4]]
    assert not split, f"{len(split)} of {len(frames)} frames are not one whole cycle: {split[:5]}"
    assert all(len({s.time_s for s in v}) == 1 for v in frames)
    times = np.array([v[0].time_s for v in frames])
    assert np.all(np.diff(times) > 0), "frame times must strictly increase"


def test_stream_cycles_stay_whole_when_the_reader_is_late(sim, driver):
    """A reader that falls behind (a loaded host; here a slow callback after every port-2 record)
    finds several records - of one cycle or of several - waiting at once, long after they arrived:
    grouping into cycles and the cycle times must come from the data, not from when reads return."""
    driver.configure("POSITION/ANGLES", metal=True, group=True, rate_hz=200.0)
    got = []

    def late_reader(sample):
        got.append(sample)
        if sample.sensor == 2:
            time.sleep(0.025)  # five periods at 200 Hz

    driver.start_stream(late_reader)
    assert wait_for(lambda: len(got) >= 4 * 40)
    reader = driver._reader
    driver.stop_stream()
    delivered = len(got)
    # stopped for good, although the late reader held an input buffer of records for a slow callback (once
    # the join gave up after 2 s while the callback went on, and these checks raced with it)
    assert not reader.is_alive()
    assert driver.stats.rejected == 0
    assert assert_subsequence_of_truth(got, sim.truth, 36) == len(got)
    assert_whole_cycles(got)
    assert len(got) == delivered  # nothing delivered after stop_stream() returned


class _UsbChunks:
    """A serial port whose reads return at most ``size`` bytes, as a USB-serial adapter delivers its
    packets: a record often arrives in two reads."""

    def __init__(self, inner, size: int = 20) -> None:
        self.inner = inner
        self.size = size

    def read(self, n: int) -> bytes:
        return self.inner.read(min(n, self.size))

    @property
    def in_waiting(self) -> int:
        return min(self.inner.in_waiting, self.size - 1)

    def __getattr__(self, name):
        return getattr(self.inner, name)


def test_a_late_reader_is_not_a_silent_line(sim, driver):
    """Records split across reads by the adapter, and a reader late by more than the gap limit (60 ms
    here): no byte was lost and the line never fell silent, so no record may be dropped as interrupted."""
    driver.configure("POSITION/ANGLES", metal=True, group=True, rate_hz=80.0)
    serial_port = driver.serial
    driver.serial = _UsbChunks(serial_port)
    got = []

    def late_reader(sample):
        got.append(sample)
        if sample.sensor == 2:
            time.sleep(0.06)

    try:
        driver.start_stream(late_reader)
        assert wait_for(lambda: len(got) >= 4 * 25)
        driver.stop_stream()
    finally:
        driver.serial = serial_port
    assert driver.stats.gap_errors == 0 and driver.stats.rejected == 0, driver.stats
    assert assert_subsequence_of_truth(got, sim.truth, 36) == len(got)
    assert_whole_cycles(got)


def test_faults_never_yield_a_wrong_pose():
    faults = FaultPlan(drop=0.004, flip=0.004)
    with TrackerSimulator(keep_truth=True, seed=7, faults=faults, fast=True) as sim, \
            TrakstarDriver(sim.path) as driver:
        driver.configure("POSITION/ANGLES", metal=True, group=True)
        got = []
        driver.start_stream(got.append)
        assert wait_for(lambda: sum(t.corrupted for t in sim.truth if t.emit_ns) > 40)  # about 0.5 s of stream
        driver.stop_stream()
        stream_truth = [t for t in sim.truth if t.emit_ns]
    corrupted = sum(t.corrupted for t in stream_truth)
    assert corrupted > 20, "the fault injection did not corrupt enough records to test anything"
    matched: list[EmittedRecord] = []
    checked = assert_subsequence_of_truth(got, stream_truth, 36, matched)
    stats = driver.stats
    assert checked == len(got)
    assert stats.phase_errors + stats.follow_errors + stats.address_errors > 0
    # the intact records sent up to the last one delivered: what the reader had reached when the stream stopped
    # (stop_stream discards what a reader late on a loaded host still held; that is no loss of the resync's)
    reached = max(t.emit_ns for t in matched)
    clean = sum(not t.corrupted for t in stream_truth if t.emit_ns <= reached)
    assert clean >= 100, "the reader reached too little of the stream to judge"
    assert len(got) >= 0.8 * clean, (len(got), clean, stats)


def test_unplugged_and_out_of_range_sensors_are_flagged(sim, driver):
    driver.configure("POSITION/ANGLES", metal=True, group=True)
    sim.set_unplugged(3)
    sim.set_out_of_range(4)
    samples = driver.point_all()
    status = {s.sensor: s.status for s in samples}
    assert status == {1: STATUS_OK, 2: STATUS_OK, 3: STATUS_NOT_ATTACHED, 4: STATUS_OUT_OF_RANGE}
    assert not samples[2].valid and not samples[3].valid and samples[3].quality == tp.METAL_MAX
    assert not driver.sensor_attached(3) and driver.sensor_attached(4)
    assert driver.error_code() == tp.ERROR_SENSOR_NOT_CONNECTED
    sim.set_unplugged(3, False)
    sim.set_out_of_range(4, False)
    assert all(s.status == STATUS_OK for s in driver.point_all())


def test_stall_then_resume(sim, driver):
    driver.configure("POSITION/ANGLES", metal=False, group=True)
    got = []
    driver.start_stream(got.append)
    assert wait_for(lambda: len(got) >= 20)
    sim.stall(0.3)
    stall_until_ns = sim._stall_until_ns
    first_after_stall = len(sim.truth)  # every record made from here on is made during or after the stall
    # data again after it: samples whose records the simulator sent once the stall was over
    assert wait_for(lambda: sum(1 for r in sim.truth[first_after_stall:] if r.emit_ns) >= 20)
    assert wait_for(lambda: len(got) >= 20 + 20)
    driver.stop_stream()
    emitted = [r.emit_ns for r in sim.truth[first_after_stall:] if r.emit_ns]
    assert min(emitted) >= stall_until_ns  # silence during the stall
    assert assert_subsequence_of_truth(got, sim.truth, 36) == len(got)  # and the same stream resumed


def test_unknown_port_is_a_clear_error(tmp_path):
    with pytest.raises(EMRegError, match="cannot open"):
        TrakstarDriver(str(tmp_path / "no-such-tty")).open()


def _small_recording(n: int = 30) -> TrackingRecording:
    rng = np.random.default_rng(9)
    rows = []
    for i in range(n):
        for sensor in (1, 2):
            pose = make_transform(random_rotation(rng, 60), rng.uniform(-400, 400, 3))
            rows.append((i * 0.02, sensor, pose))
    return TrackingRecording(np.array([r[0] for r in rows]), np.array([r[1] for r in rows]),
                             np.array([r[2][:3, 3] for r in rows]), np.array([r[2][:3, :3] for r in rows]),
                             np.zeros(len(rows)), np.array([""] * len(rows), dtype=object))


def test_replay_point_returns_successive_samples_and_stream_keeps_order():
    recording = _small_recording()
    probe = recording.for_sensor(2)
    angles = rotation_to_angles(probe.rotation)
    with TrackerSimulator(ReplayScene(recording), keep_truth=True) as sim, TrakstarDriver(sim.path) as driver:
        for k in range(5):  # successive POINT requests: the sensor's successive samples
            sample = driver.point(2)
            assert np.max(np.abs(sample.position_mm - probe.position_mm[k])) <= 0.06
        driver.configure("POSITION/ANGLES", metal=False, group=True)
        got = []
        driver.start_stream(got.append)
        assert wait_for(lambda: sum(1 for s in got if s.sensor == 2) >= 30)  # 30 frames at 50 Hz
        driver.stop_stream()
        truth = list(sim.truth)
    probes = [s for s in got if s.sensor == 2]
    assert len(probes) >= 30
    for i, sample in enumerate(probes[:30]):  # in the recording's order, from its first frame
        assert np.max(np.abs(sample.position_mm - probe.position_mm[i])) <= 0.06
        assert np.max(np.abs((sample.angles_deg - angles[i] + 180) % 360 - 180)) <= 0.012
    assert {s.status for s in got if s.sensor in (3, 4)} == {STATUS_NOT_ATTACHED}  # empty ports in group mode
    # played at the recording's own rate: the simulator scheduled frame k at the recording's time of frame k
    streamed = [r.time_s for r in truth if r.sensor == 2][-len(probes):][:30]
    np.testing.assert_allclose(np.diff(streamed), np.diff(recording.for_sensor(2).time_s[:30]), atol=1e-9)


def test_distorted_sensor_reports_bad_metal_byte(sim, driver):
    driver.configure("POSITION/ANGLES", metal=True, group=True)
    sim.set_distorted(2)
    samples = driver.point_all()
    assert samples[1].quality == DISTORTED_METAL and samples[1].valid and samples[0].quality == 0
    assert matches(samples[1], sim.truth[-3], 36)


def test_point_never_takes_a_late_reply_for_the_next_request():
    """POINT has no request id: a reply that comes after the driver gave up on it must never be taken
    as the reply to the next request. The simulator answers 30 % of the requests 1.6 timeouts late
    (the same bytes, later; the next replies queue behind it on the line, as on the cable); every pose
    the driver returns must be the one the simulator sent for that very request (its emit log)."""
    recording = _small_recording(80)  # random poses: a reply to another request is told apart at once
    with TrackerSimulator(ReplayScene(recording), keep_truth=True, seed=3) as sim, \
            TrakstarDriver(sim.path, timeout_s=0.05) as driver:
        sim.truth.clear()  # what open() asked for
        sim.faults = FaultPlan.parse(["late=0.3:0.08"])
        results = [driver.point(2) for _ in range(60)]
        truth = [t for t in sim.truth if t.sensor == 2]
        late = sim.late_replies
    assert late >= 8 and len(truth) == 60  # one record per request, some of them late
    answered = [(k, sample) for k, sample in enumerate(results) if sample is not None]
    stale = [k for k, sample in answered if not matches(sample, truth[k], 36)]
    assert not stale, f"requests {stale} returned the reply to another request"
    assert len(answered) >= 60 - late - 5  # the requests answered in time still get their pose
    assert driver.discarded_replies >= late


def test_point_discards_a_reply_with_more_bytes_behind_it():
    """A stale reply already on its way when the request goes out: the two replies arrive back to back,
    and the driver returns neither (it cannot tell which one answers its request)."""
    recording = _small_recording(20)
    baud = 9600  # a record takes 15 ms on the line: the test does not hang on a thread waking within 2 ms
    with TrackerSimulator(ReplayScene(recording), baud=baud, keep_truth=True) as sim, \
            TrakstarDriver(sim.path, baud=baud) as driver:
        sim.truth.clear()  # the reply to open()'s POINT, already drained by open()
        driver.serial.write(bytes([tp.address_byte(2), tp.POINT]))  # a request the driver does not know of
        assert wait_for(lambda: len(sim.truth) >= 1)  # its reply is being sent (or already waits)
        sample = driver.point(2)
        assert sample is None or matches(sample, sim.truth[1], 36)  # never the stale reply, truth[0]
        follow = driver.point(2)
        assert follow is not None and matches(follow, sim.truth[-1], 36)
