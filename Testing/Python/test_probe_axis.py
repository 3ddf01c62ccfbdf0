"""Probe orientation is optional evidence: +X into the hole, out of it, or no direction at all.

The same calibration points with the directions of a probe whose +X points into the pinhole
(marker +Y = -X), out of it (+Y = +X) or absent must give the same pairing; a wrong sign must
never turn a good case into a refusal; a symmetric frame is refused whatever the convention.
"""

from __future__ import annotations

import numpy as np
import pytest
from synth_registration import calibration_recording, make_frame, pairing_problem, symmetric_layout

from EMRegModule.core.calibration import FrameCalibration, calibrate_frame
from EMRegModule.core.pairing import PairingSettings
from EMRegModule.core.probe_axis import check_probe_axis, pair_with_probe_axis
from EMRegModule.errors import EMRegError, NoSafeAnswerError
from EMRegModule.io.tracking_csv import format_tracking_csv, parse_tracking_csv
from EMRegModule.simulation.tracking import apply_probe_convention

L_RANGE = (11.0, 18.5)
SETTINGS = PairingSettings()


def _stored_directions(problem, convention: str) -> np.ndarray | None:
    """Directions as a calibration under the default assumption (+X into the hole) stores them,
    for a probe of the given convention: the +x_out probe's stored directions are flipped."""
    if convention == "none":
        return None
    return problem.directions_reference * (1.0 if convention == "+x_in" else -1.0)


@pytest.mark.parametrize("convention", ["+x_in", "+x_out", "none"])
def test_auto_pairs_every_convention_and_detects_it(convention):
    problem = pairing_problem(3)
    result, report = pair_with_probe_axis(problem.origins_image, problem.axes_image, problem.points_reference,
                                          _stored_directions(problem, convention), L_RANGE, SETTINGS, "auto")
    assert problem.correct(result.pairs) and result.support == problem.expected_pairs
    assert report.detected == convention
    assert report.pairing == ("distances only" if convention == "none" else "directions up to sign")
    if convention != "none":
        assert report.median_angle_deg < 5.0


def test_a_forced_wrong_sign_falls_back_to_distances_and_says_what_the_data_show():
    problem = pairing_problem(4)
    # The probe's +X points out of the hole, but the settings say into it.
    result, report = pair_with_probe_axis(problem.origins_image, problem.axes_image, problem.points_reference,
                                          -problem.directions_reference, L_RANGE, SETTINGS, "+x_in")
    assert problem.correct(result.pairs) and result.support == problem.expected_pairs
    assert report.pairing == "distances only" and report.detected == "+x_out"
    assert any("probe_axis = +x_out" in w for w in report.warnings)


def test_a_forced_right_sign_uses_signed_directions():
    problem = pairing_problem(5)
    result, report = pair_with_probe_axis(problem.origins_image, problem.axes_image, problem.points_reference,
                                          -problem.directions_reference, L_RANGE, SETTINGS, "+x_out")
    assert problem.correct(result.pairs) and report.pairing == "directions" and report.detected == "+x_out"
    assert not report.warnings


def test_directions_not_along_the_pinhole_are_ignored():
    problem = pairing_problem(6)
    rng = np.random.default_rng(0)
    random_axes = rng.normal(size=problem.directions_reference.shape)
    random_axes /= np.linalg.norm(random_axes, axis=1, keepdims=True)
    result, report = pair_with_probe_axis(problem.origins_image, problem.axes_image, problem.points_reference,
                                          random_axes, L_RANGE, SETTINGS, "auto")
    assert problem.correct(result.pairs) and result.support == problem.expected_pairs
    assert report.detected == "none" and report.pairing == "distances only"


@pytest.mark.parametrize("convention", ["+x_in", "+x_out", "none"])
def test_symmetric_frame_is_refused_in_every_convention(convention):
    frame = make_frame(7, layout=symmetric_layout())
    problem = pairing_problem(7, frame=frame, missing_image=1, extra_image=1, missing_calibration=0,
                              extra_calibration=0)
    for setting in ("auto", convention if convention != "none" else "none"):
        with pytest.raises(NoSafeAnswerError, match="ambiguous pairing"):
            pair_with_probe_axis(problem.origins_image, problem.axes_image, problem.points_reference,
                                 _stored_directions(problem, convention), L_RANGE, SETTINGS, setting)


def test_setting_values():
    assert check_probe_axis(None) == "auto" and check_probe_axis("+X_OUT") == "+x_out"
    with pytest.raises(EMRegError, match="probe_axis must be one of"):
        check_probe_axis("sideways")
    with pytest.raises(EMRegError, match="probe_axis must be one of"):
        check_probe_axis(1)


def test_position_only_probe_rows_round_trip_and_calibrate(tmp_path):
    frame = make_frame(9, n_markers=10)
    labels = [f"M{i + 1:02d}" for i in range(10)]
    recording, true_points = calibration_recording(frame.pinholes_reference, frame.axes_reference, seed=9,
                                                   labels=labels)
    position_only = apply_probe_convention(recording, "none")
    text = format_tracking_csv(position_only)
    probe_line = next(line for line in text.splitlines()[1:] if line.split(",")[1] == "2")
    assert probe_line.split(",")[5:8] == ["", "", ""]  # empty angle fields
    parsed = parse_tracking_csv(text, "position-only.csv")
    assert np.all(np.isnan(parsed.rotation[parsed.sensor == 2]))
    assert np.all(np.isfinite(parsed.rotation[parsed.sensor == 1]))
    calibration = calibrate_frame(parsed)
    assert calibration.direction_convention == "none"
    assert all(p.to_json()["direction"] is None for p in calibration.points)
    positions = calibration.positions
    assert np.max(np.linalg.norm(positions - true_points, axis=1)) < 0.2
    again = FrameCalibration.from_json(calibration.to_json())
    assert np.all(np.isnan(again.directions))


def test_a_partly_empty_orientation_is_an_error():
    text = ("time_s,sensor,x_mm,y_mm,z_mm,azimuth_deg,elevation_deg,roll_deg,quality,label\n"
            "0.0,1,0,0,0,0,0,0,0,\n0.0,2,1,2,3,10,,,0,\n")
    with pytest.raises(EMRegError, match="line 3 has some orientation fields empty"):
        parse_tracking_csv(text, "partial.csv")


def test_a_reference_without_orientation_is_an_error():
    text = ("time_s,sensor,x_mm,y_mm,z_mm,azimuth_deg,elevation_deg,roll_deg,quality,label\n"
            + "".join(f"{t / 80:.4f},1,0,0,0,,,,0,\n{t / 80:.4f},2,1,2,3,10,0,0,0,M1\n" for t in range(20)))
    with pytest.raises(EMRegError, match="reference sensor .*without an orientation"):
        calibrate_frame(parse_tracking_csv(text, "noref.csv"))


# --- the simulated case in the three conventions, through the emreg commands --------------------

CONVENTIONS = ("+x_in", "+x_out", "none")


@pytest.fixture(scope="module")
def three_conventions(standard_case, tmp_path_factory):
    """The standard case's markers detected once; its calibration recorded (unlabelled, the frame
    bumped twice) by a probe of each convention; ``emreg calibrate`` and ``emreg register`` on each."""
    from conftest import CI_CASE_OPTIONS, STANDARD_SEED

    from EMRegModule.cli.main import main
    from EMRegModule.simulation.case import simulate_recordings

    root = tmp_path_factory.mktemp("probe_conventions")
    assert main(["detect", str(standard_case), "--out", str(root / "detect"), "--quiet"]) == 0
    outputs = {}
    for convention in CONVENTIONS:
        folder = root / convention
        simulate_recordings(folder, seed=STANDARD_SEED, calibration_labels=False, n_bumps=2,
                            probe_axis=convention, **CI_CASE_OPTIONS)
        out = folder / "out"
        assert main(["calibrate", str(folder / "calibration.csv"), "--out", str(out), "--quiet"]) == 0
        assert main(["register", "--markers", str(root / "detect" / "markers.json"), "--calibration",
                     str(out / "frame_calibration.json"), "--out", str(out), "--quiet"]) == 0
        outputs[convention] = out
    return outputs


def _json(path):
    import json

    return json.loads(path.read_text())


def test_three_conventions_give_the_same_pairing_l_and_registration(three_conventions, standard_case):
    from conftest import load_truth

    from EMRegModule.core.transforms import apply_transform, invert_rigid

    truth = load_truth(standard_case)
    true_reference_to_image = np.asarray(truth["ReferenceToImage"])
    targets_image = np.array([t["position"] for t in truth["targets"]])
    targets_reference = apply_transform(invert_rigid(true_reference_to_image), targets_image)
    results = {c: _json(out / "registration.json") for c, out in three_conventions.items()}
    calibrations = {c: _json(out / "frame_calibration.json") for c, out in three_conventions.items()}
    pairs = {c: sorted((p["image_marker"], p["calibration_point"]) for p in r["pairs"]) for c, r in results.items()}
    assert pairs["+x_in"] == pairs["+x_out"] == pairs["none"]
    true_l = truth["sensor_offset_l_mm"]
    mapped = {}
    for convention, result in results.items():
        assert result["probe_axis"]["detected"] == convention
        assert calibrations[convention]["probe_axis"]["points_with_direction"] == (
            0 if convention == "none" else len(calibrations[convention]["points"]))
        assert abs(result["sensor_offset_l_mm"] - true_l) < 0.3
        mapped[convention] = apply_transform(np.asarray(result["ReferenceToImage"]), targets_reference)
        error = np.linalg.norm(mapped[convention] - targets_image, axis=1)
        assert error.max() < 1.0, (convention, error)
    for convention in ("+x_out", "none"):
        assert abs(results[convention]["sensor_offset_l_mm"] - results["+x_in"]["sensor_offset_l_mm"]) < 0.05
        assert np.max(np.linalg.norm(mapped[convention] - mapped["+x_in"], axis=1)) < 0.05
    # the pairing itself: every pair is a true one, and every marker both in the CT and calibrated is paired
    markers = truth["markers"]
    expected = sum(1 for m in markers if m["in_ct"] and m["calibrated"])
    assert len(pairs["none"]) == expected
    detected = {m["id"]: np.asarray(m["origin"]) for m in
                _json(three_conventions["none"].parent.parent / "detect" / "markers.json")["markers"]}
    points = {p["label"]: np.asarray(p["position"]) for p in calibrations["none"]["points"]}
    for image_id, point_label in pairs["none"]:
        by_origin = min(markers, key=lambda m: np.linalg.norm(np.asarray(m["origin"]) - detected[image_id]))
        by_pinhole = min(markers, key=lambda m: np.linalg.norm(np.asarray(m["pinhole_in_reference"])
                                                               - points[point_label]))
        assert by_origin["label"] == by_pinhole["label"]
