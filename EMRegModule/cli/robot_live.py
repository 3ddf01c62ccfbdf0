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

from .args import AddCommand, out_folder, settings_of


def cmd_robot_calibrate(args: argparse.Namespace) -> int:
    from ..pipeline.robot_live import robot_calibrate

    out = out_folder(args.out, create=args.execute)
    robot_calibrate(args.robot, args.tracker, Path(out), settings_of(args), args.sensor, args.execute)
    return 0


def cmd_robot_go(args: argparse.Namespace) -> int:
    from ..pipeline.robot_live import robot_go

    out = out_folder(args.out, create=args.execute) if args.out else None
    robot_go(args.robot, args.tracker, args.target, settings_of(args), args.sensor, args.reference_sensor,
             args.igtl_port, Path(out) if out is not None else None, args.execute)
    return 0


def add_parsers(add: AddCommand) -> None:
    """The subcommands of this module (``add``: :data:`~EMRegModule.cli.args.AddCommand`)."""
    from ..names import DEFAULT_IGTL_PORT

    c = add("robot-calibrate", cmd_robot_calibrate, "move the robot through calibration poses it plans itself and "
            "solve SensorToFlange and TrackerToBase (dry run without --execute)")
    c.add_argument("--robot", required=True, metavar="URL", help="the robot: franka://HOST")
    c.add_argument("--tracker", required=True, metavar="URL",
                   help="the tracker: a device URL (trakstar:, aurora:, igtl:)")
    c.add_argument("--sensor", type=int, default=None, metavar="PORT",
                   help="the flange sensor's port (default [robot] flange_sensor)")
    c.add_argument("--out", required=True, metavar="OUT", help="output folder (robot_calibration.json, .h5, .tum)")
    c.add_argument("--execute", action="store_true", help="move the robot (without it: print the planned poses)")
    g = add("robot-go", cmd_robot_go, "move the needle guide onto the plan and correct it with the EM tracker until "
            "it is within tolerance (dry run without --execute)")
    g.add_argument("--robot", required=True, metavar="URL", help="the robot: franka://HOST")
    g.add_argument("--tracker", required=True, metavar="URL",
                   help="the tracker: a device URL (trakstar:, aurora:, igtl:)")
    g.add_argument("--target", required=True, metavar="TARGET", help="robot_target.json (emreg robot-target)")
    g.add_argument("--sensor", type=int, default=None, metavar="PORT",
                   help="the flange sensor's port (default [robot] flange_sensor)")
    g.add_argument("--reference-sensor", type=int, default=None, metavar="PORT",
                   help="the reference sensor's port (default [sensors] reference)")
    g.add_argument("--igtl-port", type=int, default=DEFAULT_IGTL_PORT, metavar="PORT",
                   help=f"stream NeedleGuideToRAS on this OpenIGTLink port (default {DEFAULT_IGTL_PORT}; 0: any free)")
    g.add_argument("--out", default=None, metavar="OUT", help="output folder for robot_go.json (optional)")
    g.add_argument("--execute", action="store_true", help="move the robot (without it: print the planned motion)")
