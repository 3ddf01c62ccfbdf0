"""The robot commands that move a robot (issue 39, section 3): ``emreg robot-calibrate`` and ``emreg robot-go``
parse their arguments and call :mod:`EMRegModule.pipeline.robot_live` (as the 3D Slicer module's robot panel does),
which prints the planned motion and, with ``--execute`` only, moves.

``emreg robot-calibrate --robot URL --tracker URL --out OUT [--sensor PORT] [--execute]``: calibration poses it plans
itself, then ``OUT/robot_calibration.json``, the two ``.h5`` and the recordings (``robot_poses.tum``,
``flange_sensor.tum``).

``emreg robot-go --robot URL --tracker URL --target OUT/robot_target.json [--out GO] [--execute]``: the needle guide
onto the plan, corrected with the tracker until it is within tolerance; ``--out`` writes ``GO/robot_go.json``.
"""

from __future__ import annotations

import argparse
from pathlib import Path

from ..pipeline.robot_live import robot_calibrate, robot_go
from .args import out_folder, settings_of


def cmd_robot_calibrate(args: argparse.Namespace) -> int:

    out = out_folder(args.out, create=args.execute)
    robot_calibrate(args.robot, args.tracker, Path(out), settings_of(args), args.sensor, args.execute)
    return 0


def cmd_robot_go(args: argparse.Namespace) -> int:

    out = out_folder(args.out, create=args.execute) if args.out else None
    robot_go(args.robot, args.tracker, args.target, settings_of(args), args.sensor, args.reference_sensor,
             args.igtl_port, Path(out) if out is not None else None, args.execute)
    return 0

