"""Sensor offset and registration: l recovered, ReferenceToImage accurate, refusals, files."""

from __future__ import annotations

import json

import numpy as np
import pytest
from synth_registration import calibration_recording, make_frame, pairing_problem

from EMRegModule.core.calibration import CalibrationPoint, FrameCalibration, calibrate_frame
from EMRegModule.core.registration import RegistrationSettings, register
from EMRegModule.core.sensor_offset import solve_sensor_offset
from EMRegModule.core.transforms import apply_transform, invert_rigid
from EMRegModule.errors import EMRegError, NoSafeAnswerError
from EMRegModule.io.itk_transform import read_slicer_linear_transform
from EMRegModule.io.registration_files import read_registration, write_registration
from EMRegModule.marker_model import MarkerModel

MODEL = MarkerModel()


def _inputs(problem):
    markers = [{"id": f"I{k + 1:02d}", "origin": o, "axis": a}
               for k, (o, a) in enumerate(zip(problem.origins_image, problem.axes_image, strict=True))]
    # the dwells' spread that goes with the simulated per-dwell error (0.73 mm RMS 3D, see below) at the tracker's
    # ratio ([registration] dwell_error_ratio): 0.73 / 1.8 mm
    points = [CalibrationPoint(f"P{k + 1:02d}", p, d, 100, 0.4)
              for k, (p, d) in enumerate(zip(problem.points_reference, problem.directions_reference, strict=True))]
    return markers, FrameCalibration(points)


def _target_error(result, frame, targets_image):
    truth = apply_transform(invert_rigid(frame.reference_to_image), targets_image)
    return np.linalg.norm(apply_transform(result.reference_to_image, truth) - targets_image, axis=1)


@pytest.mark.parametrize("seed", range(6))
def test_register_recovers_l_and_the_transform(seed):
    problem = pairing_problem(seed + 100)
    markers, calibration = _inputs(problem)
    frame = problem.frame
    targets = frame.origins_image.mean(axis=0) + np.random.default_rng(seed).uniform(-80, 80, (6, 3))
    result = register(markers, calibration, MODEL, None, targets)
    assert problem.correct([(int(p["image_marker"][1:]) - 1, int(p["calibration_point"][1:]) - 1)
                            for p in result.pairs])
    assert len(result.pairs) == problem.expected_pairs
    assert len(result.unpaired_image_markers) == len(markers) - len(result.pairs)
    assert abs(result.sensor_offset_l_mm - frame.l_mm) < 0.3
    assert result.sensor_offset_l_std_mm < 0.2
    # RMS point error ~0.73 mm (0.5 tracker, 0.2 image origin, 2 deg axis error x 14 mm), less 7 parameters
    assert 0.45 < result.fre_mm < 0.9
    error = _target_error(result, frame, targets)
    assert error.mean() < 0.35 and error.max() < 0.55
    assert result.predicted_tre_mm is not None and result.predicted_tre_mm.shape == (6,)
    n = len(result.pairs)
    assert result.fle_mm == pytest.approx(result.fre_mm * np.sqrt(n / (n - 2)), rel=1e-6)
    unpaired = [w for w in result.warnings if "paired with no" in w]  # the unpaired points are named
    assert len(unpaired) == bool(result.unpaired_image_markers) + bool(result.unpaired_calibration_points)
    assert not result.outliers and [w for w in result.warnings if w not in unpaired] == []
    assert len(result.fre_curve[0]) == 31 and result.fre_curve[1].min() <= result.fre_mm + 0.01


def test_predicted_tre_matches_the_observed_error():
    observed, predicted = [], []
    for seed in range(30):
        problem = pairing_problem(seed + 300, missing_image=0, extra_image=0, missing_calibration=0,
                                  extra_calibration=0, image_error_mm=0.05, direction_error_deg=0.5)
        markers, calibration = _inputs(problem)
        targets = problem.frame.origins_image.mean(axis=0) + np.random.default_rng(seed).uniform(-120, 120, (5, 3))
        fixed = RegistrationSettings.from_settings({"sensor_offset_l_mm": problem.frame.l_mm})
        result = register(markers, calibration, MODEL, fixed, targets)
        observed.append(_target_error(result, problem.frame, targets) ** 2)
        predicted.append(result.predicted_tre_mm**2)
    ratio = np.sqrt(np.mean(observed) / np.mean(predicted))
    assert 0.75 < ratio < 1.3, ratio


def test_parallel_axes_leave_l_undetermined_and_are_refused():
    frame = make_frame(5)
    top = np.nonzero(np.abs(frame.axes_image @ frame.axes_image[np.argmax(frame.axes_image[:, 2])]) > 0.99)[0]
    problem = pairing_problem(5, frame=_subset(frame, top), missing_image=0, extra_image=0, missing_calibration=0,
                              extra_calibration=0)
    markers, calibration = _inputs(problem)
    with pytest.raises(NoSafeAnswerError, match="poorly determined"):
        register(markers, calibration, MODEL)
    result = register(markers, calibration, MODEL, RegistrationSettings.from_settings({"sensor_offset_l_mm": 14.0}))
    assert result.sensor_offset_l_mm == 14.0 and result.sensor_offset_fixed


def _subset(frame, keep):
    from synth_registration import SyntheticFrame

    return SyntheticFrame(frame.origins_image[keep], frame.axes_image[keep], frame.reference_to_image, frame.l_mm,
                          frame.pinholes_reference[keep], frame.axes_reference[keep])


def test_l_std_reflects_the_axis_geometry():
    rng = np.random.default_rng(0)
    origins = rng.uniform(-100, 100, (12, 3))
    spread_axes = rng.normal(size=(12, 3))
    spread_axes /= np.linalg.norm(spread_axes, axis=1, keepdims=True)
    tilt = np.array([0, 0, 1.0]) + 0.02 * rng.normal(size=(12, 3))
    tilt /= np.linalg.norm(tilt, axis=1, keepdims=True)
    values = {}
    for name, axes in (("spread", spread_axes), ("nearly parallel", tilt)):
        points = origins + 14.0 * axes + rng.normal(0, 0.3, (12, 3))
        values[name] = solve_sensor_offset(points, origins, axes, (11.0, 18.5))
    assert abs(values["spread"].l_mm - 14.0) < 0.3 and values["spread"].l_std_mm < 0.15
    assert values["nearly parallel"].l_std_mm > 1.0


def test_fre_limit_refuses():
    problem = pairing_problem(7)
    markers, calibration = _inputs(problem)
    with pytest.raises(NoSafeAnswerError, match="max_fre_mm"):
        register(markers, calibration, MODEL, RegistrationSettings.from_settings({"max_fre_mm": 0.2}))


def test_an_outlier_pair_is_flagged_and_can_be_left_out():
    problem = pairing_problem(8, missing_image=0, extra_image=0, missing_calibration=0, extra_calibration=0,
                              tracker_error_mm=0.3, image_error_mm=0.1)
    markers, calibration = _inputs(problem)
    bad = calibration.points[4]
    bad.position = bad.position + np.array([1.2, -1.0, 0.6])
    result = register(markers, calibration, MODEL)
    partner = int(np.nonzero(problem.image_truth == problem.calibration_truth[4])[0][0])
    assert result.outliers == [markers[partner]["id"]]
    assert any("outlier" in w for w in result.warnings)
    cleaned = register(markers, calibration, MODEL, RegistrationSettings.from_settings({"exclude_outliers": True}))
    assert cleaned.fre_mm < result.fre_mm
    assert any("left out" in w for w in cleaned.warnings)


def test_settings_are_checked():
    with pytest.raises(EMRegError, match="unknown key"):
        RegistrationSettings.from_settings({"max_fre": 2})
    with pytest.raises(EMRegError, match="true or false"):
        RegistrationSettings.from_settings({"exclude_outliers": "yes"})
    settings = RegistrationSettings.from_settings({"max_fre_mm": 1.5, "tracker_error_mm": 0.8})
    assert settings.max_fre_mm == 1.5 and settings.pairing.tracker_error_mm == 0.8


def test_files_round_trip_and_spec_layout(tmp_path):
    problem = pairing_problem(9)
    markers, calibration = _inputs(problem)
    targets = problem.frame.origins_image[:3] + 20.0
    result = register(markers, calibration, MODEL, None, targets)
    write_registration(result, tmp_path)
    document = json.loads((tmp_path / "registration.json").read_text())
    for key in ("ReferenceToImage", "sensor_offset_l_mm", "fre_mm", "pairs", "unpaired_image_markers",
                "unpaired_calibration_points"):
        assert key in document
    assert set(document["pairs"][0]) >= {"image_marker", "calibration_point", "residual_mm"}
    assert np.asarray(document["ReferenceToImage"]).shape == (4, 4)
    np.testing.assert_allclose(read_slicer_linear_transform(tmp_path / "ReferenceToImage.h5"),
                               result.reference_to_image, atol=1e-9)
    again = read_registration(tmp_path / "registration.json")
    np.testing.assert_allclose(again.reference_to_image, result.reference_to_image)
    assert again.pairs == json.loads(json.dumps(document["pairs"]))
    assert again.predicted_tre_mm is not None and len(again.predicted_tre_mm) == 3
    (tmp_path / "registration.json").write_text('{"ReferenceToImage": [[1, 0], [0, 1]]}')
    with pytest.raises(EMRegError, match="registration"):
        read_registration(tmp_path / "registration.json")


def test_register_from_a_recording_with_bumps():
    frame = make_frame(21)
    recording, _ = calibration_recording(frame.pinholes_reference, frame.axes_reference, seed=21, bumps=True,
                                         wild_fraction=0.03)
    calibration = calibrate_frame(recording, 1, 2, None)
    markers = [{"id": f"I{k + 1:02d}", "origin": o, "axis": a}
               for k, (o, a) in enumerate(zip(frame.origins_image, frame.axes_image, strict=True))]
    result = register(markers[3:], calibration, MODEL)
    assert all(int(p["image_marker"][1:]) == int(p["calibration_point"][1:]) for p in result.pairs)
    assert result.unpaired_calibration_points == ["P01", "P02", "P03"]
    assert abs(result.sensor_offset_l_mm - frame.l_mm) < 0.2


def _write_inputs(problem, folder):
    from EMRegModule.io.atomic import atomic_write_json
    from EMRegModule.io.calibration_json import write_frame_calibration

    markers, calibration = _inputs(problem)
    atomic_write_json(folder / "markers.json", {
        "coordinate_system": "LPS", "image": {"size": [10, 10, 10], "spacing": [1, 1, 1], "origin": [0, 0, 0],
                                              "direction": [1, 0, 0, 0, 1, 0, 0, 0, 1]},
        "markers": [{"id": m["id"], "origin": list(m["origin"]), "axis": list(m["axis"]), "volume_mm3": 1985.0,
                     "fit_rms_mm": 0.1} for m in markers],
        "rejected": []})
    write_frame_calibration(calibration, folder / "frame_calibration.json")


def test_emreg_register_command_and_its_refusal_of_a_symmetric_frame(tmp_path, capsys):
    from synth_registration import symmetric_layout

    from EMRegModule.cli.main import main

    good = tmp_path / "good"
    good.mkdir()
    _write_inputs(pairing_problem(10), good)
    args = ["register", "--markers", str(good / "markers.json"), "--calibration", str(good / "frame_calibration.json")]
    assert main([*args, "--out", str(good / "out"), "--quiet"]) == 0
    assert (good / "out" / "registration.json").is_file() and (good / "out" / "ReferenceToImage.h5").is_file()

    symmetric = tmp_path / "symmetric"
    symmetric.mkdir()
    frame = make_frame(7, layout=symmetric_layout())
    _write_inputs(pairing_problem(7, frame=frame, missing_image=0, extra_image=0, missing_calibration=0,
                                  extra_calibration=0), symmetric)
    out = symmetric / "out"
    out.mkdir()
    (out / "registration.json").write_text("{}")  # a stale result of an earlier run
    code = main(["register", "--markers", str(symmetric / "markers.json"), "--calibration",
                 str(symmetric / "frame_calibration.json"), "--out", str(out), "--quiet"])
    assert code == 3
    assert "ambiguous pairing" in capsys.readouterr().err
    assert not (out / "registration.json").exists() and not (out / "ReferenceToImage.h5").exists()


@pytest.mark.parametrize("seed", range(8))
def test_a_fixed_l_the_markers_contradict_is_said(seed):
    """Markers on several faces determine l themselves: a fixed l 1 mm off is named (the predicted TRE takes
    it as exact); the true l is not; markers on one face cannot tell, and say nothing."""
    problem = pairing_problem(seed + 700)
    markers, calibration = _inputs(problem)

    def fixed_l_warnings(l_mm):
        result = register(markers, calibration, MODEL, RegistrationSettings.from_settings({"sensor_offset_l_mm": l_mm}))
        return [w for w in result.warnings if "fixed sensor offset" in w]

    assert fixed_l_warnings(problem.frame.l_mm) == []
    (said,) = fixed_l_warnings(problem.frame.l_mm + 1.0)
    assert f"l = {problem.frame.l_mm + 1.0:.2f} mm" in said and "disagrees with the markers" in said
    frame = make_frame(seed)
    top = np.nonzero(np.abs(frame.axes_image @ frame.axes_image[np.argmax(frame.axes_image[:, 2])]) > 0.99)[0]
    one_face = pairing_problem(seed, frame=_subset(frame, top), missing_image=0, extra_image=0,
                               missing_calibration=0, extra_calibration=0)
    markers, calibration = _inputs(one_face)
    assert fixed_l_warnings(one_face.frame.l_mm + 1.0) == []


def test_unpaired_points_near_a_free_pinhole_join_the_distortion_test_nearest_first():
    """A calibration point the pairing left out, within the limit of a CT pinhole no pair took, is matched to the
    nearest one (each point and pinhole once, nearest pairs first) for the distortion test; farther ones are not."""
    from EMRegModule.core.registration import near_pinholes
    from EMRegModule.core.sensor_offset import OffsetSolution

    origins = np.array([[0.0, 0.0, 0.0], [50.0, 0.0, 0.0], [0.0, 50.0, 0.0], [50.0, 50.0, 0.0], [0.0, 0.0, 50.0]])
    axes = np.tile([0.0, 0.0, 1.0], (5, 1))
    solution = OffsetSolution(2.0, 0.1, 0.3, np.eye(4), np.zeros(1), np.zeros(1))
    pinholes = origins + 2.0 * axes  # Reference = image here
    points = pinholes + np.array([[0.1, 0.0, 0.0], [3.0, 0.0, 0.0], [0.0, 4.5, 0.0], [0.0, 0.0, 20.0],
                                  [2.5, 0.0, 0.0]])
    points[4] = pinholes[1] + [0.0, 2.0, 0.0]  # competes with point 1 for pinhole 1, and is nearer
    cal, images = near_pinholes(solution, points, origins, axes, {0}, {0}, 5.0)
    assert cal.tolist() == [4, 2] and images.tolist() == [1, 2]  # point 1 lost pinhole 1; point 3 is 20 mm off
    none = near_pinholes(solution, points, origins, axes, {0, 1, 2, 3, 4}, {0}, 5.0)
    assert none[0].size == 0 and none[1].size == 0
