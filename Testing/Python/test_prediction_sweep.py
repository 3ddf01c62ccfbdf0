"""What a sweep of simulated cases found about the predicted TRE (``tre.predicted_rms_mm``, the error a
surgeon is told to expect) against the TRE measured at the targets and the simulator's truth.

The sweep: small cases (200 x 200 x 110 mm frame, 1 mm voxels, 6 targets x 3 rounds; 6 seeds each),
tracker noise x0.5 to x4, 6 / 10 / 28 markers, markers on two adjacent faces only, on one face with
l fixed, targets 150 and 300 mm outside the frame, reference jitter x5, the frame moved in the field
between navigation dwells, bumps during calibration, CT noise 60 / 120 HU, and one navigation round
(the tracking term then from the calibration). Over the seeds the measured RMS TRE was 0.81 to 1.10
x the predicted one (single seeds 0.50 to 1.89), the prediction growing with distance as the error
does (0.47 / 0.55 / 0.66 mm predicted, 0.47 / 0.54 / 0.61 measured at 0 / 150 / 300 mm outside).
All markers on one face is refused (l undetermined), as it should be. A reference sensor slipping
1.5 mm / 1 degree in its holder half way through navigation measured 1.19 x the prediction: the
scatter of repeated dwells at the targets takes most of it into the tracking term.

- Errors the model has no term for were never said. A probe whose tip is 2 mm from where its sensor
  is reported (a mis-calibrated tip offset) measured 2.09 mm RMS TRE against a predicted 0.68 mm
  (3.1 x; 4.8 x with one navigation round; every seed) and the run printed no warning: the
  prediction, its budget plot and ``tre_map.nrrd`` told the surgeon 0.7 mm. The evaluation had both
  numbers and never compared them. It now does: when the measured mean-square TRE exceeds the
  prediction by more than the model's own randomness explains (the measured errors split exactly
  into a common 3D error and the dwells' scatter, integrated numerically, with the prediction's own
  estimation error from the degrees of freedom it came from; false alarm 1 in 1000, checked here
  by Monte Carlo), a warning says by how much, on stderr, in ``evaluation.json`` and in the report.
  On the sweep it fired on all 12 tip-offset cases, on 2 of 6 with a fixed l 1 mm wrong (the two at
  2.7 x), and on none of the 138 cases of the other conditions.
- ``registration.json``'s ``error_model`` now records ``probe_sigma_dof`` (3N - P, the residual degrees
  of freedom the probe's error was estimated from), which that test needs.
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from EMRegModule.cli.main import main
from EMRegModule.core.error_model import optimism_limit
from EMRegModule.core.tracking import TrackingRecording
from EMRegModule.io.tracking_csv import read_tracking_csv, write_tracking_csv
from EMRegModule.simulation.case import simulate_case

SMALL = {"frame_size_mm": (200.0, 200.0, 110.0), "n_markers": 8, "navigation_rounds": 3, "board_rounds": 0,
         "n_targets": 5}
OPTIMISTIC = "the prediction is optimistic"


@pytest.fixture(scope="module")
def small_case(tmp_path_factory) -> Path:
    """A small simulated case (1 mm voxels, 8 markers, 5 targets visited 3 times) and its run's output."""
    folder = tmp_path_factory.mktemp("prediction_sweep") / "case"
    simulate_case(folder, seed=4, spacing_mm=1.0, **SMALL)
    assert main(["run", str(folder), "--out", str(folder.parent / "out"), "--quiet"]) == 0
    return folder


def _tre(out: Path) -> dict:
    return json.loads((out / "evaluation.json").read_text())


def test_a_matching_prediction_is_not_called_optimistic(small_case, capsys):
    evaluation = _tre(small_case.parent / "out")
    tre = evaluation["tre"]
    assert 0.5 < tre["rms_mm"] / tre["predicted_rms_mm"] < 1.6
    assert not any(OPTIMISTIC in w for w in evaluation.get("warnings", []))
    error_model = json.loads((small_case.parent / "out" / "registration.json").read_text())["error_model"]
    pairs = len(json.loads((small_case.parent / "out" / "registration.json").read_text())["pairs"])
    assert error_model["probe_sigma_dof"] == 3 * pairs - 7  # l solved: 7 parameters


def test_a_probe_tip_off_its_sensor_is_said_to_make_the_prediction_optimistic(small_case, tmp_path, capsys):
    """The navigated point 2 mm short of the tip along the probe's axis: no term of the model covers it."""
    case = tmp_path / "case"
    case.mkdir()
    for item in small_case.iterdir():
        (case / item.name).symlink_to(item)
    (case / "navigation.csv").unlink()
    recording = read_tracking_csv(small_case / "navigation.csv")
    probe = recording.sensor == 2
    position = recording.position_mm.copy()
    position[probe] -= 2.0 * recording.rotation[probe][:, :, 0]  # +X: cable to tip
    write_tracking_csv(TrackingRecording(recording.time_s, recording.sensor, position, recording.rotation,
                                         recording.quality, recording.label), case / "navigation.csv")
    out = tmp_path / "out"
    capsys.readouterr()
    assert main(["run", str(case), "--out", str(out), "--quiet"]) == 0
    err = capsys.readouterr().err
    evaluation = _tre(out)
    tre = evaluation["tre"]
    assert tre["rms_mm"] > 2.0 * tre["predicted_rms_mm"]
    said = [w for w in evaluation.get("warnings", []) if OPTIMISTIC in w]
    assert len(said) == 1 and said[0] in err
    assert f"{tre['rms_mm']:.2f} mm" in said[0]


@pytest.mark.parametrize(("common_ms", "independent_ms", "n_dwells", "prediction_dof"),
                         [(0.05, 0.1, 18, np.inf), (0.2, 0.02, 6, np.inf), (0.0, 0.1, 4, np.inf),
                          (0.05, 0.1, 18, 17.0)])
def test_the_optimism_limit_is_exceeded_by_chance_as_rarely_as_it_says(common_ms, independent_ms, n_dwells,
                                                                       prediction_dof):
    """Monte Carlo of the model's own structure: one common 3D error per session, one per dwell, and a
    prediction estimated from ``prediction_dof`` degrees of freedom."""
    rng = np.random.default_rng(3)
    runs = 200_000
    common = rng.normal(0.0, np.sqrt(common_ms / 3), (runs, 1, 3))
    independent = rng.normal(0.0, np.sqrt(independent_ms / 3), (runs, n_dwells, 3))
    measured_ms = np.mean(np.sum((common + independent) ** 2, axis=-1), axis=1)
    predicted_ms = (common_ms + independent_ms) * (
        rng.chisquare(prediction_dof, runs) / prediction_dof if np.isfinite(prediction_dof) else 1.0)
    for false_alarm in (1e-2, 1e-3):
        limit = optimism_limit(common_ms, independent_ms, n_dwells, prediction_dof, false_alarm=false_alarm)
        assert 0.7 * false_alarm < np.mean(measured_ms / predicted_ms > limit) < 1.4 * false_alarm


def test_the_optimism_limit_widens_with_an_uncertain_prediction_and_few_dwells():
    assert optimism_limit(0.05, 0.1, 18, 10) > optimism_limit(0.05, 0.1, 18, 100) > optimism_limit(0.05, 0.1, 18)
    assert optimism_limit(0.05, 0.1, 6) > optimism_limit(0.05, 0.1, 18) > optimism_limit(0.05, 0.1, 60) > 1.0
    assert optimism_limit(0.05, 0.1, 0) == float("inf")
