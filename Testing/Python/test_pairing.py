"""Automatic pairing: correct with missing and extra points, refuses symmetric layouts and too few pairs."""

from __future__ import annotations

import numpy as np
import pytest
from synth_registration import make_frame, pairing_problem, symmetric_layout

from EMRegModule.core.pairing import PairingSettings, pair_markers
from EMRegModule.errors import NoSafeAnswerError

L_RANGE = (11.0, 18.5)


def _pair(problem, settings=None, directions=True):
    return pair_markers(problem.origins_image, problem.axes_image, problem.points_reference,
                        problem.directions_reference if directions else None, L_RANGE, settings)


@pytest.mark.parametrize("seed", range(12))
def test_pairs_28_markers_with_3_missing_and_3_extra_per_side(seed):
    problem = pairing_problem(seed)
    result = _pair(problem)
    assert problem.correct(result.pairs)
    assert result.support == problem.expected_pairs
    assert abs(result.l_mm - problem.frame.l_mm) < 0.5
    assert result.rival_support < result.support - 5


@pytest.mark.parametrize("l_mm", [11.0, 18.5])
def test_pairs_with_the_offset_at_either_end_of_the_pinhole(l_mm):
    problem = pairing_problem(40, l_mm=l_mm, tracker_error_mm=0.8, image_error_mm=0.3)
    result = _pair(problem)
    assert problem.correct(result.pairs) and result.support == problem.expected_pairs


def test_pairs_without_directions():
    problem = pairing_problem(41)
    result = _pair(problem, directions=False)
    assert problem.correct(result.pairs) and result.support == problem.expected_pairs


def test_pairs_100_markers():
    problem = pairing_problem(42, n_markers=100, missing_image=5, extra_image=5, missing_calibration=5,
                              extra_calibration=5)
    result = _pair(problem)
    assert problem.correct(result.pairs) and result.support == problem.expected_pairs


def test_pairs_a_small_frame():
    problem = pairing_problem(43, n_markers=7, missing_image=1, extra_image=2, missing_calibration=1,
                              extra_calibration=1)
    result = _pair(problem)
    assert problem.correct(result.pairs) and result.support == problem.expected_pairs


@pytest.mark.parametrize("drop", [0, 1, 3])
def test_symmetric_frame_is_refused(drop):
    layout = symmetric_layout()
    frame = make_frame(7, layout=layout)
    # Image markers missing do not break the symmetry when every marker was calibrated.
    problem = pairing_problem(7, frame=frame, missing_image=drop, extra_image=1, missing_calibration=0,
                              extra_calibration=0)
    with pytest.raises(NoSafeAnswerError, match="ambiguous pairing"):
        _pair(problem)


def test_symmetry_broken_by_enough_points_is_accepted():
    origins, axes = symmetric_layout()
    # Three markers of one half exist only on that side: the rival pairing explains 3 fewer points.
    frame = make_frame(8, layout=(np.delete(origins, [14, 15, 16], axis=0), np.delete(axes, [14, 15, 16], axis=0)))
    problem = pairing_problem(8, frame=frame, missing_image=0, extra_image=0, missing_calibration=0,
                              extra_calibration=0)
    result = _pair(problem)
    assert problem.correct(result.pairs) and result.support == 25
    assert result.rival_support == 22


def test_too_few_markers_is_refused():
    problem = pairing_problem(44, n_markers=5, missing_image=2, extra_image=0, missing_calibration=0,
                              extra_calibration=0)
    with pytest.raises(NoSafeAnswerError, match="at least 4"):
        _pair(problem)


def test_unrelated_point_sets_are_refused():
    problem = pairing_problem(45)
    other = pairing_problem(46)
    with pytest.raises(NoSafeAnswerError, match="paired consistently"):
        pair_markers(problem.origins_image, problem.axes_image, other.points_reference,
                     other.directions_reference, L_RANGE)


def test_settings_from_case_toml():
    settings = PairingSettings.from_settings({"tracker_error_mm": 1.0, "min_pairs": 6, "max_fre_mm": 3})
    assert settings.tracker_error_mm == 1.0 and settings.min_pairs == 6 and isinstance(settings.min_pairs, int)
    assert settings.point_tolerance_mm == pytest.approx(4 * np.hypot(1.0, 0.3))


def test_a_near_duplicate_calibration_point_is_not_an_ambiguity():
    problem = pairing_problem(47, missing_image=0, extra_image=0, missing_calibration=0, extra_calibration=0)
    # The probe was also held 3.5 mm short of the bottom in pinhole 0 (a second, shallower dwell).
    duplicate = problem.points_reference[0] + 3.5 * problem.directions_reference[0]
    points = np.vstack([problem.points_reference, duplicate])
    directions = np.vstack([problem.directions_reference, problem.directions_reference[:1]])
    result = pair_markers(problem.origins_image, problem.axes_image, points, directions, L_RANGE)
    truth = np.append(problem.calibration_truth, problem.calibration_truth[0])
    assert all(problem.image_truth[j] == truth[i] for j, i in result.pairs)
    assert result.support == 28
