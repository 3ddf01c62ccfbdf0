"""The NDI Aurora: protocol constants, the pty simulator, and outside clients of it.

Clients of the simulator: ndicapi's Python module ``ndicapy`` and scikit-surgerynditracker (both hold
the GIL through every blocking serial read, so their simulator runs in its own process, started as
``emreg sim-tracker --model aurora``), and EMReg's driver (ndicapi through ctypes; in-process).
"""

from __future__ import annotations

import json
import os
import struct
import subprocess
import sys
import time
from pathlib import Path

import ndicapy
import numpy as np
import pyigtl
import pytest
from polling import announced_igtl_port

from EMRegModule.core.frames import LPS_TO_RAS
from EMRegModule.core.tracking import TrackingRecording
from EMRegModule.core.transforms import (
    invert_rigid,
    make_transform,
    quaternion_to_rotation,
    random_rotation,
    rotation_to_quaternion,
)
from EMRegModule.devices.aurora import protocol as ndi
from EMRegModule.devices.aurora.driver import AuroraDriver
from EMRegModule.devices.device_url import parse_device_url
from EMRegModule.devices.samples import STATUS_NOT_ATTACHED, STATUS_OK, STATUS_OUT_OF_RANGE
from EMRegModule.devices.simulator.aurora import AuroraSimulator, parse_tools
from EMRegModule.errors import EMRegError
from EMRegModule.io.tracking_csv import read_tracking_csv, write_tracking_csv

EMREG = [sys.executable, "-m", "EMRegModule"]
ENV = dict(os.environ, PYTHONUNBUFFERED="1")


# --- helpers ----------------------------------------------------------------------------------------


def _recording(n_frames: int = 120, rate_hz: float = 40.0, seed: int = 3) -> TrackingRecording:
    """Reference on port 1 (still), probe on port 2 moving as a hand would (a 60 mm circle, 126 mm/s,
    turning 120 deg/s about a tilted axis: every quaternion sign pattern), in the Tracker frame. The
    motion closes on itself, so the replay loops without a jump (the link guard's jump test would
    rightly reject one)."""
    rng = np.random.default_rng(seed)
    reference = make_transform(random_rotation(rng, 30), [250.0, 30.0, -80.0])
    axis = np.array([0.3, -0.5, 0.81]) / np.linalg.norm([0.3, -0.5, 0.81])
    start = random_rotation(rng, 180)
    t, sensors, positions, rotations = [], [], [], []
    for i in range(n_frames):
        phase = 2 * np.pi * i / n_frames  # one full turn of path and orientation per loop
        turn = quaternion_to_rotation(np.r_[np.cos(phase / 2), np.sin(phase / 2) * axis])
        path = 60.0 * np.array([np.cos(phase), np.sin(phase), 0.3 * np.sin(2 * phase)])
        probe = make_transform(turn @ start, reference[:3, 3] + path)
        for sensor, pose in ((1, reference), (2, probe)):
            t.append(i / rate_hz)
            sensors.append(sensor)
            positions.append(pose[:3, 3])
            rotations.append(pose[:3, :3])
    n = len(t)
    return TrackingRecording(np.array(t), np.array(sensors), np.array(positions), np.array(rotations),
                             np.zeros(n), np.array([""] * n, dtype=object))


def _truth(recording: TrackingRecording):
    """frame number -> sensor -> (quaternion w >= 0, position): the simulator replays frame f mod n."""
    frames = {}
    for i, (t, s) in enumerate(zip(recording.time_s, recording.sensor, strict=True)):
        k = int(round(t * 40.0))
        frames.setdefault(k, {})[int(s)] = (rotation_to_quaternion(recording.rotation[i]), recording.position_mm[i])
    return lambda frame, sensor: frames[frame % len(frames)][sensor]


def _same_quaternion(a, b, tol: float) -> bool:
    a, b = np.asarray(a, dtype=float), np.asarray(b, dtype=float)
    return min(np.abs(a - b).max(), np.abs(a + b).max()) <= tol


class _Simulator:
    """``emreg sim-tracker --model aurora`` in its own process, on a pty behind ``link``."""

    def __init__(self, tmp_path: Path, *args: str, name: str = "aurora") -> None:
        self.link = tmp_path / name
        self.log = tmp_path / f"{name}-emit.csv"
        self.proc = subprocess.Popen([*EMREG, "sim-tracker", "--model", "aurora", "--link", str(self.link),
                                      "--duration", "180", "--emit-log", str(self.log), *args],
                                     stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, env=ENV)
        self.banner = self.proc.stdout.readline()
        assert "Aurora simulator on /dev/pts/" in self.banner, self.proc.stderr.read()

    def stop(self) -> list[dict]:
        self.proc.terminate()
        _, err = self.proc.communicate(timeout=20)
        assert self.proc.returncode == 0, err
        assert not self.link.exists()
        lines = self.log.read_text().splitlines()
        keys = lines[0].split(",")
        return [dict(zip(keys, line.split(","), strict=True)) for line in lines[1:]]


@pytest.fixture()
def replay(tmp_path):
    recording = _recording()
    path = tmp_path / "rec.csv"
    write_tracking_csv(recording, path, orientation="quaternion")
    return path, _truth(read_tracking_csv(path))


# --- protocol ------------------------------------------------------------------------------------


def test_crc16_matches_the_values_ndicapi_hard_codes():
    # ndicapi's ndiSerialProbe / ndiCommand send and expect these exact strings
    assert ndi.frame_command("INIT:") == b"INIT:E3A5\r"
    assert ndi.frame_reply("OKAY") == b"OKAYA896\r"
    assert ndi.frame_reply("RESET") == b"RESETBE6F\r"
    assert ndi.frame_command("VER:0") == b"VER:065EE\r"
    assert ndi.frame_command("GETINFO:Features.Firmware.Version") == b"GETINFO:Features.Firmware.Version0492\r"
    assert ndi.frame_command("INIT") == b"INIT\r"  # no ':' -> no CRC, as ndicapi
    assert ndi.parse_command(b"BX:0801" + b"%04X" % ndi.crc16("BX:0801")).crc_ok
    assert not ndi.parse_command(b"BX:08010000").crc_ok


def test_bx_reply_layout_and_crcs():
    q = rotation_to_quaternion(random_rotation(np.random.default_rng(1)))
    reports = [ndi.ToolReport(0x0A, "valid", q, np.array([1.5, -2.25, 300.125]), 0.07, frame=12),
               ndi.ToolReport(0x0B, "missing", port_status=ndi.PORT_OCCUPIED | ndi.PORT_OUT_OF_VOLUME, frame=12),
               ndi.ToolReport(0x0C, "disabled")]
    data = ndi.bx_reply(reports, system_status=0x0080)
    assert data[:2] == b"\xc4\xa5" and struct.unpack_from("<H", data, 2)[0] == len(data) - 8
    assert ndi.crc16(data[:-2]) == struct.unpack_from("<H", data, len(data) - 2)[0]  # ndicapi's single check
    parsed, system = ndi.parse_bx_reply(data)
    assert system == 0x0080 and [r.state for r in parsed] == ["valid", "missing", "disabled"]
    assert np.array_equal(parsed[0].quaternion, q.astype(np.float32)) and parsed[0].frame == 12
    assert parsed[1].port_status & ndi.PORT_OUT_OF_VOLUME
    bad = data[:-2] + bytes([data[-2] ^ 1, data[-1]])
    with pytest.raises(ValueError, match="CRC"):
        ndi.parse_bx_reply(bad)


def test_tx_fields_round_to_the_documented_units():
    report = ndi.ToolReport(0x0A, "valid", np.array([0.70711, -0.70710, 0.00004, -0.00016]),
                            np.array([123.456, -0.014, 2000.0]), 0.1234, frame=0x1F)
    # handle count, handle, 4 x 6 chars (1e-4), 3 x 7 chars (0.01 mm), error 6 chars, port status, frame, LF, system
    expected = "010A" "+07071-07071+00000-00002" "+012346-000001+200000" "+01234" "00000031" "0000001F\n" "0000"
    assert ndi.tx_reply_text([report]) == expected
    assert ndi.freeze_tag_of(ndi.ver_reply("AURORA Rev 008")) == "AURORA Rev 008"
    assert not ndi.supports_bx("AURORA Rev 008") and ndi.supports_bx("AURORA Rev 013")


def test_device_url_aurora():
    url = parse_device_url("aurora:///dev/ttyUSB0?baud=230400&reply=tx")
    assert (url.kind, url.path, url.baud, url.options["reply"]) == ("aurora", "/dev/ttyUSB0", 230400, "tx")
    assert parse_device_url("aurora:///dev/ttyUSB0").baud == 115200
    for bad in ("aurora://", "aurora:///dev/ttyUSB0?baud=14400", "aurora:///dev/ttyUSB0?reply=gx"):
        with pytest.raises(EMRegError):
            parse_device_url(bad)


# --- ndicapi as the client -----------------------------------------------------------------------------


def _ndicapy_probe(path: str, attempts: int = 3) -> int:
    """ndicapi's probe, as a user would run it again: it waits a fixed time for the device's reply to INIT, and on
    a machine whose cores are all busy (the suite beside other work) the simulator's reply came after it once in
    about ten full runs ("Bad reply from measurement system"). A device that never answers still fails."""
    for _ in range(attempts):
        status = ndicapy.ndiProbe(path)
        if status == ndicapy.NDI_OKAY:
            break
    return status


def _ndicapy_start(path: str):
    assert _ndicapy_probe(path) == ndicapy.NDI_OKAY
    device = ndicapy.ndiOpen(path)
    assert device is not None
    ndicapy.ndiCommand(device, "INIT:")
    ndicapy.ndiCommand(device, f"COMM:{ndicapy.NDI_115200:d}{ndicapy.NDI_8N1:03d}{ndicapy.NDI_NOHANDSHAKE:d}")
    version = ndicapy.ndiVER(device, 0)
    ndicapy.ndiCommand(device, "PHSR:02")
    handles = [ndicapy.ndiGetPHSRHandle(device, i) for i in range(ndicapy.ndiGetPHSRNumberOfHandles(device))]
    for h in handles:
        ndicapy.ndiCommand(device, f"PINIT:{h:02X}")
    ndicapy.ndiCommand(device, "PHSR:02")
    assert ndicapy.ndiGetPHSRNumberOfHandles(device) == 0
    for h in handles:
        ndicapy.ndiCommand(device, f"PENA:{h:02X}D")
    ndicapy.ndiCommand(device, "PHSR:04")
    assert ndicapy.ndiGetPHSRNumberOfHandles(device) == len(handles)
    ndicapy.ndiCommand(device, "TSTART:")
    return device, handles, version


def test_ndicapi_reads_bx_and_tx_frames_equal_to_the_replay(tmp_path, replay):
    path, truth = replay
    sim = _Simulator(tmp_path, "--replay", str(path))
    try:
        device, handles, version = _ndicapy_start(str(sim.link))
        assert "Freeze Tag: AURORA Rev 013" in version and handles == [0x0A, 0x0B]
        frames = set()
        checked = 0
        while len(frames) < 240:
            ndicapy.ndiCommand(device, "BX:0801")  # two tools: the reply length is valid UTF-8 for ndicapy
            for h, sensor in ((0x0A, 1), (0x0B, 2)):
                frame = ndicapy.ndiGetBXFrame(device, bytes([h]))
                q_t = ndicapy.ndiGetBXTransform(device, bytes([h]))
                assert ndicapy.ndiGetBXPortStatus(device, bytes([h])) & 0x31 == 0x31  # occupied, init, enabled
                q, p = truth(frame, sensor)
                assert _same_quaternion(q_t[:4], np.float32(q), 1e-7)
                assert np.array_equal(np.float32(q_t[4:7]), np.float32(p))  # float32 exactly
                checked += 1
                frames.add(frame)
        for _ in range(120):
            ndicapy.ndiCommand(device, "TX:0801")
            frame = ndicapy.ndiGetTXFrame(device, bytes([0x0B]))
            q_t = ndicapy.ndiGetTXTransform(device, bytes([0x0B]))
            q, p = truth(frame, 2)
            assert _same_quaternion(q_t[:4], q, 0.5e-4 + 1e-9)
            assert np.abs(np.asarray(q_t[4:7]) - p).max() <= 0.005 + 1e-9
        ndicapy.ndiCommand(device, "TSTOP:")
        ndicapy.ndiCommand(device, "PDIS:0B")  # a disabled tool: DISABLED in BX, no transform
        ndicapy.ndiCommand(device, "TSTART:")
        ndicapy.ndiCommand(device, "BX:0801")
        assert ndicapy.ndiGetBXTransform(device, bytes([0x0B])) == "DISABLED"
        assert len(ndicapy.ndiGetBXTransform(device, bytes([0x0A]))) == 8
        ndicapy.ndiCommand(device, "TSTOP:")
        with pytest.raises(OSError, match="0x0c"):  # TX outside tracking: ERROR0C ("invalid for current mode")
            ndicapy.ndiCommand(device, "TX:0801")
        # (not sent here: BX outside tracking. ndicapi checks the text ERROR reply as a binary one - "bad CRC" -
        # and ndicapy then builds a str from the unterminated binary buffer: depending on what the buffer held
        # before, it raises or crashes the interpreter. One reason EMReg's driver calls ndicapi through ctypes.)
        ndicapy.ndiClose(device)
        assert checked >= 480
    finally:
        sim.stop()


def test_ndicapi_rejects_corrupted_crcs_and_never_makes_them_a_pose(tmp_path, replay):
    path, truth = replay
    sim = _Simulator(tmp_path, "--replay", str(path), "--fault", "crc=0.2", "--seed", "5")
    rejected = accepted = 0
    try:
        device, _, _ = _ndicapy_start(str(sim.link))
        for _ in range(300):
            try:
                ndicapy.ndiCommand(device, "BX:0801")
            except OSError as exc:
                assert "Bad CRC" in str(exc)
                rejected += 1
                continue
            frame = ndicapy.ndiGetBXFrame(device, bytes([0x0B]))
            q, p = truth(frame, 2)
            assert np.array_equal(np.float32(ndicapy.ndiGetBXTransform(device, bytes([0x0B]))[4:7]), np.float32(p))
            accepted += 1
        ndicapy.ndiCommand(device, "TSTOP:")
        ndicapy.ndiClose(device)
    finally:
        log = sim.stop()
    corrupted = sum(int(r["corrupted"]) for r in log)
    assert corrupted == rejected and 30 <= rejected <= 100 and accepted == 300 - rejected


def test_ndicapi_probe_resets_a_device_left_at_another_speed(tmp_path):
    sim = _Simulator(tmp_path, "--tools", "1:6dof")
    try:
        device, _, _ = _ndicapy_start(str(sim.link))  # leaves the device at 115200 baud
        ndicapy.ndiCommand(device, "TSTOP:")
        ndicapy.ndiClose(device)
        # a new program probes at 9600 baud: INIT is line noise to the device, ndicapi sends a break,
        # reads RESET, and INIT works the second time
        assert ndicapy.ndiProbe(str(sim.link)) == ndicapy.NDI_OKAY
    finally:
        sim.stop()


# --- scikit-surgerynditracker as the client -----------------------------------------------------------------


@pytest.mark.parametrize(("freeze_tag", "reply", "tol_q", "tol_mm"),
                         [("AURORA Rev 013", "BX", 1e-7, 0.0), ("AURORA Rev 008", "TX", 0.5e-4, 0.005)])
def test_scikit_surgerynditracker_tracks_the_replay(tmp_path, replay, freeze_tag, reply, tol_q, tol_mm):
    from sksurgerynditracker.nditracker import NDITracker

    path, truth = replay
    sim = _Simulator(tmp_path, "--replay", str(path), "--freeze-tag", freeze_tag)
    try:
        tracker = NDITracker({"tracker type": "aurora", "serial port": str(sim.link), "use quaternions": True})
        assert tracker._capture_string == f"{reply}:0801"  # noqa: SLF001 - which reply it chose
        handles, _ = tracker.get_tool_descriptions()
        assert handles == [0x0A, 0x0B]
        tracker.start_tracking()
        seen = set()
        for _ in range(200):
            port_handles, _, frames, tracking, quality = tracker.get_frame()
            assert list(port_handles) == [0x0A, 0x0B] and np.allclose(quality, 0.05, atol=1e-6)
            for frame, pose, sensor in zip(frames, tracking, (1, 2), strict=True):
                q, p = truth(int(frame), sensor)
                pose = np.asarray(pose).ravel()
                assert _same_quaternion(pose[:4], q, tol_q + 1e-9)
                assert np.abs(pose[4:7] - (np.float32(p) if reply == "BX" else p)).max() <= tol_mm + 1e-9
                seen.add(int(frame))
        tracker.stop_tracking()
        tracker.close()
        assert len(seen) >= 60
    finally:
        sim.stop()


# --- EMReg's driver as the client ---------------------------------------------------------------------------


def test_driver_reads_every_tool_with_states_and_5dof(tmp_path):
    tools = parse_tools("1:6dof,2:6dof,3:5dof,4:6dof")  # four tools: a BX length ndicapy's wrapper cannot decode
    with AuroraSimulator(tools=tools, link=tmp_path / "aurora") as sim:
        driver = AuroraDriver(str(tmp_path / "aurora"), 115200, five_dof=(3,)).open()
        try:
            assert [(t.handle, t.port, t.sensor, t.dof) for t in driver.tools] == \
                [(0x0A, 1, 1, 6), (0x0B, 2, 2, 6), (0x0C, 3, 3, 5), (0x0D, 4, 4, 6)]
            samples = []
            driver.start(samples.append)
            _wait(lambda: len(samples) >= 160)  # 40 frames of the four tools
            # counted before the states change: a reply made after set_state may be delivered before the
            # next line of this thread runs (a loaded host), and it must not be among the "before" samples
            mark = len(samples)
            sim.set_state("missing", 2)
            sim.set_state("out-of-range", 3)
            sim.set_state("unplug", 4)
            _wait(lambda: len(samples) >= mark + 40)
            sim.corrupt_next_replies(3)
            _wait(lambda: driver.stats.crc_errors >= 3)
            driver.stop()
        finally:
            driver.close()
    assert driver.stats.crc_errors == 3 and driver.stats.other_errors == 0
    good = [s for s in samples[:mark] if s.status == STATUS_OK]
    assert len(good) == mark >= 160
    for s in good:
        q, p = sim.truth_for_frame(s.sensor, s.frame)
        assert np.array_equal(np.float32(s.position_mm), np.float32(p))
        assert _same_quaternion(s.extra["quaternion"], np.float32(q), 1e-7)
        assert s.extra["dof"] == (5 if s.sensor == 3 else 6)
        # a 5-DOF sensor's coil axis (NDI +Z) is EMReg's probe axis (+X)
        axis = s.rotation[:, 0] if s.sensor == 3 else s.rotation[:, 2]
        assert np.abs(axis - quaternion_to_rotation(q)[:, 2]).max() < 1e-6
    # sample times are the device's: frame numbers at 40 Hz, never the jittery moment a poll was answered
    assert all(s.time_s == (s.frame - samples[0].frame) / 40.0 for s in samples)
    late = {s.sensor: s.status for s in samples[-4:]}
    assert late == {1: STATUS_OK, 2: STATUS_OUT_OF_RANGE, 3: STATUS_OUT_OF_RANGE, 4: STATUS_NOT_ATTACHED}
    # frames of the last four samples: one frame, all tools; poses only where the status is ok
    assert len({s.frame for s in samples[-4:]}) == 1
    assert all(np.isnan(s.position_mm).all() for s in samples[-4:] if s.sensor in (2, 4))


def test_watchdog_with_the_aurora_stops_and_resumes(tmp_path):
    from EMRegModule.devices.igtl_server import IGTLServer
    from EMRegModule.devices.link_quality import guard_for
    from EMRegModule.devices.sources import open_source
    from EMRegModule.live.navigator import LiveNavigator

    with AuroraSimulator(tools=parse_tools("1:6dof,2:6dof"), link=tmp_path / "aurora", seed=6) as sim:
        source = open_source(f"aurora://{tmp_path / 'aurora'}?rate=40")
        server = IGTLServer("127.0.0.1", 0)
        # 8 periods (200 ms): a loaded test machine must not look like a stale tracker; the RMS error in mm
        # with the tracker-agnostic link guard, as live navigation runs it: a clean Aurora line must pass it
        nav = LiveNavigator(np.eye(4), 1, 2, server, None, source.period_s, stale_periods=8, max_quality=1.0,
                            out=None, link=guard_for(source))
        try:
            source.start(nav.on_sample)

            def wait_for(reason: str, timeout: float = 30.0) -> bool:
                end = time.monotonic() + timeout
                while time.monotonic() < end:
                    if nav.tick().reason == reason:
                        return True
                    time.sleep(0.005)
                return False

            assert wait_for("ok")
            for kind, sensor, reason in (("unplug", 1, "reference_missing"), ("missing", 2, "out_of_range"),
                                         ("out-of-range", 2, "out_of_range"), ("distort", 1, "bad_quality")):
                sim.set_state(kind, sensor)
                assert wait_for(reason), kind
                during = nav.published
                time.sleep(0.15)
                assert nav.published == during, kind  # nothing published meanwhile
                sim.set_state(kind, sensor, False)
                assert wait_for("ok"), kind
                deadline = time.monotonic() + 30  # wait on the count: a loaded machine only takes longer
                while nav.published <= during and time.monotonic() < deadline:
                    time.sleep(0.005)
                assert nav.published > during, kind  # publishing again
            # a stale verdict lasts from 8 periods (0.2 s) into the stall to its end: 2.3 s for this thread to
            # see it on a loaded host (the reply waiting behind the stall still comes well within ndicapi's
            # 5 s read timeout, so the line stays clean)
            sim.stall(2.5)
            assert wait_for("stale")
            assert wait_for("ok")
        finally:
            source.stop()
            server.close()
    reasons = [v.reason for v in nav.announcer.changes]
    assert "link" not in reasons  # never judged corrupt on a clean line
    for reason in ("reference_missing", "out_of_range", "bad_quality", "stale"):
        assert reason in reasons
    assert reasons.count("ok") >= 6


def test_driver_survives_a_dropped_byte_without_a_wrong_pose(tmp_path):
    with AuroraSimulator(tools=parse_tools("1:6dof,2:6dof"), link=tmp_path / "aurora", keep_log=True) as sim:
        driver = AuroraDriver(str(tmp_path / "aurora")).open()
        samples = []
        try:
            driver.start(samples.append)
            _wait(lambda: driver.stats.frames >= 5)
            sim.drop_byte_of_next_reply()
            # ndicapi waits for the rest of the reply (its 5 s read timeout), then rejects it
            _wait(lambda: driver.stats.timeouts + driver.stats.crc_errors >= 1)
            mark = driver.stats.frames
            _wait(lambda: driver.stats.frames >= mark + 5)
        finally:
            driver.close()
    assert driver.stats.timeouts + driver.stats.crc_errors == 1 == sum(f.corrupted for f in sim.log)
    for s in samples:
        q, p = sim.truth_for_frame(s.sensor, s.frame)
        assert np.array_equal(np.float32(s.position_mm), np.float32(p)) and s.status == STATUS_OK
    assert len(samples) >= 20


def test_driver_on_a_noisy_line_starts_and_never_makes_a_wrong_pose(tmp_path):
    from EMRegModule.devices.simulator.faults import AuroraFaults

    # 0.2 % of the bytes with a flipped bit: about one reply in six is damaged, start-up replies included
    with AuroraSimulator(tools=parse_tools("1:6dof,2:6dof"), link=tmp_path / "aurora", seed=11,
                         faults=AuroraFaults(flip=0.002)) as sim:
        driver = AuroraDriver(str(tmp_path / "aurora")).open()
        samples = []
        try:
            driver.start(samples.append)
            _wait(lambda: driver.stats.frames >= 80)
        finally:
            driver.close()
    assert driver.stats.crc_errors + driver.stats.timeouts >= 5
    assert len(samples) >= 160
    for s in samples:
        q, p = sim.truth_for_frame(s.sensor, s.frame)
        assert np.array_equal(np.float32(s.position_mm), np.float32(p))
        assert _same_quaternion(s.extra["quaternion"], np.float32(q), 1e-7)


def test_driver_names_the_port_of_a_tool_without_srom(tmp_path):
    with AuroraSimulator(tools=parse_tools("1:6dof,3:nosrom"), link=tmp_path / "aurora"):
        with pytest.raises(EMRegError, match=r"port 3 .*no SROM"):
            AuroraDriver(str(tmp_path / "aurora")).open()


def test_driver_uses_tx_for_old_firmware_and_survives_a_stall(tmp_path):
    with AuroraSimulator(tools=parse_tools("1:6dof,2:6dof"), link=tmp_path / "aurora",
                         freeze_tag="AURORA Rev 008") as sim:
        driver = AuroraDriver(str(tmp_path / "aurora"), 57600).open()
        samples = []
        try:
            assert not driver.use_bx
            driver.start(samples.append)
            _wait(lambda: driver.stats.frames >= 10)
            sim.stall(0.3)
            mark = driver.stats.frames
            _wait(lambda: driver.stats.frames >= mark + 10)
        finally:
            driver.close()
    assert all(s.status == STATUS_OK for s in samples)
    for s in samples:
        q, p = sim.truth_for_frame(s.sensor, s.frame)
        assert np.abs(s.position_mm - p).max() <= 0.005 + 1e-9
        assert _same_quaternion(s.extra["quaternion"], q, 0.5e-4 + 1e-9)


def test_driver_error_for_a_path_without_device(tmp_path):
    with pytest.raises(EMRegError, match="no NDI device answered"):
        AuroraDriver(str(tmp_path / "nothing-here")).open()


def _wait(condition, timeout_s: float = 30.0) -> None:
    deadline = time.monotonic() + timeout_s
    while not condition():
        assert time.monotonic() < deadline, "timed out"
        time.sleep(0.01)


# --- the command line: record and live navigate, as for the trakSTAR ----------------------------------------


def test_cli_record_and_live_navigate_from_the_aurora(tmp_path, replay):
    path, truth = replay
    sim = _Simulator(tmp_path, "--replay", str(path))
    try:
        out = subprocess.run([*EMREG, "record", "--device", f"aurora://{sim.link}", "--out",
                              str(tmp_path / "rec.csv"), "--max-samples", "200"], capture_output=True, text=True,
                             env=ENV, timeout=60)
        assert out.returncode == 0, out.stderr
        assert "Aurora replies" in out.stderr and "rejected 0" in out.stderr
        recorded = read_tracking_csv(tmp_path / "rec.csv")
        assert len(recorded.sensor) >= 200 and set(recorded.sensor.tolist()) == {1, 2}
        replayed = read_tracking_csv(path).position_mm
        nearest = np.linalg.norm(recorded.position_mm[:, None, :] - replayed[None, :, :], axis=2).min(axis=1)
        assert nearest.max() < 2e-4  # every recorded pose is a replayed one (float32, CSV's 4 decimals)

        rng = np.random.default_rng(4)
        reference_to_image = make_transform(random_rotation(rng), rng.uniform(-100, 100, 3))
        registration = tmp_path / "registration.json"
        registration.write_text(json.dumps({"ReferenceToImage": reference_to_image.tolist(),
                                            "sensor_offset_l_mm": 14.0, "fre_mm": 0.5, "pairs": []}))
        nav = subprocess.Popen([*EMREG, "navigate", "--registration", str(registration), "--source",
                                f"aurora://{sim.link}?baud=230400", "--igtl-port", "0", "--max-samples", "200",
                                "--stale-periods", "8",
                                "--out", str(tmp_path / "out")], stdout=subprocess.PIPE, stderr=subprocess.PIPE,
                               text=True, env=ENV)
        port, said = announced_igtl_port(nav)
        client = pyigtl.OpenIGTLinkClient("127.0.0.1", port)
        try:  # as long as navigate runs (a loaded machine starts it late), not for a fixed time
            end = time.monotonic() + 180
            message = None
            while message is None and nav.poll() is None and time.monotonic() < end:
                message = client.wait_for_message("ProbeToImage", timeout=0.1)
            message = message or client.wait_for_message("ProbeToImage", timeout=1.0)
        finally:
            client.stop()
        stdout, stderr = nav.communicate(timeout=60)
        assert nav.returncode == 0, said + stderr
        assert "probe poses published" in stdout
    finally:
        sim.stop()
    rows = (tmp_path / "out" / "navigation.csv").read_text().splitlines()
    assert len(rows) - 1 >= 50  # frames the watchdog let through (the link is judged first; a loaded host pauses)
    assert message is not None
    lps = (LPS_TO_RAS @ np.asarray(message.matrix, dtype=float))[:3, 3]
    # the published pose is Eq. 12 applied to one replayed frame
    expected = []
    for frame in range(120):
        (q1, p1), (q2, p2) = truth(frame, 1), truth(frame, 2)
        ref = make_transform(quaternion_to_rotation(q1), p1)
        probe = make_transform(quaternion_to_rotation(q2), p2)
        expected.append((reference_to_image @ invert_rigid(ref) @ probe)[:3, 3])
    assert np.linalg.norm(np.array(expected) - lps, axis=1).min() < 1e-2


def test_quality_limit_defaults_to_the_sources_scale():
    from EMRegModule.devices.aurora.source import AuroraSource
    from EMRegModule.live.loop import max_quality_limit

    assert max_quality_limit(None, AuroraSource.default_max_quality) == 1.0  # the Aurora's RMS error, mm
    assert max_quality_limit(None, None) == 20.0  # trakSTAR METAL
    assert max_quality_limit(-1, 1.0) is None
    assert max_quality_limit(0.5, 1.0) == 0.5


def test_live_navigate_from_the_aurora_refuses_swapped_ports(tmp_path, replay):
    """The port check is the trakSTAR's (the offline rule, judged on the first cycles): with the replay's
    hand-held tool on the "reference" port the Aurora path also ends with exit 2 and publishes nothing."""
    path, _ = replay
    sim = _Simulator(tmp_path, "--replay", str(path))
    try:
        registration = tmp_path / "registration.json"
        registration.write_text(json.dumps({"ReferenceToImage": np.eye(4).tolist(), "sensor_offset_l_mm": 14.0,
                                            "fre_mm": 0.5, "pairs": []}))
        nav = subprocess.run([*EMREG, "navigate", "--registration", str(registration), "--source",
                              f"aurora://{sim.link}", "--out", str(tmp_path / "out"), "--duration", "60",
                              "--reference-sensor", "2", "--probe-sensor", "1", "--stale-periods", "8"],
                             capture_output=True, text=True, env=ENV, timeout=120)
    finally:
        sim.stop()
    assert nav.returncode == 2, nav.stderr
    errors = [line for line in nav.stderr.splitlines() if line.startswith("emreg navigate: error")]
    assert len(errors) == 1 and "look swapped" in errors[0]
    assert (tmp_path / "out" / "navigation.csv").read_text().splitlines()[1:] == []
