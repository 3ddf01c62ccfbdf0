"""One run owns its output folder: provenance of every output, no stale file after exit 2 / 3 or an
interrupt, consumers that refuse outputs that do not belong together, --out never over the case."""

from __future__ import annotations

import json
import os
import shutil
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest
from conftest import CI_CASE_OPTIONS

from EMRegModule.cli.main import main
from EMRegModule.errors import EMRegError
from EMRegModule.io.case import open_case
from EMRegModule.io.output_folder import OutputFolder, refuse_out_over_inputs
from EMRegModule.io.provenance import check_belongs, file_sha256
from EMRegModule.simulation.case import simulate_case

SMALL = {**CI_CASE_OPTIONS, "spacing_mm": 1.25}


@pytest.fixture(scope="module")
def cases(tmp_path_factory):
    """Two small simulated cases (A, B) and a finished run of A."""
    root = tmp_path_factory.mktemp("runs")
    simulate_case(root / "a", seed=21, difficulty="standard", **SMALL)
    simulate_case(root / "b", seed=22, difficulty="standard", **SMALL)
    assert main(["run", str(root / "a"), "--out", str(root / "out_a"), "--quiet"]) == 0
    return root


def _manifest(out: Path) -> dict:
    return json.loads((out / "run.json").read_text())


def _reused_out(cases: Path, tmp_path: Path) -> Path:
    out = tmp_path / "out"
    shutil.copytree(cases / "out_a", out)
    return out


def _error(capsys) -> str:
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1, err
    return err[0]


def _assert_only_this_runs_files(out: Path, case: Path) -> dict:
    """Every output file in OUT is listed in run.json with its sha256, and was made from ``case``'s CT."""
    manifest = _manifest(out)
    ct_sha = file_sha256(open_case(case).ct)
    assert manifest["case"] == str(case.resolve())
    for entry in out.iterdir():
        if entry.name in ("run.json", "previous"):
            continue
        assert not entry.name.startswith("."), f"temporary file left: {entry.name}"
        listed = manifest["outputs"].get(entry.name)
        assert listed is not None, f"{entry.name} is in OUT but not an output of this run"
        assert listed["sha256"] == file_sha256(entry)
        inputs = listed["provenance"]["inputs"]
        assert inputs.get("ct", {"sha256": ct_sha})["sha256"] == ct_sha
    return manifest


def test_every_output_records_what_it_was_made_from(cases):
    out, case = cases / "out_a", open_case(cases / "a")
    manifest = _assert_only_this_runs_files(out, cases / "a")
    assert manifest["status"] == "finished" and manifest["settings_sha256"] == case.settings.digest()
    assert manifest["inputs"]["calibration"]["sha256"] == file_sha256(case.calibration)
    markers = json.loads((out / "markers.json").read_text())
    assert markers["provenance"]["inputs"]["ct"]["sha256"] == file_sha256(case.ct)
    assert markers["provenance"]["settings_sha256"] == case.settings.digest()
    registration = json.loads((out / "registration.json").read_text())
    assert registration["provenance"]["uses"] == {"markers.json": file_sha256(out / "markers.json"),
                                                  "frame_calibration.json": file_sha256(out / "frame_calibration.json")}
    assert set(registration["provenance"]["inputs"]) == {"ct", "calibration", "targets"}
    navigation = manifest["outputs"]["navigation.csv"]["provenance"]
    assert navigation["uses"] == {"registration.json": file_sha256(out / "registration.json")}
    assert navigation["inputs"]["navigation"]["sha256"] == file_sha256(case.navigation)
    evaluation = json.loads((out / "evaluation.json").read_text())["provenance"]
    assert set(evaluation["inputs"]) >= {"navigation", "targets", "board", "ct", "calibration"}
    for name in ("markers.json", "registration.json", "evaluation.json", "navigation.csv"):
        check_belongs(out / name)  # the consumers' check accepts a consistent folder


def test_a_failed_run_leaves_no_output_of_the_previous_case(cases, tmp_path, capsys):
    out = _reused_out(cases, tmp_path)
    broken = tmp_path / "b"
    shutil.copytree(cases / "b", broken)
    (broken / "calibration.csv").write_text("not,a,tracking,recording\n")
    assert main(["run", str(broken), "--out", str(out), "--quiet"]) == 2
    assert "calibration.csv" in _error(capsys)
    manifest = _assert_only_this_runs_files(out, broken)
    assert manifest["status"] == "failed" and manifest["message"].startswith("calibrate:")
    # refused before the CT is read: no detection of this run either
    assert not (out / "registration.json").exists() and not (out / "markers.json").exists()
    assert json.loads((out / "previous" / "run.json").read_text())["case"] == str((cases / "a").resolve())
    # the old registration cannot be taken for this run's, even when put back into OUT
    shutil.copy2(out / "previous" / "registration.json", out / "registration.json")
    replay = ["--source", f"replay:{broken / 'navigation.csv'}", "--out", str(tmp_path / "nav"), "--quiet"]
    assert main(["navigate", "--registration", str(out / "registration.json"), *replay]) == 2
    assert "not an output of the run recorded" in _error(capsys)
    assert not (tmp_path / "nav" / "navigation.csv").exists()
    assert main(["evaluate", str(broken), "--registration", str(out / "registration.json"),
                 "--out", str(tmp_path / "ev"), "--quiet"]) == 2
    assert "not an output of the run recorded" in _error(capsys)
    # the previous run's own folder still holds a consistent registration
    assert main(["navigate", "--registration", str(out / "previous" / "registration.json"), *replay]) == 0


def test_a_refused_run_leaves_no_registration(cases, tmp_path, capsys):
    out = _reused_out(cases, tmp_path)
    (tmp_path / "tight.toml").write_text("[registration]\nmax_fre_mm = 0.01\n")
    assert main(["run", str(cases / "b"), "--out", str(out), "--settings", str(tmp_path / "tight.toml"),
                 "--quiet"]) == 3
    assert "max_fre_mm" in _error(capsys)
    manifest = _assert_only_this_runs_files(out, cases / "b")
    assert manifest["status"] == "refused" and manifest["summary"][-1].startswith("register: refused")
    assert {"markers.json", "frame_calibration.json"} <= set(manifest["outputs"])
    for name in ("registration.json", "ReferenceToImage.h5", "navigation.csv", "evaluation.json", "report.html"):
        assert not (out / name).exists(), name


def test_consumers_refuse_outputs_that_do_not_belong_together(cases, tmp_path, capsys):
    out = _reused_out(cases, tmp_path)
    # a registration listed in run.json but made from another CT than the run's
    registration = json.loads((out / "registration.json").read_text())
    registration["provenance"]["inputs"]["ct"]["sha256"] = "0" * 64
    (out / "registration.json").write_text(json.dumps(registration))
    manifest = _manifest(out)
    manifest["outputs"]["registration.json"]["sha256"] = file_sha256(out / "registration.json")
    (out / "run.json").write_text(json.dumps(manifest))
    with pytest.raises(EMRegError, match="made from another ct"):
        check_belongs(out / "registration.json")
    assert main(["report", str(out), "--quiet"]) == 2
    assert "made from another ct" in _error(capsys)
    # a file changed after the run wrote it
    shutil.copytree(cases / "out_a", tmp_path / "changed")
    (tmp_path / "changed" / "markers.json").write_text((tmp_path / "changed" / "markers.json").read_text() + " ")
    with pytest.raises(EMRegError, match="changed since the run"):
        check_belongs(tmp_path / "changed" / "markers.json")
    # outputs copied together from two runs, with no run.json: the registration used other markers
    mixed = tmp_path / "mixed"
    mixed.mkdir()
    shutil.copy2(cases / "out_a" / "registration.json", mixed)
    shutil.copy2(tmp_path / "changed" / "markers.json", mixed)
    with pytest.raises(EMRegError, match="made from another markers.json"):
        check_belongs(mixed / "registration.json")


def test_out_over_the_case_is_refused(cases, tmp_path, capsys):
    case = tmp_path / "case"
    shutil.copytree(cases / "a", case)
    before = {p.name: file_sha256(p) for p in case.iterdir() if p.is_file()}
    assert main(["run", str(case), "--out", str(case), "--quiet"]) == 2
    assert "would overwrite" in _error(capsys)
    replay = ["--source", f"replay:{case / 'navigation.csv'}", "--out", str(case), "--quiet"]
    assert main(["navigate", "--registration", str(cases / "out_a" / "registration.json"), *replay]) == 2
    assert "navigation.csv" in _error(capsys)
    assert {p.name: file_sha256(p) for p in case.iterdir() if p.is_file()} == before
    (tmp_path / "dicom").mkdir()  # a ct/ DICOM folder is an input: nothing may be written inside it
    with pytest.raises(EMRegError, match="inside the input"):
        refuse_out_over_inputs(tmp_path / "dicom" / "out", [tmp_path / "dicom"], ["markers.json"])
    # a folder inside the case that cannot overwrite anything is accepted
    refuse_out_over_inputs(case / "emreg-output", [open_case(case).ct, case / "navigation.csv"],
                           ["markers.json", "navigation.csv"], case)
    refuse_out_over_inputs(case, [open_case(case).ct], ["markers.json", "markers.mrk.json"], case)


def _wait_for(out: Path, process: subprocess.Popen, ready) -> None:
    """Wait until ``ready(run.json)`` holds (an event in the run, not a time), or fail if the run ends first."""
    deadline = time.monotonic() + 600  # a safety net only; nothing is asserted about time
    while time.monotonic() < deadline:
        assert process.poll() is None, "the run ended before the moment to interrupt it"
        try:
            if ready(_manifest(out)):
                return
        except (OSError, ValueError):
            pass  # run.json is being replaced
        time.sleep(0.01)
    raise AssertionError("the run never reached the moment to interrupt it")


#: The stages of a run in order with the output each one lists last (``start``: before any stage).
_RUN_STAGES = (("start", None), ("detect", "markers.json"), ("calibrate", "frame_calibration.json"),
               ("register", "registration.json"))


def _default_sigint() -> None:
    """In the child before exec: SIGINT back to its default. A harness that starts pytest in the background
    of a non-interactive shell makes it ignore SIGINT, and Python keeps an ignored SIGINT ignored: the run
    would then never see the test's Ctrl-C (exit 0 instead of 130)."""
    signal.signal(signal.SIGINT, signal.SIG_DFL)


def _interrupt_in_stage(out: Path, case: Path, moment: str,
                        signum: int) -> tuple[subprocess.Popen, tuple[str, str]] | None:
    """Start ``emreg run``, stop it (SIGSTOP) once ``moment`` is listed in run.json, and, if it is still in the
    stage after ``moment`` (run.json "running", the next stage's output not listed), send ``signum`` and let it
    go on: the signal lands in that stage, whatever the load (or in the last instructions of the stage that
    listed ``moment``); the process and those two stages. None when the run had gone past that stage."""
    env = {**os.environ, "PYTHONUNBUFFERED": "1"}
    process = subprocess.Popen([sys.executable, "-m", "EMRegModule.cli.main", "run", str(case), "--out", str(out),
                                "--quiet"], stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, env=env,
                               preexec_fn=_default_sigint)
    names = [name for name, _ in _RUN_STAGES]
    after = _RUN_STAGES[names.index("start" if moment == "start" else
                                    next(n for n, o in _RUN_STAGES if o == moment)) + 1]

    def ready(manifest: dict) -> bool:
        if manifest.get("case") != str(case.resolve()) or manifest.get("status") != "running":
            return False
        return moment == "start" or moment in manifest.get("outputs", {})

    _wait_for(out, process, ready)
    process.send_signal(signal.SIGSTOP)
    manifest = _manifest(out)  # frozen while the run is stopped (run.json is replaced atomically)
    if manifest.get("status") != "running" or after[1] in manifest.get("outputs", {}):
        process.send_signal(signal.SIGCONT)
        process.communicate(timeout=600)
        return None
    process.send_signal(signum)
    process.send_signal(signal.SIGCONT)
    return process, (names[names.index(after[0]) - 1], after[0])


@pytest.mark.parametrize(("moment", "signum"), [
    ("start", signal.SIGTERM), ("markers.json", signal.SIGINT), ("frame_calibration.json", signal.SIGTERM),
])
def test_an_interrupted_run_in_a_reused_folder(cases, tmp_path, moment, signum):
    """An interrupt in the stage after ``moment``: exit 130 / 143, run.json "interrupted" naming that stage,
    only this run's files (each listed) in OUT, the previous run in OUT/previous. The signal is sent while
    the run is stopped in that stage (no race with the run's progress); a run that got past it before it
    could be stopped (a starved test process) is tried again in a fresh folder."""
    for attempt in range(5):
        out = _reused_out(cases, tmp_path / f"attempt{attempt}")
        case = cases / "b"
        started = _interrupt_in_stage(out, case, moment, signum)
        if started is not None:
            break
    else:
        raise AssertionError(f"the run was never stopped in the stage after {moment} in 5 attempts")
    process, stages = started
    _, err = process.communicate(timeout=600)
    name = "SIGTERM" if signum == signal.SIGTERM else "SIGINT"
    assert process.returncode == (143 if signum == signal.SIGTERM else 130), err
    assert err.strip().splitlines() == [f"emreg run: interrupted ({name}); no partial file was left in place of "
                                        "a complete one"]
    manifest = _assert_only_this_runs_files(out, case)
    assert manifest["status"] == "interrupted"
    # after the start, the calibration recording is read (and its ports checked) before the CT
    allowed = {*stages, "calibrate"} if moment == "start" else set(stages)
    assert manifest["message"].split(":")[0] in allowed, manifest["message"]
    assert not (out / "registration.json").exists() or "registration.json" in manifest["outputs"]
    assert json.loads((out / "previous" / "run.json").read_text())["case"] == str((cases / "a").resolve())


def test_a_signal_as_the_run_records_its_end_is_told_in_run_json(cases, tmp_path, monkeypatch, capsys):
    """SIGINT while run.json is written "finished": run.json ends "interrupted", as the exit code (130) says."""
    original = OutputFolder.finish

    def finish(self, status, message=None):
        if status == "finished":
            os.kill(os.getpid(), signal.SIGINT)  # lands inside the final write of run.json
        original(self, status, message)

    monkeypatch.setattr(OutputFolder, "finish", finish)
    # SIGINT as an emreg started from a terminal has it (a pytest started in the background ignores SIGINT,
    # and Python keeps it ignored); conftest puts the session's handler back afterwards
    signal.signal(signal.SIGINT, signal.default_int_handler)
    out = _reused_out(cases, tmp_path)
    assert main(["run", str(cases / "b"), "--out", str(out), "--quiet"]) == 130
    assert "interrupted (SIGINT)" in capsys.readouterr().err
    manifest = _assert_only_this_runs_files(out, cases / "b")
    assert manifest["status"] == "interrupted" and "recorded its end" in manifest["message"]
    assert "EMReg.mrb" in manifest["outputs"] or "report.html" in manifest["outputs"]


def test_an_output_written_as_the_signal_came_is_not_left_unlisted(cases, tmp_path, monkeypatch, capsys):
    """SIGTERM between the atomic write of frame_calibration.json and its listing in run.json: the file is not
    left in OUT unlisted (consumers would refuse the folder); run.json says interrupted in calibrate."""
    original = OutputFolder.record

    def record(self, names, provenance, sha256=None):
        if "frame_calibration.json" in names:
            assert (self.path / "frame_calibration.json").is_file()
            os.kill(os.getpid(), signal.SIGTERM)
        original(self, names, provenance, sha256)

    monkeypatch.setattr(OutputFolder, "record", record)
    out = _reused_out(cases, tmp_path)
    assert main(["run", str(cases / "b"), "--out", str(out), "--quiet"]) == 143
    assert "interrupted (SIGTERM)" in capsys.readouterr().err
    manifest = _assert_only_this_runs_files(out, cases / "b")
    assert manifest["status"] == "interrupted" and manifest["message"].startswith("calibrate:")
    assert not (out / "frame_calibration.json").exists() and "markers.json" in manifest["outputs"]
