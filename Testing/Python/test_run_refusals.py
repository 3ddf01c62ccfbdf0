"""The run, recording, settings and outputs classes of issue 28's bad-input matrix: each is refused with the
documented exit code and one line naming the input and what is wrong; nothing plausible but wrong is written.

Classes: a damaged ``run.json`` (the tamper check must not turn off), labelled dwells in which the probe moves
(or one label over every row / several pinholes), a case file name held by a folder, an empty targets file, a
duplicated CSV column, impossible values in ``registration.json`` / ``frame_calibration.json``, ``report OUT
--batch DIR``, settings errors named after the file they are in, a ``min_samples`` refusal that names
``min_samples``, a full disk while the bundle is written, and SIGINT / SIGTERM while slicer-core loads.
"""

from __future__ import annotations

import csv
import errno
import gc
import json
import os
import shutil
import signal
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from synth_registration import calibration_recording, make_frame

from EMRegModule.cli.main import main
from EMRegModule.core.calibration import calibrate_frame
from EMRegModule.errors import EMRegError

LABELS = [f"M{i + 1:02d}" for i in range(28)]


def _refused(capsys, argv, *needles, code=2):
    """Run ``emreg argv``; assert exit ``code`` and one line on stderr holding every needle; the line."""
    capsys.readouterr()
    result = main([str(a) for a in argv])
    err = "\n".join(line for line in capsys.readouterr().err.strip().splitlines() if not line.startswith("[emreg]"))
    assert result == code, err
    assert len(err.splitlines()) == 1 and "Traceback" not in err, err
    for needle in needles:
        assert needle in err, err
    return err


def _copy_run(small_case: Path, target: Path) -> Path:
    """The small case's run outputs (without the bundle: not needed, and large) copied to ``target``."""
    shutil.copytree(small_case.parent / "out", target, ignore=shutil.ignore_patterns("EMReg.mrb", "previous"))
    return target


def _rows(path: Path) -> tuple[list[str], list[dict[str, str]]]:
    with path.open(newline="") as f:
        reader = csv.DictReader(f)
        return list(reader.fieldnames or []), list(reader)


def _write_rows(path: Path, fields: list[str], rows: list[dict[str, str]]) -> Path:
    with path.open("w", newline="") as f:
        writer = csv.DictWriter(f, fieldnames=fields)
        writer.writeheader()
        writer.writerows(rows)
    return path


def _probe_moves_in_labelled_dwells(source: Path, target: Path, mm: float = 10.0) -> Path:
    """``source`` with the probe sliding ``mm`` along x (tracker frame) through each labelled dwell."""
    fields, rows = _rows(source)
    runs: list[list[int]] = []
    previous = ""
    for i, row in enumerate(rows):
        if row["sensor"] != "2":
            continue
        if row["label"] and row["label"] != previous:
            runs.append([])
        if row["label"]:
            runs[-1].append(i)
        previous = row["label"]
    for run in runs:
        for k, i in enumerate(run):
            rows[i]["x_mm"] = f"{float(rows[i]['x_mm']) + mm * k / (len(run) - 1):.4f}"
    return _write_rows(target, fields, rows)


# --- a damaged run.json ---------------------------------------------------------------------------


def _shift_registration(out: Path, mm: float = 5.0) -> None:
    path = out / "registration.json"
    document = json.loads(path.read_text())
    document["ReferenceToImage"][0][3] += mm
    path.write_text(json.dumps(document))


@pytest.mark.parametrize("damage", ["garbage", "a list", "outputs a list", "a folder"])
def test_a_damaged_run_json_is_refused_never_taken_for_absent(small_case, tmp_path, capsys, damage):
    """With run.json garbage and registration.json moved 5 mm by hand, navigate exited 0 and wrote shifted poses:
    the damaged manifest was read as "no manifest", which turns the tamper check off."""
    out = _copy_run(small_case, tmp_path / "out")
    _shift_registration(out)
    run_json = out / "run.json"
    if damage == "garbage":
        run_json.write_text("garbage{")
    elif damage == "a list":
        run_json.write_text("[1, 2]")
    elif damage == "outputs a list":
        run_json.write_text(json.dumps({**json.loads(run_json.read_text()), "outputs": []}))
    else:
        run_json.unlink()
        run_json.mkdir()
    before = {name: (out / name).read_bytes() for name in ("registration.json", "report.html")}
    consumers = {
        "navigate": ["navigate", "--registration", out / "registration.json", "--source",
                     f"replay:{small_case / 'navigation.csv'}", "--out", tmp_path / "nav"],
        "evaluate": ["evaluate", small_case, "--registration", out / "registration.json", "--out", tmp_path / "ev"],
        "report": ["report", out, "--case", small_case, "--quiet"],
        "register into it": ["register", "--markers", out / "markers.json", "--calibration",
                             out / "frame_calibration.json", "--out", out],
    }
    for argv in consumers.values():
        _refused(capsys, argv, str(run_json), "run record")
    assert not (tmp_path / "nav" / "navigation.csv").exists() and not (tmp_path / "ev" / "evaluation.json").exists()
    assert {name: (out / name).read_bytes() for name in before} == before  # nothing written, adopted or moved
    assert not (out / "previous").exists()


def test_a_run_into_a_folder_with_a_damaged_run_json_replaces_it(small_case, tmp_path, capsys):
    """``emreg run`` trusts nothing in OUT: the damaged record goes to previous/ with the rest."""
    out = _copy_run(small_case, tmp_path / "out")
    (out / "run.json").write_text("garbage{")
    capsys.readouterr()
    assert main(["run", str(small_case), "--out", str(out), "--quiet"]) == 0, capsys.readouterr().err
    assert json.loads((out / "run.json").read_text())["status"] == "finished"
    assert (out / "previous" / "run.json").read_text() == "garbage{"


# --- labelled dwells -------------------------------------------------------------------------------


@pytest.fixture(scope="module")
def frame():
    return make_frame(seed=21, n_markers=8)


def _labelled(frame, **options):
    return calibration_recording(frame.pinholes_reference, frame.axes_reference, seed=3, labels=LABELS[:8],
                                 **options)


def test_a_probe_moving_10_mm_in_a_labelled_dwell_is_refused(frame):
    """Averaged silently before: points up to 3 mm off. Now the label, its time and how far the probe moved."""
    recording, _ = _labelled(frame)
    dwell = (recording.sensor == 2) & (recording.label == "M04")
    ramp = np.linspace(0.0, 10.0, int(np.count_nonzero(dwell)))
    recording.position_mm[dwell, 0] += ramp
    with pytest.raises(EMRegError, match=r"not still during the dwell labelled 'M04' .*drifts 7\.\d mm, more than "
                                         r"2 mm \(4 x \[calibration\] still_radius_mm\)"):
        calibrate_frame(recording, 1, 2, None)


def test_genuine_labelled_dwells_still_calibrate(frame):
    """Hand-held tremor, jitter and 15 % wild samples inside the labelled dwells are not a moving probe."""
    recording, true_points = _labelled(frame, jitter_mm=0.3, wild_fraction=0.15)
    calibration = calibrate_frame(recording, 1, 2, None)
    assert calibration.labels == LABELS[:8]
    assert np.linalg.norm(calibration.positions - true_points, axis=1).max() < 0.2


def test_one_label_over_every_row_or_every_pinhole_is_refused(frame):
    """All rows given one label: 28 visits hundreds of mm apart were averaged into one point."""
    recording, _ = _labelled(frame)
    every_row = recording.label.copy()
    every_row[:] = "M01"
    recording.label = every_row
    with pytest.raises(EMRegError, match=r"not still during the dwell labelled 'M01'"):
        calibrate_frame(recording, 1, 2, None)
    recording, _ = _labelled(frame)
    recording.label = np.where(recording.label != "", "M01", "").astype(object)  # every dwell, transitions empty
    with pytest.raises(EMRegError, match=r"the 8 dwells labelled 'M01' lie up to \d+\.\d mm apart.*several "
                                         "pinholes"):
        calibrate_frame(recording, 1, 2, None)


def test_evaluate_refuses_a_moving_probe_in_a_labelled_target_dwell(small_case, tmp_path, capsys):
    case = tmp_path / "case"
    shutil.copytree(small_case, case, ignore=shutil.ignore_patterns("ct.*"))
    _probe_moves_in_labelled_dwells(small_case / "navigation.csv", case / "navigation.csv")
    (case / "board.csv").unlink()
    _refused(capsys, ["evaluate", case, "--registration", small_case.parent / "out" / "registration.json",
                      "--out", tmp_path / "ev"], str(case / "navigation.csv"), "dwell labelled 'T1'",
             "[evaluation] still_radius_mm")
    assert not (tmp_path / "ev" / "evaluation.json").exists()


# --- case files ---------------------------------------------------------------------------------


def test_targets_file_that_is_a_folder_is_refused_by_evaluate_and_named_by_run(small_case, tmp_path, capsys):
    """``evaluate`` dropped the TRE silently and exited 0: the folder was taken for "no targets"."""
    case = tmp_path / "case"
    shutil.copytree(small_case, case)
    (case / "targets.mrk.json").unlink()
    (case / "targets.mrk.json").mkdir()
    registration = small_case.parent / "out" / "registration.json"
    _refused(capsys, ["evaluate", case, "--registration", registration, "--out", tmp_path / "ev"],
             str(case / "targets.mrk.json"), "is a folder")
    assert not (tmp_path / "ev" / "evaluation.json").exists()
    assert main(["run", str(case), "--out", str(tmp_path / "run"), "--quiet"]) == 0  # the TRE is optional in a run
    run = json.loads((tmp_path / "run" / "run.json").read_text())
    assert "is a folder" in run["not_evaluated"]["tre"] and "tre" not in json.loads(
        (tmp_path / "run" / "evaluation.json").read_text())
    assert "TRE not evaluated" in capsys.readouterr().err


def test_an_empty_targets_file_is_named(small_case, tmp_path, capsys):
    case = tmp_path / "case"
    shutil.copytree(small_case, case, ignore=shutil.ignore_patterns("ct.*", "board.csv"))
    (case / "targets.mrk.json").write_text(json.dumps({"markups": [{"type": "Fiducial", "controlPoints": []}]}))
    out = small_case.parent / "out"
    _refused(capsys, ["evaluate", case, "--registration", out / "registration.json", "--out", tmp_path / "ev"],
             f"{case / 'targets.mrk.json'}: the targets file holds no target points")
    _refused(capsys, ["register", "--markers", out / "markers.json", "--calibration", out / "frame_calibration.json",
                      "--targets", case / "targets.mrk.json", "--out", tmp_path / "reg"],
             f"{case / 'targets.mrk.json'}: the targets file holds no target points")


def test_a_case_toml_that_is_a_folder_is_not_the_defaults(small_case, tmp_path, capsys):
    case = tmp_path / "case"
    shutil.copytree(small_case, case, ignore=shutil.ignore_patterns("ct.*"))
    (case / "case.toml").unlink()
    (case / "case.toml").mkdir()
    _refused(capsys, ["evaluate", case, "--registration", small_case.parent / "out" / "registration.json",
                      "--out", tmp_path / "ev"], str(case / "case.toml"), "is a folder")


@pytest.mark.parametrize("column", ["x_mm", "label", "Sensor"])
def test_a_duplicated_csv_column_is_refused(small_case, tmp_path, capsys, column):
    """Which of two x_mm columns is the data? It was guessed (the first), and the recording accepted."""
    rows = list(csv.reader((small_case / "calibration.csv").open(newline="")))
    at = [h.lower() for h in rows[0]].index(column.lower())
    path = tmp_path / "dup.csv"
    with path.open("w", newline="") as f:
        csv.writer(f).writerows([row[:at + 1] + [column if i == 0 else row[at]] + row[at + 1:]
                                 for i, row in enumerate(rows)])
    _refused(capsys, ["calibrate", path, "--out", tmp_path / "cal"], str(path), column.lower(), "more than once")
    assert not (tmp_path / "cal" / "frame_calibration.json").exists()


# --- impossible values in outputs -------------------------------------------------------------------


@pytest.mark.parametrize("key,value", [("fre_mm", -1.0), ("sensor_offset_l_mm", -14.0), ("sensor_offset_l_mm", 0.0),
                                       ("fle_mm", -0.3), ("sensor_offset_l_std_mm", -0.1)])
def test_impossible_registration_values_are_refused(small_case, tmp_path, capsys, key, value):
    path = tmp_path / "registration.json"
    document = json.loads((small_case.parent / "out" / "registration.json").read_text())
    document[key] = value
    path.write_text(json.dumps(document))
    _refused(capsys, ["navigate", "--registration", path, "--source", f"replay:{small_case / 'navigation.csv'}",
                      "--out", tmp_path / "nav"], str(path), key)
    assert not (tmp_path / "nav" / "navigation.csv").exists()


@pytest.mark.parametrize("key,value", [("samples", -80), ("std_mm", -0.1), ("visits", 0)])
def test_impossible_calibration_values_are_refused(small_case, tmp_path, capsys, key, value):
    path = tmp_path / "frame_calibration.json"
    document = json.loads((small_case.parent / "out" / "frame_calibration.json").read_text())
    document["points"][2][key] = value
    path.write_text(json.dumps(document))
    _refused(capsys, ["register", "--markers", small_case.parent / "out" / "markers.json", "--calibration", path,
                      "--out", tmp_path / "reg"], str(path), "point 3")


# --- the command line and settings --------------------------------------------------------------


@pytest.mark.parametrize("extra", [["OUT"], ["--case", "CASE"]])
def test_report_out_and_batch_together_are_refused(small_case, tmp_path, capsys, extra):
    """``report OUT --batch DIR`` reported the batch and ignored OUT (and --case) without a word."""
    extra = [str(small_case.parent / "out") if a == "OUT" else str(small_case) if a == "CASE" else a for a in extra]
    _refused(capsys, ["report", *extra, "--batch", tmp_path], "--batch", "not both")


def test_settings_errors_name_the_settings_file(small_case, tmp_path, capsys):
    """Errors in a --settings file were blamed on case.toml."""
    out = small_case.parent / "out"
    offset = tmp_path / "offset.toml"
    offset.write_text("[registration]\nsensor_offset_l_mm = 30\n")
    line = _refused(capsys, ["register", "--markers", out / "markers.json", "--calibration",
                             out / "frame_calibration.json", "--out", tmp_path / "reg", "--settings", offset],
                    f"{offset}: [registration] sensor_offset_l_mm = 30 lies outside the marker's pinhole")
    assert "case.toml" not in line
    edges = tmp_path / "edges.toml"
    edges.write_text("[board]\nedges_mm = [10.0, 20.0, 30.0]\n")
    line = _refused(capsys, ["evaluate", small_case, "--registration", out / "registration.json", "--out",
                             tmp_path / "ev", "--settings", edges], f"{edges}: [board] edges_mm has 3 values")
    assert "case.toml" not in line


def test_settings_given_replace_a_broken_case_toml(small_case, tmp_path, capsys):
    case = tmp_path / "case"
    shutil.copytree(small_case, case, ignore=shutil.ignore_patterns("ct.*"))
    good = tmp_path / "good.toml"
    shutil.copy(case / "case.toml", good)
    (case / "case.toml").write_text("[calibrat]\n")
    argv = ["evaluate", case, "--registration", small_case.parent / "out" / "registration.json", "--out",
            tmp_path / "ev"]
    _refused(capsys, argv, str(case / "case.toml"), "[calibrat]")
    assert main([str(a) for a in [*argv, "--settings", good, "--quiet"]]) == 0, capsys.readouterr().err


def test_a_min_samples_refusal_names_min_samples(small_case, tmp_path, capsys):
    """It said "raise [calibration] still_radius_mm" for still periods too few samples long."""
    fields, rows = _rows(small_case / "calibration.csv")
    for row in rows:
        row["label"] = ""
    recording = _write_rows(tmp_path / "unlabelled.csv", fields, rows)
    settings = tmp_path / "many.toml"
    settings.write_text("[calibration]\nmin_samples = 100000\n")
    line = _refused(capsys, ["calibrate", recording, "--out", tmp_path / "cal", "--settings", settings],
                    "[calibration] min_samples", "lower [calibration] min_samples")
    assert "raise [calibration] still_radius_mm" not in line


# --- a full disk ---------------------------------------------------------------------------------------


def test_a_failed_write_of_a_mapped_region_leaves_no_buffer_error(tmp_path, monkeypatch):
    """On a full disk the bundle's archive writer printed "BufferError: cannot close exported pointers exist":
    a view of the mapped file outlived the failed write, so its mapping could not be closed."""
    from EMRegModule.io import zip_store

    source = tmp_path / "voxels.raw"
    source.write_bytes(os.urandom(1 << 16))
    monkeypatch.setattr(zip_store, "_kernel_copy", lambda *args: 0)  # every byte through os.write
    real_write = os.write

    def full(fd, data):
        if len(data) > 1000:
            del data  # as os.write itself, keep no reference to the bytes it was given
            raise OSError(errno.ENOSPC, "No space left on device")
        return real_write(fd, data)

    monkeypatch.setattr(zip_store.os, "write", full)
    unraisable = []
    monkeypatch.setattr(sys, "unraisablehook", unraisable.append)
    with pytest.raises(OSError, match="No space"), zip_store.StoredZipWriter(tmp_path / "a.zip") as archive:
        archive.add("voxels.raw", [zip_store.FileRegion(source, 0, 1 << 16)])
    gc.collect()
    assert not unraisable, [u.exc_value for u in unraisable]


@pytest.fixture
def small_tmpfs(tmp_path):
    """A 20 MB tmpfs (a real full disk): the outputs of the small case fit, its scene bundle does not."""
    mount = tmp_path / "tmpfs"
    mount.mkdir()
    if shutil.which("mount") is None or subprocess.run(["mount", "-t", "tmpfs", "-o", "size=20m", "tmpfs", str(mount)],
                                                       capture_output=True).returncode != 0:
        pytest.skip("cannot mount a tmpfs here (not root)")
    yield mount
    subprocess.run(["umount", "-l", str(mount)], check=False)


def test_a_full_disk_while_the_bundle_is_written_is_one_line_naming_it(small_case, small_tmpfs, capsys):
    pytest.importorskip("slicer")
    out = small_tmpfs / "out"
    capsys.readouterr()
    assert main(["run", str(small_case), "--out", str(out), "--quiet"]) == 0  # the bundle is optional
    err = [line for line in capsys.readouterr().err.splitlines()
           if line.strip() and "max_undetectable_distortion_mm" not in line]  # the small case's own warning
    assert err == [f"emreg run: warning: no EMReg.mrb written: {out / 'EMReg.mrb'}: cannot write (No space left on "
                   "device)"], err
    assert not [p.name for p in out.iterdir() if p.name.startswith(".")]  # no temporary left behind
    assert "EMReg.mrb" not in json.loads((out / "run.json").read_text())["outputs"]


# --- signals while slicer-core loads ----------------------------------------------------------------------


def _signal_during(monkeypatch, owner, attribute, matches) -> list[bool]:
    """Make ``owner.attribute`` (an import step) raise SIGINT in the middle of the first call ``matches``; the list
    it returns gets True once that call goes on after the signal (the signal did not cut it)."""
    real = getattr(owner, attribute)
    during: list[bool] = []

    def with_a_signal(*args, **kwargs):
        if matches(*args) and not during:
            signal.raise_signal(signal.SIGINT)
            during.append(True)
        return real(*args, **kwargs)

    monkeypatch.setattr(owner, attribute, with_a_signal)
    return during


def test_a_signal_while_slicer_core_loads_waits_for_the_import(monkeypatch):
    """SIGINT / SIGTERM landing in slicer-core's import crashed the process (SIGSEGV: a half-initialised VTK
    module) or became an ImportError, reported as "slicer-core is not installed" with exit 0. The import is
    now never cut: the signal is delivered once it is done, as the interrupt it is."""
    import builtins

    from EMRegModule.slicer_export.mrml import slicer_mrml_missing

    pytest.importorskip("slicer")
    during = _signal_during(monkeypatch, builtins, "__import__", lambda name, *rest: name == "slicer")
    with pytest.raises(KeyboardInterrupt):
        slicer_mrml_missing()
    assert during == [True]


_VTK_MODULE_LOADS_WHOLE = """
import importlib, importlib.machinery, signal, sys
from EMRegModule.interrupts import vtk_imports_uninterrupted

name = sys.argv[1]
assert name not in sys.modules
vtk_imports_uninterrupted()
real = importlib.machinery.ExtensionFileLoader.exec_module
during = []

def with_a_signal(loader, module):
    if module.__name__ == name and not during:
        signal.raise_signal(signal.SIGINT)
        during.append(True)
    return real(loader, module)

importlib.machinery.ExtensionFileLoader.exec_module = with_a_signal
try:
    importlib.import_module(name)
except KeyboardInterrupt:
    interrupted = True
else:
    interrupted = False
importlib.machinery.ExtensionFileLoader.exec_module = real
print(interrupted, during == [True], importlib.import_module(name).__name__ == name)
"""


def test_a_signal_while_a_vtk_module_loads_waits_for_it():
    """pyvista's Plotter loads VTK's rendering modules lazily, in the report: a signal there was an ImportError
    traceback with run.json "running", or a SIGSEGV. Every VTK module now loads whole, then the signal acts.
    In a fresh interpreter, where the module is certainly not loaded yet (whatever tests ran before)."""
    import importlib.util

    pytest.importorskip("vtkmodules")
    name = "vtkmodules.vtkIOMINC"
    assert importlib.util.find_spec(name) is not None
    done = subprocess.run([sys.executable, "-c", _VTK_MODULE_LOADS_WHOLE, name], capture_output=True, text=True,
                          preexec_fn=_default_sigint, timeout=120)
    assert done.returncode == 0, done.stderr
    # interrupted once loaded, the signal raised during the load, and the module usable afterwards
    assert done.stdout.split() == ["True", "True", "True"], done.stdout + done.stderr


def _default_sigint() -> None:
    """In the child before exec: SIGINT back to its default, whatever this process inherited."""
    signal.signal(signal.SIGINT, signal.SIG_DFL)


def test_a_run_interrupted_in_its_bundle_says_so(small_case, tmp_path):
    """SIGTERM as the bundle starts (slicer-core loading): exit 143, one line, run.json "interrupted"."""
    pytest.importorskip("slicer")
    out = tmp_path / "out"
    import EMRegModule

    package_root = str(Path(EMRegModule.__file__).resolve().parents[1])  # the EMRegModule under test
    env = {**os.environ, "PYTHONPATH": os.pathsep.join([package_root, os.environ.get("PYTHONPATH", "")])}
    process = subprocess.Popen([sys.executable, "-m", "EMRegModule", "run", str(small_case), "--out", str(out)],
                               stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True, env=env)
    lines = []
    for line in process.stderr:
        lines.append(line.rstrip())
        if "scene bundle ..." in line:
            process.send_signal(signal.SIGTERM)
            break
    lines += process.stderr.read().splitlines()
    assert process.wait() == 143, lines
    said = [line for line in lines if not line.startswith("[emreg]")
            and "max_undetectable_distortion_mm" not in line]  # the small case's own warning
    assert said == ["emreg run: interrupted (SIGTERM); no partial file was left in place of a complete one"], said
    run = json.loads((out / "run.json").read_text())
    assert run["status"] == "interrupted" and run["message"] == "bundle: interrupted (SIGTERM)", run
    assert not (out / "EMReg.mrb").exists() and "EMReg.mrb" not in run["outputs"]


@pytest.mark.parametrize("signum,code", [(signal.SIGTERM, 143), (signal.SIGINT, 130)])
def test_a_signal_lost_in_a_vtk_callback_still_ends_the_run_as_interrupted(small_case, tmp_path, capsys, monkeypatch,
                                                                          signum, code):
    """A signal landing in a pyvista filter is raised inside VTK's callback: VTK logs it and the filter fails
    with an error of its own, which ended emreg run in a traceback (exit 1, run.json "running")."""
    import dataclasses

    from EMRegModule.pipeline import controller

    def stage_whose_signal_vtk_swallows(*args):
        try:
            signal.raise_signal(signum)
        except KeyboardInterrupt:
            pass  # what VTK does with an exception raised in a Python callback: logs it, the algorithm fails
        raise RuntimeError("Algorithm vtkPythonAlgorithm returned failure for request")

    monkeypatch.setattr(controller, "PIPELINE", tuple(
        dataclasses.replace(entry, prepare=stage_whose_signal_vtk_swallows) if entry.name == "calibrate" else entry
        for entry in controller.PIPELINE))
    out = tmp_path / "out"
    capsys.readouterr()
    assert main(["run", str(small_case), "--out", str(out), "--quiet"]) == code
    name = signal.Signals(signum).name
    assert capsys.readouterr().err.splitlines() == [
        f"emreg run: interrupted ({name}); no partial file was left in place of a complete one"]
    run = json.loads((out / "run.json").read_text())
    assert run["status"] == "interrupted" and run["message"] == f"calibrate: interrupted ({name})"
    assert main(["run", str(tmp_path / "missing"), "--out", str(tmp_path / "o2"), "--quiet"]) == 2  # a new command
