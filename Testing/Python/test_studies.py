"""``emreg study``: the accuracy studies run on Dask, locally or on a scheduler, with results that do not
depend on the number of workers."""

from __future__ import annotations

import json
import os
from dataclasses import replace

import cv2  # noqa: F401  (its loader adds LD_LIBRARY_PATH to os.environ at the first import, the report's)
import numpy as np
import pytest
from distributed import LocalCluster

from EMRegModule.cli.main import main
from EMRegModule.studies import STUDIES
from EMRegModule.studies.frame import prepare_frame


@pytest.fixture(scope="module")
def study_work(tmp_path_factory):
    return tmp_path_factory.mktemp("study-work")  # the CI case's CT is detected once for all studies here


def _study(name: str, out, case, work, *options: str) -> dict:
    assert main(["study", name, "--quick", "--quiet", "--case", str(case), "--work", str(work), "--out", str(out),
                 *options]) == 0
    for suffix in (".json", ".csv", ".png"):
        assert (out / f"{name}{suffix}").stat().st_size > 0
    return json.loads((out / f"{name}.json").read_text())


def test_results_do_not_depend_on_the_number_of_workers(standard_case, study_work, tmp_path):
    environment = dict(os.environ)
    one = _study("calibration", tmp_path / "one", standard_case, study_work, "--workers", "1")
    two = _study("calibration", tmp_path / "two", standard_case, study_work, "--workers", "2")
    assert dict(os.environ) == environment  # the local cluster's worker settings stay out of this process
    assert one == two
    assert len(one["rows"]) == 3 and len({r["fre_mm"] for r in one["rows"]}) == 3  # different sessions
    assert (tmp_path / "one" / "calibration.csv").read_text() == (tmp_path / "two" / "calibration.csv").read_text()


def test_prediction_study_on_a_scheduler_address_validates_the_error_model(standard_case, study_work, tmp_path,
                                                                           capsys):
    with LocalCluster(n_workers=1, threads_per_worker=1, processes=False, dashboard_address=None) as cluster:
        result = _study("prediction", tmp_path, standard_case, study_work, "--scheduler", cluster.scheduler_address)
    out = capsys.readouterr().out
    assert "predicted / measured" in out
    header, rows = result["summary"]["header"], result["summary"]["rows"]
    ratio = header.index("predicted / measured")
    assert len(rows) == 2  # tracker noise x1 and x4
    for row in rows:
        assert 0.8 <= float(row[ratio]) <= 1.25, row


def test_clean_sessions_are_predicted_neither_pessimistic_nor_optimistic_far_from_the_reference(standard_case,
                                                                                                 study_work):
    """Issue 37: on clean cases the prediction must come within 0.9-1.1 x the measured TRE. 60 clean sessions of the
    trust study, their targets moved to twice their distance from the reference sensor (about 300 mm), where the
    reference sensor's rotation error weighs most: pooled, predicted / measured is 1.01. With the old prior (a rotation
    level with the position error at 100 mm, not the trakSTAR's 160 mm) the same sessions gave 1.13."""
    frame = prepare_frame(study_work, standard_case, log=lambda message: None)
    origin = frame.reference_to_image[:3, 3]
    frame = replace(frame, targets_image=origin + 2.0 * (frame.targets_image - origin))
    rows = [row for k in range(60) for row in STUDIES["trust"].run(
        frame, {"family": "clean", "distortion_mm": 0.0, "noise": 1.0}, np.random.default_rng(200 + k))]
    navigated = [r for r in rows if "measured_ms" in r]
    assert len(navigated) >= 55
    ratio = np.sqrt(sum(r["predicted_ms"] for r in navigated) / sum(r["measured_ms"] for r in navigated))
    assert 0.93 <= ratio <= 1.07, ratio


def test_unknown_study_and_unreachable_scheduler_are_one_line_errors(tmp_path, capsys):
    assert main(["study", "nonsense", "--out", str(tmp_path)]) == 2
    assert "unknown study 'nonsense'" in capsys.readouterr().err
    assert main(["study", "calibration", "--quick", "--out", str(tmp_path), "--scheduler", "tcp://127.0.0.1:9"]) == 2
    assert "cannot reach the Dask scheduler tcp://127.0.0.1:9" in capsys.readouterr().err


def test_tool_study_compares_the_pinhole_probe_with_a_pivot_calibrated_pointer(standard_case, study_work, tmp_path):
    result = _study("tool", tmp_path, standard_case, study_work, "--workers", "1")
    rows = result["rows"]
    assert sorted(r["route"] for r in rows) == ["pinhole", "pinhole", "pivot", "pivot"]
    assert not any(r["refused"] for r in rows)
    pivot = [r for r in rows if r["route"] == "pivot"]
    assert all(r["tip_error_mm"] < 2.0 for r in pivot)
    assert all(r["tip_error_mm"] is None for r in rows if r["route"] == "pinhole")
    # the pointer's tip error reaches the targets: its end-to-end TRE is the larger (the paper: about 2 mm more)
    mean = {route: np.mean([r["tre_rms_mm"] for r in rows if r["route"] == route]) for route in ("pinhole", "pivot")}
    assert mean["pivot"] > mean["pinhole"]


def test_trust_study_measures_checkpoints_latency_and_reference_jumps(standard_case, study_work, tmp_path):
    """The quick trust study's navigations with checkpoints: clean ones pass (at noise x1 and x4, where the fixed
    limit alone fails some), a 2 mm / 0.5 deg slip is flagged at the first checkpoint after it and warned as a
    reference jump, the alarm latency is measured, and a bump of the whole frame is warned but fails nothing."""
    result = _study("trust", tmp_path, standard_case, study_work, "--workers", "1")
    header, table = result["summary"]["header"], result["summary"]["rows"]
    rows = {row[0]: dict(zip(header, row, strict=True)) for row in table}
    assert {"clean, noise x1", "dipole (development) 1 mm, noise x1", "magpylib (held out) 1 mm, noise x1"} <= set(rows)
    assert rows["clean, noise x1"]["detected"] == "0.0 %"
    for noise in ("1", "4"):
        clean = rows[f"checkpoints: clean, noise x{noise}"]
        assert clean["clean checkpoints passed"].startswith("100.0 %"), clean
    slip = rows["checkpoints: slip 2 mm/0.5 deg, noise x1"]
    assert slip["flagged at the first checkpoint after"] == "100.0 % (1/1)"
    assert slip["reference jump warned"] == "100.0 % (1/1)"
    latency = next(r["latency_s"] for r in result["rows"] if r.get("checkpoints") == "slip")
    assert 0 < latency < 30
    assert rows["checkpoints: onset 1 mm, noise x1"]["sessions with a false jump warning"] == "0.0 % (0/1)"
    # the frame knocked as a whole by as much: the jump is warned, the slip test rules the slip out, nothing fails
    bump = rows["checkpoints: bump 2 mm/0.5 deg (false alarms), noise x1"]
    assert bump["reference jump warned"] == "100.0 % (1/1)" and bump["clean checkpoints passed"].startswith("100.0 %")
    assert bump["flagged at the first checkpoint after"] == "0.0 % (0/1)"
    session = next(r for r in result["rows"] if r.get("checkpoints") == "bump")
    assert session["first_slip_verdict"] in ("ruled_out", "neither") and session["first_true_error_mm"] == 0.0


def test_a_study_runs_only_the_tasks_selected_with_the_seeds_they_have_in_the_whole_study(standard_case, study_work,
                                                                                          tmp_path, capsys):
    """``--only family=...``: the trust study's held-out rows alone, each task keeping its index (its seed) in the
    whole study; a selection that keeps no task is one line, exit 2, before any work."""
    result = _study("trust", tmp_path / "held_out", standard_case, study_work, "--workers", "1",
                    "--only", "family=magpylib", "--only", "family=clean")
    everything = list(enumerate(STUDIES["trust"].tasks(True)))
    expected = [i for i, params in everything if params.get("family") in ("magpylib", "clean")]
    assert sorted({row["task"] for row in result["rows"]}) == expected
    assert {row["family"] for row in result["rows"]} == {"magpylib", "clean"}
    assert result["only"] == {"family": ["magpylib", "clean"]}
    assert main(["study", "trust", "--quick", "--out", str(tmp_path / "none"), "--only", "family=steel"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "no task has family=steel" in err[0] and "family=magpylib" in err[0]
    assert not (tmp_path / "none").exists()
    assert main(["study", "trust", "--quick", "--out", str(tmp_path / "none"), "--only", "family"]) == 2
    assert "give KEY=VALUE" in capsys.readouterr().err
