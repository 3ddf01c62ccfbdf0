"""Kinematics of the robots EMReg knows, for choosing the needle guide's free roll and refusing what a robot cannot
reach: Franka FR3 and Panda (7 joints), from their published modified Denavit-Hartenberg parameters and joint
limits (Franka's robot and interface specifications). Pure: arrays in, arrays out; mm and radians.

Frames: ``Base`` (the robot's base, link 0), ``Flange`` as EMReg means it: the frame the robot's controller reports
and commands (Franka's ``O_T_EE``: the mechanical flange, link 8, times the end effector configured on the robot,
``F_T_EE``). :attr:`RobotModel.flange_to_end_effector` is that ``F_T_EE`` (identity: no end effector set).

Inverse kinematics (:meth:`RobotModel.inverse`) is damped least squares on a batch of seeds, with the redundant
joint's freedom spent pulling every joint toward the middle of its range; :func:`limit_margin` says how far a
configuration stays from its limits (1: every joint at its mid-range, 0: one at a limit).
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from ..errors import EMRegError
from .transforms import axis_angle_to_rotation, rotation_vectors

#: Modified DH rows (a mm, d mm, alpha rad) of joints 1..7 and the flange (Franka's published table; the same for
#: FR3 and Panda): link i is link i-1 turned by alpha about x, moved by a along x, turned by q_i about z, moved
#: by d along z.
FRANKA_DH = np.array([
    [0.0, 333.0, 0.0],
    [0.0, 0.0, -np.pi / 2],
    [0.0, 316.0, np.pi / 2],
    [82.5, 0.0, np.pi / 2],
    [-82.5, 384.0, -np.pi / 2],
    [0.0, 0.0, np.pi / 2],
    [88.0, 0.0, np.pi / 2],
    [0.0, 107.0, 0.0],
])


@dataclass(frozen=True)
class RobotModel:
    """A serial arm: ``dh`` (joints + 1, 3) modified DH rows (the last the flange, no joint), joint limits
    ``lower_rad`` / ``upper_rad`` (joints,), a configuration ``ready_rad`` well inside them, and the end
    effector ``flange_to_end_effector`` (4x4, mm)."""

    name: str
    dh: np.ndarray
    lower_rad: np.ndarray
    upper_rad: np.ndarray
    ready_rad: np.ndarray
    flange_to_end_effector: np.ndarray = field(default_factory=lambda: np.eye(4))

    @property
    def joints(self) -> int:
        return len(self.lower_rad)

    def _links(self, q: np.ndarray) -> np.ndarray:
        """Each link's pose in the base frame (B, joints + 2, 4, 4, mm) for configurations ``q`` (B, joints): links
        1..joints, the flange, then the end effector."""
        q = np.atleast_2d(q)
        batch = len(q)
        pose = np.tile(np.eye(4), (batch, 1, 1))
        out = []
        for i, (a, d, alpha) in enumerate(self.dh):
            theta = q[:, i] if i < self.joints else np.zeros(batch)
            ct, st, ca, sa = np.cos(theta), np.sin(theta), np.cos(alpha), np.sin(alpha)
            step = np.zeros((batch, 4, 4))
            step[:, 0, 0], step[:, 0, 1], step[:, 0, 3] = ct, -st, a
            step[:, 1, 0], step[:, 1, 1], step[:, 1, 2], step[:, 1, 3] = st * ca, ct * ca, -sa, -sa * d
            step[:, 2, 0], step[:, 2, 1], step[:, 2, 2], step[:, 2, 3] = st * sa, ct * sa, ca, ca * d
            step[:, 3, 3] = 1.0
            pose = pose @ step
            out.append(pose)
        out.append(pose @ self.flange_to_end_effector)
        return np.stack(out, axis=1)

    def forward(self, q: np.ndarray) -> np.ndarray:
        """``FlangeToBase`` (the end effector's pose, 4x4 mm; (B, 4, 4) for a batch) at joint angles ``q`` (rad)."""
        poses = self._links(q)[:, -1]
        return poses[0] if np.ndim(q) == 1 else poses

    def jacobian(self, q: np.ndarray) -> np.ndarray:
        """The geometric Jacobian (B, 6, joints): the end effector's linear velocity (mm/rad) and angular
        velocity (rad/rad), both in the base frame, per joint speed."""
        return self._jacobian(self._links(q))

    def _jacobian(self, links: np.ndarray) -> np.ndarray:
        tip = links[:, -1, :3, 3]
        axes = links[:, :self.joints, :3, 2]  # joint i turns about link i's z
        origins = links[:, :self.joints, :3, 3]
        linear = np.cross(axes, tip[:, None, :] - origins)
        return np.concatenate([np.swapaxes(linear, 1, 2), np.swapaxes(axes, 1, 2)], axis=1)

    def inverse(self, targets: np.ndarray, seeds: np.ndarray, iterations: int = 200, tolerance_mm: float = 1e-3,
                tolerance_rad: float = 1e-6) -> tuple[np.ndarray, np.ndarray]:
        """Joint angles (B, joints, rad) that put the end effector at ``targets`` (B, 4, 4, mm), each from its
        seed (B, joints), kept within the limits; and which of them reached their target (B,). Damped least
        squares, the redundant freedom spent pulling every joint toward the middle of its range; then a few
        steps without that pull, to land on the target exactly."""
        q = np.clip(np.array(seeds, dtype=float), self.lower_rad, self.upper_rad)
        q, _ = self._steps(q, targets, iterations, 0.2, tolerance_mm, tolerance_rad)
        return self._steps(q, targets, 40, 0.0, tolerance_mm, tolerance_rad)

    def _steps(self, q: np.ndarray, targets: np.ndarray, iterations: int, centre_gain: float, tolerance_mm: float,
               tolerance_rad: float) -> tuple[np.ndarray, np.ndarray]:
        middle, half_range = (self.lower_rad + self.upper_rad) / 2, (self.upper_rad - self.lower_rad) / 2
        lever = 100.0  # mm per rad: the rotation error's weight against the position error's
        for iteration in range(iterations + 1):
            links = self._links(q)
            pose = links[:, -1]
            position_error = targets[:, :3, 3] - pose[:, :3, 3]
            turn = rotation_vectors(np.swapaxes(pose[:, :3, :3], 1, 2) @ targets[:, :3, :3])
            rotation_error = (pose[:, :3, :3] @ turn[:, :, None])[:, :, 0]  # in the base frame
            done = ((np.linalg.norm(position_error, axis=1) < tolerance_mm)
                    & (np.linalg.norm(rotation_error, axis=1) < tolerance_rad))
            if iteration == iterations or (np.all(done) and centre_gain == 0.0):
                break
            jac = self._jacobian(links)
            jac[:, 3:] *= lever
            error = np.concatenate([position_error, lever * rotation_error], axis=1)
            pseudo = np.swapaxes(jac, 1, 2) @ np.linalg.inv(jac @ np.swapaxes(jac, 1, 2) + 1e-2 * np.eye(6))
            centre = -centre_gain * (q - middle) / half_range ** 2
            null = np.eye(self.joints) - pseudo @ jac
            step = (pseudo @ error[:, :, None])[:, :, 0] + (null @ centre[:, :, None])[:, :, 0]
            scale = np.minimum(1.0, 0.3 / np.maximum(np.max(np.abs(step), axis=1), 1e-12))  # at most 0.3 rad a step
            q = np.clip(q + step * scale[:, None], self.lower_rad, self.upper_rad)
        return q, done

    def limit_margin(self, q: np.ndarray) -> np.ndarray:
        """How far configurations (B, joints) stay from the joint limits: the least over the joints of the distance
        to the nearer limit as a fraction of half the joint's range (1: all at mid-range, 0: one at a limit)."""
        half_range = (self.upper_rad - self.lower_rad) / 2
        distance = np.minimum(q - self.lower_rad, self.upper_rad - q)
        return np.min(distance / half_range, axis=-1)


#: The models by ``[robot] model`` name: joint limits from Franka's datasheets (FR3, Panda).
MODELS = {
    "fr3": dict(lower=[-2.9007, -1.8361, -2.9007, -3.0770, -2.8763, 0.4398, -3.0508],
                upper=[2.9007, 1.8361, 2.9007, -0.1169, 2.8763, 4.6216, 3.0508]),
    "panda": dict(lower=[-2.8973, -1.7628, -2.8973, -3.0718, -2.8973, -0.0175, -2.8973],
                  upper=[2.8973, 1.7628, 2.8973, -0.0698, 2.8973, 3.7525, 2.8973]),
}

#: Franka's "ready" configuration (rad), well inside both models' limits.
FRANKA_READY = np.array([0.0, -np.pi / 4, 0.0, -3 * np.pi / 4, 0.0, np.pi / 2, np.pi / 4])


def robot_model(name: str, end_effector_mm=(0.0, 0.0, 0.0), end_effector_rpy_deg=(0.0, 0.0, 0.0)) -> RobotModel:
    """The model called ``name`` (``fr3``, ``panda``) with the end effector set on the robot (``F_T_EE``): its
    translation (mm) and roll-pitch-yaw (degrees, about the flange's fixed x, then y, then z)."""
    key = name.strip().lower()
    if key not in MODELS:
        raise EMRegError(f"robot model {name!r} is not known (known: {', '.join(MODELS)})")
    roll, pitch, yaw = np.radians(np.asarray(end_effector_rpy_deg, dtype=float))
    end_effector = np.eye(4)
    end_effector[:3, :3] = (axis_angle_to_rotation([0.0, 0.0, 1.0], yaw)
                            @ axis_angle_to_rotation([0.0, 1.0, 0.0], pitch)
                            @ axis_angle_to_rotation([1.0, 0.0, 0.0], roll))
    end_effector[:3, 3] = np.asarray(end_effector_mm, dtype=float)
    limits = MODELS[key]
    return RobotModel(key, FRANKA_DH, np.array(limits["lower"]), np.array(limits["upper"]), FRANKA_READY.copy(),
                      end_effector)


def seeds_around(model: RobotModel, count: int = 6) -> np.ndarray:
    """``count`` seed configurations (count, joints): the ready pose, then ready with the first joint and the
    elbow (joint 3) turned to spread the redundant arm's branches."""
    turns = np.array([[0.0, 0.0], [0.6, 0.0], [-0.6, 0.0], [0.0, 0.8], [0.0, -0.8], [0.6, 0.8], [-0.6, -0.8],
                      [1.2, 0.0], [-1.2, 0.0]])[:count]
    seeds = np.tile(model.ready_rad, (len(turns), 1))
    seeds[:, 0] += turns[:, 0]
    seeds[:, 2] += turns[:, 1]
    return np.clip(seeds, model.lower_rad, model.upper_rad)
