"""Bad inputs that must never give a plausible wrong answer (issue 11): every class is refused with
exit 2 and one line naming the input, through the ``emreg`` command where a user meets it.

Inputs are generated here, in the test run. Classes: CT geometry and voxel values, header sizes
against the data length, sensor ports, registration files, markups units, the fixed sensor
offset, recordings with time resets and gaps, output paths and odd recording paths, oversized
CSV fields and lines.
"""

from __future__ import annotations

import json
import os

import numpy as np
import pytest
import SimpleITK as sitk

from EMRegModule.cli.main import main


def _refused(capsys, argv, *needles, code=2):
    """Run ``emreg argv``; assert exit ``code``, one line on stderr containing every needle; the line."""
    result = main([str(a) for a in argv])
    err = "\n".join(line for line in capsys.readouterr().err.strip().splitlines()
                    if not line.startswith("[emreg]"))  # progress lines on a terminal-less run
    assert result == code, err
    assert len(err.splitlines()) == 1, err
    assert "Traceback" not in err
    for needle in needles:
        assert needle in err, err
    return err


# --- CT -------------------------------------------------------------------------------------


def _ct(values=None, direction=None):
    array = np.full((12, 14, 16), -1000, np.float32) if values is None else values
    image = sitk.GetImageFromArray(array)
    image.SetSpacing((0.8, 0.8, 1.0))
    if direction is not None:
        image.SetDirection(direction)
    return image


@pytest.mark.parametrize("name", ["ct.nrrd", "ct.mha", "ct.nhdr"])  # NIfTI cannot store a shear
def test_sheared_direction_is_refused(tmp_path, capsys, name):
    sitk.WriteImage(_ct(direction=(1, 0.05, 0, 0, 1, 0, 0, 0, 1)), str(tmp_path / name))
    _refused(capsys, ["detect", tmp_path / name, "--out", tmp_path / "out", "--quiet"], "not orthogonal")
    assert not (tmp_path / "out" / "markers.json").exists()


def test_tiny_rounding_of_direction_cosines_is_accepted(tmp_path):
    angle = np.radians(1.5)
    rotation = np.array([[np.cos(angle), -np.sin(angle), 0], [np.sin(angle), np.cos(angle), 0], [0, 0, 1]])
    rounded = np.round(rotation, 6)  # DICOM writes direction cosines with about six digits
    sitk.WriteImage(_ct(direction=tuple(rounded.ravel())), str(tmp_path / "ct.nrrd"))
    from EMRegModule.io.image import read_ct

    assert read_ct(tmp_path / "ct.nrrd").GetSize() == (16, 14, 12)


@pytest.mark.parametrize("kind", ["nan slab", "-inf slab", "sprinkled nan/inf"])
@pytest.mark.parametrize("name,compress", [("ct.nrrd", True), ("ct.nrrd", False), ("ct.mha", True),
                                           ("ct.nii.gz", True), ("ct.nhdr", False)])
def test_non_finite_voxels_are_refused_with_their_count(tmp_path, capsys, kind, name, compress):
    values = np.full((12, 14, 16), -1000, np.float32)
    if kind == "nan slab":
        values[5] = np.nan
    elif kind == "-inf slab":
        values[:, 3] = -np.inf
    else:
        rng = np.random.default_rng(1)
        flat = values.reshape(-1)
        flat[rng.choice(flat.size, 40, replace=False)] = np.nan
        flat[rng.choice(flat.size, 7, replace=False)] = np.inf
    expected = int(np.count_nonzero(~np.isfinite(values)))
    sitk.WriteImage(_ct(values), str(tmp_path / name), compress)
    _refused(capsys, ["detect", tmp_path / name, "--out", tmp_path / "out", "--quiet"],
             f"{expected} non-finite voxel")


def test_non_finite_voxels_of_an_image_in_memory_are_refused():
    from EMRegModule.errors import EMRegError
    from EMRegModule.pipeline.controller import EMRegController

    values = np.zeros((12, 14, 16), np.float64)
    values[0, 0, :3] = np.nan
    with pytest.raises(EMRegError, match="3 non-finite"):
        EMRegController().give(ct=_ct(values))


def _write_with_sizes(path, compress, change):
    image = sitk.GetImageFromArray(np.zeros((10, 12, 14), np.int16))
    sitk.WriteImage(image, str(path), compress)
    if path.suffix == ".nhdr":
        header = path.read_text()
        path.write_text(header.replace("sizes: 14 12 10", f"sizes: 14 12 {10 + change}"))
        return
    raw = path.read_bytes()
    old = b"sizes: 14 12 10" if path.suffix == ".nrrd" else b"DimSize = 14 12 10"
    assert old in raw
    path.write_bytes(raw.replace(old, old[:-2] + str(10 + change).encode()))


@pytest.mark.parametrize("name,compress", [("ct.nrrd", False), ("ct.nrrd", True), ("ct.mha", False),
                                           ("ct.mha", True), ("ct.nhdr", False)])
@pytest.mark.parametrize("change,needle", [(-1, "more than its header"), (+1, "truncated")])
def test_header_sizes_must_match_the_data_length(tmp_path, capsys, name, compress, change, needle):
    _write_with_sizes(tmp_path / name, compress, change)
    _refused(capsys, ["detect", tmp_path / name, "--out", tmp_path / "out", "--quiet"], needle)


def test_sizes_check_also_holds_on_the_simpleitk_path(tmp_path, monkeypatch):
    """Without the fast path (no isal), the SimpleITK reader gets the same length check."""
    from EMRegModule.errors import EMRegError
    from EMRegModule.io import fast_read
    from EMRegModule.io.image import read_ct

    monkeypatch.setattr(fast_read, "igzip_lib", None)
    for compress in (False, True):
        _write_with_sizes(tmp_path / "ct.nrrd", compress, -2)
        with pytest.raises(EMRegError, match="more than its header"):
            read_ct(tmp_path / "ct.nrrd")


# --- registration files: every consumer refuses an untrustworthy one -------------------------------

HEADER = "time_s,sensor,x_mm,y_mm,z_mm,azimuth_deg,elevation_deg,roll_deg,quality,label\n"


def _recording_text(n=200, probe_port=2, reference_port=1, probe_moves=True, times=None):
    """A small recording: a still reference and a probe walking between two places (tracker frame)."""
    rows = []
    times = np.arange(n) / 40.0 if times is None else np.asarray(times, dtype=float)
    for k, t in enumerate(times):
        rows.append(f"{t:.4f},{reference_port},10.0,20.0,-150.0,5.0,0.0,0.0,0,")
        x = 60.0 + (40.0 if probe_moves and (k // 50) % 2 else 0.0)
        rows.append(f"{t:.4f},{probe_port},{x:.3f},35.0,-120.0,30.0,10.0,0.0,0,")
    return HEADER + "\n".join(rows) + "\n"


def _registration(path, matrix=None, fre=0.6, l_mm=14.0):
    matrix = np.eye(4) if matrix is None else matrix
    text = json.dumps({"ReferenceToImage": np.asarray(matrix).tolist(), "sensor_offset_l_mm": l_mm, "fre_mm": fre,
                       "pairs": [], "unpaired_image_markers": [], "unpaired_calibration_points": []})
    path.write_text(text.replace("NaN", "NaN").replace("1e999", "Infinity"))
    return path


def _consumers(tmp_path, registration):
    """argv of every consumer of registration.json, on small valid other inputs."""
    case = tmp_path / "case"
    case.mkdir(exist_ok=True)
    (case / "navigation.csv").write_text(_recording_text())
    (case / "targets.mrk.json").write_text(json.dumps({"markups": [{"controlPoints": [
        {"label": "T1", "position": [60.0, 35.0, -120.0]}]}]}))
    out = tmp_path / "out"
    out.mkdir(exist_ok=True)
    (out / "registration.json").write_text(registration.read_text())
    return {
        "navigate": ["navigate", "--registration", registration, "--source", f"replay:{case / 'navigation.csv'}",
                     "--out", tmp_path / "nav"],
        "navigate live": ["navigate", "--registration", registration, "--source",
                          f"replay:{case / 'navigation.csv'}", "--igtl-port", "0", "--fast", "--quiet"],
        "evaluate": ["evaluate", case, "--registration", registration, "--out", tmp_path / "eval"],
        "report": ["report", out, "--case", case, "--quiet"],
    }


@pytest.mark.parametrize("consumer", ["navigate", "navigate live", "evaluate", "report"])
@pytest.mark.parametrize("problem,needle,code", [
    ("infinity", "finite", 2), ("nan fre", "fre_mm is not a finite", 2), ("sheared", "not a rigid transform", 2),
    ("scaled", "not a rigid transform", 2), ("fre 50", "above the limit of 2 mm", 3), ("corrupt", "registration", 2),
])
def test_every_consumer_refuses_an_untrustworthy_registration(tmp_path, capsys, consumer, problem, needle, code):
    path = tmp_path / "registration.json"
    matrix = np.eye(4)
    matrix[:3, 3] = [10, 20, 30]
    if problem == "infinity":
        matrix[1, 3] = 1e999
        _registration(path, matrix)
    elif problem == "nan fre":
        _registration(path, matrix, fre=float("nan"))
    elif problem == "sheared":
        matrix[0, 1] = 0.01
        _registration(path, matrix)
    elif problem == "scaled":
        matrix[:3, :3] *= 1.001
        _registration(path, matrix)
    elif problem == "fre 50":
        _registration(path, matrix, fre=50.0)
    else:
        _registration(path, matrix)
        path.write_text(path.read_text()[:40])
    if problem == "infinity":
        assert "Infinity" in path.read_text()
    _refused(capsys, _consumers(tmp_path, path)[consumer], needle, code=code)
    assert not (tmp_path / "nav" / "navigation.csv").exists()
    assert not (tmp_path / "eval" / "evaluation.json").exists()
    assert not (tmp_path / "out" / "report.html").exists()


def test_a_good_registration_is_used_by_navigate(tmp_path, capsys):
    path = _registration(tmp_path / "registration.json")
    argv = _consumers(tmp_path, path)["navigate"]
    assert main([str(a) for a in argv]) == 0, capsys.readouterr().err
    assert (tmp_path / "nav" / "navigation.csv").is_file()


def test_a_tightened_fre_limit_in_the_settings_is_applied_by_consumers(tmp_path, capsys):
    path = _registration(tmp_path / "registration.json", fre=0.6)
    (tmp_path / "tight.toml").write_text("[registration]\nmax_fre_mm = 0.5\n")
    argv = _consumers(tmp_path, path)["navigate"] + ["--settings", tmp_path / "tight.toml"]
    _refused(capsys, argv, "above the limit of 0.5 mm", code=3)


def test_evaluate_without_recordings_is_exit_2(tmp_path, capsys):
    path = _registration(tmp_path / "registration.json")
    (tmp_path / "case").mkdir()
    _refused(capsys, ["evaluate", tmp_path / "case", "--registration", path, "--out", tmp_path / "eval"],
             "nothing to evaluate")
    assert not (tmp_path / "eval" / "evaluation.json").exists()


def test_fixed_sensor_offset_outside_the_pinhole_is_refused():
    from synth_registration import pairing_problem
    from test_registration import _inputs

    from EMRegModule.core.registration import RegistrationSettings, register
    from EMRegModule.errors import EMRegError
    from EMRegModule.marker_model import MarkerModel

    markers, calibration = _inputs(pairing_problem(3))
    for l_mm in (1000.0, 5.0, 18.6):
        with pytest.raises(EMRegError, match="outside the marker's pinhole 11..18.5") as info:
            register(markers, calibration, MarkerModel(), RegistrationSettings(sensor_offset_l_mm=l_mm))
        assert info.value.exit_code == 2
    assert register(markers, calibration, MarkerModel(),
                    RegistrationSettings(sensor_offset_l_mm=18.5)).sensor_offset_fixed


@pytest.mark.parametrize("units,scale", [("mm", 1.0), ("m", 1000.0), (None, 1.0)])
def test_markups_units_are_honoured(tmp_path, units, scale):
    from EMRegModule.io.markups import read_markups

    markup = {"coordinateSystem": "LPS", "controlPoints": [{"label": "T1", "position": [0.01, -0.02, 0.3]}]}
    if units is not None:
        markup["coordinateUnits"] = units
    (tmp_path / "t.mrk.json").write_text(json.dumps({"markups": [markup]}))
    labels, positions = read_markups(tmp_path / "t.mrk.json")
    np.testing.assert_allclose(positions[0], np.array([0.01, -0.02, 0.3]) * scale)


def test_unknown_markups_units_are_an_error(tmp_path, capsys):
    from EMRegModule.errors import EMRegError
    from EMRegModule.io.markups import read_markups

    (tmp_path / "t.mrk.json").write_text(json.dumps({"markups": [
        {"coordinateUnits": "inch", "controlPoints": [{"label": "T1", "position": [1, 2, 3]}]}]}))
    with pytest.raises(EMRegError, match="unknown coordinateUnits 'inch'"):
        read_markups(tmp_path / "t.mrk.json")


# --- sensor ports ---------------------------------------------------------------------------------


def _calibration_csv(tmp_path, n_markers=6, seed=4):
    from synth_registration import calibration_recording, make_frame

    from EMRegModule.io.tracking_csv import write_tracking_csv

    frame = make_frame(seed, n_markers=n_markers)
    recording, _ = calibration_recording(frame.pinholes_reference, frame.axes_reference, seed=seed)
    path = tmp_path / "calibration.csv"
    write_tracking_csv(recording, path)
    return path


@pytest.mark.parametrize("ports,needle", [
    (("2", "2"), "both port 2"), (("1", "3"), "no samples from the probe sensor on port 3"),
    (("5", "2"), "no samples from the reference sensor on port 5"), (("2", "1"), "look swapped"),
])
def test_calibrate_refuses_port_mistakes(tmp_path, capsys, ports, needle):
    path = _calibration_csv(tmp_path)
    _refused(capsys, ["calibrate", path, "--out", tmp_path / "out", "--reference-sensor", ports[0],
                      "--probe-sensor", ports[1]], needle)
    assert not (tmp_path / "out" / "frame_calibration.json").exists()


def test_a_probe_fixed_to_the_reference_is_refused(tmp_path, capsys):
    (tmp_path / "rec.csv").write_text(_recording_text(probe_moves=False))
    _refused(capsys, ["calibrate", tmp_path / "rec.csv", "--out", tmp_path / "out"], "never moves relative")


@pytest.mark.parametrize("ports,needle", [(("2", "1"), "look swapped"), (("1", "1"), "both port 1"),
                                          (("1", "4"), "port 4")])
def test_navigate_and_evaluate_refuse_port_mistakes(tmp_path, capsys, ports, needle):
    path = _registration(tmp_path / "registration.json")
    argv = _consumers(tmp_path, path)
    options = ["--reference-sensor", ports[0], "--probe-sensor", ports[1]]
    _refused(capsys, argv["navigate"] + options, needle)
    _refused(capsys, argv["evaluate"] + options, needle)
    assert not (tmp_path / "nav" / "navigation.csv").exists()


def test_live_navigate_refuses_the_same_port(tmp_path, capsys):
    path = _registration(tmp_path / "registration.json")
    argv = _consumers(tmp_path, path)["navigate live"] + ["--reference-sensor", "2", "--probe-sensor", "2"]
    _refused(capsys, argv, "port 2")


def test_run_refuses_probe_equal_reference_in_case_toml(tmp_path, capsys):
    sitk.WriteImage(_ct(), str(tmp_path / "ct.nrrd"))
    (tmp_path / "case.toml").write_text("[sensors]\nreference = 2\nprobe = 2\n")
    _refused(capsys, ["run", tmp_path, "--out", tmp_path / "out", "--quiet"], "both port 2")


# --- time: resets and gaps split the recording into segments -------------------------------------


def _retimed(path, change):
    from EMRegModule.io.tracking_csv import read_tracking_csv, write_tracking_csv

    recording = read_tracking_csv(path)
    half = len(recording) // 2
    half -= half % 2  # keep the two rows of one moment together
    time_s = recording.time_s.copy()
    time_s[half:] = change(time_s[half:], time_s[half - 1])
    recording.time_s = time_s
    write_tracking_csv(recording, path)
    return half


def _pinholes(capsys, argv):
    assert main([str(a) for a in argv]) == 0
    captured = capsys.readouterr()
    return int(captured.out.split()[0]), captured.err


@pytest.mark.parametrize("kind,needle", [("reset", "time goes back"), ("gap", "nothing recorded for")])
def test_time_reset_or_gap_midway_keeps_every_pinhole(tmp_path, capsys, kind, needle):
    path = _calibration_csv(tmp_path, n_markers=8)
    expected, err = _pinholes(capsys, ["calibrate", path, "--out", tmp_path / "a"])
    assert expected == 8 and needle not in err
    if kind == "reset":
        _retimed(path, lambda t, last: t - t[0] + 0.0)  # the clock restarts at 0 s
    else:
        _retimed(path, lambda t, last: t + 30.0)
    found, err = _pinholes(capsys, ["calibrate", path, "--out", tmp_path / "b"])
    assert found == expected
    assert needle in err and "separate time segment" in err
    document = json.loads((tmp_path / "b" / "frame_calibration.json").read_text())
    assert any(needle in w for w in document["warnings"])


def test_time_that_does_not_increase_within_a_segment_is_refused(tmp_path, capsys):
    text = _recording_text(n=20).splitlines()
    text.insert(8, text[6])  # a repeated sample of the reference sensor: same time twice
    (tmp_path / "rec.csv").write_text("\n".join(text) + "\n")
    _refused(capsys, ["calibrate", tmp_path / "rec.csv", "--out", tmp_path / "out"], "does not increase")


def test_segments_are_never_matched_across_a_reset():
    from EMRegModule.core.tracking import match_moments
    from EMRegModule.io.tracking_csv import parse_tracking_csv

    text = _recording_text(n=100, times=np.r_[np.arange(50) / 40.0, np.arange(50) / 40.0])
    recording = parse_tracking_csv(text)
    assert sorted(set(recording.segment.tolist())) == [0, 1]
    reference, probe = recording.for_sensor(1), recording.for_sensor(2)
    ref_idx, probe_idx = match_moments(reference, probe)
    assert len(probe_idx) == 100
    assert np.all(reference.segment[ref_idx] == probe.segment[probe_idx])


# --- output paths and odd input paths: exit 2, one line, never a traceback ------------------------


def _unwritable_folder(tmp_path):
    """A folder this process cannot write into (as root, permissions do not stop it: /sys does)."""
    if os.geteuid() != 0:
        folder = tmp_path / "locked"
        folder.mkdir()
        folder.chmod(0o555)
        return folder
    return "/sys/kernel"


def _out_cases(tmp_path):
    (tmp_path / "a_file").write_text("not a folder")
    os.symlink(tmp_path / "loop_b", tmp_path / "loop_a")
    os.symlink(tmp_path / "loop_a", tmp_path / "loop_b")
    return {
        "file": (tmp_path / "a_file", "is a file"),
        "symlink loop": (tmp_path / "loop_a", "symbolic"),
        "unwritable": (_unwritable_folder(tmp_path), "cannot write"),
        "cannot be made": ("/proc/emreg/out", "cannot write"),
    }


@pytest.mark.parametrize("case", ["file", "symlink loop", "unwritable", "cannot be made"])
def test_bad_output_folders_are_one_line_exit_2(tmp_path, capsys, case):
    out, needle = _out_cases(tmp_path)[case]
    calibration = _calibration_csv(tmp_path)
    registration = _registration(tmp_path / "registration.json")
    consumers = _consumers(tmp_path, registration)
    sitk.WriteImage(_ct(), str(tmp_path / "ct.nrrd"))
    for argv in (
        ["detect", tmp_path / "ct.nrrd", "--out", out, "--quiet"],
        ["calibrate", calibration, "--out", out],
        ["register", "--markers", tmp_path / "m.json", "--calibration", tmp_path / "c.json", "--out", out],
        consumers["navigate"][:-1] + [out],
        consumers["evaluate"][:-1] + [out],
        ["run", tmp_path, "--out", out, "--quiet"],
        ["simulate", out, "--quiet"],
        ["record", "--device", f"replay:{calibration}", "--out", f"{out}/rec.csv", "--fast", "--quiet"],
    ):
        _refused(capsys, argv, str(out))


def test_record_into_a_folder_name_is_refused(tmp_path, capsys):
    calibration = _calibration_csv(tmp_path)
    _refused(capsys, ["record", "--device", f"replay:{calibration}", "--out", tmp_path, "--fast", "--quiet"],
             "is a folder")


def test_read_only_output_folder_is_one_line_exit_2(tmp_path, capsys, monkeypatch):
    """A read-only file system (EROFS) cannot be made here without privileges: the error is injected where
    the folder is probed, the first write of every command."""
    import errno
    import tempfile

    def read_only(*args, **kwargs):
        raise OSError(errno.EROFS, os.strerror(errno.EROFS))

    monkeypatch.setattr(tempfile, "TemporaryFile", read_only)
    _refused(capsys, ["calibrate", _calibration_csv(tmp_path), "--out", tmp_path / "out"], "Read-only file system")


@pytest.mark.parametrize("source", ["replay:", "replay:{folder}", "replay:{missing}"])
@pytest.mark.parametrize("live", [False, True])
def test_replay_of_nothing_or_a_folder_is_refused(tmp_path, capsys, source, live):
    registration = _registration(tmp_path / "registration.json")
    source = source.format(folder=tmp_path, missing=tmp_path / "none.csv")
    argv = ["navigate", "--registration", registration, "--source", source]
    argv += ["--igtl-port", "0", "--fast", "--quiet"] if live else ["--out", tmp_path / "nav"]
    _refused(capsys, argv)


def test_calibrate_a_folder_is_refused(tmp_path, capsys):
    _refused(capsys, ["calibrate", tmp_path, "--out", tmp_path / "out"], "is a folder")


# --- oversized CSV fields and lines: bounded before allocation ----------------------------------


def _row(label="", time_s=0.0):
    return f"{time_s:.4f},1,1,2,3,0,0,0,0,{label}\n"


@pytest.mark.parametrize("kind,needle", [
    ("quoted field over 128 KB", "longer than 65536 bytes"),
    ("quoted field of 5 KB", "at most 4096 characters"),
    ("unquoted 1 MB label", "longer than 65536 bytes"),
    ("unquoted 5 KB label", "at most 4096 characters"),
    ("1 MB header", "line 1"),
])
def test_oversized_csv_fields_are_refused(tmp_path, capsys, kind, needle):
    path = tmp_path / "rec.csv"
    if kind == "quoted field over 128 KB":
        path.write_text(HEADER + _row('"' + "x" * 140_000 + '"'))
    elif kind == "quoted field of 5 KB":
        path.write_text(HEADER + _row('"' + "x" * 5000 + '"'))
    elif kind == "unquoted 1 MB label":
        path.write_text(HEADER + _row("x" * (1 << 20)))
    elif kind == "unquoted 5 KB label":
        path.write_text(HEADER + _row("x" * 5000) + _row(time_s=0.1))
    else:
        path.write_text("y" * (1 << 20) + "\n" + _row())
    _refused(capsys, ["calibrate", path, "--out", tmp_path / "out"], needle)


def test_a_2_gb_line_is_refused_without_reading_it(tmp_path, capsys):
    """A sparse file: 2 GB of one line costs no disk, and the reader stops after 64 KB of it."""
    path = tmp_path / "huge.csv"
    with path.open("wb") as stream:
        stream.write(HEADER.encode() + b"0.0,1,1,2,3,0,0,0,0,")
        stream.seek((2 << 30) + 10)
        stream.write(b"\n")
    assert path.stat().st_size > 2 << 30
    _refused(capsys, ["calibrate", path, "--out", tmp_path / "out"], "line 2 is longer than 65536 bytes")
    _refused(capsys, ["navigate", "--registration", _registration(tmp_path / "registration.json"),
                      "--source", f"replay:{path}", "--out", tmp_path / "nav"], "longer than 65536 bytes")


def test_field_limits_keep_normal_labels(tmp_path):
    from EMRegModule.io.tracking_csv import read_tracking_csv

    long_label = "M" * 1000
    (tmp_path / "rec.csv").write_text(HEADER + _row(long_label) + _row('"a, quoted label"', 0.1))
    recording = read_tracking_csv(tmp_path / "rec.csv")
    assert list(recording.label) == [long_label, "a, quoted label"]
