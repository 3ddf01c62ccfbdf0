"""Live navigation of a tool to a plan (issue 38), as users run it: ``emreg navigate --tool FILE --plan PLAN`` on a
replay over real TCP, on the trakSTAR simulator over a pty and on the Aurora simulator with a 5-DOF needle, each
received by an OpenIGTLink client. The tracking data are the small case's needle recording (``test_navigate_tool``:
tip 118 mm along the sensor's +x, resting on the case's targets), registered by the case's run; the judge is the
offline ``emreg navigate --tool --plan`` of the same recording and, for the numbers, each row's own tip and the plan.
"""

from __future__ import annotations

import csv
import json
import os
import subprocess
import sys
import threading
import time
from pathlib import Path

import numpy as np
import pyigtl
import pytest
from polling import announced_igtl_port
from test_guidance import plan_at_target
from test_live_navigate import _igtl_server_ports
from test_navigate_tool import (
    needle,  # noqa: F401 - the module fixture, shared
    needle_tip_to_probe,
    read_navigation,
    write_plus_device_set,
)

from EMRegModule.cli.main import main
from EMRegModule.core.frames import LPS_TO_RAS
from EMRegModule.core.tracking import TrackingRecording
from EMRegModule.devices.aurora.driver import FIVE_DOF_X_TO_NDI
from EMRegModule.devices.igtl_client import IGTLReceiver
from EMRegModule.io.navigation_csv import GUIDANCE_COLUMNS, NAVIGATION_HEADER
from EMRegModule.io.plan_markups import read_plan
from EMRegModule.io.recording import read_recording
from EMRegModule.io.tracking_csv import write_tracking_csv
from EMRegModule.live.guide import LiveGuide, trajectory_to_image

EMREG = [sys.executable, "-m", "EMRegModule"]
ENV = dict(os.environ, PYTHONUNBUFFERED="1")


@pytest.fixture(scope="module")
def guided(needle, tmp_path_factory):  # noqa: F811
    """The needle replay's tool file, a plan ending on target T1, and the offline navigation with both."""
    folder = tmp_path_factory.mktemp("guided")
    tool = write_plus_device_set(folder / "needle.xml", needle_tip_to_probe(), error_mm=0.4)
    plan = plan_at_target(folder / "plan.mrk.json", needle["truth"], "T1")
    assert main(["navigate", "--registration", str(needle["out"] / "registration.json"), "--source",
                 f"replay:{needle['recording']}", "--tool", str(tool), "--plan", str(plan), "--out",
                 str(folder / "offline"), "--quiet"]) == 0
    header, rows = read_navigation(folder / "offline" / "navigation.csv")
    return {**needle, "tool": tool, "plan": plan, "offline_header": header, "offline": rows, "folder": folder}


def _tips(rows: list[dict[str, str]]) -> np.ndarray:
    return np.array([[float(r[k]) for k in ("x_mm", "y_mm", "z_mm")] for r in rows]).reshape(-1, 3)


def _check_rows_against_offline(rows: list[dict[str, str]], guided: dict, tolerance_mm: float | np.ndarray) -> None:
    """Every live row's tip is an offline tip of the same recording (within ``tolerance_mm``, per row: the tracker
    protocol's rounding), and its guidance columns are those of its own tip and the plan."""
    assert rows
    live, offline = _tips(rows), _tips(guided["offline"])
    nearest = np.linalg.norm(live[:, None, :] - offline[None, :, :], axis=2).min(axis=1)
    assert np.all(nearest < tolerance_mm), (nearest - tolerance_mm).max()
    plan = read_plan(guided["plan"])
    to_target = plan.target_mm - live
    np.testing.assert_allclose([float(r["target_distance_mm"]) for r in rows], np.linalg.norm(to_target, axis=1),
                               atol=2e-4)
    np.testing.assert_allclose([float(r["to_go_mm"]) for r in rows], to_target @ plan.direction, atol=2e-4)
    np.testing.assert_allclose([float(r["lateral_mm"]) for r in rows],
                               np.linalg.norm(np.cross(to_target, plan.direction), axis=1), atol=2e-4)
    assert all(r["angle_deg"] != "" for r in rows)


def test_live_numbers_are_the_offline_ones():
    """:class:`LiveGuide`'s per-pose scalar arithmetic against :func:`EMRegModule.core.guidance.guidance` on random
    poses, for a line, a target alone and a tool without a shaft."""
    from EMRegModule.core.guidance import Plan, guidance
    from EMRegModule.core.transforms import make_transform, random_rotation

    rng = np.random.default_rng(3)
    poses = np.array([make_transform(random_rotation(rng), rng.uniform(-100, 100, 3)) for _ in range(40)])
    for plan, shaft in ((Plan(np.array([5.0, 6.0, 7.0]), np.array([-40.0, 20.0, 90.0])), np.array([0.0, 0.6, 0.8])),
                        (Plan(np.array([5.0, 6.0, 7.0])), np.array([1.0, 0.0, 0.0])),
                        (Plan(np.array([5.0, 6.0, 7.0]), np.array([-40.0, 20.0, 90.0])), None)):
        expected = guidance(poses, plan, shaft)
        guide = LiveGuide(plan, shaft)
        got = np.array([guide.numbers(pose) for pose in poses])
        for k, name in enumerate(GUIDANCE_COLUMNS):
            np.testing.assert_allclose(got[:, k], getattr(expected, name), atol=1e-9, equal_nan=True)


def test_replay_over_tcp_publishes_the_tip_the_plan_and_the_guidance(guided, tmp_path, monkeypatch):
    """``--source replay:`` with ``--igtl-port``: the tip under ``StylusTipToImage`` (the PLUS tool's name), each pose
    an offline tip; ``TrajectoryToImage`` from Entry along Entry -> Target and the POINT ``Plan`` (RAS); STRING
    ``Guidance`` with a row's numbers and the predicted error at the target; navigation.csv / navigation.json as
    offline."""
    ports = _igtl_server_ports(monkeypatch)
    received: dict[str, list] = {}
    lock = threading.Lock()

    def collect(message) -> None:
        with lock:
            received.setdefault(f"{message.message_type}:{message.device_name}", []).append(message)

    argv = ["navigate", "--registration", str(guided["out"] / "registration.json"), "--source",
            f"replay:{guided['recording']}", "--tool", str(guided["tool"]), "--plan", str(guided["plan"]),
            "--igtl-port", "0", "--max-samples", "300", "--out", str(tmp_path / "live"), "--quiet"]
    result: dict[str, int] = {}
    runner = threading.Thread(target=lambda: result.setdefault("code", main(argv)))
    client = None
    try:
        runner.start()
        client = IGTLReceiver("127.0.0.1", ports.get(timeout=120), collect, reconnect_s=0.01)
        runner.join(timeout=300)
    finally:
        if client is not None:
            client.close()
    assert result.get("code") == 0
    header, rows = read_navigation(tmp_path / "live" / "navigation.csv")
    assert header == guided["offline_header"] == NAVIGATION_HEADER.split(",") + list(GUIDANCE_COLUMNS)
    offline = {r["time_s"]: r for r in guided["offline"]}
    assert rows and all(r == offline[r["time_s"]] for r in rows)  # the same rows, byte for byte
    tips = [m for m in received.get("TRANSFORM:StylusTipToImage", []) if m.metadata.get("TransformStatus") == "OK"]
    assert len(tips) >= 50
    offline_tips = _tips(guided["offline"])
    for message in tips:
        lps = (LPS_TO_RAS @ np.asarray(message.matrix, dtype=float))[:3, 3]
        assert np.linalg.norm(offline_tips - lps, axis=1).min() < 1e-3
    plan = read_plan(guided["plan"])
    trajectory = received["TRANSFORM:TrajectoryToImage"][-1]
    expected = LPS_TO_RAS @ trajectory_to_image(plan)
    np.testing.assert_allclose(np.asarray(trajectory.matrix, dtype=float), expected, atol=1e-3)
    np.testing.assert_allclose(expected[:3, 3] + plan.length_mm * expected[:3, 2],
                               LPS_TO_RAS[:3, :3] @ plan.target_mm, atol=1e-6)  # the line ends on the target
    points = received["POINT:Plan"][-1]
    assert list(points.names) == ["Entry", "Target"]
    np.testing.assert_allclose(np.asarray(points.positions, dtype=float),
                               [LPS_TO_RAS[:3, :3] @ plan.entry_mm, LPS_TO_RAS[:3, :3] @ plan.target_mm], atol=1e-3)
    texts = [m.string for m in received["STRING:Guidance"]]
    document = json.loads((tmp_path / "live" / "navigation.json").read_text())
    said = f"target {document['predicted_at_target']['rms_mm']:.1f} mm predicted"
    table = np.array([[float(r[name]) for name in GUIDANCE_COLUMNS] for r in rows])
    assert texts and all(said in t for t in texts)
    for text in texts:  # "target 12.31 mm; lateral 1.02 mm; angle 4.40 deg; to go 11.80 mm; target 0.6 mm ..."
        numbers = [float(part.split()[-2]) for part in text.split("; ")[:4]]
        assert np.abs(table - numbers).max(axis=1).min() <= 0.005 + 1e-4, text  # a row's numbers, to 2 decimals
    distances = np.array([float(r["target_distance_mm"]) for r in rows])
    assert document["closest_approach"]["target_distance_mm"] == pytest.approx(distances.min(), abs=1e-3)
    assert document["tool"]["name"] == "Stylus"


def _wait_for(client, name: str, process: subprocess.Popen, end: float):
    message = None
    while message is None and process.poll() is None and time.monotonic() < end:
        message = client.wait_for_message(name, timeout=0.1)
    return message or client.wait_for_message(name, timeout=1.0)


def _live_navigate(guided: dict, source: str, out: Path, *extra: str) -> tuple[dict, str, list[dict[str, str]]]:
    """``emreg navigate SOURCE --tool --plan --igtl-port 0`` in a process of its own; what a pyigtl client got (the
    newest message of each device name), what it printed, and its navigation.csv rows."""
    nav = subprocess.Popen([*EMREG, "navigate", "--registration", str(guided["out"] / "registration.json"),
                            "--source", source, "--tool", str(guided["tool"]), "--plan", str(guided["plan"]),
                            "--igtl-port", "0", "--out", str(out), *extra],
                           stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, env=ENV)
    try:
        port, said = announced_igtl_port(nav)
        client = pyigtl.OpenIGTLinkClient("127.0.0.1", port)
        got = {}
        try:
            end = time.monotonic() + 180
            for name in ("StylusTipToImage", "Guidance", "TrajectoryToImage"):
                got[name] = _wait_for(client, name, nav, end)
        finally:
            client.stop()
        stdout, stderr = nav.communicate(timeout=120)
    finally:
        if nav.poll() is None:
            nav.kill()
            nav.communicate()
    assert nav.returncode == 0, said + stderr
    with open(out / "navigation.csv", newline="", encoding="utf-8") as handle:
        rows = list(csv.DictReader(handle))
    return got, stdout, rows


def test_trakstar_simulator_over_a_pty_navigates_the_tip_to_the_plan(guided, tmp_path):
    """The trakSTAR simulator replays the needle recording on a pty; live navigation with the tool and the plan
    writes the tips (each an offline tip, within the rounding of the protocol's 14-bit words: 0.11 mm in position,
    0.022 degree in angle) with their guidance and publishes tip, plan and guidance."""
    link = tmp_path / "trakstar"
    sim = subprocess.Popen([*EMREG, "sim-tracker", "--link", str(link), "--replay", str(guided["recording"]),
                            "--duration", "600"], stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, env=ENV)
    try:
        assert "trakSTAR simulator on /dev/pts/" in sim.stdout.readline()
        got, stdout, rows = _live_navigate(guided, f"trakstar://{link}?baud=115200", tmp_path / "out",
                                           "--max-samples", "320")
    finally:
        sim.terminate()
        sim.communicate(timeout=20)
    assert "tool tip poses published" in stdout and "mm predicted (95 %:" in stdout
    assert all(got[name] is not None for name in got), got
    # the bound of the protocol's rounding for each row: both positions (per axis half a 0.1116 mm step) and the
    # three angles of both sensors (half a 0.022 degree step each), the reference's over the tip's lever arm from it
    position_mm = 2 * np.sqrt(3) * (36 * 25.4 / 8192) / 2
    angle_rad = 3 * np.radians(180 / 8192) / 2
    reference_origin = np.array(json.loads((guided["out"] / "registration.json").read_text())["ReferenceToImage"])
    lever_mm = np.linalg.norm(_tips(rows) - reference_origin[:3, 3], axis=1)
    _check_rows_against_offline(rows, guided, position_mm + angle_rad * (lever_mm + 118.0))
    assert "target " in got["Guidance"].string and "predicted" in got["Guidance"].string
    tip = (LPS_TO_RAS @ np.asarray(got["StylusTipToImage"].matrix, dtype=float))[:3, 3]
    assert np.linalg.norm(_tips(guided["offline"]) - tip, axis=1).min() < 0.1


def _five_dof_recording(path: Path, out: Path) -> Path:
    """The needle recording with the probe's rotation turned so that the needle's shaft (its +x) is the axis the
    Aurora simulator takes as a 5-DOF coil's (the pose's +Z, reported by the driver as EMReg's +X)."""
    recording = read_recording(path)
    rotation = recording.rotation.copy()
    probe = recording.sensor == 2
    rotation[probe] = rotation[probe] @ FIVE_DOF_X_TO_NDI.T
    write_tracking_csv(TrackingRecording(recording.time_s, recording.sensor, recording.position_mm, rotation,
                                         recording.quality, recording.label), out, orientation="quaternion")
    return out


class _Aurora:
    """``emreg sim-tracker --model aurora`` on a pty behind ``link``, in a process of its own."""

    def __init__(self, tmp_path: Path, recording: Path, tools: str) -> None:
        self.link = tmp_path / "aurora"
        self.proc = subprocess.Popen([*EMREG, "sim-tracker", "--model", "aurora", "--link", str(self.link),
                                      "--replay", str(recording), "--tools", tools, "--duration", "300"],
                                     stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, env=ENV)
        banner = self.proc.stdout.readline()
        assert "Aurora simulator on /dev/pts/" in banner and "5-DOF" in banner, banner

    def stop(self) -> None:
        self.proc.terminate()
        self.proc.communicate(timeout=20)


def test_aurora_simulator_navigates_a_5dof_needle_whose_tip_is_on_its_axis(guided, tmp_path):
    recording = _five_dof_recording(guided["recording"], tmp_path / "needle5.csv")
    sim = _Aurora(tmp_path, recording, "1:6dof,2:5dof")
    try:
        got, stdout, rows = _live_navigate(guided, f"aurora://{sim.link}?baud=230400&five_dof=2", tmp_path / "out",
                                           "--max-samples", "160", "--stale-periods", "8")
    finally:
        sim.stop()
    assert "tool tip poses published" in stdout
    assert all(got[name] is not None for name in got), got
    # the Aurora sends float32 (BX) poses: at 118 mm from the sensor the tip is within a few hundredths of a mm
    _check_rows_against_offline(rows, guided, 0.05)


def test_a_tool_off_the_axis_of_a_5dof_sensor_or_on_an_empty_port_is_refused(guided, tmp_path):
    """PLUS issue #286's case: a tip 2 mm off a 5-DOF needle's axis would move with the roll nobody measures. And
    a tool on a port with no sensor. One line each, exit 2, no navigation.csv."""
    off_axis = needle_tip_to_probe()
    off_axis[1, 3] = 2.0
    tool = write_plus_device_set(tmp_path / "off_axis.xml", off_axis)
    sim = _Aurora(tmp_path, _five_dof_recording(guided["recording"], tmp_path / "needle5.csv"), "1:6dof,2:5dof")
    try:
        refused = []
        for extra in (["--tool", str(tool)], ["--tool", str(guided["tool"]), "--probe-sensor", "3"]):
            nav = subprocess.run([*EMREG, "navigate", "--registration", str(guided["out"] / "registration.json"),
                                  "--source", f"aurora://{sim.link}?five_dof=2", "--out", str(tmp_path / "out"),
                                  "--max-samples", "10", *extra], capture_output=True, text=True, env=ENV,
                                 timeout=120)
            errors = [line for line in nav.stderr.splitlines() if line.startswith("emreg navigate: error")]
            refused.append((nav.returncode, errors))
    finally:
        sim.stop()
    (code_5dof, errors_5dof), (code_port, errors_port) = refused
    assert code_5dof == 2 and len(errors_5dof) == 1
    assert "port 2 holds a 5-DOF sensor" in errors_5dof[0] and "2.00 mm off the sensor's axis" in errors_5dof[0]
    assert code_port == 2 and len(errors_port) == 1
    assert "no sensor on the probe port 3 for the tool of" in errors_port[0]
    assert not (tmp_path / "out" / "navigation.csv").exists()


def test_igtl_source_navigates_the_tip_to_the_plan(guided, tmp_path):
    """``emreg serve`` publishes the needle replay's sensors (ReferenceToTracker, ProbeToTracker); live navigation
    from ``igtl://`` with the tool and the plan writes the same tips and guidance as the offline replay (float32
    transforms: within 1e-3 mm)."""
    serve = subprocess.Popen([*EMREG, "serve", "--device", f"replay:{guided['recording']}", "--igtl-port", "0",
                              "--duration", "300"], stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, env=ENV)
    try:
        port, said = announced_igtl_port(serve)
        got, stdout, rows = _live_navigate(guided, f"igtl://127.0.0.1:{port}", tmp_path / "out", "--max-samples", "200")
    finally:
        serve.terminate()
        serve.communicate(timeout=20)
    assert "tool tip poses published" in stdout
    assert all(got[name] is not None for name in got), got
    _check_rows_against_offline(rows, guided, 1e-3)
