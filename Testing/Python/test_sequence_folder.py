"""A recording saved by 3D Slicer: one sequence file per transform (``ReferenceToTracker.seq.nrrd``,
``ProbeToTracker.seq.nrrd``), in a folder (``CASE/calibration/``, or any folder on the command line).

The files are written here by 3D Slicer's own ``vtkMRMLLinearTransformSequenceStorageNode`` (the
``slicer-core`` wheel), one ``vtkMRMLSequenceNode`` per transform, as the Sequences module saves them.
"""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import numpy as np
import pytest

from EMRegModule.cli.main import main
from EMRegModule.core.tracking import TrackingRecording
from EMRegModule.io.tracking_csv import read_tracking_csv
from EMRegModule.simulation.case import simulate_case

SMALL = {"frame_size_mm": (200.0, 200.0, 110.0), "n_markers": 8, "navigation_rounds": 2, "board_rounds": 3,
         "n_targets": 3}


def slicer_write(rows: TrackingRecording, node_name: str, path: Path, stamps: np.ndarray | None = None) -> None:
    """One transform's samples as a 3D Slicer sequence node, saved by Slicer's linear-transform sequence storage
    node to ``path`` (index values = the sample times, or ``stamps``)."""
    import slicer  # the slicer-core wheel: a test dependency installed by scripts/setup
    import vtk

    scene = slicer.vtkMRMLScene()
    sequence = slicer.vtkMRMLSequenceNode()
    scene.AddNode(sequence)
    sequence.SetName(node_name)
    sequence.SetIndexName("time")
    sequence.SetIndexUnit("s")
    poses = rows.transforms()
    times = rows.time_s if stamps is None else stamps
    for pose, stamp in zip(poses, times, strict=True):
        node = slicer.vtkMRMLLinearTransformNode()
        matrix = vtk.vtkMatrix4x4()
        for r in range(4):
            for c in range(4):
                matrix.SetElement(r, c, float(pose[r, c]))
        node.SetMatrixTransformToParent(matrix)
        sequence.SetDataNodeAtValue(node, f"{stamp:.6f}")
    storage = slicer.vtkMRMLLinearTransformSequenceStorageNode()
    scene.AddNode(storage)
    storage.SetFileName(str(path))
    assert storage.WriteData(sequence) == 1


def slicer_recording(csv_path: Path, folder: Path, names=("ReferenceToTracker", "ProbeToTracker"),
                     suffix: str = ".seq.nrrd", files: tuple[str, str] | None = None) -> Path:
    """The recording of a tracking CSV as 3D Slicer saves it: one sequence file per sensor in ``folder``."""
    recording = read_tracking_csv(csv_path)
    folder.mkdir(parents=True, exist_ok=True)
    for port, name, file in zip((1, 2), names, files or names, strict=True):
        slicer_write(recording.for_sensor(port), name, folder / f"{file}{suffix}")
    return folder


@pytest.fixture(scope="module")
def case(tmp_path_factory) -> Path:
    """A small simulated case (1 mm voxels, 8 markers) and its detection (``det/``)."""
    root = tmp_path_factory.mktemp("slicer_seq")
    simulate_case(root / "case", seed=5, spacing_mm=1.0, **SMALL)
    assert main(["detect", str(root / "case"), "--out", str(root / "det"), "--quiet"]) == 0
    return root


def _json(path: Path) -> dict:
    return json.loads(path.read_text())


def test_slicer_writes_one_transform_per_file(case, tmp_path):
    """The layout checked against: Slicer's own files, one transform each, MetaIO text under the .seq.nrrd name."""
    folder = slicer_recording(case / "case" / "calibration.csv", tmp_path / "calibration")
    assert sorted(p.name for p in folder.iterdir()) == ["ProbeToTracker.seq.nrrd", "ReferenceToTracker.seq.nrrd"]
    text = (folder / "ProbeToTracker.seq.nrrd").read_text()
    assert "Seq_Frame0000_ProbeToTrackerTransform =" in text and "ReferenceToTracker" not in text
    assert text.rstrip().endswith("ElementDataFile = LOCAL")


def test_a_folder_of_slicer_files_reads_as_the_recording(case, tmp_path, capsys):
    """``emreg convert FOLDER out.csv``: every sample of both sensors at its time, as in the CSV it came from;
    ``emreg calibrate FOLDER`` and ``navigate --source replay:FOLDER`` as from one sequence file."""
    source = case / "case" / "calibration.csv"
    folder = slicer_recording(source, tmp_path / "calibration")
    assert main(["convert", str(folder), str(tmp_path / "back.csv"), "--quiet"]) == 0
    before, after = read_tracking_csv(source), read_tracking_csv(tmp_path / "back.csv")
    for port in (1, 2):
        a, b = before.for_sensor(port), after.for_sensor(port)
        assert len(a) == len(b)
        assert np.allclose(a.time_s, b.time_s, atol=1e-6)
        assert np.allclose(a.transforms(), b.transforms(), atol=1e-4)

    single = tmp_path / "calibration.seq.mha"  # the same samples in one sequence file (the existing path)
    assert main(["convert", str(source), str(single), "--quiet"]) == 0
    assert main(["calibrate", str(single), "--out", str(tmp_path / "one"), "--quiet"]) == 0
    assert main(["calibrate", str(folder), "--out", str(tmp_path / "two"), "--quiet"]) == 0
    one = _json(tmp_path / "one" / "frame_calibration.json")["points"]
    two = _json(tmp_path / "two" / "frame_calibration.json")["points"]
    assert len(one) == len(two) == 8
    assert np.allclose([p["position"] for p in one], [p["position"] for p in two], atol=1e-3)

    assert main(["register", "--markers", str(case / "det" / "markers.json"), "--calibration",
                 str(tmp_path / "two" / "frame_calibration.json"), "--out", str(tmp_path / "two"), "--quiet"]) == 0
    navigation = slicer_recording(case / "case" / "navigation.csv", tmp_path / "navigation",
                                  names=("ReferenceToTracker-Sequence", "ProbeToTracker-Sequence"))
    assert main(["navigate", "--registration", str(tmp_path / "two" / "registration.json"), "--source",
                 f"replay:{navigation}", "--out", str(tmp_path / "nav"), "--quiet"]) == 0
    rows = (tmp_path / "nav" / "navigation.csv").read_text().splitlines()
    assert len(rows) - 1 == len(read_tracking_csv(case / "case" / "navigation.csv").for_sensor(2))


def test_a_case_folder_with_slicer_recordings_runs(case, tmp_path, capsys):
    """CASE/calibration/ and CASE/navigation/ (Slicer's files, .seq.mha this time) instead of the CSVs:
    the run pairs, registers and evaluates as the CSV case does."""
    target = tmp_path / "case"
    shutil.copytree(case / "case", target)
    for stem in ("calibration", "navigation"):
        slicer_recording(target / f"{stem}.csv", target / stem, suffix=".seq.mha")
        (target / f"{stem}.csv").unlink()
    assert main(["run", str(target), "--out", str(tmp_path / "out"), "--quiet"]) == 0
    run = _json(tmp_path / "out" / "run.json")
    assert run["status"] == "finished" and run["inputs"]["calibration"]["path"] == str(target / "calibration")
    registration = _json(tmp_path / "out" / "registration.json")
    assert len(registration["pairs"]) == 8 and registration["fre_mm"] < 1.0
    evaluation = _json(tmp_path / "out" / "evaluation.json")
    assert evaluation["tre"]["mean_mm"] < 3.0 and evaluation["board"]["edges"]


def test_frames_are_matched_by_timestamp(case, tmp_path, capsys):
    """Probe stamps 0.4 ms off the reference's still match; frames missing from one file are left out with
    a warning that counts them; a file named by its role (its transform Unknown1ToUnknown2) takes that role."""
    recording = read_tracking_csv(case / "case" / "calibration.csv")
    reference, probe = recording.for_sensor(1), recording.for_sensor(2)
    folder = tmp_path / "calibration"
    folder.mkdir()
    slicer_write(reference, "Unknown1ToUnknown2", folder / "ReferenceToTracker.seq.nrrd")
    keep = np.ones(len(probe), dtype=bool)
    keep[::10] = False  # every tenth probe frame missing from its file
    slicer_write(probe.select(keep), "ProbeToTracker", folder / "ProbeToTracker.seq.nrrd",
                 stamps=probe.time_s[keep] + 0.0004)
    capsys.readouterr()
    assert main(["convert", str(folder), str(tmp_path / "back.csv")]) == 0
    err = capsys.readouterr().err
    missing = int(np.count_nonzero(~keep))
    assert f"{missing} of {len(reference)} frames of ReferenceToTracker.seq.nrrd" in err
    back = read_tracking_csv(tmp_path / "back.csv")
    assert len(back.for_sensor(1)) == len(back.for_sensor(2)) == int(keep.sum())
    assert np.allclose(back.for_sensor(2).transforms(), probe.select(keep).transforms(), atol=1e-4)


def _error(capsys) -> str:
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1, err
    return err[0]


def test_missing_or_mismatched_partner_files_are_refused(case, tmp_path, capsys):
    capsys.readouterr()
    calibration = slicer_recording(case / "case" / "calibration.csv", tmp_path / "calibration")
    navigation = slicer_recording(case / "case" / "navigation.csv", tmp_path / "navigation")
    # the partner file missing
    lone = tmp_path / "lone"
    lone.mkdir()
    shutil.copy2(calibration / "ProbeToTracker.seq.nrrd", lone)
    assert main(["calibrate", str(lone), "--out", str(tmp_path / "o1"), "--quiet"]) == 2
    line = _error(capsys)
    assert "no ReferenceToTrackerTransform" in line and "ProbeToTracker.seq.nrrd" in line
    # two files of different recordings (calibration's reference, navigation's probe)
    mixed = tmp_path / "mixed"
    mixed.mkdir()
    shutil.copy2(calibration / "ReferenceToTracker.seq.nrrd", mixed)
    shutil.copy2(navigation / "ProbeToTracker.seq.nrrd", mixed)
    assert main(["calibrate", str(mixed), "--out", str(tmp_path / "o2"), "--quiet"]) == 2
    assert "do not hold the same frames" in _error(capsys)
    # the probe twice
    twice = tmp_path / "twice"
    twice.mkdir()
    shutil.copy2(calibration / "ProbeToTracker.seq.nrrd", twice)
    shutil.copy2(navigation / "ProbeToTracker.seq.nrrd", twice / "ProbeToTracker-1.seq.nrrd")
    shutil.copy2(calibration / "ReferenceToTracker.seq.nrrd", twice)
    assert main(["navigate", "--registration", str(tmp_path / "none.json"), "--source", f"replay:{twice}",
                 "--out", str(tmp_path / "o3"), "--quiet"]) == 2
    _error(capsys)
    assert main(["calibrate", str(twice), "--out", str(tmp_path / "o3"), "--quiet"]) == 2
    assert "more than one file" in _error(capsys)
    # an empty folder
    (tmp_path / "empty").mkdir()
    assert main(["calibrate", str(tmp_path / "empty"), "--out", str(tmp_path / "o4"), "--quiet"]) == 2
    assert "is a folder with no sequence file" in _error(capsys)
