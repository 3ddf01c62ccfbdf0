"""Field distortion: the simulator's induced-dipole model, its detection at registration, and what a user sees.

The end-to-end case is CI-sized (a 220 mm frame with 16 markers, 1 mm voxels) with a steel rod leaving 1.0 mm
RMS non-rigid error at the pinholes; the clean case is conftest's ``small_case``. The study (``emreg study
trust``) measures the rates; these tests assert what a single case must show.
"""

from __future__ import annotations

import json
import re
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest
from conftest import SMALL_CASE_OPTIONS
from scipy.optimize import least_squares

from EMRegModule.cli.main import main
from EMRegModule.core.distortion import DistortionEstimate, NoisePrior, estimate_distortion
from EMRegModule.core.em_field import coil_field, induced_coupling, position_error
from EMRegModule.core.transforms import apply_transform, fit_rigid, invert_rigid, make_transform, random_rotation
from EMRegModule.io.registration_files import read_registration
from EMRegModule.simulation.case import load_truth, simulate_case
from EMRegModule.simulation.distortion import FieldDistortion, nonrigid_errors, place_object

DISTORTED_OPTIONS = {**SMALL_CASE_OPTIONS, "frame_size_mm": (220.0, 220.0, 140.0), "n_markers": 16}


def _frame(rng: np.random.Generator, n: int = 16) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Pinholes (n, 3) and marker axes of a 200 mm frame (Reference frame), and a ReferenceToTracker 330 mm away."""
    points = rng.uniform(-100.0, 100.0, (n, 3)) * np.array([1.0, 1.0, 0.5])
    axes = rng.normal(size=(n, 3))
    axes /= np.linalg.norm(axes, axis=1)[:, None]
    reference_to_tracker = make_transform(random_rotation(rng, 180.0), [330.0, 20.0, 10.0])
    return points, axes, reference_to_tracker


def test_first_order_position_error_matches_the_exact_inversion():
    """The tracker's free-space solve of a distorted coupling, done exactly, moves the position as the first-order
    model says (within 5 % at a 3-6 mm error, 330 mm from the transmitter)."""
    sensor = np.array([[330.0, 40.0, -20.0]])
    rod = np.eye(3) + 5.0 * np.outer([0.6, 0.0, 0.8], [0.6, 0.0, 0.8])
    unit = np.linalg.norm(position_error(sensor, sensor[0] + [60.0, -50.0, 40.0], rod))
    distortion = FieldDistortion(sensor[0] + [60.0, -50.0, 40.0], rod * 4.0 / unit)
    first_order = position_error(sensor, distortion.object_mm, distortion.polarisability)[0]
    measured = coil_field(sensor) + induced_coupling(sensor, distortion.object_mm, distortion.polarisability)
    invariant = (np.swapaxes(measured, -1, -2) @ measured)[0]
    scale = 1.0 / np.linalg.norm(invariant)

    def mismatch(x: np.ndarray) -> np.ndarray:
        field = coil_field(x[None])[0]
        return ((field.T @ field) - invariant).ravel() * scale

    exact = least_squares(mismatch, sensor[0], xtol=1e-12, ftol=1e-15, gtol=1e-15).x - sensor[0]
    assert 3.0 < np.linalg.norm(exact) < 6.0 and np.linalg.norm(first_order) == pytest.approx(4.0)
    assert np.linalg.norm(first_order - exact) < 0.05 * np.linalg.norm(exact)


def test_rod_is_scaled_to_the_requested_nonrigid_size_and_rolled_in_when_asked():
    rng = np.random.default_rng(5)
    points, _, reference_to_tracker = _frame(rng)
    distortion = place_object(rng, points, reference_to_tracker, np.eye(4), 1.0, onset_s=10.0)
    raw, nonrigid = nonrigid_errors(distortion, points, reference_to_tracker, np.eye(4))
    assert np.sqrt(np.mean(np.sum(nonrigid**2, axis=1))) == pytest.approx(1.0, rel=1e-3)
    assert np.max(np.linalg.norm(raw, axis=1)) > np.max(np.linalg.norm(nonrigid, axis=1)) > 1.0
    poses = np.broadcast_to(reference_to_tracker, (3, 4, 4))
    moved = distortion.distort(np.array([9.0, 11.0, 13.0]), poses)
    assert np.allclose(moved[0], poses[0])  # before the rod is rolled in
    shift = np.linalg.norm(moved[1:, :3, 3] - poses[1:, :3, 3], axis=1)
    assert 0 < shift[0] < shift[1]  # half-way in, then fully in


def _residuals(rng: np.random.Generator, size_mm: float, outlier_mm: float = 0.0):
    """Calibration points with 0.25 mm noise, plus a rod's non-rigid error of ``size_mm`` RMS or one probe not
    fully inserted by ``outlier_mm`` (along its marker's axis); the transmitter's pose per point."""
    points, axes, reference_to_tracker = _frame(rng)
    residuals = rng.normal(0.0, 0.25, points.shape)
    if size_mm:
        distortion = place_object(rng, points, reference_to_tracker, np.eye(4), size_mm)
        residuals += nonrigid_errors(distortion, points, reference_to_tracker, np.eye(4))[1]
    residuals[0] += outlier_mm * axes[0]
    poses = np.broadcast_to(invert_rigid(reference_to_tracker), (len(points), 4, 4))
    return points + residuals, residuals, axes, poses


def test_distortion_is_detected_and_noise_or_one_bad_pair_is_not():
    points, residuals, axes, poses = _residuals(np.random.default_rng(21), 0.0)
    clean = estimate_distortion(points, residuals, axes, 0.002, tracker_to_reference=poses)
    assert clean.tested and not clean.detected and clean.mean_square_at(np.zeros((1, 3)))[0] == 0.0
    points, residuals, axes, poses = _residuals(np.random.default_rng(22), 0.0, outlier_mm=4.0)
    bad_pair = estimate_distortion(points, residuals, axes, 0.002, tracker_to_reference=poses)
    assert not bad_pair.detected and bad_pair.left_out == "P01"
    points, residuals, axes, poses = _residuals(np.random.default_rng(23), 1.0)
    distorted = estimate_distortion(points, residuals, axes, 0.002, tracker_to_reference=poses)
    assert distorted.detected and distorted.p_value <= 0.002
    assert 0.6 < distorted.rms_mm < 1.4


def test_distortion_block_round_trips_and_the_field_is_evaluable_from_it():
    points, residuals, axes, poses = _residuals(np.random.default_rng(23), 1.0)
    estimate = estimate_distortion(points, residuals, axes, 0.002, tracker_to_reference=poses)
    document = json.loads(json.dumps(estimate.to_json()))
    again = DistortionEstimate.from_json(document)
    probe = np.array([[0.0, 0.0, 0.0], [50.0, -20.0, 30.0]])
    assert np.allclose(again.field_at(probe), estimate.field_at(probe), atol=1e-5)
    assert np.allclose(again.mean_square_at(probe), estimate.mean_square_at(probe), rtol=1e-4)
    assert document["detected"] and document["rms_mm"] == pytest.approx(estimate.rms_mm, abs=1e-4)
    assert document["field"]["model"]["kind"] == "dipole"
    # without the transmitter's pose (an older calibration), smooth bumps stand in
    bumps = estimate_distortion(points, residuals, axes, 0.002).to_json()
    assert (bumps["field"]["model"] or {"kind": "bumps"})["kind"] == "bumps" and "transmitter" in bumps["note"]


@pytest.fixture(scope="module")
def distorted_case(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """A CI-sized case with a steel rod leaving 1.0 mm RMS non-rigid error at the pinholes, run once."""
    folder = tmp_path_factory.mktemp("distorted") / "case"
    simulate_case(folder, seed=4, spacing_mm=1.0, distortion_mm=1.0, **DISTORTED_OPTIONS)
    assert main(["run", str(folder), "--out", str(folder.parent / "out"), "--quiet"]) == 0
    return folder


def test_run_detects_distortion_says_where_and_predicts_with_it(distorted_case: Path):
    truth = load_truth(distorted_case)["distortion"]
    assert truth["rms_nonrigid_mm"] == pytest.approx(1.0, rel=1e-3)
    out = distorted_case.parent / "out"
    document = json.loads((out / "registration.json").read_text())
    distortion = document["distortion"]
    assert distortion["detected"] and distortion["p_value"] <= distortion["alpha"]
    assert 0.4 < distortion["rms_mm"] < 1.6 and distortion["max_mm"] >= distortion["rms_mm"]
    assert any(w.startswith("field distortion detected") and distortion["max_at"] in w for w in document["warnings"])
    assert not any("likely not in a pinhole" in w for w in document["warnings"])
    assert set(distortion["tested_unpaired"]) <= set(document["unpaired_calibration_points"])
    assert not set(distortion["tested_unpaired"]) & set(distortion["labels"])
    registration = read_registration(out)
    assert registration.error.distortion.detected
    evaluation = json.loads((out / "evaluation.json").read_text())
    budgets = [t["budget_rms_mm"] for t in evaluation["tre"]["targets"].values()]
    assert all(b["distortion"] > 0 for b in budgets)
    assert (out / "report_figures" / "distortion.png").stat().st_size > 0
    assert "Field distortion" in (out / "report.html").read_text(encoding="utf-8")


def test_distortion_figure_draws_the_field_where_it_is_and_the_vectors():
    """The figure's colour is brightest on the pinholes' side of the largest field; the arrows are drawn."""
    from EMRegModule.rendering.error_views import distortion_views

    points, residuals, axes, poses = _residuals(np.random.default_rng(23), 1.0)
    estimate = estimate_distortion(points, residuals, axes, 0.002, tracker_to_reference=poses)
    image = distortion_views(estimate.points_mm, estimate.residuals_mm, estimate.pinhole_field(),
                             lambda p: np.linalg.norm(estimate.field_at(p), axis=1), "title", panel_px=300)
    assert image.shape[1] == 600 and image.dtype == np.uint8
    magenta = np.all(image == (230, 0, 230), axis=-1)
    assert magenta.sum() > 50  # fitted-field arrows
    clean = estimate_distortion(*_residuals(np.random.default_rng(21), 0.0)[:3], 0.002)
    flat = distortion_views(clean.points_mm, clean.residuals_mm, clean.pinhole_field(),
                            lambda p: np.linalg.norm(clean.field_at(p), axis=1), "title", panel_px=300)
    assert not np.all(flat == (230, 0, 230), axis=-1).sum() > 50  # no field fitted, no magenta arrows


def test_distortion_above_the_limit_is_refused(distorted_case: Path, tmp_path: Path):
    settings = tmp_path / "strict.toml"
    settings.write_text((distorted_case / "case.toml").read_text() + "\n[registration]\nmax_distortion_mm = 0.2\n")
    out = tmp_path / "out"
    assert main(["run", str(distorted_case), "--out", str(out), "--settings", str(settings), "--quiet"]) == 3
    assert not (out / "registration.json").exists()


def test_clean_case_shows_no_distortion(small_case: Path):
    distortion = json.loads((small_case.parent / "out" / "registration.json").read_text())["distortion"]
    assert distortion["tested"] and not distortion["detected"]


def test_a_field_the_calibration_could_miss_is_said_and_refused_when_asked(small_case: Path, tmp_path: Path):
    """Eight markers cannot rule out a 1 mm field: the clean run says how large a field it could miss, in
    registration.json, prediction_trust and a warning; with refuse_undetectable_distortion it is refused (exit 3),
    with nothing written; a limit above what it could miss leaves the prediction trusted."""
    document = json.loads((small_case.parent / "out" / "registration.json").read_text())
    size = document["distortion"]["detectable_rms_mm"]
    assert size > 1.0 and document["distortion"]["undetectable_limit_mm"] == 1.0
    assert not document["prediction_trust"]["trusted"]
    assert any("could miss a field" in r for r in document["prediction_trust"]["reasons"])
    assert any("max_undetectable_distortion_mm" in w for w in document["warnings"])
    report = (small_case.parent / "out" / "report.html").read_text(encoding="utf-8")
    assert "could miss a field" in report and f"check finds a field of {size:.2f} mm RMS or more" in report
    text = (small_case / "case.toml").read_text()
    strict, loose = tmp_path / "strict.toml", tmp_path / "loose.toml"
    strict.write_text(text + "\n[registration]\nrefuse_undetectable_distortion = true\n")
    loose.write_text(text + f"\n[registration]\nmax_undetectable_distortion_mm = {size + 0.5:.2f}\n")
    assert main(["run", str(small_case), "--out", str(tmp_path / "strict"), "--settings", str(strict), "--quiet"]) == 3
    assert not (tmp_path / "strict" / "registration.json").exists()
    assert main(["run", str(small_case), "--out", str(tmp_path / "loose"), "--settings", str(loose), "--quiet"]) == 0
    loose_document = json.loads((tmp_path / "loose" / "registration.json").read_text())
    assert not any("could miss" in r for r in loose_document["prediction_trust"]["reasons"])


def test_simulate_command_passes_the_distortion_options(tmp_path: Path, monkeypatch: pytest.MonkeyPatch):
    seen = {}

    def fake_simulate_case(out, **kwargs):
        seen.update(kwargs)

    monkeypatch.setattr("EMRegModule.pipeline.simulate.simulate_case", fake_simulate_case)
    assert main(["simulate", str(tmp_path / "c"), "--distortion", "1.0", "--distortion-during", "navigation",
                 "--distortion-onset", "12", "--quiet"]) == 0
    assert (seen["distortion_mm"], seen["distortion_during"], seen["distortion_onset_s"]) == (1.0, "navigation", 12.0)


def test_unpaired_point_is_not_blamed_on_the_user_when_distortion_is_detected():
    from EMRegModule.core.registration import _unpaired_warnings

    points, residuals, axes, poses = _residuals(np.random.default_rng(23), 1.0)
    estimate = estimate_distortion(points, residuals, axes, 0.002, tracker_to_reference=poses)
    (line,) = _unpaired_warnings([], ["M07"], estimate)
    assert "distortion" in line and "likely not in a pinhole" not in line
    (line,) = _unpaired_warnings([], ["M07"], None)
    assert "likely not in a pinhole" in line
    clean = estimate_distortion(*_residuals(np.random.default_rng(21), 0.0)[:3], 0.002)
    near = replace(clean, tested_unpaired=["M07"])
    point, marker = _unpaired_warnings(["I09"], ["M07", "M11"], near)[:2]
    assert "M07" in point and "field distortion" in point and "likely" not in point
    assert "M11" in _unpaired_warnings(["I09"], ["M07", "M11"], near)[1]
    assert "likely not in a pinhole" in _unpaired_warnings(["I09"], ["M07", "M11"], near)[1]
    lines = _unpaired_warnings(["I09"], ["M07"], near)
    assert len(lines) == 2 and "local field distortion" in lines[1] and "likely" not in " ".join(lines)


def test_points_left_unpaired_near_a_pinhole_add_evidence_but_not_the_field_or_the_noise():
    """A field concentrated near two pinholes moves them beyond the pairing tolerance and their neighbours a little:
    the pairs alone do not show it; with the two joined to the test (``fitted_count``: the pairs come first) it is
    found, while the field, the noise and the labels stay those of the pairs."""
    rng = np.random.default_rng(79)
    points, axes, reference_to_tracker = _frame(rng, 18)  # its last two pinholes are 27 mm apart
    poses = np.broadcast_to(invert_rigid(reference_to_tracker), (len(points), 4, 4))
    centre = points[-1] + 0.5 * (points[-2] - points[-1])
    bump = np.exp(-np.sum((points - centre) ** 2, axis=1) / (2 * 20.0**2))[:, None] * np.array([2.5, -2.0, 1.5])
    residuals = rng.normal(0.0, 0.25, points.shape) + bump  # 2.8 mm at the two, under 0.4 mm elsewhere
    paired = estimate_distortion(points[:-2], residuals[:-2], axes[:-2], 0.002, tracker_to_reference=poses[:-2],
                                 noise=NoisePrior(0.25, "known"))
    joined = estimate_distortion(points, residuals, axes, 0.002, [f"P{k:02d}" for k in range(18)],
                                 tracker_to_reference=poses, noise=NoisePrior(0.25, "known"), fitted_count=16)
    assert not paired.detected and joined.detected and joined.p_value < paired.p_value
    assert joined.tested_unpaired == ["P16", "P17"] and len(joined.labels) == len(joined.points_mm) == 16
    assert joined.to_json()["tested_unpaired"] == ["P16", "P17"]


def test_trust_study_summary_counts_detections_false_alarms_and_the_prediction():
    from EMRegModule.studies.catalog import STUDIES

    def row(size, detected, predicted_ms=1.0, measured_ms=1.0, detectable=0.4):
        return {"distortion_mm": size, "refused": None, "detected": detected, "estimated_rms_mm": 1.0,
                "truth_paired_rms_mm": size, "measured_ms": measured_ms, "predicted_ms": predicted_ms,
                "predicted_without_distortion_ms": 0.25 * predicted_ms, "detectable_rms_mm": detectable,
                "flagged": not detected and detectable > 1.0}

    rows = [row(0.0, False)] * 19 + [row(0.0, True)] + [row(1.0, True, 1.21)] * 3 + [row(1.0, False, 1.21, 1.0, 1.6)]
    rows.append({"distortion_mm": 1.0, "refused": "the EM field is distorted"})
    summary = STUDIES["trust"].summarize(rows)
    clean, distorted = summary.rows
    assert clean[:5] == ["clean, noise x1", "20", "0", "5.0 %", "5.0 %"]
    assert distorted[:5] == ["dipole (development) 1 mm, noise x1", "5", "1", "75.0 %", "80.0 %"]  # refused: caught
    assert distorted[5:7] == ["100.0 %", "0.40"]  # the miss could have been missed: flagged; median detectable
    assert clean[5] == "5.0 %"
    assert distorted[11:13] == ["1.10", "0.55"]  # predicted / measured RMS, and without the distortion term
    assert any("held out (never tuned on) magpylib, multi" in n for n in summary.notes)
    assert summary.figure.ndim == 3


def test_an_unpaired_point_is_measured_against_the_field_fitted_to_the_others():
    """The evidence for blaming the distortion: taking the field fitted to the paired pinholes off an unpaired
    calibration point brings it nearer its CT pinhole."""
    from types import SimpleNamespace

    from EMRegModule.core.registration import _distortion_evidence

    rng = np.random.default_rng(24)
    points, axes, reference_to_tracker = _frame(rng)
    distortion = place_object(rng, points, reference_to_tracker, np.eye(4), 1.0)
    raw, _ = nonrigid_errors(distortion, points, reference_to_tracker, np.eye(4))
    worst = int(np.argmax(np.linalg.norm(raw, axis=1)))
    measured = points + raw + rng.normal(0.0, 0.1, points.shape)
    paired = np.arange(len(points)) != worst
    fit = fit_rigid(measured[paired], points[paired])  # the registration (Image = the true Reference frame here)
    in_image = apply_transform(fit, measured)
    estimate = estimate_distortion(in_image[paired], in_image[paired] - points[paired], axes[paired], 0.002,
                                   tracker_to_reference=np.broadcast_to(invert_rigid(reference_to_tracker),
                                                                        (int(paired.sum()), 4, 4)))
    assert estimate.detected
    labels, ids = [f"M{k:02d}" for k in range(len(points))], [f"I{k:02d}" for k in range(len(points))]
    solution = SimpleNamespace(reference_to_image=np.eye(4), l_mm=0.0)
    (line,) = _distortion_evidence(estimate, solution, in_image, labels, set(np.nonzero(paired)[0].tolist()),
                                   points, axes, ids, set(np.nonzero(paired)[0].tolist()))
    before, after = (float(v) for v in re.findall(r"([0-9.]+) mm", line)[:2])
    assert line.startswith(f"M{worst:02d}: ") and f"CT marker I{worst:02d}'s" in line
    assert after < 0.7 * before


def _smooth_residuals(rng: np.random.Generator, size_mm: float, noise_mm: float = 0.25):
    """Calibration points with noise and the non-rigid part of a random smooth (Gaussian-process) field of
    ``size_mm`` RMS: a field of no physical family, with no transmitter pose given to the detector."""
    from EMRegModule.simulation.field_families import place_field

    points, axes, reference_to_tracker = _frame(rng)
    residuals = rng.normal(0.0, noise_mm, points.shape)
    if size_mm:
        field = place_field("gp", rng, points, reference_to_tracker, np.eye(4), size_mm)
        residuals += nonrigid_errors(field, points, reference_to_tracker, np.eye(4))[1]
    return points + residuals, residuals, axes


def test_a_field_of_no_physical_family_is_detected_by_the_generic_candidates():
    points, residuals, axes = _smooth_residuals(np.random.default_rng(31), 1.0)
    estimate = estimate_distortion(points, residuals, axes, 0.002)
    assert estimate.detected and estimate.p_value <= 0.002
    assert estimate.to_json()["field"]["model"]["kind"] in ("polynomial", "modes", "bumps")
    assert 0.5 < estimate.rms_mm < 1.5
    clean = estimate_distortion(*_smooth_residuals(np.random.default_rng(32), 0.0), 0.002)
    assert clean.tested and not clean.detected


def test_the_false_alarm_rate_holds_on_noise_of_any_size():
    """Isotropic noise of three sizes, 12 geometries each: no more false alarms than the rate allows (0.002: the
    chance of 2 or more in 36 is 0.2 %), and the p-values spread over (0, 1) as a calibrated test's do (the study
    measures the rate on simulated sessions)."""
    p_values = []
    for seed in range(12):
        for k, noise in enumerate((0.1, 0.4, 1.6)):
            points, residuals, axes = _smooth_residuals(np.random.default_rng([1000 + seed, k]), 0.0, noise)
            p_values.append(estimate_distortion(points, residuals, axes, 0.002).p_value)
    p_values = np.array(p_values)
    assert np.count_nonzero(p_values <= 0.002) <= 1
    assert 0.25 < np.median(p_values) < 0.75 and np.mean(p_values <= 0.1) < 0.25


def test_one_bad_pair_needs_every_sign_of_one_to_overrule_the_test():
    """The rule that puts the evidence down to one bad pair: all of an outlier by itself, the others not even weakly
    significant, not predicted by their field, and along its pinhole's axis."""
    from EMRegModule.core.distortion.detect import _several_points

    assert not _several_points(0.4, 0.1, 0.001, 0.95)  # a probe not fully inserted: one point, along its axis
    assert _several_points(0.4, 0.1, 0.2, 0.95)  # not an outlier by itself: the field is spread
    assert _several_points(0.02, 0.1, 0.001, 0.95)  # the others weakly significant alone
    assert _several_points(0.4, 0.7, 0.001, 0.95)  # their field predicts it
    assert _several_points(0.4, 0.1, 0.001, 0.2)  # moved across its axis: not a depth error
    assert _several_points(float("nan"), float("nan"), 0.001, 1.0)  # untestable without it
    assert _several_points(0.4, 0.1, 0.001, 0.95, unpaired_near=True)  # a neighbour left unpaired: moved too


def test_a_neighbour_left_unpaired_keeps_one_large_residual_from_being_put_down_to_one_bad_pair():
    """One large residual along its pinhole's axis, the rest noise: one bad pair, unless a calibration point near it
    was left out of the pairing (a field moved that one too, beyond the tolerance); a far one changes nothing."""
    points, residuals, axes, poses = _residuals(np.random.default_rng(22), 0.0, outlier_mm=4.0)
    alone = estimate_distortion(points, residuals, axes, 0.002, tracker_to_reference=poses)
    assert not alone.detected and alone.left_out == "P01"
    centroid = points.mean(axis=0)
    far = centroid + 3.0 * (centroid - points[0])
    near = points[0] + [12.0, -8.0, 5.0]
    with_far = estimate_distortion(points, residuals, axes, 0.002, tracker_to_reference=poses,
                                   unpaired_reference=far[None])
    with_near = estimate_distortion(points, residuals, axes, 0.002, tracker_to_reference=poses,
                                    unpaired_reference=near[None])
    assert not with_far.detected and with_near.detected


def test_the_distortion_term_is_the_true_field_on_average_plus_what_the_fitted_family_misses():
    """The distortion predicted at a point is the fitted field's square less its variance (navigation holds the true
    field, whose square the fitted one's overstates by that variance) plus what the fitted family misses where it
    was not fitted (its leave-one-out errors at the pinholes beyond their noise): over rods of 1 mm it comes within
    25 % of the true non-rigid field's mean square at the pinholes, with next to no miss for a family it fits (an
    induced dipole), and more for random smooth fields of none."""
    predicted, true, dipole_misses, smooth_misses = [], [], [], []
    for seed in range(6):
        rng = np.random.default_rng([23, seed])
        points, axes, reference_to_tracker = _frame(rng)
        noise = rng.normal(0.0, 0.25, points.shape)
        rod = place_object(rng, points, reference_to_tracker, np.eye(4), 1.0)
        field = nonrigid_errors(rod, points, reference_to_tracker, np.eye(4))[1]
        poses = np.broadcast_to(invert_rigid(reference_to_tracker), (len(points), 4, 4))
        dipole = estimate_distortion(points + noise + field, noise + field, axes, 0.002, tracker_to_reference=poses)
        assert dipole.detected
        at_pinholes = dipole.mean_square_at(dipole.points_mm)
        assert np.all(at_pinholes <= np.sum(dipole.pinhole_field() ** 2, axis=1) + dipole.extension_ms + 1e-9)
        assert np.all(at_pinholes >= dipole.extension_ms - 1e-12)
        predicted.append(np.mean(at_pinholes))
        true.append(np.mean(np.sum(field**2, axis=1)))
        dipole_misses.append(dipole.extension_ms / dipole.rms_mm**2)
        smooth = estimate_distortion(*_smooth_residuals(np.random.default_rng([31, seed]), 1.0), 0.002)
        assert smooth.detected
        assert DistortionEstimate.from_json(smooth.to_json()).extension_ms == pytest.approx(smooth.extension_ms,
                                                                                             abs=2e-4)
        smooth_misses.append(smooth.extension_ms / smooth.rms_mm**2)
    assert np.mean(predicted) / np.mean(true) == pytest.approx(1.0, abs=0.25)
    assert max(dipole_misses) < 0.01 and np.mean(smooth_misses) > 5 * np.mean(dipole_misses) + 0.01
    trust = dipole.prediction_trust()
    assert not trust["trusted"] and "field distortion measured" in trust["reasons"][0]
    clean = estimate_distortion(*_residuals(np.random.default_rng(21), 0.0)[:3], 0.002)
    assert clean.prediction_trust() == {"trusted": True, "reasons": [], "distortion_ms_mm2": 0.0}


def test_a_smooth_field_is_predicted_where_no_pinhole_is_as_large_as_at_the_pinholes():
    """A Gaussian process's modes, fitted, fall to 0 away from the pinholes (their extension is the kernel's), where
    a field of no physics does not: the prediction adds the process's posterior variance there, the field's mean square
    at the pinholes times what the pinholes leave unexplained. Over 12 random smooth fields of 1 mm (20 pinholes of a
    200 mm frame) the distortion predicted at 40 points inside the frame comes within 12 % of the true field's mean
    square there (1.00; it was 0.83 from the modes' extension alone). At the pinholes the added term is only the
    noise's share (a third of the field's there or less, 0.25 mm noise against a 1 mm field); far from them, all of
    the field's mean square."""
    from EMRegModule.simulation.field_families import place_field

    predicted, true, modes = [], [], None
    for seed in range(12):
        rng = np.random.default_rng([41, seed])
        points, axes, reference_to_tracker = _frame(rng, 20)
        noise = rng.normal(0.0, 0.25, points.shape)
        field = place_field("gp", rng, points, reference_to_tracker, np.eye(4), 1.0)
        nonrigid = nonrigid_errors(field, points, reference_to_tracker, np.eye(4))[1]
        inside = rng.uniform(-50.0, 50.0, (40, 3)) * np.array([1.0, 1.0, 0.5])
        truth = nonrigid_errors(field, points, reference_to_tracker, np.eye(4), at_body=inside)[1]
        estimate = estimate_distortion(points + noise + nonrigid, noise + nonrigid, axes, 0.002)
        if estimate.detected:
            predicted.append(np.mean(estimate.mean_square_at(inside)))
            true.append(np.mean(np.sum(truth**2, axis=1)))
            if estimate.to_json()["field"]["model"]["kind"] == "modes":
                modes = estimate
    assert len(predicted) >= 10
    assert np.sum(predicted) / np.sum(true) == pytest.approx(1.0, abs=0.12)
    assert modes is not None
    assert np.max(modes._unseen_ms(modes.points_mm)) < 0.35 * modes.rms_mm**2
    far = modes.points_mm.mean(axis=0) + [2000.0, 0.0, 0.0]
    assert modes._unseen_ms(far[None])[0] == pytest.approx(modes.rms_mm**2)


def test_the_detectable_size_follows_the_noise_and_is_what_the_test_finds():
    """``detectable_rms_mm``: the field size found in 90 % of random smooth fields at this noise and geometry. It
    grows in proportion to the noise; fields of another family (induced dipoles) of twice that size are found
    nearly always, and of a third of it seldom; without a noise level the FRE limit bounds it (the share test alone
    misses some smooth fields at any size)."""
    points, residuals, axes, poses = _residuals(np.random.default_rng(5), 0.0)
    sizes = []
    for noise in (0.2, 0.4):
        scaled = residuals / 0.25 * noise
        estimate = estimate_distortion(points, scaled, axes, 0.002, tracker_to_reference=poses,
                                       noise=NoisePrior(noise, "known"))
        sizes.append(estimate.detectable_rms_mm)
    assert 0.2 < sizes[0] < 1.5 and sizes[1] / sizes[0] == pytest.approx(2.0, rel=0.15)
    assert DistortionEstimate.from_json(estimate.to_json()).detectable_rms_mm == pytest.approx(sizes[1], abs=1e-3)
    found = {2.0: 0, 0.33: 0}
    for seed in range(10):
        for factor in found:
            rng = np.random.default_rng([61, seed])
            points, axes, reference_to_tracker = _frame(rng)
            noisy = rng.normal(0.0, 0.2, points.shape)
            rod = place_object(rng, points, reference_to_tracker, np.eye(4), factor * sizes[0])
            field = nonrigid_errors(rod, points, reference_to_tracker, np.eye(4))[1]
            poses = np.broadcast_to(invert_rigid(reference_to_tracker), (len(points), 4, 4))
            found[factor] += estimate_distortion(points + noisy + field, noisy + field, axes, 0.002,
                                                 tracker_to_reference=poses, noise=NoisePrior(0.2, "known")).detected
    assert found[2.0] >= 9 and found[0.33] <= 4
    alone = estimate_distortion(points, residuals, axes, 0.002, tracker_to_reference=poses)
    bounded = estimate_distortion(points, residuals, axes, 0.002, tracker_to_reference=poses, max_fre_mm=2.0)
    assert alone.detectable_rms_mm == np.inf and alone.to_json()["detectable_rms_mm"] is None
    assert DistortionEstimate.from_json(alone.to_json()).detectable_rms_mm == np.inf
    assert 1.0 < bounded.detectable_rms_mm < 2.5


def test_a_suspected_distortion_is_named_before_the_user_is_blamed():
    from dataclasses import replace

    from EMRegModule.core.registration import _unpaired_warnings

    clean = estimate_distortion(*_residuals(np.random.default_rng(21), 0.0)[:3], 0.002)
    suspected = replace(clean, p_value=0.01)
    assert not suspected.detected and not suspected.prediction_trust()["trusted"]
    lines = _unpaired_warnings(["I03"], ["M07"], suspected)
    assert all("likely not" not in line for line in lines) and all("distortion" in line for line in lines)
    assert any("likely not in a pinhole" in line for line in _unpaired_warnings(["I03"], ["M07"], clean))


def test_a_smooth_field_fitted_to_the_paired_points_explains_an_unpaired_one():
    """The field fitted to the paired pinholes (complexity by leave-one-out) taken off the point the field moved most,
    left out of the pairing: nearer its pinhole in most of 10 random smooth fields (beyond the pinholes a field of
    unknown shape extrapolates only roughly, so the registration claims it only when it lands within the pairing
    tolerance)."""
    from EMRegModule.core.distortion import fit_field
    from EMRegModule.simulation.field_families import place_field

    improved = 0
    for seed in range(33, 43):
        rng = np.random.default_rng(seed)
        points, _, reference_to_tracker = _frame(rng)
        field = place_field("gp", rng, points, reference_to_tracker, np.eye(4), 1.0)
        raw, _ = nonrigid_errors(field, points, reference_to_tracker, np.eye(4))
        worst = int(np.argmax(np.linalg.norm(raw, axis=1)))
        measured = points + raw + rng.normal(0.0, 0.05, points.shape)
        paired = np.arange(len(points)) != worst
        in_truth = apply_transform(fit_rigid(measured[paired], points[paired]), measured)
        fitted = fit_field(in_truth[paired], in_truth[paired] - points[paired], None)
        before = np.linalg.norm(in_truth[worst] - points[worst])
        after = np.linalg.norm(in_truth[worst] - fitted.field_at(in_truth[worst][None])[0] - points[worst])
        improved += after < 0.7 * before
    assert improved >= 6


def test_a_noise_level_known_apart_from_the_residuals_finds_a_field_in_larger_noise():
    """A 0.5 mm smooth field in 0.3 mm (per axis) noise, 8 geometries: the share test alone (which divides by the
    residuals' own sum of squares, the field's included) finds few; with the noise known from the dwells (the
    known-noise test beside it) most."""
    alone = with_prior = 0
    for seed in range(8):
        points, residuals, axes = _smooth_residuals(np.random.default_rng([77, seed]), 0.5, 0.3)
        alone += estimate_distortion(points, residuals, axes, 0.002).detected
        estimate = estimate_distortion(points, residuals, axes, 0.002, noise=NoisePrior(0.3, "the dwells"))
        with_prior += estimate.detected
        assert estimate.noise_prior_sigma_mm == 0.3 and estimate.to_json()["noise_prior"]["source"] == "the dwells"
    assert with_prior >= 6 and with_prior >= alone + 4


def test_the_false_alarm_rate_holds_with_a_known_noise_level():
    """Noise of three sizes, 8 geometries each, with that noise known: no more false alarms than the rate allows
    (the smaller of two p-values, against its own null: the chance of 2 or more in 24 at 0.002 is 0.1 %), and the FRE
    agrees with the noise (its ratio near 1, no reason not to trust the prediction from it)."""
    p_values, ratios = [], []
    for seed in range(8):
        for k, noise in enumerate((0.1, 0.4, 1.6)):
            points, residuals, axes = _smooth_residuals(np.random.default_rng([2000 + seed, k]), 0.0, noise)
            estimate = estimate_distortion(points, residuals, axes, 0.002, noise=NoisePrior(noise, "known"))
            p_values.append(estimate.p_value)
            ratios.append(estimate.fle_ratio)
    assert np.count_nonzero(np.array(p_values) <= 0.002) <= 1
    assert np.mean(np.array(p_values) <= 0.1) < 0.3
    assert 0.85 < np.median(ratios) < 1.15 and max(ratios) < 1.5


def test_residuals_beyond_the_known_noise_are_said_and_refused_above_the_limit():
    """Residuals three times what the tracker's noise explains (a probe not seated, an error the model has no term
    for): the FRE check says so in prediction_trust, and the registration is refused above max_fle_ratio."""
    from EMRegModule.core.registration import check_fle
    from EMRegModule.errors import NoSafeAnswerError
    from EMRegModule.settings import RegistrationSettings

    points, residuals, axes = _smooth_residuals(np.random.default_rng(41), 0.0, 0.6)
    estimate = estimate_distortion(points, residuals, axes, 0.002, noise=NoisePrior(0.2, "1.8 x the dwells' spread"))
    assert estimate.fle_ratio > 2.5 and not estimate.fle_consistent
    trust = estimate.prediction_trust()
    assert not trust["trusted"] and any("times what the tracker's own noise explains" in r for r in trust["reasons"])
    with pytest.raises(NoSafeAnswerError, match="max_fle_ratio"):
        check_fle(estimate, RegistrationSettings())
    check_fle(estimate, RegistrationSettings(max_fle_ratio=4.0))  # below the limit: said, not refused
    same = estimate_distortion(points, residuals, axes, 0.002, noise=NoisePrior(0.6, "known"))
    assert same.fle_consistent and same.prediction_trust()["trusted"] == (not same.p_value <= 0.05)
    assert DistortionEstimate.from_json(estimate.to_json()).fle_ratio == pytest.approx(estimate.fle_ratio, rel=1e-3)


def test_points_the_trackers_noise_puts_beyond_the_tolerance_are_not_blamed_on_the_user():
    """A noise (from the dwells) that alone puts points beyond the pairing tolerance names itself for the points
    left out, not the user; a small one leaves the wording as it was."""
    from EMRegModule.core.registration import _unpaired_warnings, noise_beyond_tolerance

    points, residuals, axes = _smooth_residuals(np.random.default_rng(43), 0.0, 1.0)
    noisy = estimate_distortion(points, residuals, axes, 0.002, noise=NoisePrior(1.0, "the dwells"))
    quiet = estimate_distortion(points, residuals, axes, 0.002, noise=NoisePrior(0.25, "the dwells"))
    beyond = noise_beyond_tolerance(noisy, 28, 2.33)
    assert beyond is not None and 2.0 < beyond[1] < 5.0  # 28 x P(chi2(3) > 2.33^2): 3.4
    assert noise_beyond_tolerance(quiet, 28, 2.33) is None
    lines = _unpaired_warnings(["I07"], ["P03"], noisy, beyond)
    assert len(lines) == 2 and all("tracker's noise" in line for line in lines)
    assert not any(blame in line for line in lines for blame in ("likely not in a pinhole", "likely not recorded"))
    assert "likely not in a pinhole" in _unpaired_warnings([], ["P03"], quiet, None)[0]
