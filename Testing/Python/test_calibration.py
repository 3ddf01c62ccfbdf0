"""Frame calibration: dwells by label or found automatically, robust averages, revisits, files, CLI."""

from __future__ import annotations

import json

import numpy as np
import pytest
from synth_registration import calibration_recording, make_frame

from EMRegModule.cli.main import main
from EMRegModule.core.calibration import FrameCalibration, calibrate_frame
from EMRegModule.core.dwell import DwellSettings, find_dwells, good_quality_mask, robust_mean
from EMRegModule.core.tracking import TrackingRecording
from EMRegModule.core.transforms import angle_between_deg, make_transform, random_rotation
from EMRegModule.errors import EMRegError
from EMRegModule.io.calibration_json import read_frame_calibration, write_frame_calibration
from EMRegModule.io.tracking_csv import write_tracking_csv
from EMRegModule.settings import CalibrationSettings, Settings

LABELS = [f"M{i + 1:02d}" for i in range(28)]


@pytest.fixture(scope="module")
def frame():
    return make_frame(seed=11)


def _check_points(calibration: FrameCalibration, true_points: np.ndarray, true_axes: np.ndarray,
                  tolerance_mm: float = 0.06) -> None:
    error = np.linalg.norm(calibration.positions - true_points, axis=1)
    assert error.max() < tolerance_mm, error
    assert angle_between_deg(calibration.directions, true_axes).max() < 0.5


def test_labelled_recording_gives_one_point_per_label(frame):
    recording, true_points = calibration_recording(frame.pinholes_reference, frame.axes_reference, seed=1,
                                                   labels=LABELS)
    calibration = calibrate_frame(recording, 1, 2, None)
    assert calibration.labels == LABELS
    assert calibration.labelled
    _check_points(calibration, true_points, frame.axes_reference)
    for point in calibration.points:
        assert 100 <= point.samples <= 120
        assert 0.1 < point.std_mm < 0.3  # jitter 0.1 mm per axis -> RMS 3D spread ~0.17 mm


def test_unlabelled_recording_with_bumps_wild_samples_bad_quality_and_short_stops(frame):
    recording, true_points = calibration_recording(
        frame.pinholes_reference, frame.axes_reference, seed=2, bumps=True, wild_fraction=0.05,
        bad_quality_fraction=0.05, short_stops=True)
    calibration = calibrate_frame(recording, 1, 2, None)
    assert not calibration.labelled
    assert calibration.labels == [f"P{i + 1:02d}" for i in range(28)]  # time order of the visits
    _check_points(calibration, true_points, frame.axes_reference, tolerance_mm=0.08)
    assert calibration.warnings == []


def test_moving_the_frame_or_transmitter_changes_nothing(frame):
    recording, _ = calibration_recording(frame.pinholes_reference, frame.axes_reference, seed=3)
    reference = calibrate_frame(recording, 1, 2, None)
    # Move both sensors rigidly by a different tracker-frame motion in each second of the recording.
    rng = np.random.default_rng(0)
    seconds = int(recording.time_s.max()) + 1
    motions = [make_transform(random_rotation(rng, 20), rng.uniform(-50, 50, 3)) for _ in range(seconds)]
    which = (recording.time_s // 1.0).astype(int)
    moved_transforms = np.einsum("nij,njk->nik", np.asarray(motions)[which], recording.transforms())
    moved = TrackingRecording(recording.time_s, recording.sensor, moved_transforms[:, :3, 3],
                              moved_transforms[:, :3, :3], recording.quality, recording.label)
    again = calibrate_frame(moved, 1, 2, None)
    assert again.labels == reference.labels
    np.testing.assert_allclose(again.positions, reference.positions, atol=1e-6)


def test_wild_samples_do_not_move_the_average(frame):
    clean, true_points = calibration_recording(frame.pinholes_reference, frame.axes_reference, seed=4,
                                               labels=LABELS)
    wild, wild_true_points = calibration_recording(frame.pinholes_reference, frame.axes_reference, seed=4,
                                                   labels=LABELS, wild_fraction=0.15)
    assert np.linalg.norm(calibrate_frame(clean, 1, 2, None).positions - true_points, axis=1).max() < 0.06
    assert np.linalg.norm(calibrate_frame(wild, 1, 2, None).positions - wild_true_points, axis=1).max() < 0.08
    # A plain mean would be pulled by the wild samples (5 mm sigma): the robust one is not.
    points = np.vstack([np.zeros((90, 3)), np.full((10, 3), 8.0)])
    assert np.linalg.norm(robust_mean(points).mean) < 1e-9
    assert np.linalg.norm(points.mean(axis=0)) > 1.0


def test_revisits_merge_into_one_point(frame):
    order = list(range(28)) + [5, 17]
    for labels in (LABELS, None):
        recording, _ = calibration_recording(frame.pinholes_reference, frame.axes_reference, seed=5,
                                             labels=labels, visit_order=order)
        calibration = calibrate_frame(recording, 1, 2, None)
        assert len(calibration.points) == 28
        visits = {p.label: p.visits for p in calibration.points}
        assert sorted(visits.values()) == [1] * 26 + [2, 2]
        error = np.linalg.norm(calibration.positions - frame.pinholes_reference, axis=1)
        assert error.max() < 0.6  # per-visit bias 0.3 mm RMS


def test_revisit_disagreeing_is_flagged(frame):
    recording, _ = calibration_recording(frame.pinholes_reference[:6], frame.axes_reference[:6], seed=6,
                                         labels=LABELS[:6], visit_order=[0, 1, 2, 3, 4, 5, 2], bias_mm=0.0)
    # Shift the probe in the second visit of M03 by 2 mm along the hole (probe not fully inserted).
    probe = (recording.sensor == 2) & (recording.label == "M03")
    times = recording.time_s[probe]
    second = probe & (recording.time_s > times[np.argmax(np.diff(times)) ])
    recording.position_mm[second] += 2.0 * (recording.rotation[second][:, :, 0])
    calibration = calibrate_frame(recording, 1, 2, None)
    m03 = calibration.points[2]
    assert m03.visits == 2 and "disagree" in m03.warning
    assert any("M03" in w for w in calibration.warnings)


def test_min_duration_setting_and_short_dwells(frame):
    recording, _ = calibration_recording(frame.pinholes_reference[:5], frame.axes_reference[:5], seed=7,
                                         dwell_s=0.4)
    with pytest.raises(EMRegError, match="no dwell"):
        calibrate_frame(recording, 1, 2, None)
    calibration = calibrate_frame(recording, 1, 2, CalibrationSettings(min_duration_s=0.3))
    assert len(calibration.points) == 5


def test_settings_are_checked():
    with pytest.raises(EMRegError, match=r"\[calibration\] unknown key min_duration; known: .*min_duration_s"):
        Settings.from_mapping({"calibration": {"min_duration": 1.0}})
    with pytest.raises(EMRegError, match="positive"):
        DwellSettings.from_settings({"still_radius_mm": -1})
    assert DwellSettings.from_settings({"min_samples": 12.0}).min_samples == 12


def test_quality_filter():
    quality = np.array([0.1, 0.2, 0.15, 0.3, 40.0, np.nan, 0.25])
    assert good_quality_mask(quality).tolist() == [True, True, True, True, False, True, True]
    assert good_quality_mask(quality, max_quality=0.2).tolist() == [True, True, True, False, False, True, False]


def test_find_dwells_on_a_plain_track():
    t = np.arange(0, 6, 1 / 80)
    position = np.zeros((len(t), 3))
    position[t >= 2] = [30.0, 0, 0]  # jump: two dwells of 2 and 4 s
    position[(t >= 1.9) & (t < 2.0)] = np.linspace([0, 0, 0], [30, 0, 0], 8)
    position += np.random.default_rng(0).normal(0, 0.05, position.shape)
    dwells = find_dwells(t, position)
    assert len(dwells) == 2
    assert dwells[0].start_s < 0.2 and 1.7 < dwells[0].end_s < 2.0
    assert 2.0 <= dwells[1].start_s < 2.3 and dwells[1].end_s > 5.8


def test_file_round_trip_and_spec_layout(tmp_path, frame):
    recording, _ = calibration_recording(frame.pinholes_reference[:4], frame.axes_reference[:4], seed=8,
                                         labels=LABELS[:4])
    calibration = calibrate_frame(recording, 1, 2, None)
    path = tmp_path / "frame_calibration.json"
    write_frame_calibration(calibration, path)
    document = json.loads(path.read_text())
    assert document["reference_sensor"] == 1 and document["probe_sensor"] == 2
    assert set(document["points"][0]) >= {"label", "position", "direction", "samples", "std_mm"}
    again = read_frame_calibration(path)
    np.testing.assert_allclose(again.positions, calibration.positions)
    np.testing.assert_allclose(again.directions, calibration.directions)
    assert again.labels == calibration.labels
    path.write_text('{"points": [{"label": "A"}]}')
    with pytest.raises(EMRegError, match="frame_calibration.json"):
        read_frame_calibration(path)
    with pytest.raises(EMRegError, match="not found"):
        read_frame_calibration(tmp_path / "missing.json")


def test_emreg_calibrate_command(tmp_path, frame, capsys):
    recording, true_points = calibration_recording(frame.pinholes_reference[:6], frame.axes_reference[:6],
                                                   seed=9, bumps=True)
    csv = tmp_path / "calibration.csv"
    write_tracking_csv(recording, csv)
    # Swap the ports on the command line: nothing is found on the wrong port mapping.
    assert main(["calibrate", str(csv), "--out", str(tmp_path / "out"), "--quiet"]) == 0
    document = json.loads((tmp_path / "out" / "frame_calibration.json").read_text())
    positions = np.array([p["position"] for p in document["points"]])
    assert np.linalg.norm(positions - true_points, axis=1).max() < 0.1
    assert main(["calibrate", str(csv), "--out", str(tmp_path / "out2"), "--probe-sensor", "3", "--quiet"]) == 2
    assert "probe sensor on port 3" in capsys.readouterr().err


def test_two_labels_at_one_pinhole_are_flagged(frame):
    points = frame.pinholes_reference[:4].copy()
    points[3] = points[1] + [1.0, 0.5, 0.0]  # "M04" recorded in M02's pinhole
    recording, _ = calibration_recording(points, frame.axes_reference[:4], seed=12, labels=LABELS[:4])
    calibration = calibrate_frame(recording, 1, 2, None)
    assert len(calibration.points) == 4
    assert any("M02 and M04" in w for w in calibration.warnings)
