"""``franka://HOST``: a Franka FR3 or Panda through franky-control, the community's Python client over libfranka
(the robot's own network protocol). The same unmodified client drives the real robot and ``franky-sim``, a
MuJoCo simulation server that speaks the protocol.

Units at the boundary: franky speaks metres, radians and ``[x, y, z, w]`` quaternions; EMReg millimetres and 4x4
matrices. ``Flange`` is the robot's end-effector frame (``O_T_EE``: the flange with the end effector set in the
robot's own configuration). Moves are Cartesian (franky plans them with Ruckig within the velocity, acceleration
and jerk limits set here); a move runs in the background, so that :mod:`.guard` can stop it.
"""

from __future__ import annotations

import contextlib
import threading

import numpy as np

from ...errors import EMRegError, NoSafeAnswerError
from .driver import MotionLimits

#: Seconds to wait for the robot to take the connection (a second client waits while another is connected).
CONNECT_TIMEOUT_S = 10.0
#: Jerk limits follow the acceleration limits: this many times the acceleration, per second.
JERK_PER_ACCELERATION = 10.0


def _franky():
    try:
        import franky
    except ImportError:
        raise EMRegError("franka://: the robot driver needs franky-control (pip install 'emreg[robot]')") from None
    return franky


def _set_limit(limit, value: float) -> None:
    """Set a franky dynamics limit, never above the robot's own maximum."""
    limit.set(float(min(value, limit.max)))


class FrankaRobot:
    """A Franka FR3/Panda (or ``franky-sim``) at ``host`` (see the module docstring)."""

    def __init__(self, host: str, options: dict[str, str] | None = None) -> None:
        franky = _franky()
        self.franky = franky
        self.host = host
        self.robot = self._connect(franky, host)
        with contextlib.suppress(Exception):
            self.robot.recover_from_errors()
        self.description = f"Franka robot at {host} (franky-control, libfranka protocol)"
        self._closed = False

    @staticmethod
    def _connect(franky, host: str):
        """franky's client, connected; :class:`EMRegError` when the robot refuses or does not answer within
        ``CONNECT_TIMEOUT_S`` (the protocol serves one client at a time: a second one waits)."""
        answer: dict[str, object] = {}

        def connect() -> None:
            try:
                robot = franky.Robot(host, realtime_config=franky.RealtimeConfig.Ignore)
            except Exception as exc:  # franky.NetworkException, IncompatibleVersionException...
                answer["error"] = exc
                return
            if not answer.get("abandoned"):
                answer["robot"] = robot
            # given up meanwhile: dropped here, which disconnects, so that it never holds the robot

        thread = threading.Thread(target=connect, name="franka-connect", daemon=True)
        thread.start()
        thread.join(CONNECT_TIMEOUT_S)
        if thread.is_alive():
            answer["abandoned"] = True
            raise EMRegError(f"franka://{host}: no answer within {CONNECT_TIMEOUT_S:g} s; is another program in "
                             "control of the robot?")
        if "error" in answer:
            exc = answer["error"]
            raise EMRegError(f"franka://{host}: cannot connect ({type(exc).__name__}: {str(exc)[:120]}); is the "
                             "robot (or franky-sim) on, FCI active and the host right?")
        return answer["robot"]

    def flange_to_base(self) -> np.ndarray:
        """``FlangeToBase`` now (4x4, mm): the end-effector frame at the measured joint angles, through the robot's
        own kinematic model (libfranka's ``Model``: what ``O_T_EE`` is on the robot).

        Not the state's ``O_T_EE`` field itself: between moves, franky-sim 1.0.4 sends every other state with the
        ``O_T_EE`` the last move ended on while its joints still settle (its joint angles are always current)."""
        state = self.robot.state
        pose = self.robot.model.pose(self.franky.Frame.EndEffector, state.q, state.F_T_EE, state.EE_T_K)
        matrix = np.array(pose.matrix, dtype=float)
        matrix[:3, 3] *= 1000.0
        return matrix

    def apply_limits(self, limits: MotionLimits) -> None:
        """Set the Cartesian velocity, acceleration and jerk limits franky plans every move within."""
        robot = self.robot
        _set_limit(robot.translation_velocity_limit, limits.velocity_mm_s / 1000.0)
        _set_limit(robot.translation_acceleration_limit, limits.acceleration_mm_s2 / 1000.0)
        _set_limit(robot.translation_jerk_limit, JERK_PER_ACCELERATION * limits.acceleration_mm_s2 / 1000.0)
        _set_limit(robot.rotation_velocity_limit, np.radians(limits.rotation_deg_s))
        _set_limit(robot.rotation_acceleration_limit, np.radians(limits.rotation_acceleration_deg_s2))
        _set_limit(robot.rotation_jerk_limit, JERK_PER_ACCELERATION * np.radians(limits.rotation_acceleration_deg_s2))

    def start_move(self, flange_to_base: np.ndarray, limits: MotionLimits) -> None:
        """Start a Cartesian move of the flange to ``flange_to_base`` (4x4, mm); returns at once."""
        franky = self.franky
        self.apply_limits(limits)
        pose = np.array(flange_to_base, dtype=float)
        pose[:3, 3] /= 1000.0
        motion = franky.CartesianMotion(franky.Affine(pose), franky.ReferenceType.Absolute)
        try:
            self.robot.move(motion, asynchronous=True)
        except Exception as exc:
            raise NoSafeAnswerError(f"franka://{self.host}: the robot refused the move ({str(exc)[:160]})") from None

    def moving(self) -> bool:
        try:
            self.robot.poll_motion()  # raises what ended a move with an error
            return bool(self.robot.is_in_control)
        except Exception as exc:  # a reflex, a joint limit, an unreachable pose: the robot stopped itself
            with contextlib.suppress(Exception):
                self.robot.recover_from_errors()
            raise NoSafeAnswerError(f"franka://{self.host}: the robot stopped the move ({str(exc)[:160]})") from None

    def stop(self) -> None:
        with contextlib.suppress(Exception):
            self.robot.stop()
        with contextlib.suppress(Exception):
            self.robot.join_motion(timeout=2.0)
        with contextlib.suppress(Exception):
            self.robot.recover_from_errors()

    def close(self) -> None:
        if self._closed:
            return
        self._closed = True
        self.stop()
        # the protocol takes one client at a time: drop the client now (its destructor disconnects), not whenever
        # the garbage collector gets to it
        self.robot = None
