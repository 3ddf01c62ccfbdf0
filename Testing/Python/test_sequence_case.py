"""``emreg run`` on a case given as PLUS sequence metafiles, and runs that finish.

- The standard simulated case with its three recordings as ``.seq.mha`` (no labels; 3 % of the
  probe frames INVALID and carrying wild poses) gives the same pairing, l, ``ReferenceToImage``
  and navigation as the CSV case.
- A case whose navigation recording has no usable dwell still runs to the end (exit 0): the TRE
  is "not evaluated" with its reason in run.json, evaluation.json, the report and stderr;
  ``emreg evaluate`` alone exits 2 and says what the dwell search found.
"""

from __future__ import annotations

import csv
import json
import shutil
from pathlib import Path

import numpy as np
import pytest
from conftest import load_truth

from EMRegModule.cli.main import main
from EMRegModule.core.tracking import TrackingRecording
from EMRegModule.core.transforms import apply_transform, invert_rigid, random_rotation
from EMRegModule.io.sequence_metafile import format_sequence_metafile
from EMRegModule.io.tracking_csv import read_tracking_csv, write_tracking_csv

INVALID_FRACTION = 0.03


def _case_copy(source: Path, target: Path, recordings: bool) -> Path:
    target.mkdir(parents=True, exist_ok=True)
    for item in source.iterdir():
        if item.suffix == ".csv" and not recordings:
            continue
        if item.is_dir():
            shutil.copytree(item, target / item.name)
        else:
            shutil.copy(item, target / item.name)
    return target


def _with_invalid_frames(recording: TrackingRecording, rng: np.random.Generator) -> tuple[str, int]:
    """Sequence metafile text of a recording with some probe frames INVALID and carrying wild poses."""
    probe_rows = np.flatnonzero(recording.sensor == 2)
    bad = rng.choice(probe_rows, size=int(INVALID_FRACTION * len(probe_rows)), replace=False)
    wild = TrackingRecording(recording.time_s, recording.sensor, recording.position_mm.copy(),
                             recording.rotation.copy(), recording.quality, recording.label, recording.source)
    for row in bad:
        wild.position_mm[row] += rng.normal(0, 1, 3) / np.sqrt(3) * rng.uniform(50, 300)
        wild.rotation[row] = random_rotation(rng) @ wild.rotation[row]
    statuses = np.full(len(recording), "OK", dtype=object)
    statuses[bad] = "INVALID"
    return format_sequence_metafile(wild, statuses={2: statuses}), len(bad)


@pytest.fixture(scope="module")
def runs(standard_case, standard_run, tmp_path_factory):
    """The standard case's run (conftest's, read only) and the run of the same case as sequence metafiles."""
    root = tmp_path_factory.mktemp("sequence_case")
    seq_case = _case_copy(standard_case, root / "seq_case", recordings=False)
    rng = np.random.default_rng(5)
    invalid = {}
    for stem in ("calibration", "navigation", "board"):
        text, invalid[stem] = _with_invalid_frames(read_tracking_csv(standard_case / f"{stem}.csv"), rng)
        (seq_case / f"{stem}.seq.mha").write_text(text)
    assert main(["run", str(seq_case), "--out", str(root / "out_seq"), "--quiet"]) == 0
    return {"csv": standard_run.out, "seq": root / "out_seq", "invalid": invalid, "case": standard_case}


def _json(path: Path) -> dict:
    return json.loads(path.read_text(encoding="utf-8"))


def _navigation(path: Path) -> dict[float, np.ndarray]:
    with path.open() as f:
        return {round(float(r["time_s"]), 4): np.array([float(r["x_mm"]), float(r["y_mm"]), float(r["z_mm"])])
                for r in csv.DictReader(f)}


def test_a_sequence_metafile_case_gives_the_csv_case_registration(runs):
    truth = load_truth(runs["case"])
    csv_reg, seq_reg = _json(runs["csv"] / "registration.json"), _json(runs["seq"] / "registration.json")
    csv_cal = {p["label"]: np.array(p["position"]) for p in _json(runs["csv"] / "frame_calibration.json")["points"]}
    seq_cal_doc = _json(runs["seq"] / "frame_calibration.json")
    seq_cal = {p["label"]: np.array(p["position"]) for p in seq_cal_doc["points"]}
    assert not seq_cal_doc["labelled"]  # no labels in a sequence metafile: dwells found automatically
    assert any("frames of ProbeToTracker have a status other than OK" in w for w in seq_cal_doc["warnings"])
    # the same pairs: each image marker with the calibration point at the same place
    csv_pairs = {p["image_marker"]: csv_cal[p["calibration_point"]] for p in csv_reg["pairs"]}
    seq_pairs = {p["image_marker"]: seq_cal[p["calibration_point"]] for p in seq_reg["pairs"]}
    assert set(csv_pairs) == set(seq_pairs)
    assert max(np.linalg.norm(csv_pairs[k] - seq_pairs[k]) for k in csv_pairs) < 0.1
    assert abs(csv_reg["sensor_offset_l_mm"] - seq_reg["sensor_offset_l_mm"]) < 0.05
    targets = np.array([t["position"] for t in truth["targets"]])
    targets_reference = apply_transform(invert_rigid(np.asarray(truth["ReferenceToImage"])), targets)
    at_csv = apply_transform(np.asarray(csv_reg["ReferenceToImage"]), targets_reference)
    at_seq = apply_transform(np.asarray(seq_reg["ReferenceToImage"]), targets_reference)
    assert np.max(np.linalg.norm(at_csv - at_seq, axis=1)) < 0.05
    assert np.max(np.linalg.norm(at_seq - targets, axis=1)) < 1.0


def test_a_sequence_metafile_case_gives_the_csv_case_navigation(runs):
    csv_rows, seq_rows = _navigation(runs["csv"] / "navigation.csv"), _navigation(runs["seq"] / "navigation.csv")
    # every valid probe frame is navigated; the INVALID ones (wild poses) never are
    assert len(csv_rows) - len(seq_rows) == runs["invalid"]["navigation"]
    assert set(seq_rows) <= set(csv_rows)
    difference = np.array([np.linalg.norm(csv_rows[t] - seq_rows[t]) for t in seq_rows])
    assert difference.max() < 0.05
    csv_eval, seq_eval = _json(runs["csv"] / "evaluation.json"), _json(runs["seq"] / "evaluation.json")
    assert "not_evaluated" not in seq_eval
    assert seq_eval["tre"]["labelled"] is False and seq_eval["tre"]["n"] == csv_eval["tre"]["n"]
    assert abs(seq_eval["tre"]["mean_mm"] - csv_eval["tre"]["mean_mm"]) < 0.05
    for edge, values in csv_eval["board"]["edges"].items():
        assert abs(seq_eval["board"]["edges"][edge]["mean_mm"] - values["mean_mm"]) < 0.05


def test_a_run_finishes_when_the_navigation_recording_cannot_be_evaluated(standard_case, tmp_path, capsys):
    case = _case_copy(standard_case, tmp_path / "short_dwells", recordings=True)
    navigation = read_tracking_csv(case / "navigation.csv")
    # unlabelled, and played six times faster than it was (dwells of 0.17-0.33 s): none is long enough
    navigation.label[:] = ""
    navigation.time_s = navigation.time_s / 6.0
    write_tracking_csv(navigation, case / "navigation.csv")
    out = tmp_path / "out"
    capsys.readouterr()
    assert main(["run", str(case), "--out", str(out), "--quiet"]) == 0
    err = capsys.readouterr().err
    assert "emreg run: warning: TRE not evaluated:" in err
    run = _json(out / "run.json")
    assert "no probe dwell at any target was found" in run["not_evaluated"]["tre"]
    assert "still period(s) found" in run["not_evaluated"]["tre"]
    assert "[evaluation] min_duration_s" in run["not_evaluated"]["tre"]
    evaluation = _json(out / "evaluation.json")
    assert "tre" not in evaluation and "board" in evaluation
    assert evaluation["not_evaluated"]["tre"] == run["not_evaluated"]["tre"]
    for name in ("registration.json", "navigation.csv", "report.html"):
        assert (out / name).is_file()
    assert "TRE not evaluated" in (out / "report.html").read_text(encoding="utf-8")
    # emreg evaluate on its own keeps its exit code
    code = main(["evaluate", str(case), "--registration", str(out / "registration.json"),
                 "--out", str(tmp_path / "eval"), "--quiet"])
    assert code == 2
    line = capsys.readouterr().err.strip().splitlines()
    assert len(line) == 1 and "still period(s) found" in line[0]
