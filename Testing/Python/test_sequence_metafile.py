"""PLUS / 3D Slicer sequence metafiles: read, write, convert, record; checked with Slicer's own MRML reader.

3D Slicer's ``vtkMRMLLinearTransformSequenceStorageNode`` (the ``slicer-core`` wheel) reads what
EMReg writes and writes what EMReg reads. Bad files get one line naming the file and frame, exit 2.
"""

from __future__ import annotations

import numpy as np
import pytest
from synth_registration import calibration_recording, make_frame

from EMRegModule.cli.main import main
from EMRegModule.errors import EMRegError
from EMRegModule.io.recording import read_recording
from EMRegModule.io.sequence_metafile import (
    format_sequence_metafile,
    read_sequence_frames,
    read_sequence_metafile,
    write_sequence_metafile,
)
from EMRegModule.io.tracking_csv import read_tracking_csv, write_tracking_csv
from EMRegModule.simulation.tracking import apply_probe_convention


@pytest.fixture(scope="module")
def recording():
    frame = make_frame(21, n_markers=6)
    rec, _ = calibration_recording(frame.pinholes_reference, frame.axes_reference, seed=21, dwell_s=0.5)
    rec.quality[:] = np.round(rec.quality * 4) / 4  # quality numbers as a tracker gives them
    return rec


def _slicer():
    import slicer  # the slicer-core wheel (3D Slicer's MRML): a test dependency, installed by scripts/setup

    return slicer


def _slicer_read(path):
    """(index values, 4x4 matrices) of the first transform of a sequence file, as 3D Slicer reads it."""
    import vtk

    slicer = _slicer()
    scene = slicer.vtkMRMLScene()
    storage = slicer.vtkMRMLLinearTransformSequenceStorageNode()
    scene.AddNode(storage)
    sequence = slicer.vtkMRMLSequenceNode()
    scene.AddNode(sequence)
    storage.SetFileName(str(path))
    assert storage.ReadData(sequence) == 1
    matrices, times = [], []
    for i in range(sequence.GetNumberOfDataNodes()):
        matrix = vtk.vtkMatrix4x4()
        sequence.GetNthDataNode(i).GetMatrixTransformToParent(matrix)
        matrices.append([[matrix.GetElement(r, c) for c in range(4)] for r in range(4)])
        times.append(float(sequence.GetNthIndexValue(i)))
    return np.array(times), np.array(matrices), sequence.GetName()


def test_csv_to_sequence_and_back_is_lossless(recording, tmp_path):
    csv_in, seq, csv_out = tmp_path / "rec.csv", tmp_path / "rec.seq.mha", tmp_path / "back.csv"
    write_tracking_csv(recording, csv_in)
    assert main(["convert", str(csv_in), str(seq), "--quiet"]) == 0
    assert main(["convert", str(seq), str(csv_out), "--quiet"]) == 0
    before, after = read_tracking_csv(csv_in), read_tracking_csv(csv_out)
    assert len(before) == len(after)
    assert np.array_equal(before.sensor, after.sensor)
    assert np.allclose(before.time_s, after.time_s, atol=1e-6)
    assert np.allclose(before.position_mm, after.position_mm, atol=1e-6)
    assert np.allclose(before.rotation, after.rotation, atol=1e-6)
    assert np.array_equal(before.quality, after.quality)
    text = seq.read_text()
    assert text.rstrip().endswith("ElementDataFile = LOCAL")
    assert "Seq_Frame0000_ReferenceToTrackerTransformStatus = OK" in text
    assert "Seq_Frame0000_ProbeToTrackerTransformStatus = OK" in text


def test_position_only_probe_rows_survive_a_round_trip(recording, tmp_path):
    position_only = apply_probe_convention(recording, "none")
    write_sequence_metafile(position_only, tmp_path / "p.seq.mha")
    back = read_sequence_metafile(tmp_path / "p.seq.mha")
    assert np.all(np.isnan(back.rotation[back.sensor == 2])) and np.all(np.isfinite(back.rotation[back.sensor == 1]))
    assert np.allclose(back.position_mm, position_only.position_mm, atol=1e-6)


def test_slicer_reads_what_emreg_writes(recording, tmp_path):
    path = tmp_path / "rec.seq.mha"
    write_sequence_metafile(recording, path)
    times, matrices, _ = _slicer_read(path)  # Slicer keeps the first transform name: ReferenceToTracker
    reference = recording.select(recording.sensor == 1)
    assert len(times) == len(reference)
    assert np.allclose(times, reference.time_s, atol=1e-3)  # Slicer's index values carry 3 decimals
    assert np.allclose(matrices, reference.transforms(), atol=1e-9)
    # the probe transform first: Slicer reads ProbeToTracker
    swapped = tmp_path / "probe_first.seq.mha"
    write_sequence_metafile(recording, swapped, reference_transform="ProbeToTracker",
                            probe_transform="ReferenceToTracker", reference_port=2, probe_port=1)
    _, matrices, name = _slicer_read(swapped)
    assert "ProbeToTracker" in name
    assert np.allclose(matrices, recording.select(recording.sensor == 2).transforms(), atol=1e-9)


@pytest.mark.parametrize("suffix", [".seq.mha", ".seq.nrrd"])
def test_emreg_reads_what_slicer_writes(suffix, tmp_path):
    import vtk

    slicer = _slicer()
    scene = slicer.vtkMRMLScene()
    sequence = slicer.vtkMRMLSequenceNode()
    scene.AddNode(sequence)
    sequence.SetName("ProbeToTracker")
    rng = np.random.default_rng(2)
    from EMRegModule.core.transforms import make_transform, random_rotation

    poses = [make_transform(random_rotation(rng), rng.uniform(-200, 200, 3)) for _ in range(5)]
    for k, pose in enumerate(poses):
        node = slicer.vtkMRMLLinearTransformNode()
        matrix = vtk.vtkMatrix4x4()
        for r in range(4):
            for c in range(4):
                matrix.SetElement(r, c, pose[r, c])
        node.SetMatrixTransformToParent(matrix)
        sequence.SetDataNodeAtValue(node, f"{0.0125 * k:.4f}")
    storage = slicer.vtkMRMLLinearTransformSequenceStorageNode()
    scene.AddNode(storage)
    path = tmp_path / f"slicer{suffix}"
    storage.SetFileName(str(path))
    assert storage.WriteData(sequence) == 1
    frames = read_sequence_frames(path)
    assert frames.names == ["ProbeToTracker"]
    assert np.allclose(frames.matrices["ProbeToTracker"], poses, atol=1e-5)
    assert np.allclose(frames.time_s, 0.0125 * np.arange(5), atol=1e-6) and frames.valid["ProbeToTracker"].all()


def _frame_text(index, name="ProbeToTracker", matrix="1 0 0 1 0 1 0 2 0 0 1 3 0 0 0 1", status="OK", stamp=None):
    lines = [f"Seq_Frame{index:04d}_ReferenceToTrackerTransform = 1 0 0 0 0 1 0 0 0 0 1 0 0 0 0 1",
             f"Seq_Frame{index:04d}_ReferenceToTrackerTransformStatus = OK",
             f"Seq_Frame{index:04d}_{name}Transform = {matrix}"]
    if status is not None:
        lines.append(f"Seq_Frame{index:04d}_{name}TransformStatus = {status}")
    lines.append(f"Seq_Frame{index:04d}_Timestamp = {0.0125 * index if stamp is None else stamp}")
    return "\n".join(lines)


HEADER = "ObjectType = Image\nNDims = 3\nDimSize = 0 0 {n}\nElementType = MET_UCHAR\n"


def _file(tmp_path, frames, header=None, end="ElementDataFile = LOCAL\n"):
    path = tmp_path / "bad.seq.mha"
    path.write_text((header if header is not None else HEADER.format(n=len(frames))) + "\n".join(frames) + "\n"
                    + end)
    return path


def test_invalid_frames_are_dropped_and_counted(tmp_path):
    frames = [_frame_text(i) for i in range(6)]
    frames[2] = _frame_text(2, matrix="nan 7 7 7 7 7 7 7 7 7 7 7 0 0 0 0", status="INVALID")
    frames[4] = _frame_text(4, matrix="0 0 0 9e9 0 0 0 9e9 0 0 0 9e9 0 0 0 1", status="OUT_OF_VIEW")
    path = _file(tmp_path, frames)
    recording = read_sequence_metafile(path)
    assert np.count_nonzero(recording.sensor == 2) == 4 and np.count_nonzero(recording.sensor == 1) == 6
    assert recording.warnings == [f"{path}: 2 of 6 frames of ProbeToTracker have a status other than OK "
                                  "(no valid pose): dropped"]


BAD_FILES = {
    "broken header": (lambda tmp: _file(tmp, [_frame_text(0)], header="ObjectType = Image\nthis is not a field\n"),
                      "line 2 is not 'key = value'"),
    "truncated": (lambda tmp: _file(tmp, [_frame_text(0), _frame_text(1)], end=""), "ends before 'ElementDataFile'"),
    "no status": (lambda tmp: _file(tmp, [_frame_text(0), _frame_text(1, status=None)]),
                  "frame 1 has ProbeToTrackerTransform but no ProbeToTrackerTransformStatus"),
    "not rigid": (lambda tmp: _file(tmp, [_frame_text(0, matrix="1.01 0 0 1 0 1 0 2 0 0 1 3 0 0 0 1")]),
                  "frame 0: ProbeToTrackerTransform is not a rigid transform"),
    "nan": (lambda tmp: _file(tmp, [_frame_text(0), _frame_text(1, matrix="1 0 0 nan 0 1 0 2 0 0 1 3 0 0 0 1")]),
            "frame 1: ProbeToTrackerTransform holds NaN"),
    "repeated time": (lambda tmp: _file(tmp, [_frame_text(0, stamp=2.0), _frame_text(1, stamp=2.0)]),
                      "frame 1: time 2.0000 s of sensor 1 does not increase"),
    # two transforms, one the reference: the other is the tool (test_tool.py); with a third the choice is not plain
    "other names": (lambda tmp: _file(tmp, [_frame_text(0, name="StylusToTracker").replace(
                        "Seq_Frame0000_Timestamp", "Seq_Frame0000_NeedleToTrackerTransform = 1 0 0 0 0 1 0 0 0 0 1 0 "
                        "0 0 0 1\nSeq_Frame0000_NeedleToTrackerTransformStatus = OK\nSeq_Frame0000_Timestamp")]),
                    "no ProbeToTrackerTransform in the file; it holds ReferenceToTrackerTransform, "
                    "StylusToTrackerTransform, NeedleToTrackerTransform"),
    "frame count": (lambda tmp: _file(tmp, [_frame_text(0)], header=HEADER.format(n=5)),
                    "the header says 5 frames"),
}


@pytest.mark.parametrize("kind", sorted(BAD_FILES))
def test_bad_sequence_files_get_one_line_and_exit_2(kind, tmp_path, capsys):
    make, message = BAD_FILES[kind]
    path = make(tmp_path)
    with pytest.raises(EMRegError, match=None) as caught:
        read_recording(path)
    assert message in str(caught.value) and str(path) in str(caught.value)
    out = tmp_path / "out"
    assert main(["calibrate", str(path), "--out", str(out), "--quiet"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and message in err[0] and "Traceback" not in err[0]
    assert not (out / "frame_calibration.json").exists()


def test_transform_names_from_case_toml(recording, tmp_path):
    path = tmp_path / "named.seq.mha"
    write_sequence_metafile(recording, path, reference_transform="FrameToTracker", probe_transform="StylusToTracker")
    with pytest.raises(EMRegError, match="it holds FrameToTrackerTransform, StylusToTrackerTransform"):
        read_recording(path)
    settings = {"sensors": {"reference_transform": "FrameToTracker", "probe_transform": "StylusToTracker"}}
    again = read_recording(path, settings)
    assert len(again) == len(recording)
    assert format_sequence_metafile(again, "FrameToTracker", "StylusToTracker") == path.read_text()


def test_record_from_a_tracker_writes_a_sequence_metafile(tmp_path):
    from EMRegModule.devices.simulator.trakstar import TrackerSimulator

    out = tmp_path / "rec.seq.mha"
    with TrackerSimulator(keep_truth=True, seed=3) as sim:
        assert main(["record", "--device", f"trakstar://{sim.path}?rate=100", "--out", str(out),
                     "--max-samples", "200", "--quiet"]) == 0
    assert not (tmp_path / "rec.seq.mha.partial.csv").exists()
    frames = read_sequence_frames(out)  # every transform of the file, not only reference and probe
    assert frames.names == ["ReferenceToTracker", "ProbeToTracker", "Sensor3ToTracker", "Sensor4ToTracker"]
    assert sum(int(v.sum()) for v in frames.valid.values()) >= 200
    assert set(read_recording(out).sensors) == {1, 2}
    times, _, _ = _slicer_read(out)
    assert len(times) > 0


def test_record_from_a_replay_writes_what_slicer_loads(recording, tmp_path):
    source = tmp_path / "source.csv"
    write_tracking_csv(recording, source)
    out = tmp_path / "rec.seq.mha"
    assert main(["record", "--device", f"replay:{source}", "--fast", "--out", str(out), "--quiet"]) == 0
    again = read_recording(out)
    assert len(again) == len(recording)
    assert np.allclose(again.position_mm, recording.position_mm, atol=1e-4)
    times, matrices, _ = _slicer_read(out)
    reference = recording.select(recording.sensor == 1)
    assert len(times) == len(reference)
    assert np.allclose(times, reference.time_s, atol=1e-3)
    assert np.allclose(matrices, reference.transforms(), atol=1e-4)


def test_the_plus_nrrd_header_variant_is_read(tmp_path):
    """PLUS's NRRD flavour: a NRRD header whose per-frame fields are ``key:=value`` lines."""
    lines = ["NRRD0004", "type: uint8", "dimension: 3", "sizes: 0 0 2", "encoding: raw"]
    for k, x in enumerate((10.0, 11.5)):
        lines += [f"Seq_Frame{k:04d}_ReferenceToTrackerTransform:=1 0 0 0 0 1 0 0 0 0 1 0 0 0 0 1",
                  f"Seq_Frame{k:04d}_ReferenceToTrackerTransformStatus:=OK",
                  f"Seq_Frame{k:04d}_ProbeToTrackerTransform:=0 -1 0 {x} 1 0 0 2 0 0 1 3 0 0 0 1",
                  f"Seq_Frame{k:04d}_ProbeToTrackerTransformStatus:=OK",
                  f"Seq_Frame{k:04d}_Timestamp:={0.0125 * k}"]
    path = tmp_path / "plus.igs.nrrd"
    path.write_text("\n".join(lines) + "\n\n")
    recording = read_recording(path)
    probe = recording.select(recording.sensor == 2)
    assert np.allclose(probe.position_mm[:, 0], [10.0, 11.5]) and np.allclose(probe.rotation[0][:, 0], [0, 1, 0])


# --- one rule for time resets, CSV or sequence file -------------------------------------------------


def _with_reset(recording):
    """The recording with its clock restarting at 0.01 s half way (rows of one moment kept together)."""
    half = len(recording) // 2
    half -= half % 2
    time_s = recording.time_s.copy()
    time_s[half:] = time_s[half:] - time_s[half] + 0.01
    reset = recording.select(np.arange(len(recording)))
    reset.time_s = time_s
    return reset, half


def test_a_clock_reset_splits_a_sequence_file_into_segments_as_it_splits_a_csv(tmp_path, capsys):
    """A PLUS / Slicer file whose timestamps go back is split there with a warning, like a CSV: nothing
    dropped, never matched across the reset; converting either way keeps the reset where it was."""
    frame = make_frame(22, n_markers=6)
    recording, _ = calibration_recording(frame.pinholes_reference, frame.axes_reference, seed=22)
    reset, half = _with_reset(recording)
    csv_path, seq_path, back_path = tmp_path / "reset.csv", tmp_path / "reset.seq.mha", tmp_path / "back.csv"
    write_tracking_csv(reset, csv_path)
    assert main(["convert", str(csv_path), str(seq_path), "--quiet"]) == 0
    stamps = [float(line.split("=")[1]) for line in seq_path.read_text().splitlines() if "_Timestamp =" in line]
    assert np.count_nonzero(np.diff(stamps) < 0) == 1  # the segments follow each other, never interleaved
    from_csv, from_seq = read_tracking_csv(csv_path), read_recording(seq_path)
    for rec in (from_csv, from_seq):
        assert len(rec) == len(recording)
        assert np.bincount(rec.segment).tolist() == [half, len(recording) - half]
        assert any("time goes back" in w and "separate time segment" in w for w in rec.warnings)
    assert any(f"{seq_path}: time goes back" in w and "at frame" in w for w in from_seq.warnings)
    order = np.lexsort((from_csv.sensor, from_csv.time_s, from_csv.segment))
    assert np.allclose(from_seq.time_s, from_csv.time_s[order], atol=1e-6)
    assert np.allclose(from_seq.position_mm, from_csv.position_mm[order], atol=1e-6)
    assert np.array_equal(from_seq.segment, from_csv.segment[order])
    assert main(["convert", str(seq_path), str(back_path), "--quiet"]) == 0
    assert np.array_equal(read_tracking_csv(back_path).segment, from_seq.segment)
    capsys.readouterr()
    counts = []
    for path in (csv_path, seq_path):
        assert main(["calibrate", str(path), "--out", str(tmp_path / path.name.replace(".", "_"))]) == 0
        captured = capsys.readouterr()
        assert "time goes back" in captured.err and "Traceback" not in captured.err
        counts.append(int(captured.out.split()[0]))
    assert counts[0] == counts[1] == 6


def test_convert_names_the_transforms_from_the_typed_settings(recording, tmp_path):
    """``emreg convert --settings case.toml`` writes the ``[sensors]`` transform names and ports (read as the
    typed settings every command uses) and reads them back."""
    toml = tmp_path / "case.toml"
    toml.write_text('[sensors]\nreference = 3\nprobe = 4\nreference_transform = "FrameToTracker"\n'
                    'probe_transform = "StylusToTracker"\n')
    csv_in, seq, csv_out = tmp_path / "rec.csv", tmp_path / "rec.seq.mha", tmp_path / "back.csv"
    moved = recording.select(np.arange(len(recording)))
    moved.sensor = np.where(recording.sensor == 1, 3, 4)
    write_tracking_csv(moved, csv_in)
    assert main(["convert", str(csv_in), str(seq), "--settings", str(toml), "--quiet"]) == 0
    assert read_sequence_frames(seq).names == ["FrameToTracker", "StylusToTracker"]
    assert main(["convert", str(seq), str(csv_out), "--settings", str(toml), "--quiet"]) == 0
    before, back = read_tracking_csv(csv_in), read_tracking_csv(csv_out)
    assert np.array_equal(back.sensor, before.sensor) and set(back.sensor.tolist()) == {3, 4}
    assert np.allclose(back.position_mm, before.position_mm, atol=1e-6)


def test_convert_refuses_to_write_a_sensor_under_another_roles_name(recording, tmp_path, capsys):
    """A CSV whose reference is port 3 and probe port 1, converted without naming the ports, once became a file
    whose ReferenceToTracker was the probe and whose ProbeToTracker was INVALID in every frame (exit 0). The
    default ports missing while other ports are present is now refused, naming the ports the file holds."""
    moved = recording.select(np.arange(len(recording)))
    moved.sensor = np.where(recording.sensor == 1, 3, 1)
    csv_in, seq = tmp_path / "ports.csv", tmp_path / "ports.seq.mha"
    write_tracking_csv(moved, csv_in)
    capsys.readouterr()
    assert main(["convert", str(csv_in), str(seq), "--quiet"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and str(csv_in) in err[0] and "port 2" in err[0] and "[1, 3]" in err[0]
    assert not seq.exists()
    assert main(["convert", str(csv_in), str(seq), "--reference-sensor", "3", "--probe-sensor", "1", "--quiet"]) == 0
    back = read_recording(seq, None, reference_port=3, probe_port=1)
    assert np.array_equal(np.bincount(back.sensor), np.bincount(read_tracking_csv(csv_in).sensor))
    # a board recording without a reference (probe only) still converts
    probe_only = recording.select(recording.sensor == 2)
    write_tracking_csv(probe_only, tmp_path / "board.csv")
    assert main(["convert", str(tmp_path / "board.csv"), str(tmp_path / "board.seq.mha"), "--quiet"]) == 0
