"""``emreg record`` keeps what a clean link delivers and never calls an empty recording a success; the live
commands refuse option values outside their range with one line (issue 28).

Everything is judged by counts (cycles sent, rows written, exit codes), never by how long something took.
"""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from EMRegModule.cli.main import main
from EMRegModule.devices.link_quality import JumpFilter, LinkGuard, LinkQualityMonitor
from EMRegModule.devices.samples import SensorSample
from EMRegModule.devices.simulator.faults import FaultPlan
from EMRegModule.devices.simulator.scene import ReplayScene
from EMRegModule.devices.simulator.trakstar import TrackerSimulator
from EMRegModule.io.recording import read_recording
from EMRegModule.io.tracking_csv import HEADER_ANGLES, read_tracking_csv

RATE_HZ = 80.0
PROBE_START_MM = np.array([250.0, 60.0, 100.0])
STEP_MM = 0.5  # the probe's x moves this much per cycle (40 mm/s): its x names the cycle
RESEATED_AT, RESEAT_MM = 60, 80.0  # the probe really jumps there (re-seated), and stays
SPIKE_AT, SPIKE_MM = 100, 30.0  # one pose 30 mm off, the next back: an outlier the guard refuses


def _write_recording(path: Path, cycles: int, probe_in: int | None = None) -> Path:
    """A 2-sensor recording at 80 Hz: reference at rest, probe moving ``STEP_MM`` per cycle in x (its y jumps by
    ``RESEAT_MM`` at cycle ``RESEATED_AT``, its z by ``SPIKE_MM`` at cycle ``SPIKE_AT`` only); the probe only in
    the first ``probe_in`` cycles when given."""
    lines = [",".join(HEADER_ANGLES)]
    for k in range(cycles):
        t = k / RATE_HZ
        lines.append(f"{t:.4f},1,300.0000,40.0000,120.0000,20.000000,-10.000000,5.000000,0,")
        if probe_in is None or k < probe_in:
            x, y, z = PROBE_START_MM + [STEP_MM * k, RESEAT_MM * (k >= RESEATED_AT), SPIKE_MM * (k == SPIKE_AT)]
            lines.append(f"{t:.4f},2,{x:.4f},{y:.4f},{z:.4f},10.000000,20.000000,30.000000,0,")
    path.write_text("\n".join(lines) + "\n")
    return path


def _one_line(capsys) -> str:
    err = [line for line in capsys.readouterr().err.strip().splitlines() if not line.startswith("[emreg]")]
    assert len(err) == 1, err
    assert "Traceback" not in err[0]
    return err[0]


# --- a clean link loses nothing -------------------------------------------------------------------------------


def test_a_clean_link_records_every_cycle_with_every_attached_sensor(tmp_path):
    """Every cycle the simulated trakSTAR streams, from the first, has its reference and probe row; the link's
    first records (judged before anything is trusted) and a probe re-seated far away (confirmed by the pose
    after it) are kept, not lost; only the one outlier pose the jump test refuses is missing."""
    scene = ReplayScene(read_recording(_write_recording(tmp_path / "scene.csv", 400)))
    out = tmp_path / "rec.csv"
    cycles = 120
    with TrackerSimulator(scene) as sim:
        assert main(["record", "--device", f"trakstar://{sim.path}", "--out", str(out), "--quiet",
                     "--max-samples", str(2 * cycles - 1)]) == 0  # cycle SPIKE_AT has no probe row
    rec = read_tracking_csv(out)
    times = np.unique(rec.time_s)
    assert len(times) == cycles and len(rec) == 2 * cycles - 1
    for j, t in enumerate(times):
        at = rec.time_s == t
        sensors = sorted(rec.sensor[at].tolist())
        assert sensors == ([1] if j == SPIKE_AT else [1, 2]), (j, sensors)
        if j != SPIKE_AT:  # the probe's x says which streamed cycle the row is: the j-th, none skipped
            probe_x = rec.position_mm[at & (rec.sensor == 2)][0, 0]
            assert round((probe_x - PROBE_START_MM[0]) / STEP_MM) == j
    reseated = rec.position_mm[(rec.sensor == 2)][RESEATED_AT]
    assert reseated[1] == pytest.approx(PROBE_START_MM[1] + RESEAT_MM, abs=0.1)


def _sample(sensor: int, frame: int, position) -> SensorSample:
    return SensorSample(sensor, frame / RATE_HZ, np.asarray(position, dtype=float), np.eye(3), frame=frame)


def test_hold_back_passes_on_in_order_only_what_the_guard_confirmed():
    from EMRegModule.devices.link_quality import HoldBack

    counts = [0, 0]
    guard = LinkGuard(lambda: tuple(counts), LinkQualityMonitor(min_records=4), JumpFilter(),
                      period_s=1 / RATE_HZ)
    written: list[tuple[int, int]] = []
    held = HoldBack(guard, lambda s: written.append((s.frame, s.sensor)))
    path = {0: [0, 0, 0], 1: [0.5, 0, 0], 2: [1, 0, 0], 3: [40, 0, 0], 4: [1.5, 0, 0], 5: [90, 0, 0], 6: [90.5, 0, 0]}
    for frame, probe in path.items():
        counts[0] += 2 if frame == 0 else 100  # the link judged from frame 1 on; one failure is no alarm
        held.push(_sample(1, frame, [300, 0, 0]))
        held.push(_sample(2, frame, probe))
        if frame == 0:  # a sensor that sends one pose, then nothing: it must not block the others
            held.push(_sample(3, frame, [-200, 0, 0]))
    held.close()
    # frames 0-1: held while the link is judged and the first probe pose waits, then passed on; 3: an outlier
    # (frame 4 is back on the path) dropped; 5: a real jump, passed on once frame 6 confirmed it; port 3's
    # unconfirmed pose given up once max_queued samples waited behind it
    assert written == [(f, s) for f in range(7) for s in (1, 2) if (f, s) != (3, 2)]
    assert held.dropped == 2 and held.max_queued < 14


# --- an unusable recording is no success ------------------------------------------------------------------------


def test_a_corrupt_link_is_no_recording_exit_3_and_no_file(tmp_path, capsys):
    out = tmp_path / "rec.csv"
    with TrackerSimulator(faults=FaultPlan(drop=0.05, flip=0.05), attached=(1, 2), seed=2) as sim:
        code = main(["record", "--device", f"trakstar://{sim.path}", "--out", str(out), "--duration", "1.5",
                     "--quiet"])
    line = _one_line(capsys)
    assert code == 3, line
    for needle in (str(out), "not a usable recording", "0 reference (port 1) and 0 probe (port 2) samples",
                   "link guard: tracker link corrupt", "records failed", "trakSTAR records:", "rejected"):
        assert needle in line, line
    assert list(tmp_path.iterdir()) == []  # no empty rec.csv, no .incomplete


def test_a_recording_without_the_probe_exits_3_and_is_moved_aside(tmp_path, capsys):
    out = tmp_path / "rec.csv"
    with TrackerSimulator(attached=(1,), seed=3) as sim:
        code = main(["record", "--device", f"trakstar://{sim.path}", "--out", str(out), "--max-samples", "60",
                     "--quiet"])
    line = _one_line(capsys)
    assert code == 3 and "60 reference (port 1) and 0 probe (port 2) samples" in line, line
    assert not out.exists() and "rec.csv.incomplete" in line
    assert len(read_tracking_csv(tmp_path / "rec.csv.incomplete")) == 60


@pytest.mark.parametrize(("probe_in", "code"), [(40, 0), (19, 3)])
def test_a_replay_below_half_its_frames_is_refused(tmp_path, capsys, probe_in, code):
    """The stated share: the probe in 40 of 40 frames records; in 19 of 40 (below 50 %) exits 3."""
    source = _write_recording(tmp_path / "source.csv", 40, probe_in=probe_in)
    out = tmp_path / "rec.seq.mha"
    assert main(["record", "--device", f"replay:{source}", "--fast", "--out", str(out), "--quiet"]) == code
    if code:
        line = _one_line(capsys)
        assert f"40 reference (port 1) and {probe_in} probe (port 2) samples of 40 expected (50 % needed)" in line
        assert not out.exists() and (tmp_path / "rec.seq.mha.incomplete").exists()
    else:
        assert len(read_recording(out)) == 80


# --- the live commands' options ---------------------------------------------------------------------------------


RECORD = ["record", "--device", "replay:x.csv", "--out", "r.csv"]
SERVE = ["serve", "--device", "replay:x.csv"]
NAVIGATE = ["navigate", "--registration", "r.json", "--source", "replay:x.csv", "--out", "o"]


@pytest.mark.parametrize(("command", "option", "value"), [
    (RECORD, "--duration", "0"), (RECORD, "--duration", "-3"), (RECORD, "--duration", "nan"),
    (RECORD, "--max-samples", "0"), (RECORD, "--max-samples", "-5"),
    (SERVE, "--stale-periods", "0"), (SERVE, "--stale-periods", "-1"), (SERVE, "--duration", "-1"),
    (NAVIGATE, "--reconnect", "-1"), (NAVIGATE, "--stale-periods", "0"), (NAVIGATE, "--max-samples", "0"),
    (["sim-tracker", "--model", "aurora"], "--rate", "0"), (["sim-tracker", "--model", "aurora"], "--rate", "-40"),
    (["sim-tracker"], "--duration", "0"), (["sim-tracker"], "--max-records", "-1"),
])
def test_a_live_option_that_is_not_positive_is_a_usage_error(tmp_path, capsys, monkeypatch, command, option, value):
    monkeypatch.chdir(tmp_path)
    assert main([*command, option, value]) == 2
    assert f"{option} {value}" in _one_line(capsys)
    assert list(tmp_path.iterdir()) == []  # refused before anything is opened or written


@pytest.mark.parametrize("port", ["70000", "-1", "65536"])
@pytest.mark.parametrize("command", ["serve", "navigate"])
def test_an_igtl_port_outside_the_tcp_range_is_one_line(tmp_path, capsys, monkeypatch, command, port):
    monkeypatch.chdir(tmp_path)
    source = ["--device", "replay:x.csv"] if command == "serve" else ["--registration", "r.json", "--source",
                                                                       "replay:x.csv"]
    assert main([command, *source, "--igtl-port", port]) == 2
    assert f"--igtl-port {port}" in _one_line(capsys)


@pytest.mark.parametrize(("model", "fault"), [
    ("trakstar", "drop=1.5"), ("trakstar", "flip=-0.1"), ("trakstar", "corrupt=2"), ("trakstar", "drop=nan"),
    ("trakstar", "stall=0:1"), ("trakstar", "stall=1:0"), ("trakstar", "stall=-1:0.2"), ("trakstar", "late=2:0.1"),
    ("trakstar", "late=0.5:-1"), ("trakstar", "unplug=5@0-1"), ("trakstar", "unplug=0@0-1"),
    ("trakstar", "out-of-range=2@3-1"), ("trakstar", "distort=2@1-1"),
    ("aurora", "crc=1.2"), ("aurora", "drop=-0.5"), ("aurora", "stall=0:1"), ("aurora", "missing=9@0-1"),
    ("aurora", "unplug=1@2-1"),
])
def test_a_fault_out_of_range_is_refused(capsys, model, fault):
    assert main(["sim-tracker", "--model", model, "--fault", fault, "--duration", "1"]) == 2
    assert f"--fault '{fault}'" in _one_line(capsys)


@pytest.mark.parametrize("model", ["trakstar", "aurora"])
def test_a_link_into_a_missing_folder_names_the_folder(tmp_path, capsys, model):
    link = tmp_path / "missing" / "trakstar"
    assert main(["sim-tracker", "--model", model, "--link", str(link), "--duration", "1"]) == 2
    line = _one_line(capsys)
    assert str(tmp_path / "missing") in line and "/dev/pts" not in line, line


def test_a_fifo_as_a_recording_is_refused_not_waited_on(tmp_path):
    fifo = tmp_path / "calibration.csv"
    os.mkfifo(fifo)
    done = subprocess.run([sys.executable, "-m", "EMRegModule", "calibrate", str(fifo), "--out",
                           str(tmp_path / "out")], capture_output=True, text=True, timeout=120)
    assert done.returncode == 2, done.stderr
    assert done.stderr.strip().splitlines() == [f"emreg calibrate: error: {fifo}: not a regular file (a FIFO, "
                                                "device or socket); give the recording's file"]
