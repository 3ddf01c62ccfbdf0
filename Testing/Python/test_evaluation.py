"""Evaluation: TRE per target over dwells (labelled and unlabelled), the board table, evaluation.json."""

from __future__ import annotations

import json

import numpy as np
import pytest
from synth_registration import calibration_recording, make_frame

from EMRegModule.core.evaluation import Evaluation, evaluate, evaluate_board
from EMRegModule.core.transforms import apply_transform, invert_rigid, make_transform, random_rotation
from EMRegModule.errors import EMRegError
from EMRegModule.io.case import open_case
from EMRegModule.io.evaluation_json import read_evaluation, write_evaluation
from EMRegModule.io.markups import write_markups
from EMRegModule.io.tracking_csv import write_tracking_csv

TARGETS = ["T1", "T2", "T3"]
EDGES = [75.3, 60.4, 75.5, 60.4]


def _board_holes(rng) -> np.ndarray:
    """Four corner holes with the given edge lengths (a slightly skewed quadrilateral), posed in Reference."""
    l1, l2, l3, l4 = EDGES
    h1 = np.zeros(3)
    h2 = np.array([l1, 0, 0])
    # Place h4 at distance l4 from h1, then h3 at distances l2 from h2 and l3 from h4 (in the plane z=0).
    h4 = l4 * np.array([np.sin(np.radians(1.0)), np.cos(np.radians(1.0)), 0])
    d = np.linalg.norm(h4 - h2)
    a = (l2**2 - l3**2 + d**2) / (2 * d)
    h = np.sqrt(l2**2 - a**2)
    e = (h4 - h2) / d
    n = np.array([-e[1], e[0], 0])
    h3 = h2 + a * e + h * n
    holes = np.array([h1, h2, h3, h4])
    board_to_reference = make_transform(random_rotation(rng), [100.0, -50.0, 20.0])
    return apply_transform(board_to_reference, holes)


@pytest.fixture(scope="module")
def case_folder(tmp_path_factory):
    folder = tmp_path_factory.mktemp("evalcase")
    frame = make_frame(51)
    rng = np.random.default_rng(51)
    targets_image = frame.origins_image[:3] + 25.0 * frame.axes_image[:3]
    write_markups(folder / "targets.mrk.json", TARGETS, targets_image)
    targets_reference = apply_transform(invert_rigid(frame.reference_to_image), targets_image)
    visits = [0, 1, 2] * 4
    navigation, nav_truth = calibration_recording(targets_reference, frame.axes_reference[:3], seed=52, bumps=True,
                                                  labels=TARGETS, visit_order=visits, dwell_s=1.0, tremor_mm=0.3)
    write_tracking_csv(navigation, folder / "navigation.csv")
    holes = _board_holes(rng)
    board, board_truth = calibration_recording(holes, np.tile([0, 0, 1.0], (4, 1)), seed=53, bumps=True,
                                               labels=["H1", "H2", "H3", "H4"], visit_order=[0, 1, 2, 3] * 5,
                                               dwell_s=0.8)
    write_tracking_csv(board, folder / "board.csv")
    (folder / "case.toml").write_text("[board]\nedges_mm = [75.3, 60.4, 75.5, 60.4]\n")
    return folder, frame, targets_image, visits, nav_truth, board, board_truth


def evaluate_case(case, reference_to_image, reference_sensor, probe_sensor) -> dict:
    """The evaluation of a case folder's recordings, as written to evaluation.json."""
    result = evaluate(reference_to_image, reference_sensor, probe_sensor, case.settings.evaluation,
                      navigation=case.read_recording("navigation"), targets=case.read_targets(),
                      board=case.read_recording("board"), nominal_edges_mm=case.settings.board.edges_mm)
    assert isinstance(result, Evaluation)
    return result.to_json()


def _expected_target_errors(frame, targets_image, visits, nav_truth):
    mapped = apply_transform(frame.reference_to_image, nav_truth)
    return np.linalg.norm(mapped - targets_image[visits], axis=1)


def _expected_edges(board_truth):
    rounds = board_truth.reshape(-1, 4, 3)
    return np.stack([np.linalg.norm(rounds[:, k] - rounds[:, (k + 1) % 4], axis=1) for k in range(4)], axis=1)


def test_tre_and_board_from_a_labelled_case(case_folder):
    folder, frame, targets_image, visits, nav_truth, _, board_truth = case_folder
    result = evaluate_case(open_case(folder), frame.reference_to_image, 1, 2)
    expected = _expected_target_errors(frame, targets_image, visits, nav_truth)
    tre = result["tre"]
    assert tre["n"] == 12 and set(tre["targets"]) == set(TARGETS)
    assert tre["mean_mm"] == pytest.approx(expected.mean(), abs=0.06)  # hand tremor 0.3 mm does not average out
    assert tre["std_mm"] == pytest.approx(expected.std(ddof=1), abs=0.06)
    for k, label in enumerate(TARGETS):
        assert tre["targets"][label]["n"] == 4
        assert tre["targets"][label]["mean_mm"] == pytest.approx(expected[k::3].mean(), abs=0.06)
    edges = result["board"]["edges"]
    lengths = _expected_edges(board_truth)
    assert list(edges) == ["L1", "L2", "L3", "L4"] and result["board"]["rounds"] == 5
    for k, name in enumerate(edges):
        assert edges[name]["n"] == 5
        assert edges[name]["mean_mm"] == pytest.approx(lengths[:, k].mean(), abs=0.03)
        assert edges[name]["std_mm"] == pytest.approx(lengths[:, k].std(ddof=1), abs=0.03)
        assert edges[name]["nominal_mm"] == EDGES[k]
        assert edges[name]["abs_error_mm"] == pytest.approx(abs(lengths[:, k].mean() - EDGES[k]), abs=0.03)
        assert edges[name]["rel_error_percent"] == pytest.approx(100 * edges[name]["abs_error_mm"] / EDGES[k], abs=1e-3)


def test_a_wrong_registration_shows_in_the_tre(case_folder):
    folder, frame, *_ = case_folder
    shifted = make_transform(translation=[1.0, 0, 0]) @ frame.reference_to_image
    good = evaluate_case(open_case(folder), frame.reference_to_image, 1, 2)["tre"]["mean_mm"]
    bad = evaluate_case(open_case(folder), shifted, 1, 2)["tre"]["mean_mm"]
    assert bad > good + 0.5


def test_unlabelled_recordings_give_the_same_figures(case_folder, tmp_path):
    folder, frame, targets_image, visits, nav_truth, board, board_truth = case_folder
    from EMRegModule.io.tracking_csv import read_tracking_csv

    for name in ("navigation.csv", "board.csv"):
        recording = read_tracking_csv(folder / name)
        recording.label[:] = ""
        write_tracking_csv(recording, tmp_path / name)
    for name in ("targets.mrk.json", "case.toml"):
        (tmp_path / name).write_bytes((folder / name).read_bytes())
    result = evaluate_case(open_case(tmp_path), frame.reference_to_image, 1, 2)
    expected = _expected_target_errors(frame, targets_image, visits, nav_truth)
    assert result["tre"]["n"] == 12 and not result["tre"]["labelled"]  # every hand-held dwell found
    assert result["tre"]["mean_mm"] == pytest.approx(expected.mean(), abs=0.06)
    lengths = _expected_edges(board_truth)
    assert result["board"]["rounds"] == 5 and not result["board"]["labelled"]
    for k, name in enumerate(("L1", "L2", "L3", "L4")):
        assert result["board"]["edges"][name]["mean_mm"] == pytest.approx(lengths[:, k].mean(), abs=0.03)


def test_board_without_nominal_edges_and_bad_settings(case_folder):
    folder, *_, board, board_truth = case_folder
    result = evaluate_board(board, 1, 2, None)
    assert result.edges["L1"].nominal_mm is None and result.edges["L1"].length.n == 5
    assert "nominal_mm" not in result.to_json()["edges"]["L1"]
    with pytest.raises(EMRegError, match="edges_mm has 3 values"):
        evaluate_board(board, 1, 2, [1.0, 2.0, 3.0])


def test_write_evaluation_spec_layout(case_folder, tmp_path):
    folder, frame, *_ = case_folder
    case = open_case(folder)
    result = evaluate(frame.reference_to_image, 1, 2, case.settings.evaluation,
                      navigation=case.read_recording("navigation"), targets=case.read_targets(),
                      board=case.read_recording("board"), nominal_edges_mm=case.settings.board.edges_mm)
    write_evaluation(result, tmp_path / "evaluation.json")
    document = json.loads((tmp_path / "evaluation.json").read_text())
    # full precision in memory, 4 decimals on disk; reading back and writing again changes nothing
    assert result.tre.dwells[0].error_mm != round(result.tre.dwells[0].error_mm, 4)
    assert document["tre"]["dwells"][0]["error_mm"] == round(result.tre.dwells[0].error_mm, 4)
    again = read_evaluation(tmp_path / "evaluation.json")
    assert again.to_json() == document and again.tre.targets["T1"].n == 4
    assert set(document["tre"]) >= {"mean_mm", "std_mm", "targets"}
    assert set(document["tre"]["targets"]["T1"]) >= {"mean_mm", "std_mm", "n"}
    assert set(document["board"]["edges"]["L1"]) >= {"mean_mm", "std_mm", "n"}


def test_emreg_evaluate_command(case_folder, tmp_path):
    from EMRegModule.cli.main import main
    from EMRegModule.core.registration import RegistrationResult
    from EMRegModule.io.registration_files import write_registration

    folder, frame, *_ = case_folder
    write_registration(RegistrationResult(frame.reference_to_image, 14.0, 0.5, []), tmp_path / "reg")
    code = main(["evaluate", str(folder), "--registration", str(tmp_path / "reg" / "registration.json"),
                 "--out", str(tmp_path / "out"), "--quiet"])
    assert code == 0
    document = json.loads((tmp_path / "out" / "evaluation.json").read_text())
    assert document["tre"]["n"] == 12 and document["board"]["rounds"] == 5
