"""Field distortion: the simulator's induced-dipole model, its detection at registration, and what a user sees.

The end-to-end case is CI-sized (a 220 mm frame with 16 markers, 1 mm voxels) with a steel rod leaving 1.0 mm
RMS non-rigid error at the pinholes; the clean case is conftest's ``small_case``. The study (``emreg study
trust``) measures the rates; these tests assert what a single case must show.
"""

from __future__ import annotations

import json
import re
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


def test_trust_study_summary_counts_detections_false_alarms_and_the_prediction():
    from EMRegModule.studies.catalog import STUDIES

    def row(size, detected, predicted_ms=1.0, measured_ms=1.0):
        return {"distortion_mm": size, "refused": None, "detected": detected, "estimated_rms_mm": 1.0,
                "truth_paired_rms_mm": size, "measured_ms": measured_ms, "predicted_ms": predicted_ms,
                "predicted_without_distortion_ms": 0.25 * predicted_ms}

    rows = [row(0.0, False)] * 19 + [row(0.0, True)] + [row(1.0, True, 1.21)] * 3 + [row(1.0, False, 1.21)]
    rows.append({"distortion_mm": 1.0, "refused": "the EM field is distorted"})
    summary = STUDIES["trust"].summarize(rows)
    clean, distorted = summary.rows
    assert clean[:5] == ["clean, noise x1", "20", "0", "5.0 %", "5.0 %"]
    assert distorted[:5] == ["dipole (development) 1 mm, noise x1", "5", "1", "75.0 %", "80.0 %"]  # refused: caught
    assert distorted[9:11] == ["1.10", "0.55"]  # predicted / measured RMS, and without the distortion term
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
    from EMRegModule.core.distortion import _several_points

    assert not _several_points(0.4, 0.1, 0.001, 0.95)  # a probe not fully inserted: one point, along its axis
    assert _several_points(0.4, 0.1, 0.2, 0.95)  # not an outlier by itself: the field is spread
    assert _several_points(0.02, 0.1, 0.001, 0.95)  # the others weakly significant alone
    assert _several_points(0.4, 0.7, 0.001, 0.95)  # their field predicts it
    assert _several_points(0.4, 0.1, 0.001, 0.2)  # moved across its axis: not a depth error
    assert _several_points(float("nan"), float("nan"), 0.001, 1.0)  # untestable without it


def test_the_distortion_term_never_falls_below_what_the_pinholes_measured():
    points, residuals, axes, poses = _residuals(np.random.default_rng(23), 1.0)
    estimate = estimate_distortion(points, residuals, axes, 0.002, tracker_to_reference=poses)
    assert estimate.detected
    far = np.array([[0.0, 0.0, 0.0], [400.0, 300.0, -200.0]])
    measured = estimate.measured_ms()
    assert measured >= estimate.rms_mm**2 > 0
    assert np.all(estimate.mean_square_at(far) >= measured - 1e-12)
    trust = estimate.prediction_trust()
    assert not trust["trusted"] and "field distortion measured" in trust["reasons"][0]
    clean = estimate_distortion(*_residuals(np.random.default_rng(21), 0.0)[:3], 0.002)
    assert clean.prediction_trust() == {"trusted": True, "reasons": [], "distortion_ms_mm2": 0.0}


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
