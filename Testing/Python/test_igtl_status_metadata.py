"""PLUS-style status on every transform (OpenIGTLink header version 2 metadata), both ways, over real TCP.

- EMReg's server (live ``navigate``): a pyigtl client sees ``TransformStatus = OK`` /
  ``TransformValid = true`` on each published ``ProbeToImage``, and ``INVALID`` / ``false`` on the
  transform itself while the watchdog withholds poses (the STATUS message still comes too).
- EMReg's ``igtl://`` source against a pyigtl server standing in for PLUS: a transform whose status
  is INVALID (carrying a wild pose) is never used for a pose; ``emreg record`` keeps it as INVALID
  in a sequence metafile.
"""

from __future__ import annotations

import threading
import time

import numpy as np
import pyigtl
import pytest

from EMRegModule.cli.main import main
from EMRegModule.core.frames import LPS_TO_RAS
from EMRegModule.core.transforms import make_transform
from EMRegModule.devices.device_url import parse_device_url
from EMRegModule.devices.igtl_server import IGTLServer
from EMRegModule.devices.igtl_status import StatusMessage
from EMRegModule.devices.samples import STATUS_OUT_OF_RANGE, SensorSample
from EMRegModule.devices.sources import IGTLSource
from EMRegModule.io.sequence_metafile import read_sequence_frames
from EMRegModule.live.navigator import LiveNavigator


def _sample(sensor: int, frame: int, status: str = "ok", position=(100.0, 0.0, 0.0)) -> SensorSample:
    return SensorSample(sensor, frame * 0.0125, np.asarray(position, dtype=float), np.eye(3), 0.0, status,
                        frame=frame, received_ns=time.monotonic_ns())


def _messages(client: pyigtl.OpenIGTLinkClient, name: str, count: int, timeout_s: float = 30.0) -> list:
    out = []
    deadline = time.monotonic() + timeout_s
    while len(out) < count and time.monotonic() < deadline:
        message = client.wait_for_message(name, timeout=1)
        if message is not None:
            out.append(message)
    return out


def test_a_pyigtl_client_sees_the_status_on_each_transform():
    reference_to_image = make_transform(None, [5.0, -3.0, 2.0])
    received = []  # (frame, message) as the pyigtl client has it after each frame (it keeps the latest)
    with IGTLServer("127.0.0.1", 0) as server:
        client = pyigtl.OpenIGTLinkClient("127.0.0.1", server.port)
        try:
            assert server.wait_for_clients(1, 10.0)
            nav = LiveNavigator(reference_to_image, 1, 2, server, None, period_s=0.0125, out=None)
            for frame in range(8):
                probe_out = frame >= 5  # the probe leaves the tracker's range: poses withheld
                nav.on_sample(_sample(1, frame))
                nav.on_sample(_sample(2, frame, STATUS_OUT_OF_RANGE if probe_out else "ok",
                                      position=(900.0, 900.0, 900.0) if probe_out else (110.0 + frame, 5.0, 0.0)))
                sent = nav.published + nav.invalid_sent
                deadline = time.monotonic() + 30
                while time.monotonic() < deadline:  # wait for this frame's transform (counts, not time)
                    message = client.wait_for_message("ProbeToImage", timeout=1)
                    if message is not None:
                        received.append((frame, message))
                        if sum(1 for _ in received) >= 1 and sent <= server.messages_sent:
                            break
            status = client.wait_for_message("Navigation", timeout=30)
        finally:
            client.stop()
    good = [(f, m) for f, m in received if m.metadata.get("TransformStatus") == "OK"]
    paused = [(f, m) for f, m in received if f >= 5]
    assert len(good) >= 3 and len(paused) >= 3
    for frame, message in good:
        assert message.header_version == 2 and frame < 5
        assert message.metadata == {"TransformStatus": "OK", "TransformValid": "true"}
        expected = LPS_TO_RAS @ reference_to_image @ make_transform(None, [10.0 + frame, 5.0, 0.0])
        np.testing.assert_allclose(message.matrix, expected, atol=1e-4)
    last_good = good[-1][1].matrix
    for _, message in paused:
        assert message.metadata == {"TransformStatus": "INVALID", "TransformValid": "false"}
        np.testing.assert_allclose(message.matrix, last_good, atol=1e-6)  # the last pose, never the wild one
    assert isinstance(status, StatusMessage) and status.error_name != "OK"


def _plus_like_sender(server: pyigtl.OpenIGTLinkServer, frames: int, invalid: set[int],
                      done: threading.Event) -> None:
    """Sends ReferenceToTracker / ProbeToTracker with PLUS's status metadata from a pyigtl server
    (made in the main thread: it installs signal handlers); frames in ``invalid`` carry a wild probe
    pose with TransformStatus INVALID."""
    try:
        deadline = time.monotonic() + 30
        while not server.is_connected() and time.monotonic() < deadline:
            time.sleep(0.01)
        time.sleep(0.2)
        for k in range(frames):
            stamp = 1000.0 + 0.0125 * k
            reference = make_transform(None, [100.0, 0.0, 0.0])
            bad = k in invalid
            probe = make_transform(None, [9999.0, -9999.0, 9999.0] if bad else [110.0 + 0.1 * k, 5.0, 0.0])
            for name, matrix, ok in (("ReferenceToTracker", reference, True), ("ProbeToTracker", probe, not bad)):
                message = pyigtl.TransformMessage(matrix, timestamp=stamp, device_name=name)
                message.header_version = 2
                message.metadata = {"TransformStatus": "OK" if ok else "INVALID",
                                    "TransformValid": "true" if ok else "false"}
                server.send_message(message, wait=True)
            time.sleep(0.0125)
        time.sleep(0.5)
    finally:
        done.set()


def test_the_igtl_source_never_uses_an_invalid_transform():
    invalid = {5, 6, 11, 17}
    done = threading.Event()
    plus = pyigtl.OpenIGTLinkServer(port=0, local_server=True)  # any free port, chosen as it binds
    port = plus.server_address[1]
    thread = threading.Thread(target=_plus_like_sender, args=(plus, 24, invalid, done), daemon=True)
    thread.start()
    source = IGTLSource(parse_device_url(f"igtl://127.0.0.1:{port}"), 1, 2)
    samples: list[SensorSample] = []
    nav = LiveNavigator(np.eye(4), 1, 2, None, None, period_s=None, out=None)

    def on_sample(sample: SensorSample) -> None:
        samples.append(sample)
        nav.on_sample(sample)

    try:
        source.start(on_sample)
        assert done.wait(60)
        deadline = time.monotonic() + 30
        while sum(s.sensor == 2 for s in samples) < 24 and time.monotonic() < deadline:
            time.sleep(0.01)
    finally:
        source.stop()
        plus.stop()
    probe = [s for s in samples if s.sensor == 2]
    assert len(probe) == 24
    bad = [s for s in probe if not s.valid]
    assert len(bad) == len(invalid) and all(s.status == "invalid" for s in bad)
    assert all(s.position_mm[0] == 9999.0 for s in bad) and all(s.position_mm[0] < 200 for s in probe if s.valid)
    # the navigator published only the valid frames, none of the wild poses
    assert nav.published == 24 - len(invalid)
    assert np.all(np.abs(nav.last_probe_to_image[:3, 3]) < 100)


def test_record_from_a_plus_server_keeps_invalid_frames_invalid(tmp_path):
    invalid = {3, 8, 9}
    done = threading.Event()
    plus = pyigtl.OpenIGTLinkServer(port=0, local_server=True)  # any free port, chosen as it binds
    port = plus.server_address[1]
    thread = threading.Thread(target=_plus_like_sender, args=(plus, 16, invalid, done), daemon=True)
    thread.start()
    out = tmp_path / "plus.seq.mha"
    try:
        # 16 frames of two transforms; the INVALID ones are not counted as samples by the recorder
        code = main(["record", "--device", f"igtl://127.0.0.1:{port}", "--out", str(out), "--max-samples",
                     str(32 - len(invalid)), "--duration", "60", "--quiet"])  # duration: a safety stop only
    finally:
        plus.stop()
    assert code == 0
    frames = read_sequence_frames(out)
    probe_valid = frames.valid["ProbeToTracker"]
    assert np.count_nonzero(~probe_valid) == len(invalid)
    assert np.all(frames.matrices["ProbeToTracker"][probe_valid][:, 0, 3] < 200)
    assert "Seq_Frame0003_ProbeToTrackerTransformStatus = INVALID" in out.read_text()


@pytest.fixture(autouse=True)
def _quiet_pyigtl_logs(caplog):
    caplog.set_level("ERROR")
