"""Live navigation: watchdog states, ProbeToImage over real TCP vs offline navigation, emreg record,
the serve -> igtl:// chain, and the command line (sim-tracker --link + navigate --igtl-port)."""

from __future__ import annotations

import json
import os
import queue
import subprocess
import sys
import threading
import time
from pathlib import Path

import numpy as np
import pyigtl
import pytest
from polling import announced_igtl_port, wait_for

from EMRegModule.cli.main import main as cli
from EMRegModule.core.frames import LPS_TO_RAS
from EMRegModule.core.navigation import navigate_recording
from EMRegModule.core.tracking import TrackingRecording
from EMRegModule.core.transforms import invert_rigid, make_transform, random_rotation
from EMRegModule.devices.device_url import parse_device_url
from EMRegModule.devices.igtl_client import IGTLReceiver
from EMRegModule.devices.igtl_server import IGTLServer
from EMRegModule.devices.igtl_status import StatusMessage
from EMRegModule.devices.samples import STATUS_NOT_ATTACHED, STATUS_OK, STATUS_OUT_OF_RANGE, SensorSample
from EMRegModule.devices.simulator.trakstar import TrackerSimulator
from EMRegModule.devices.sources import IGTLSource
from EMRegModule.devices.trakstar.source import TrakstarSource
from EMRegModule.io.tracking_csv import read_tracking_csv, write_tracking_csv
from EMRegModule.live.navigator import LiveNavigator, TrackerPublisher, Watchdog

# --- helpers --------------------------------------------------------------------------------


def _sample(sensor: int, frame: int, status: str = "ok", quality: float = 0.0, position=(100.0, 0.0, 0.0)):
    return SensorSample(sensor, frame * 0.0125, np.asarray(position, dtype=float), np.eye(3), quality, status,
                        frame=frame, received_ns=time.monotonic_ns())


def _igtl_server_ports(monkeypatch) -> queue.Queue:
    """The ports of the OpenIGTLink servers made from now on, in order. A command run in this process with
    ``--igtl-port 0`` (any free port, chosen as its server binds) and ``--quiet`` says its port nowhere; a port
    found free beforehand could be taken in between by another process (another pytest-xdist worker's test). The
    server is replaced where the live loops make it (``emreg serve``, live ``emreg navigate``)."""
    from EMRegModule.devices import igtl_server
    from EMRegModule.live import serve
    from EMRegModule.pipeline import live_session

    ports: queue.Queue = queue.Queue()

    class PortSayingServer(igtl_server.IGTLServer):
        def __init__(self, *args, **kwargs) -> None:
            super().__init__(*args, **kwargs)
            ports.put(self.port)

    for module in (serve, live_session):
        monkeypatch.setattr(module, "IGTLServer", PortSayingServer)
    return ports


def _reference_to_image(seed: int = 4) -> np.ndarray:
    rng = np.random.default_rng(seed)
    return make_transform(random_rotation(rng), rng.uniform(-100, 100, 3))


def _write_registration(path: Path, reference_to_image: np.ndarray) -> Path:
    path.write_text(json.dumps({"ReferenceToImage": reference_to_image.tolist(), "sensor_offset_l_mm": 14.0,
                                "fre_mm": 0.5, "pairs": []}))
    return path


def _recording(n_frames: int = 100, rate_hz: float = 50.0, seed: int = 2) -> TrackingRecording:
    rng = np.random.default_rng(seed)
    t = np.arange(n_frames) / rate_hz
    reference_to_tracker = make_transform(random_rotation(rng, 30), [250.0, 30.0, 80.0])
    rows_time, sensors, positions, rotations, quality, labels = [], [], [], [], [], []
    for i in range(n_frames):
        probe = make_transform(random_rotation(rng, 40), reference_to_tracker[:3, 3] + rng.uniform(-60, 60, 3))
        for sensor, pose in ((1, reference_to_tracker), (2, probe)):
            rows_time.append(t[i])
            sensors.append(sensor)
            positions.append(pose[:3, 3])
            rotations.append(pose[:3, :3])
            quality.append(0.0 if i != 40 else 90.0)  # one bad-quality moment
            labels.append("T1" if 10 <= i < 20 else "")
    return TrackingRecording(np.array(rows_time), np.array(sensors), np.array(positions), np.array(rotations),
                             np.array(quality), np.array(labels, dtype=object))


class _FakeServer:
    def __init__(self) -> None:
        self.messages = []

    def send(self, message) -> int:
        self.messages.append(message)
        return time.monotonic_ns()

    def send_transform(self, name, matrix, timestamp=None, status="OK") -> int:
        self.messages.append((name, np.asarray(matrix), status))
        return time.monotonic_ns()


# --- watchdog ----------------------------------------------------------------------------------


def test_watchdog_states():
    dog = Watchdog(1, 2, period_s=0.0125, stale_periods=3, max_quality=20)
    assert dog.evaluate(0.0).reason == "no_data"
    dog.observe(_sample(1, 0), 0.0)
    assert dog.evaluate(0.001).reason == "no_data"  # start-up: the probe record is on its way
    assert dog.evaluate(0.05).reason == "stale"  # nothing at all for 50 ms > 3 periods
    dog.observe(_sample(1, 3), 0.045)
    assert dog.evaluate(0.05).reason == "probe_missing"
    dog.observe(_sample(2, 3), 0.052)
    assert dog.evaluate(0.053).ok
    assert dog.evaluate(0.045 + 0.037).ok  # within 3 periods (37.5 ms) of both sensors
    stale = dog.evaluate(0.052 + 0.040)
    assert stale.reason == "stale" and stale.code == 7
    t = 0.1
    dog.observe(_sample(1, 4), t)
    dog.observe(_sample(2, 4), t)
    assert dog.evaluate(t + 0.001).ok  # resumes by itself
    dog.observe(_sample(1, 5, STATUS_NOT_ATTACHED), t + 0.0125)
    missing = dog.evaluate(t + 0.013)
    assert missing.reason == "reference_missing" and missing.code == 16 and "not attached" in missing.message
    dog.observe(_sample(1, 6), t + 0.025)
    dog.observe(_sample(2, 6, STATUS_OUT_OF_RANGE), t + 0.025)
    assert dog.evaluate(t + 0.026).reason == "out_of_range"
    dog.observe(_sample(2, 7, quality=55), t + 0.0375)
    assert dog.evaluate(t + 0.038).reason == "bad_quality"
    dog.observe(_sample(2, 8, quality=float("nan")), t + 0.05)
    assert dog.evaluate(t + 0.05).ok
    # the reference alone going quiet (probe still streaming) is "reference missing", not "stale"
    for k in range(9, 20):
        dog.observe(_sample(2, k), t + 0.05 + (k - 8) * 0.0125)
    assert dog.evaluate(t + 0.05 + 11 * 0.0125).reason == "reference_missing"


def test_navigator_and_publisher_stop_at_the_sample_limit():
    """--max-samples N: frames after the N-th are ignored even when the reader delivers them before the
    command loop notices (a loaded host)."""
    server = _FakeServer()
    nav = LiveNavigator(_reference_to_image(), 1, 2, server, None, period_s=0.0125, out=None)
    nav.max_frames = 3
    publisher = TrackerPublisher(_FakeServer(), 1, 2, 0.0125, out=None)
    publisher.max_samples = 5
    for frame in range(6):
        for sensor in (1, 2):
            nav.on_sample(_sample(sensor, frame))
            publisher.on_sample(_sample(sensor, frame))
    assert nav.frames == 3 and nav.published == 3
    assert [m[0] for m in server.messages if isinstance(m, tuple)] == ["ProbeToImage"] * 3
    assert publisher.samples == 5 and publisher.published == 5


def test_navigator_publishes_only_good_frames_and_announces_changes(capsys):
    server = _FakeServer()
    reference_to_image = _reference_to_image()
    nav = LiveNavigator(reference_to_image, 1, 2, server, None, period_s=0.0125, out=sys.stderr)
    nav.on_sample(_sample(1, 0))
    nav.on_sample(_sample(2, 0, position=(110.0, 5.0, 0.0)))
    nav.on_sample(_sample(1, 1, STATUS_NOT_ATTACHED))
    nav.on_sample(_sample(2, 1))
    nav.on_sample(_sample(1, 2))
    nav.on_sample(_sample(2, 2))
    transforms = [m for m in server.messages if isinstance(m, tuple) and m[2] == "OK"]
    statuses = [m for m in server.messages if isinstance(m, StatusMessage)]
    assert nav.published == 2 and nav.withheld == 1 and len(transforms) == 2
    # the withheld frame went out as the last pose with TransformStatus INVALID (PLUS habit)
    invalid = [m for m in server.messages if isinstance(m, tuple) and m[2] == "INVALID"]
    assert invalid and all(np.allclose(m[1], transforms[0][1]) for m in invalid)
    expected = reference_to_image @ invert_rigid(make_transform(None, [100, 0, 0])) @ make_transform(None, [110, 5, 0])
    np.testing.assert_allclose(transforms[0][1], LPS_TO_RAS @ expected, atol=1e-9)
    assert [s.error_name for s in statuses][-3:] == ["OK", "ReferenceMissing", "OK"]
    err = capsys.readouterr().err
    assert "not publishing ProbeToImage: reference sensor (port 1) missing: not attached" in err
    assert "publishing ProbeToImage again" in err
    assert {s.device_name for s in statuses} == {"Navigation"}


# --- ProbeToImage over TCP vs offline navigation -------------------------------------------------


def test_replay_published_over_tcp_matches_offline_navigation(tmp_path, monkeypatch):
    recording = _recording()
    csv = tmp_path / "navigation_rec.csv"
    write_tracking_csv(recording, csv)
    reference_to_image = _reference_to_image()
    registration = _write_registration(tmp_path / "registration.json", reference_to_image)
    offline = navigate_recording(read_tracking_csv(csv), reference_to_image, 1, 2)
    assert cli(["navigate", "--registration", str(registration), "--source", f"replay:{csv}",
                     "--out", str(tmp_path / "offline")]) == 0
    ports = _igtl_server_ports(monkeypatch)
    received = []

    # every message, decoded by pyigtl (polling pyigtl's client only sees the newest one: a loaded test thread
    # that polls late loses the others)
    def collect(message):
        if message.device_name == "ProbeToImage" and message.metadata.get("TransformStatus") == "OK":
            received.append(np.asarray(message.matrix, dtype=float))

    argv = ["navigate", "--registration", str(registration), "--source", f"replay:{csv}", "--igtl-port", "0",
            "--out", str(tmp_path / "live"), "--quiet"]
    result = {}
    runner = threading.Thread(target=lambda: result.setdefault("code", cli(argv)))
    client = None
    try:
        runner.start()
        client = IGTLReceiver("127.0.0.1", ports.get(timeout=120), collect, reconnect_s=0.01)
        runner.join(timeout=120)
    finally:
        if client is not None:
            client.close()
    assert result.get("code") == 0
    # every pose received equals (float32) an offline ProbeToImage, in RAS
    offline_ras = LPS_TO_RAS @ offline.probe_to_image
    assert len(received) >= 0.5 * (len(offline) - 1)
    for matrix in received:
        error = np.abs(offline_ras - matrix).max(axis=(1, 2))
        assert error.min() < 1e-3, error.min()
    # the live navigation.csv equals the offline one, except the bad-quality moment the watchdog withheld
    offline_rows = (tmp_path / "offline" / "navigation.csv").read_text().splitlines()
    live_rows = (tmp_path / "live" / "navigation.csv").read_text().splitlines()
    assert live_rows[0] == offline_rows[0] == "time_s,x_mm,y_mm,z_mm,label,status"
    assert live_rows[1:] == [r for r in offline_rows[1:] if not r.startswith("0.8000,")]


# --- emreg record, serve -> igtl:// chain ----------------------------------------------------------


def test_record_from_the_simulator(tmp_path):
    out = tmp_path / "rec.csv"
    with TrackerSimulator(keep_truth=True, seed=3) as sim:
        assert cli(["record", "--device", f"trakstar://{sim.path}?rate=100", "--out", str(out),
                         "--max-samples", "200", "--quiet"]) == 0
        truth = list(sim.truth)
    rec = read_tracking_csv(out)
    assert len(rec) >= 200 and set(rec.sensors) == {1, 2, 3, 4}
    assert np.all(rec.quality == 0)
    truth_positions = {s: np.array([t.pose.position_mm for t in truth if t.sensor == s]) for s in (1, 2, 3, 4)}
    for i in range(len(rec)):
        distance = np.linalg.norm(truth_positions[int(rec.sensor[i])] - rec.position_mm[i], axis=1).min()
        assert distance < 0.1  # within the quantisation (0.056 mm per axis) of a pose the tracker sent
    # rows of one moment share time_s (spec)
    assert len(np.unique(rec.time_s)) * 4 == pytest.approx(len(rec), abs=8)


def test_serve_to_igtl_source_navigation_chain():
    reference_to_image = _reference_to_image()
    with TrackerSimulator(seed=5) as sim:
        source = TrakstarSource(parse_device_url(f"trakstar://{sim.path}"))
        server = IGTLServer("127.0.0.1", 0)
        publisher = TrackerPublisher(server, 1, 2, source.period_s, out=None)
        downstream = IGTLServer("127.0.0.1", 0)
        navigator = LiveNavigator(reference_to_image, 1, 2, downstream, None, None, out=None)
        consumer = IGTLSource(parse_device_url(f"igtl://127.0.0.1:{server.port}"), 1, 2)
        poses = []
        received = IGTLReceiver("127.0.0.1", downstream.port, poses.append)
        pairs = []
        original = publisher.on_sample

        def tee(sample):
            original(sample)
            pairs.append(sample)

        try:
            consumer.start(navigator.on_sample)
            assert consumer.receiver.connected.wait(30) and received.connected.wait(30)
            assert server.wait_for_clients(1, 30.0) and downstream.wait_for_clients(1, 30.0)
            source.start(tee)
            # wait on counts, not for a time: a loaded machine only takes longer
            wait_for(lambda: navigator.published >= 40 and sum(m.message_type == "TRANSFORM" for m in poses) >= 40)
        finally:
            source.stop()
            consumer.stop()
            received.close()
            server.close()
            downstream.close()
    transforms = [m for m in poses if m.message_type == "TRANSFORM"]
    assert navigator.published >= 40 and len(transforms) >= 40
    # recompute ProbeToImage from the tracker's own samples of each frame and compare the last one
    frames = {}
    for s in pairs:
        frames.setdefault(s.frame, {})[s.sensor] = s.transform()
    expected = [reference_to_image @ invert_rigid(f[1]) @ f[2] for f in frames.values() if 1 in f and 2 in f]
    got = LPS_TO_RAS @ np.asarray(transforms[-1].matrix, dtype=float)
    assert min(np.abs(e - got).max() for e in expected) < 1e-3


# --- watchdog end to end with the simulator -------------------------------------------------------------


def test_watchdog_with_the_simulator_stops_and_resumes():
    with TrackerSimulator(seed=6) as sim:
        source = TrakstarSource(parse_device_url(f"trakstar://{sim.path}?rate=80"))
        server = IGTLServer("127.0.0.1", 0)
        # 8 periods (100 ms) rather than 3: a loaded test machine must not look like a stale tracker
        nav = LiveNavigator(_reference_to_image(), 1, 2, server, None, source.period_s, stale_periods=8, out=None)
        try:
            frames = {}

            def tee(sample):
                frames.setdefault(sample.frame, {})[sample.sensor] = sample
                nav.on_sample(sample)

            source.start(tee)

            def reason_is(reason: str):
                return lambda: nav.tick().reason == reason

            assert wait_for(reason_is("ok"))
            assert wait_for(lambda: nav.published > 10)
            published = nav.published
            sim.set_unplugged(1)
            assert wait_for(reason_is("reference_missing"))
            time.sleep(0.2)
            during = nav.published
            time.sleep(0.1)
            assert nav.published == during  # nothing published while the reference is missing
            sim.set_unplugged(1, False)
            assert wait_for(reason_is("ok"))
            assert wait_for(lambda: nav.published > during)  # publishing again
            # silent until the watchdog has been seen to say so (a fixed stall could end before a late
            # test thread looks), then the line resumes
            sim.stall(60.0)
            assert wait_for(reason_is("stale"))
            sim.stall(0.0)
            assert wait_for(reason_is("ok"))
            sim.set_out_of_range(2)
            assert wait_for(reason_is("out_of_range"))
            sim.set_out_of_range(2, False)
            sim.set_distorted(1)  # metal distortion at the reference: METAL byte 90 > 20
            assert wait_for(reason_is("bad_quality"))
            sim.set_distorted(1, False)
            assert wait_for(reason_is("ok"))
        finally:
            source.stop()
            server.close()
    reasons = [v.reason for v in nav.announcer.changes]
    assert published > 10 and during >= published
    # every pose published came from one measurement cycle in which both sensors were fine (the watchdog
    # judges each cycle, whatever the reader's lag): none while the reference was unplugged or out of range
    published_frames = [frame for frame, _, _ in nav.latencies]
    assert len(published_frames) == nav.published
    assert all(frames[f][1].status == STATUS_OK and frames[f][2].status == STATUS_OK for f in published_frames)
    for reason in ("reference_missing", "stale", "out_of_range", "bad_quality"):
        assert reason in reasons
    assert reasons.count("ok") >= 4


# --- the command line, in subprocesses -------------------------------------------------------------


def _wait_for_message_while_running(client, process, name: str = "ProbeToImage", limit_s: float = 180.0):
    """The newest ``name`` message, waiting for as long as ``process`` runs (a loaded machine only starts
    it later); ``limit_s`` only guards against a hang."""
    end = time.monotonic() + limit_s
    message = None
    while message is None and process.poll() is None and time.monotonic() < end:
        message = client.wait_for_message(name, timeout=0.1)
    return message or client.wait_for_message(name, timeout=1.0)


def test_cli_sim_tracker_link_and_live_navigate(tmp_path):
    link = tmp_path / "trakstar"
    registration = _write_registration(tmp_path / "registration.json", _reference_to_image())
    env = dict(os.environ, PYTHONUNBUFFERED="1")
    emreg = [sys.executable, "-m", "EMRegModule"]
    # the simulator runs until the test stops it (a fixed lifetime ran out on a loaded machine before navigate started)
    sim = subprocess.Popen([*emreg, "sim-tracker", "--link", str(link), "--duration", "600"], stdout=subprocess.PIPE,
                           stderr=subprocess.PIPE, text=True, env=env)
    try:
        line = sim.stdout.readline()
        assert "trakSTAR simulator on /dev/pts/" in line and link.is_symlink()
        nav = subprocess.Popen([*emreg, "navigate", "--registration", str(registration), "--source",
                                f"trakstar://{link}?baud=115200", "--igtl-port", "0", "--max-samples", "200",
                                "--out", str(tmp_path / "out")], stdout=subprocess.PIPE, stderr=subprocess.PIPE,
                               text=True, env=env)
        port, said = announced_igtl_port(nav)
        client = pyigtl.OpenIGTLinkClient("127.0.0.1", port)
        try:
            message = _wait_for_message_while_running(client, nav)
        finally:
            client.stop()
        out, err = nav.communicate(timeout=60)
        assert nav.returncode == 0, said + err
        assert "probe poses published" in out
    finally:
        sim.terminate()
        sim.communicate(timeout=10)
    assert sim.returncode == 0 and not link.exists()  # stopped cleanly, link removed
    rows = (tmp_path / "out" / "navigation.csv").read_text().splitlines()
    # 200 frames at 80 Hz; the first ~0.8 s are withheld while the port check waits for the probe to move
    assert rows[0] == "time_s,x_mm,y_mm,z_mm,label,status" and 100 <= len(rows) - 1 <= 201
    positions = np.array([[float(v) for v in r.split(",")[1:4]] for r in rows[1:]])
    assert message is not None
    lps = (LPS_TO_RAS @ np.asarray(message.matrix, dtype=float))[:3, 3]
    assert np.linalg.norm(positions - lps, axis=1).min() < 1e-2


def test_cli_serve_publishes_tracker_transforms_as_measured(tmp_path, monkeypatch):
    recording = _recording(n_frames=60)
    csv = tmp_path / "rec.csv"
    write_tracking_csv(recording, csv)
    ports = _igtl_server_ports(monkeypatch)
    argv = ["serve", "--device", f"replay:{csv}", "--igtl-port", "0", "--max-samples", "110", "--quiet"]
    result = {}
    runner = threading.Thread(target=lambda: result.setdefault("code", cli(argv)))
    got = {}
    client = None
    try:
        runner.start()
        client = pyigtl.OpenIGTLinkClient("127.0.0.1", ports.get(timeout=120))
        deadline = time.monotonic() + 15
        while runner.is_alive() and time.monotonic() < deadline and len(got) < 3:
            for message in client.get_latest_messages():
                got.setdefault(message.device_name, message)
            time.sleep(0.01)
        runner.join(timeout=10)
        for message in client.get_latest_messages():  # what arrived after this thread last looked
            got.setdefault(message.device_name, message)
    finally:
        if client is not None:
            client.stop()
    assert result.get("code") == 0
    assert {"ReferenceToTracker", "ProbeToTracker", "Tracker"} <= set(got)
    assert isinstance(got["Tracker"], StatusMessage)
    probe_rows = recording.transforms()[recording.sensor == 2]
    sent = np.asarray(got["ProbeToTracker"].matrix, dtype=float)
    assert np.abs(probe_rows - sent).max(axis=(1, 2)).min() < 1e-3  # tracker frame, unchanged (no RAS flip)
