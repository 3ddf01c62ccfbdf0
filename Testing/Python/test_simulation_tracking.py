"""The simulator's tracking recordings map back to the ground truth within the tracker's noise."""

from __future__ import annotations

import numpy as np
import pytest
from conftest import load_truth

from EMRegModule.core.tracking import probe_in_reference
from EMRegModule.core.transforms import angle_between_deg, apply_transform
from EMRegModule.io.case import open_case
from EMRegModule.io.markups import read_markups
from EMRegModule.io.tracking_csv import read_tracking_csv
from EMRegModule.simulation.case import board_holes, simulate_case

GOOD_QUALITY = 10.0


def _dwell_means(samples, dwells: list[dict]) -> list[tuple[str, np.ndarray, np.ndarray]]:
    """(name, median position, mean +X direction) of the good samples in each truth dwell."""
    out = []
    for dwell in dwells:
        inside = (samples.time_s >= dwell["start_s"] - 1e-6) & (samples.time_s <= dwell["end_s"] + 1e-6)
        good = inside & (np.nan_to_num(samples.quality) < GOOD_QUALITY)
        assert good.sum() >= 0.9 * inside.sum() >= 40, dwell
        direction = samples.direction[good].mean(axis=0)
        out.append((dwell["name"], np.median(samples.position_mm[good], axis=0), direction / np.linalg.norm(direction)))
    return out


def test_calibration_dwells_sit_at_the_pinholes(standard_case):
    truth = load_truth(standard_case)
    recording = read_tracking_csv(standard_case / "calibration.csv")
    assert recording.sensors == [1, 2]
    times = recording.time_s.reshape(-1, 2)
    assert np.all(times[:, 0] == times[:, 1]) and np.allclose(np.diff(times[:, 0]), 1 / 80, atol=1e-4)
    samples = probe_in_reference(recording, 1, 2)
    markers = {m["label"]: m for m in truth["markers"]}
    labels = {str(v) for v in samples.label if v}
    assert labels == {m["label"] for m in truth["markers"] if m["calibrated"]}
    reference_to_frame = np.asarray(truth["frame"]["ReferenceToFrame"])
    errors = []
    for name, position, direction in _dwell_means(samples, truth["calibration"]["dwells"]):
        labelled = samples.label[(samples.time_s >= 0) & (samples.label == name)]
        assert len(labelled) >= 80  # 1..2 s at 80 Hz
        errors.append(np.linalg.norm(position - markers[name]["pinhole_in_reference"]))
        # probe +X goes into the hole: the pinhole direction (marker +Y) is -X
        axis_frame = np.linalg.inv(np.asarray(truth["frame"]["FrameToImage"]))[:3, :3] @ markers[name]["axis"]
        axis_reference = reference_to_frame[:3, :3].T @ axis_frame
        assert angle_between_deg(-direction, axis_reference) < 1.5
    errors = np.asarray(errors)
    assert errors.max() < 1.0
    assert 0.05 < errors.mean() < 0.6  # the per-dwell error is there, and small


def test_calibration_has_transitions_jitter_and_bad_samples(standard_case):
    recording = read_tracking_csv(standard_case / "calibration.csv")
    probe = recording.for_sensor(2)
    moving = probe.label == ""
    assert 0.3 < moving.mean() < 0.8
    speed = np.linalg.norm(np.diff(probe.position_mm, axis=0), axis=1) * 80
    assert np.median(speed[moving[1:]]) > 30  # mm/s while moving between pinholes
    quality = probe.quality
    assert np.mean(quality <= 3) > 0.99 and np.any(quality >= 40)
    bad = quality >= 40
    still = (~moving) & ~bad
    same_dwell = still[1:] & still[:-1] & (probe.label[1:] == probe.label[:-1])
    jitter = np.std(np.diff(probe.position_mm, axis=0)[same_dwell], axis=0)  # sample-to-sample, per axis
    assert np.all((jitter > 0.01) & (jitter < 0.2)), jitter


def test_hard_calibration_is_unlabelled_and_bumped_but_consistent_in_reference(hard_case):
    truth = load_truth(hard_case)
    recording = read_tracking_csv(hard_case / "calibration.csv")
    assert not any(recording.label)
    assert truth["calibration"]["bumps"] == 2
    dwells = truth["calibration"]["dwells"]
    reference_positions = np.array([np.asarray(d["ReferenceToTracker"])[:3, 3] for d in dwells])
    assert np.ptp(reference_positions, axis=0).max() > 2.0  # the frame moved in the tracker's field
    samples = probe_in_reference(recording, 1, 2)
    markers = {m["label"]: m for m in truth["markers"]}
    assert {d["name"] for d in dwells} == {m["label"] for m in truth["markers"] if m["calibrated"]}
    errors = [np.linalg.norm(p - markers[name]["pinhole_in_reference"]) for name, p, _ in _dwell_means(samples, dwells)]
    assert max(errors) < 1.0


@pytest.mark.parametrize("case_name", ["standard_case", "hard_case"])
def test_navigation_dwells_map_to_the_targets(case_name, request):
    case = request.getfixturevalue(case_name)
    truth = load_truth(case)
    labels, positions = read_markups(case / "targets.mrk.json")
    assert labels == [f"T{i}" for i in range(1, 7)]
    assert np.allclose(positions, [t["position"] for t in truth["targets"]], atol=1e-6)
    recording = read_tracking_csv(case / "navigation.csv")
    samples = probe_in_reference(recording, 1, 2)
    reference_to_image = np.asarray(truth["ReferenceToImage"])
    targets = dict(zip(labels, positions, strict=True))
    errors = {label: [] for label in labels}
    for name, position, _ in _dwell_means(samples, truth["navigation"]["dwells"]):
        errors[name].append(np.linalg.norm(apply_transform(reference_to_image, position) - targets[name]))
    for label, values in errors.items():
        assert len(values) == 15, label
        assert max(values) < 1.5, (label, values)
    assert 0.1 < np.mean(np.concatenate(list(errors.values()))) < 0.8
    # the frame was moved elsewhere in the tracker's field for navigation
    calibration_reference = np.asarray(truth["calibration"]["dwells"][0]["ReferenceToTracker"])
    navigation_reference = np.asarray(truth["navigation"]["ReferenceToTracker"])
    assert np.linalg.norm(calibration_reference[:3, 3] - navigation_reference[:3, 3]) > 20.0
    assert {str(v) for v in recording.label if v} == set(labels)


@pytest.mark.parametrize("case_name", ["standard_case", "hard_case"])
def test_board_edges(case_name, request):
    case = request.getfixturevalue(case_name)
    truth = load_truth(case)
    settings = open_case(case).settings
    assert (settings.sensors.reference, settings.sensors.probe) == (1, 2)
    assert settings.board.edges_mm == pytest.approx(truth["board"]["edges_mm"])
    assert truth["board"]["edges_mm"] == pytest.approx([75.3, 60.4, 75.5, 60.4])
    recording = read_tracking_csv(case / "board.csv")
    samples = probe_in_reference(recording, 1, 2)
    holes = np.asarray(truth["board"]["holes_in_reference"])
    per_hole: dict[str, list[np.ndarray]] = {f"H{i}": [] for i in range(1, 5)}
    for name, position, _ in _dwell_means(samples, truth["board"]["dwells"]):
        per_hole[name].append(position)
        assert np.linalg.norm(position - holes[int(name[1]) - 1]) < 1.2
    assert [len(v) for v in per_hole.values()] == [60] * 4
    rounds = np.stack([np.asarray(per_hole[f"H{i}"]) for i in range(1, 5)], axis=1)  # (60, 4, 3)
    edges = np.linalg.norm(rounds - np.roll(rounds, -1, axis=1), axis=2)  # L1..L4 per round
    assert np.allclose(edges.mean(axis=0), truth["board"]["edges_mm"], atol=0.15)
    assert np.all((edges.std(axis=0) > 0.1) & (edges.std(axis=0) < 0.6))


def test_board_hole_geometry():
    holes = board_holes([75.3, 60.4, 75.5, 60.4])
    edges = np.linalg.norm(holes - np.roll(holes, -1, axis=0), axis=1)
    assert np.allclose(edges, [75.3, 60.4, 75.5, 60.4], atol=1e-9)
    assert np.allclose(holes.mean(axis=0), 0.0) and np.allclose(holes[:, 2], 0.0)


def test_noise_free_recordings_are_exact(tmp_path):
    """With the tracker's errors off, every dwell sample is the truth itself (frames and angle conventions)."""
    case = tmp_path / "exact"
    truth = simulate_case(case, seed=9, difficulty="hard", spacing_mm=2.0, tracker_noise_scale=0.0,
                          bad_sample_rate=0.0, frame_size_mm=(160.0, 160.0, 100.0), n_markers=8,
                          navigation_rounds=1, board_rounds=1, n_targets=3, n_decoys=0)
    markers = {m["label"]: m for m in truth["markers"]}
    reference_to_frame = np.asarray(truth["frame"]["ReferenceToFrame"])
    image_to_frame = np.linalg.inv(np.asarray(truth["frame"]["FrameToImage"]))
    samples = probe_in_reference(read_tracking_csv(case / "calibration.csv"), 1, 2)
    for dwell in truth["calibration"]["dwells"]:
        inside = (samples.time_s >= dwell["start_s"] - 1e-6) & (samples.time_s <= dwell["end_s"] + 1e-6)
        pinhole = markers[dwell["name"]]["pinhole_in_reference"]
        assert np.abs(samples.position_mm[inside] - pinhole).max() < 2e-3  # CSV keeps 4 decimals
        axis_reference = reference_to_frame[:3, :3].T @ image_to_frame[:3, :3] @ markers[dwell["name"]]["axis"]
        assert np.abs(samples.direction[inside] + axis_reference).max() < 1e-4  # probe +X = marker -Y
    samples = probe_in_reference(read_tracking_csv(case / "navigation.csv"), 1, 2)
    reference_to_image = np.asarray(truth["ReferenceToImage"])
    targets = {t["label"]: np.asarray(t["position"]) for t in truth["targets"]}
    for dwell in truth["navigation"]["dwells"]:
        inside = (samples.time_s >= dwell["start_s"] - 1e-6) & (samples.time_s <= dwell["end_s"] + 1e-6)
        mapped = apply_transform(reference_to_image, samples.position_mm[inside])
        assert np.linalg.norm(mapped - targets[dwell["name"]], axis=1).max() < 0.5  # hand tremor only
