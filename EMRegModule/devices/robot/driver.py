"""What a robot is to EMReg (the URL that names one: :mod:`.url`).

A robot driver does four things: connect, report the flange's pose (``FlangeToBase``, 4x4, mm), move the flange
to a pose within velocity and acceleration limits (interruptible: a move runs in the background and
:meth:`RobotDriver.stop` ends it), and stop. ``Flange`` is the frame the robot's controller reports and commands
(for a Franka: ``O_T_EE``, its end-effector frame); ``Base`` its base frame.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Protocol

import numpy as np


@dataclass(frozen=True)
class MotionLimits:
    """Limits of a move: the flange's translational velocity (mm/s) and acceleration (mm/s^2), its rotational
    velocity (deg/s) and acceleration (deg/s^2)."""

    velocity_mm_s: float = 50.0
    acceleration_mm_s2: float = 250.0
    rotation_deg_s: float = 20.0
    rotation_acceleration_deg_s2: float = 90.0


class RobotDriver(Protocol):
    """A connected robot (see the module docstring)."""

    description: str

    def flange_to_base(self) -> np.ndarray:
        """The flange's pose now, ``FlangeToBase`` (4x4, mm)."""
        ...

    def start_move(self, flange_to_base: np.ndarray, limits: MotionLimits) -> None:
        """Start moving the flange to ``flange_to_base`` (4x4, mm) in a straight line within ``limits``; returns
        at once."""
        ...

    def moving(self) -> bool:
        """True while a move runs; raises :class:`EMRegError` (exit 3) when the robot ended it with an error."""
        ...

    def stop(self) -> None:
        """Stop any move now (the robot brakes to a standstill) and clear the error it left, if any."""
        ...

    def close(self) -> None:
        """Stop and disconnect (idempotent)."""
        ...
