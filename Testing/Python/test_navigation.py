"""Offline navigation: Eq. 12 vectorised, the single-pose function, navigation.csv, emreg navigate."""

from __future__ import annotations

import csv

import numpy as np
import pytest
from synth_registration import calibration_recording, make_frame

from EMRegModule.core.navigation import navigate_recording, probe_to_image
from EMRegModule.core.tracking import TrackingRecording
from EMRegModule.core.transforms import apply_transform, invert_rigid, make_transform, random_rotation
from EMRegModule.errors import EMRegError
from EMRegModule.io.navigation_csv import write_navigation_csv
from EMRegModule.io.tracking_csv import write_tracking_csv


@pytest.fixture(scope="module")
def case():
    frame = make_frame(31)
    targets_image = frame.origins_image[:4] + 30.0 * frame.axes_image[:4]
    targets_reference = apply_transform(invert_rigid(frame.reference_to_image), targets_image)
    recording, truth = calibration_recording(targets_reference, frame.axes_reference[:4], seed=31, bumps=True,
                                             labels=["T1", "T2", "T3", "T4"], dwell_s=0.5)
    return frame, recording, truth


def test_single_pose_is_paper_eq_12():
    rng = np.random.default_rng(0)
    reference_to_image = make_transform(random_rotation(rng), rng.uniform(-100, 100, 3))
    reference_to_tracker = make_transform(random_rotation(rng), rng.uniform(-300, 300, 3))
    probe_in_reference = make_transform(random_rotation(rng), [10.0, 20.0, 30.0])
    probe_to_tracker = reference_to_tracker @ probe_in_reference
    mapped = probe_to_image(reference_to_image, reference_to_tracker, probe_to_tracker)
    np.testing.assert_allclose(mapped, reference_to_image @ probe_in_reference, atol=1e-9)
    np.testing.assert_allclose(mapped[:3, 3], apply_transform(reference_to_image, [10.0, 20.0, 30.0]), atol=1e-9)
    stacked = probe_to_image(reference_to_image, np.stack([reference_to_tracker] * 3), np.stack([probe_to_tracker] * 3))
    np.testing.assert_allclose(stacked, np.stack([mapped] * 3), atol=1e-9)


def test_recording_maps_every_probe_sample_like_the_per_sample_formula(case):
    frame, recording, truth = case
    result = navigate_recording(recording, frame.reference_to_image, 1, 2)
    assert len(result) == np.count_nonzero(recording.sensor == 2)
    reference = recording.for_sensor(1)
    probe = recording.for_sensor(2)
    for k in range(0, len(result), 97):
        expected = probe_to_image(frame.reference_to_image, reference.transforms()[k], probe.transforms()[k])
        np.testing.assert_allclose(result.probe_to_image[k], expected, atol=1e-9)
    # In the dwells the probe sits at its (biased) target, whatever the frame did in between.
    t1 = result.label == "T1"
    target = apply_transform(frame.reference_to_image, truth[0])
    assert np.linalg.norm(np.median(result.position_mm[t1], axis=0) - target) < 0.05


def test_probe_samples_without_a_reference_partner_are_dropped(case):
    frame, recording, _ = case
    keep = np.ones(len(recording), dtype=bool)
    reference_rows = np.nonzero(recording.sensor == 1)[0]
    keep[reference_rows[::10]] = False
    thinned = recording.select(keep)
    result = navigate_recording(thinned, frame.reference_to_image, 1, 2)
    assert len(result) == np.count_nonzero(recording.sensor == 2) - len(reference_rows[::10])


def test_missing_sensor_is_a_clear_error(case):
    frame, recording, _ = case
    with pytest.raises(EMRegError, match="reference sensor on port 3"):
        navigate_recording(recording, frame.reference_to_image, 3, 2)


def test_navigation_csv(tmp_path, case):
    frame, recording, _ = case
    result = navigate_recording(recording, frame.reference_to_image, 1, 2)
    path = tmp_path / "navigation.csv"
    write_navigation_csv(result, path)
    with path.open() as f:
        rows = list(csv.reader(f))
    assert rows[0][:5] == ["time_s", "x_mm", "y_mm", "z_mm", "label"]  # the spec's columns first, then "status"
    assert rows[0][5:] == ["status"] and {row[5] for row in rows[1:]} == {"OK"}  # not judged: OK
    assert len(rows) == len(result) + 1
    positions = np.array([[float(v) for v in row[1:4]] for row in rows[1:]])
    np.testing.assert_allclose(positions, result.position_mm, atol=1e-4)
    assert {row[4] for row in rows[1:]} == {"", "T1", "T2", "T3", "T4"}


def test_emreg_navigate_replay(tmp_path, case):
    from EMRegModule.cli.main import main
    from EMRegModule.core.registration import RegistrationResult
    from EMRegModule.io.registration_files import write_registration

    frame, recording, _ = case
    write_registration(RegistrationResult(frame.reference_to_image, 14.0, 0.5, []), tmp_path / "reg")
    source = tmp_path / "navigation_input.csv"
    write_tracking_csv(recording, source)
    code = main(["navigate", "--registration", str(tmp_path / "reg" / "registration.json"),
                 "--source", f"replay:{source}", "--out", str(tmp_path / "out"), "--quiet"])
    assert code == 0
    rows = (tmp_path / "out" / "navigation.csv").read_text().splitlines()
    assert len(rows) == np.count_nonzero(recording.sensor == 2) + 1


def test_empty_recording_rows_are_refused():
    empty = TrackingRecording(np.zeros(0), np.zeros(0), np.zeros((0, 3)), np.zeros((0, 3, 3)), np.zeros(0),
                              np.zeros(0))
    with pytest.raises(EMRegError):
        navigate_recording(empty, np.eye(4))
