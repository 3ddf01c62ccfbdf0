"""The robot models of ``emreg robot-target`` (issue 39, section 2): FR3 / Panda forward kinematics against two
implementations we did not write (franky-sim's URDF through pinocchio, KinHEC's DH), inverse kinematics against
forward kinematics, and the roll about the needle's axis chosen to keep the arm furthest from its joint limits."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from EMRegModule.core.robot_kinematics import robot_model, seeds_around
from EMRegModule.core.robot_target import ROLL_STEP_DEG, plan_flange_pose, robot_target
from EMRegModule.core.transforms import axis_angle_to_rotation, invert_rigid
from EMRegModule.errors import NoSafeAnswerError


def _random_joints(model, rng, count: int, fraction: float = 0.6) -> np.ndarray:
    middle, half = (model.lower_rad + model.upper_rad) / 2, (model.upper_rad - model.lower_rad) / 2
    return middle + rng.uniform(-fraction, fraction, size=(count, model.joints)) * half


def test_fr3_forward_kinematics_is_franky_sims_urdf():
    """The flange (link 8) and a Franka hand's end effector (103.4 mm, -45 deg about z: franky-sim's TCP) where
    pinocchio puts them on franky-sim's FR3 URDF, to 1e-9 mm, and the joint limits are the URDF's."""
    pin = pytest.importorskip("pinocchio")
    franky_sim = pytest.importorskip("franky_sim")
    urdf = Path(franky_sim.__file__).parent / "assets" / "fr3.urdf"
    reference = pin.buildModelFromUrdf(str(urdf))
    data = reference.createData()
    flange = reference.getFrameId("fr3_link8")
    hand = robot_model("fr3", (0.0, 0.0, 103.4), (0.0, 0.0, -45.0))
    bare = robot_model("fr3")
    np.testing.assert_allclose(bare.lower_rad, reference.lowerPositionLimit[:7])
    np.testing.assert_allclose(bare.upper_rad, reference.upperPositionLimit[:7])
    tcp = np.eye(4)
    tcp[:3, :3] = axis_angle_to_rotation([0.0, 0.0, 1.0], -np.pi / 4)
    tcp[2, 3] = 103.4
    for q in _random_joints(bare, np.random.default_rng(1), 20, 1.0):
        pin.forwardKinematics(reference, data, np.concatenate([q, np.zeros(reference.nq - 7)]))
        pin.updateFramePlacements(reference, data)
        truth = data.oMf[flange].homogeneous.copy()
        truth[:3, 3] *= 1000.0
        np.testing.assert_allclose(bare.forward(q), truth, atol=1e-9)
        np.testing.assert_allclose(hand.forward(q), truth @ tcp, atol=1e-9)


def test_panda_forward_kinematics_is_kinhecs():
    kinhec = pytest.importorskip("kinhec.kinematics")
    from kinhec.robots import get_robot

    panda = robot_model("panda")
    theirs = get_robot("panda")
    q = _random_joints(panda, np.random.default_rng(2), 20, 1.0)
    truth = kinhec.forward_kinematics_batch(theirs, q)
    truth[:, :3, 3] *= 1000.0
    np.testing.assert_allclose(panda.forward(q), truth, atol=1e-9)
    np.testing.assert_allclose(panda.lower_rad, theirs.q_min)


def test_inverse_kinematics_reaches_what_forward_kinematics_says():
    """Poses of random configurations inside the limits: the solver, from Franka's ready pose and a few turned
    seeds, lands on each (FK of its answer within 1e-3 mm and 1e-6 rad), always within the joint limits."""
    model = robot_model("fr3", (0.0, 0.0, 103.4), (0.0, 0.0, -45.0))
    targets = model.forward(_random_joints(model, np.random.default_rng(3), 40))
    seeds = seeds_around(model)
    joints, reached = model.inverse(np.repeat(targets, len(seeds), axis=0), np.tile(seeds, (len(targets), 1)))
    reached_any = reached.reshape(len(targets), len(seeds)).any(axis=1)
    assert np.mean(reached_any) >= 0.9
    assert np.all((joints >= model.lower_rad) & (joints <= model.upper_rad))
    poses = model.forward(joints[reached])
    wanted = np.repeat(targets, len(seeds), axis=0)[reached]
    assert np.max(np.linalg.norm(poses[:, :3, 3] - wanted[:, :3, 3], axis=1)) < 1e-3
    turn = np.swapaxes(poses[:, :3, :3], 1, 2) @ wanted[:, :3, :3]
    assert np.max(np.arccos(np.clip((np.trace(turn, axis1=1, axis2=2) - 1) / 2, -1, 1))) < 1e-5


def _plan(model):
    """A plan in front of the robot: Entry 550 mm out at table height + 200 mm, the needle going down and away;
    the tracker, reference and registration identities (the plan given in the base frame)."""
    entry = np.array([550.0, 100.0, 200.0])
    target = entry + 70.0 * np.array([0.3, 0.1, -1.0]) / np.linalg.norm([0.3, 0.1, -1.0])
    guide_to_sensor = np.eye(4)
    guide_to_sensor[:3, 3] = [0.0, 15.0, 40.0]
    sensor_to_flange = np.eye(4)
    sensor_to_flange[:3, 3] = [0.0, -30.0, 60.0]
    return entry, target, np.eye(4), np.eye(4), np.eye(4), sensor_to_flange, guide_to_sensor


def test_the_roll_keeps_the_arm_furthest_from_its_joint_limits():
    """With the FR3's model the flange pose is one its joints reach (FK of the answer's joints), the guide's exit
    on Entry and its axis along the plan, and no other roll about the axis gives a larger margin to the limits
    (each roll solved on its own from the same seeds), while some come much nearer a limit."""
    model = robot_model("fr3", (0.0, 0.0, 103.4), (0.0, 0.0, -45.0))
    entry, target, *chain = _plan(model)
    flange, guide, roll, joints, margin = plan_flange_pose(entry, target, *chain, robot_model=model)
    np.testing.assert_allclose(model.forward(joints), flange, atol=1e-3)
    assert np.allclose(guide[:3, 3], entry) and np.allclose(guide[:3, 2], (target - entry) / 70.0)
    assert np.isclose(margin, model.limit_margin(joints)) and margin > 0.2
    seeds = seeds_around(model)
    guide_to_flange = chain[3] @ chain[4]
    margins = {}
    for other in np.arange(0.0, 360.0, 3 * ROLL_STEP_DEG):
        turned = guide.copy()
        turned[:3, :3] = guide[:3, :3] @ axis_angle_to_rotation([0.0, 0.0, 1.0], np.radians(other) - roll)
        q, ok = model.inverse(np.repeat((turned @ invert_rigid(guide_to_flange))[None], len(seeds), axis=0), seeds)
        margins[other] = float(np.max(np.where(ok, model.limit_margin(q), -np.inf)))
    assert margin >= max(margins.values()) - 1e-6
    assert min(margins.values()) < margin - 0.1  # the roll matters: some rolls come much nearer a limit
    print(f"\nchosen roll {np.degrees(roll):.0f} deg, margin {margin:.2f}; other rolls "
          f"{min(margins.values()):.2f} .. {max(margins.values()):.2f}")


def test_a_plan_the_robot_cannot_reach_is_refused():
    model = robot_model("panda")
    entry, target, *chain = _plan(model)
    far = np.array([1500.0, 0.0, 200.0])
    with pytest.raises(NoSafeAnswerError, match="cannot reach the plan at any roll") as refused:
        robot_target(far, far + (target - entry), *chain, np.zeros((13, 13)), 0.0, robot_model=model)
    assert "\n" not in str(refused.value)
