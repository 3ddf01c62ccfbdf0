"""The robot's own motion planning and the closed-loop step (EMRegModule.core.robot_motion), without a robot."""

from __future__ import annotations

import numpy as np
import pytest

from EMRegModule.core.handeye import motion_spread
from EMRegModule.core.robot_motion import (
    check_step,
    correct_flange,
    guide_error,
    keep_in_volume,
    plan_calibration_poses,
    spread_axes,
)
from EMRegModule.core.transforms import axis_angle_to_rotation, invert_rigid, make_transform, rotation_matrices
from EMRegModule.errors import NoSafeAnswerError


def _pose(rotvec, translation) -> np.ndarray:
    """A 4x4 pose (mm) from a rotation vector (radians) and a translation (mm)."""
    return make_transform(rotation_matrices(rotvec), translation)


START = _pose([np.pi, 0.0, 0.0], [550.0, 0.0, 520.0])


def test_calibration_poses_are_well_conditioned() -> None:
    axes = spread_axes(12)
    assert np.allclose(np.linalg.norm(axes, axis=1), 1.0) and np.all(axes[:, 2] >= 0)
    # spread: the axes' scatter has no small direction
    assert np.linalg.eigvalsh(axes.T @ axes / len(axes)).min() > 0.15
    poses = plan_calibration_poses(START, 12, 25.0, 20.0)
    turns = [np.degrees(np.arccos(np.clip((np.trace(START[:3, :3].T @ p[:3, :3]) - 1) / 2, -1, 1))) for p in poses]
    assert np.allclose(turns, 25.0)
    moved = np.linalg.norm(poses[:, :3, 3] - START[:3, 3], axis=1)
    assert np.all(moved <= 20.0 + 1e-9) and moved.max() > 15.0
    spread, second = motion_spread(np.concatenate([START[None], poses]))
    assert spread >= 25.0 and second > 8.0  # far above emreg handeye's minima (10 and 3 deg)


def test_poses_that_could_take_the_sensor_out_of_the_volume_are_left_out() -> None:
    poses = plan_calibration_poses(START, 12, 25.0, 20.0)
    assert keep_in_volume(START, poses, np.array([300.0, 0.0, 100.0]), 660.0).all()
    near_edge = keep_in_volume(START, poses, np.array([600.0, 0.0, 0.0]), 660.0, sensor_radius_mm=150.0)
    assert not near_edge.any()  # 600 + up to 20 mm + a 25 deg chord at 150 mm (65 mm) > 660


def test_guide_error_and_the_closed_loop_step() -> None:
    entry, target = np.array([10.0, 20.0, 30.0]), np.array([10.0, 20.0, 110.0])
    on_plan = _pose([0.0, 0.0, 0.3], entry)  # +z along Entry -> Target, any roll
    error = guide_error(on_plan, entry, target)
    assert error.exit_mm < 1e-9 and error.angle_deg < 1e-6 and error.tip_mm < 1e-9 and error.within(0.1, 0.1)
    off = _pose([np.radians(2.0), 0.0, 0.0], entry + [1.0, 0.0, 0.0])
    error = guide_error(off, entry, target)
    assert error.exit_mm == pytest.approx(1.0) and error.angle_deg == pytest.approx(2.0)
    assert error.tip_mm == pytest.approx(np.hypot(1.0 + 0.0, 80.0 * np.sin(np.radians(2.0))), rel=0.05)
    # the loop: a flange whose guide sits off by an unknown bump converges in one step when measured exactly
    guide_to_flange = _pose([0.1, 0.2, 0.0], [0.0, 30.0, 80.0])
    bump = _pose([0.02, -0.01, 0.0], [1.5, -1.0, 0.5])
    wanted_guide = on_plan
    flange = wanted_guide @ invert_rigid(guide_to_flange)  # planned with the unbumped guide
    seen = flange @ bump @ guide_to_flange
    corrected = correct_flange(flange, seen, wanted_guide)
    assert np.allclose(corrected @ bump @ guide_to_flange, wanted_guide, atol=1e-9)
    check_step(flange, corrected, 20.0, 5.0)
    with pytest.raises(NoSafeAnswerError, match="correction would move the flange"):
        check_step(flange, corrected, 0.5, 5.0)


def test_the_watch_stops_on_a_reference_jump_between_moves() -> None:
    """Between moves (nothing held), the slip detector's jump test on the reference's recent samples stops the
    robot; a still reference and a lone wild sample do not."""
    from EMRegModule.devices.robot.guard import TrackerWatch
    from EMRegModule.devices.samples import SensorSample

    rng = np.random.default_rng(1)
    watch = TrackerWatch(flange_port=3, reference_port=1, max_tracker_distance_mm=660.0, stale_s=10.0)
    rotation = axis_angle_to_rotation(np.array([0.0, 0.0, 1.0]), 0.3)

    def feed(position, count) -> None:
        for _ in range(count):
            watch.on_sample(SensorSample(1, 0.0, position + rng.normal(0, 0.02, 3), rotation))
            watch.on_sample(SensorSample(3, 0.0, np.array([300.0, 50.0, 100.0]), np.eye(3)))

    feed(np.array([200.0, 0.0, 50.0]), 40)
    assert watch.check() is None
    feed(np.array([205.0, 0.0, 50.0]), 1)  # one wild sample
    feed(np.array([200.0, 0.0, 50.0]), 12)
    assert watch.check() is None
    feed(np.array([202.0, 0.0, 50.0]), 12)  # the reference jumped 2 mm and stays
    assert "the reference sensor jumped (the slip detector" in watch.check()
