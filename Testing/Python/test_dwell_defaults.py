"""Evaluation dwell defaults: a hand-held probe held still for 0.4 s at 80 Hz within 1 mm of a
target is a dwell; transit motion (fast, slow, a short hesitation) is not. A search that finds
nothing says what it found and which setting to change.
"""

from __future__ import annotations

import numpy as np
import pytest

from EMRegModule.core.dwell import describe_still_periods, find_dwells
from EMRegModule.settings import EvaluationSettings, Settings


def evaluation_dwell_settings(table: dict) -> EvaluationSettings:
    """The ``[evaluation]`` table as ``case.toml`` would give it (defaults where absent)."""
    return Settings.from_mapping({"evaluation": table}, "test").evaluation

RATE_HZ = 80.0


def _min_jerk(n: int) -> np.ndarray:
    s = np.linspace(0.0, 1.0, n)
    return 10 * s**3 - 15 * s**4 + 6 * s**5


def _travel(a: np.ndarray, b: np.ndarray, speed_mm_s: float) -> np.ndarray:
    """Hand-held travel from a to b with a minimum-jerk profile (stops only at the ends)."""
    n = max(8, int(RATE_HZ * np.linalg.norm(b - a) / speed_mm_s))
    return a + (b - a) * _min_jerk(n)[:, None]


def _hand_held(rng: np.random.Generator, target: np.ndarray, n: int, radius_mm: float) -> np.ndarray:
    """n samples wobbling smoothly around a target, every one within ``radius_mm`` of it."""
    wobble = np.cumsum(rng.normal(0, 1, (n, 3)), axis=0)
    wobble -= wobble.mean(axis=0)
    wobble += rng.normal(0, 0.3, (n, 3))  # tracker jitter on top of the hand
    wobble *= radius_mm / np.max(np.linalg.norm(wobble, axis=1))
    return target + wobble


def _track(parts: list[np.ndarray]) -> tuple[np.ndarray, np.ndarray]:
    position = np.vstack(parts)
    return np.arange(len(position)) / RATE_HZ, position


def test_the_defaults_are_what_the_evaluation_uses():
    settings = evaluation_dwell_settings({})
    assert settings.min_duration_s == 0.35
    assert settings.still_radius_mm == 1.0
    assert settings.drift_limit_mm == 2.0
    assert Settings().calibration.min_duration_s == 0.5  # a probe resting in a pinhole: unchanged
    assert evaluation_dwell_settings({"min_duration_s": 0.8, "max_target_distance_mm": 5}).min_duration_s == 0.8


@pytest.mark.parametrize("seed", range(8))
def test_a_hand_held_probe_still_for_0_4_s_within_1_mm_is_a_dwell(seed):
    rng = np.random.default_rng(seed)
    target = rng.uniform(-100, 100, 3)
    start, end = target + rng.normal(0, 60, 3), target + rng.normal(0, 60, 3)
    held = _hand_held(rng, target, int(0.4 * RATE_HZ), radius_mm=1.0)  # 32 samples = 0.4 s at 80 Hz
    assert np.max(np.linalg.norm(held - target, axis=1)) <= 1.0 + 1e-9
    time_s, position = _track([_travel(start, held[0], 150.0), held, _travel(held[-1], end, 150.0)])
    dwells = find_dwells(time_s, position, settings=evaluation_dwell_settings({}))
    assert len(dwells) == 1
    mean = position[dwells[0].indices].mean(axis=0)
    assert np.linalg.norm(mean - target) < 1.0
    assert dwells[0].duration_s >= 0.35


@pytest.mark.parametrize("mean_speed_mm_s", [40.0, 80.0, 150.0, 250.0])
def test_transit_motion_is_not_a_dwell(mean_speed_mm_s):
    """A hand-held sweep over the frame: a smooth curve whose speed swings between a fifth of the
    mean and nearly twice it (never stopping), with the hand's wobble on top."""
    rng = np.random.default_rng(int(mean_speed_mm_s))
    n = int(4.0 * RATE_HZ)
    phase = np.linspace(0, 2 * np.pi, n)
    speed = mean_speed_mm_s * (1.0 + 0.8 * np.sin(3 * phase + rng.uniform(0, 2 * np.pi)))
    heading = np.column_stack([np.cos(phase + 1.3 * np.sin(2 * phase)), np.sin(phase + 1.3 * np.sin(2 * phase)),
                               0.3 * np.sin(5 * phase)])
    heading /= np.linalg.norm(heading, axis=1, keepdims=True)
    position = np.cumsum(heading * speed[:, None] / RATE_HZ, axis=0) + rng.normal(0, 0.15, (n, 3))
    time_s = np.arange(n) / RATE_HZ
    assert find_dwells(time_s, position, settings=evaluation_dwell_settings({})) == []


def test_the_simulators_transitions_with_mid_air_hesitations_are_not_dwells():
    from EMRegModule.simulation.tracking import _travel as simulated_travel

    rng = np.random.default_rng(11)
    holes = rng.uniform(-150, 150, (12, 3))
    poses = []
    for hole in holes:
        pose = np.eye(4)
        pose[:3, 3] = hole
        poses.append(pose)
    parts = []
    for a, b in zip(poses[:-1], poses[1:], strict=True):
        path = simulated_travel(rng, a, b, np.array([0, 0, 1.0]), np.array([0, 0, 1.0]), np.zeros(3), 20.0,
                                hesitate=True)
        parts.append(np.array([p[:3, 3] for p in path]))
    time_s, position = _track(parts)
    dwells = find_dwells(time_s, position, settings=evaluation_dwell_settings({}))
    # only the holes themselves may look still (each travel starts and ends there); never mid-air
    for dwell in dwells:
        centre = position[dwell.indices].mean(axis=0)
        assert np.min(np.linalg.norm(holes - centre, axis=1)) < 2.0


def test_slow_steady_drift_and_a_short_hesitation_are_not_dwells():
    rng = np.random.default_rng(5)
    a, b = np.zeros(3), np.array([12.0, 0.0, 0.0])
    drift = a + (b - a) * np.linspace(0, 1, int(1.2 * RATE_HZ))[:, None]  # 10 mm/s for 1.2 s
    drift += rng.normal(0, 0.1, drift.shape)
    pause = _hand_held(rng, b + [0, 40, 0], int(0.2 * RATE_HZ), radius_mm=0.8)  # a 0.2 s hesitation
    time_s, position = _track([_travel(b + [0, 0, 80], a, 150), drift, _travel(b, pause[0], 150), pause,
                               _travel(pause[-1], b + [80, 80, 0], 150)])
    assert find_dwells(time_s, position, settings=evaluation_dwell_settings({})) == []


def test_a_search_that_finds_nothing_says_what_it_found():
    rng = np.random.default_rng(7)
    target = np.array([10.0, 20.0, 30.0])
    held = _hand_held(rng, target + [0.4, 0, 0], int(0.2 * RATE_HZ), radius_mm=0.8)
    time_s, position = _track([_travel(target + 50, held[0], 150), held, _travel(held[-1], target - 50, 150)])
    settings = evaluation_dwell_settings({})
    assert find_dwells(time_s, position, settings=settings) == []
    text = describe_still_periods(time_s, position, None, settings, target[None], "target")
    assert text.startswith("1 still period(s) found: 0.")
    assert "mm from the nearest target" in text and "[evaluation] min_duration_s" in text
    assert "lower [evaluation] min_duration_s" in text
