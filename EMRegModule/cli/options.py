"""The arguments of every ``emreg`` command, declared (no command's work here).

Every command, and ``emreg --help``, builds the whole parser, so this module imports only argparse and the names
of :mod:`EMRegModule.names`: a command's own modules (numpy, the pipeline, the devices) are imported when that
command runs (:data:`EMRegModule.cli.main.COMMANDS`). One function per command, ``<command>_arguments(parser)``,
and the options several commands share.
"""

from __future__ import annotations

import argparse

from ..names import (
    DEFAULT_IGTL_PORT,
    DEFAULT_RECONNECT_S,
    DEFAULT_TRAKSTAR_BAUD,
    MIN_RECORDED_SHARE,
)

# --- options several commands share -------------------------------------------------------------------------


def add_plan_option(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--plan", default=None, metavar="PLAN.mrk.json",
                        help="a planned trajectory, for guidance numbers: a Slicer markups Line (Entry, Target), "
                             "points labelled Entry and Target, or one target point; LPS or RAS as the file "
                             "declares (default: [navigation] plan)")


def add_sensor_options(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--reference-sensor", type=int, default=None, metavar="PORT",
                        help="port of the reference sensor (default 1 or case.toml [sensors])")
    parser.add_argument("--probe-sensor", type=int, default=None, metavar="PORT",
                        help="port of the probe sensor (default 2 or case.toml [sensors])")


def add_tool_option(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--tool", default=None, metavar="FILE",
                        help="a tracked tool's tip: tool_calibration.json, an ITK/Slicer TipToProbe transform "
                             "(.h5/.tfm/.txt) or a PLUS device-set .xml (default: [tool] calibration, else the "
                             "pinhole probe)")


def add_series_option(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--series", default=None, metavar="UID|NUMBER",
                        help="the DICOM series to use (Series Instance UID or series number; default: the CT "
                             "volume best for detection)")


def _add_limits(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--duration", type=float, default=None, metavar="S", help="stop after S seconds")
    parser.add_argument("--max-samples", type=int, default=None, metavar="N", help="stop after N samples / frames")


def _add_replay_options(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--fast", action="store_true", help="replay: as fast as possible, not at the recording's rate")
    parser.add_argument("--loop", action="store_true", help="replay: start again at the end")


def _add_watchdog_options(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--max-quality", type=float, default=None, metavar="Q",
                        help="worst acceptable tracker quality number, 0 = best (default: 20 for the trakSTAR's "
                             "METAL number, 1 mm for the Aurora's RMS error; -1: do not check)")
    parser.add_argument("--stale-periods", type=float, default=3.0, metavar="K",
                        help="data are stale after K sample periods without a sample (default 3)")


def add_live_navigate_arguments(parser: argparse.ArgumentParser) -> None:
    """Options of live ``emreg navigate`` beyond those of the replay."""
    parser.add_argument("--host", default="127.0.0.1", help="address the OpenIGTLink server listens on")
    parser.add_argument("--reconnect", type=float, default=DEFAULT_RECONNECT_S, metavar="S",
                        help="when the tracker is lost, try to reopen it once a second for up to S seconds "
                             f"(default {DEFAULT_RECONNECT_S:g}; 0: end at once); STATUS is not OK meanwhile")
    _add_replay_options(parser)
    _add_limits(parser)
    _add_watchdog_options(parser)


# --- emreg simulate, study ----------------------------------------------------------------------------------


def simulate_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("out", metavar="OUT")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--difficulty", choices=("standard", "hard"), default="standard")
    p.add_argument("--spacing", type=float, default=None, metavar="MM", help="CT voxel size in mm")
    p.add_argument("--probe-axis", choices=("+x_in", "+x_out", "none"), default=None,
                   help="probe convention of the recordings: +X into the hole (default), out of it, or "
                        "position only")
    p.add_argument("--tool-tip", type=float, nargs=3, default=None, metavar=("X", "Y", "Z"),
                   help="touch with a stylus whose tip is at X Y Z mm in its sensor's frame (pivoting at the "
                        "pinholes; writes tool_calibration.json, pivot.csv and [tool] calibration)")
    p.add_argument("--distortion", type=float, default=0.0, metavar="MM",
                   help="a steel rod beside the frame distorts the field: RMS non-rigid error (mm) it leaves at the "
                        "calibrated pinholes after the best rigid fit (truth.json 'distortion')")
    p.add_argument("--distortion-during", choices=("calibration", "navigation", "both"), default="both",
                   help="the recordings the rod is in (default both; the navigation is then recorded where the "
                        "frame was calibrated)")
    p.add_argument("--distortion-onset", type=float, default=None, metavar="S",
                   help="the rod is rolled in S seconds into the first recording it is in (default: there from "
                        "the start)")


def study_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("name", metavar="NAME", help="calibration, board, tre, noise, markers, prediction, tool or trust")
    p.add_argument("--out", required=True, metavar="DIR")
    p.add_argument("--quick", action="store_true", help="a small frame and few sessions (a smoke-sized run)")
    p.add_argument("--scheduler", metavar="tcp://HOST:PORT", help="an existing Dask scheduler (default: a local one)")
    p.add_argument("--workers", type=int, default=None, metavar="N", help="local worker processes (default 2)")
    p.add_argument("--case", metavar="CASE", help="a simulated case folder with truth.json (default: simulate one)")
    p.add_argument("--work", metavar="DIR", help="where the simulated case and its detection are kept (OUT/work)")
    p.add_argument("--seed", type=int, default=1, help="seed of the simulated case")
    p.add_argument("--only", action="append", default=[], metavar="KEY=VALUE[,VALUE]",
                   help="run only the tasks whose parameter KEY takes one of these values, each with the seed it has "
                        "in the whole study (e.g. --only family=clean,magpylib,multi for trust's held-out families); "
                        "repeat for several keys")


# --- the per-stage commands ---------------------------------------------------------------------------------


def detect_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("ct", metavar="CT_OR_CASE", help="a CT file, a DICOM folder, or a case folder")
    p.add_argument("--out", required=True, metavar="OUT")
    add_series_option(p)


def calibrate_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("recording", metavar="RECORDING")
    p.add_argument("--out", required=True, metavar="OUT")
    add_sensor_options(p)
    add_tool_option(p)


def pivot_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("recording", metavar="RECORDING", help="the tip resting in a divot while the tool swings")
    p.add_argument("--out", required=True, metavar="OUT")
    add_sensor_options(p)


def register_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("--markers", metavar="markers.json", help="the CT markers of emreg detect")
    p.add_argument("--fiducials", metavar="FILE",
                   help="fiducial points instead of CT markers: a Slicer markups file (.mrk.json in LPS or RAS, "
                        ".fcsv), a PLUS device-set XML with <PhantomDefinition> landmarks, or markers.json; "
                        "a rigid point fit of the calibration points (tool tips) onto them, no sensor offset")
    p.add_argument("--calibration", required=True, metavar="frame_calibration.json")
    p.add_argument("--targets", metavar="targets.mrk.json", help="targets for the predicted TRE")
    p.add_argument("--out", required=True, metavar="OUT")


def navigate_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("--registration", required=True, metavar="registration.json")
    p.add_argument("--source", required=True, metavar="URL",
                   help="replay:FILE.csv, trakstar:///dev/ttyUSB0?baud=115200 or igtl://HOST:PORT")
    p.add_argument("--out", metavar="OUT")
    p.add_argument("--igtl-port", type=int, default=None, metavar="PORT",
                   help="publish ProbeToImage over OpenIGTLink (with --tool: <Name>TipToImage; with --plan also "
                        "TrajectoryToImage, the POINT Plan and the STRING Guidance)")
    add_sensor_options(p)
    add_tool_option(p)
    add_plan_option(p)
    add_live_navigate_arguments(p)


def evaluate_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("case", metavar="CASE")
    p.add_argument("--registration", required=True, metavar="registration.json")
    p.add_argument("--out", required=True, metavar="OUT")
    add_sensor_options(p)
    add_tool_option(p)


# --- emreg convert, report, run, demo -----------------------------------------------------------------------


def convert_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("input", metavar="IN")
    p.add_argument("output", metavar="OUT")
    p.add_argument("--quaternion", action="store_true", help="write CSV orientations as qw,qx,qy,qz")
    add_sensor_options(p)


def report_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("out", nargs="?", metavar="OUT")
    p.add_argument("--case", metavar="CASE", help="the case folder (for the CT), when not recorded in OUT")
    p.add_argument("--batch", metavar="DIR", help="render a report in every output folder under DIR")
    p.add_argument("--jobs", type=int, default=1,
                   help="reports rendered at a time with --batch (lowered to what the available memory holds)")


def run_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("case", metavar="CASE")
    p.add_argument("--out", required=True, metavar="OUT")
    add_series_option(p)
    add_sensor_options(p)
    add_tool_option(p)
    add_plan_option(p)


def demo_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("--out", default="demo-output", metavar="DIR")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--spacing", type=float, default=None, metavar="MM")


# --- the live commands: record, sim-tracker, serve ----------------------------------------------------------


def record_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--device", required=True, metavar="URL",
                        help="trakstar:///dev/ttyUSB0?baud=115200, aurora:///dev/ttyUSB0, igtl://HOST:PORT or "
                             "replay:FILE.csv")
    parser.add_argument("--out", required=True, metavar="rec.csv",
                        help="tracking CSV to write (flushed every second), or a PLUS sequence metafile "
                             "rec.seq.mha (written at the end; samples kept meanwhile in rec.seq.mha.partial.csv); "
                             f"a recording whose reference or probe has under {100 * MIN_RECORDED_SHARE:g} %% of "
                             "the expected samples exits 3 and is removed, or moved to OUT.incomplete")
    parser.add_argument("--reference-sensor", type=int, default=None, metavar="PORT")
    parser.add_argument("--probe-sensor", type=int, default=None, metavar="PORT")
    _add_limits(parser)
    _add_replay_options(parser)


def sim_tracker_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--model", choices=("trakstar", "aurora"), default="trakstar",
                        help="trakstar (Flock-of-Birds binary RS-232) or aurora (NDI serial API: BX/TX, CRC16)")
    parser.add_argument("--tools", default=None, metavar="1:6dof,2:5dof,...",
                        help="aurora: tools on ports 1-4 (6dof, 5dof, 5dof2 = two on a splitter, nosrom, none); "
                             "default: a 6-DOF tool on every port the scene has")
    parser.add_argument("--rate", type=float, default=None, metavar="HZ",
                        help="aurora: measuring rate (default 40 Hz; a replay: its recording's rate)")
    parser.add_argument("--freeze-tag", default=None, metavar="TAG",
                        help="aurora: firmware tag VER reports (default 'AURORA Rev 013'; 'AURORA Rev 008' makes "
                             "scikit-surgerynditracker use TX)")
    parser.add_argument("--replay", metavar="FILE.csv", help="replay this tracking recording (default: built-in scene)")
    parser.add_argument("--fast", action="store_true", help="STREAM as fast as the baud rate allows")
    parser.add_argument("--baud", type=int, default=DEFAULT_TRAKSTAR_BAUD,
                        help=f"line speed to emulate (default {DEFAULT_TRAKSTAR_BAUD})")
    parser.add_argument("--link", metavar="PATH", help="also make PATH a symbolic link to the pty (like socat's link)")
    parser.add_argument("--seed", type=int, default=0, help="seed of the scene and of the faults")
    parser.add_argument("--fault", action="append", default=[], metavar="KIND=VALUE",
                        help="inject faults: drop=P, flip=P, corrupt=P (per byte), stall=EVERY_S:DURATION_S, "
                             "late=P:DELAY_S (a POINT reply DELAY_S late), "
                             "unplug=SENSOR@START-END, out-of-range=SENSOR@START-END (repeatable)")
    parser.add_argument("--attached", default=None, metavar="1,2,3,4", help="ports with a sensor (default all)")
    parser.add_argument("--duration", type=float, default=None, metavar="S", help="stop after S seconds")
    parser.add_argument("--max-records", type=int, default=None, metavar="N", help="stop after N records sent")
    parser.add_argument("--emit-log", metavar="FILE.csv", help="at exit, write every record sent: seq, sensor, "
                        "monotonic ns of its last byte, truth position (for latency measurements)")
    parser.add_argument("--distortion", default=None, metavar="MM[@X,Y,Z,R]",
                        help="field distortion the tracker flags: MM everywhere, or MM at R mm from a metal object at "
                             "X,Y,Z (tracker frame, falling off as 1/r^3); trakstar: the METAL byte (40 per mm), "
                             "aurora: the tools' RMS error (+MM)")
    parser.add_argument("--volume", default=None, metavar="X0,Y0,Z0,X1,Y1,Z1[:MARGIN]",
                        help="aurora: the characterised volume (tracker frame, mm): a tool outside is out of volume, "
                             "within MARGIN (10) mm of a face partly out")


def serve_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--device", required=True, metavar="URL",
                        help="trakstar:///dev/ttyUSB0?baud=115200, aurora:///dev/ttyUSB0, igtl://HOST:PORT or "
                             "replay:FILE.csv")
    parser.add_argument("--igtl-port", type=int, default=DEFAULT_IGTL_PORT, metavar="PORT",
                        help=f"OpenIGTLink port (default {DEFAULT_IGTL_PORT})")
    parser.add_argument("--host", default="127.0.0.1", help="address to listen on (default 127.0.0.1)")
    parser.add_argument("--reference-sensor", type=int, default=None, metavar="PORT")
    parser.add_argument("--probe-sensor", type=int, default=None, metavar="PORT")
    _add_limits(parser)
    _add_replay_options(parser)
    _add_watchdog_options(parser)


# --- the robot commands -------------------------------------------------------------------------------------


def handeye_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("--robot-poses", required=True, metavar="ROBOT",
                   help="the flange's poses in the robot base frame (FlangeToBase): a TUM trajectory file "
                        "(timestamp tx ty tz qx qy qz qw; s, m) or a PLUS sequence file ([handeye] flange_transform)")
    p.add_argument("--tracker", required=True, metavar="TRACKER",
                   help="the flange sensor's recording: a PLUS sequence file or EMReg tracking CSV")
    p.add_argument("--sensor", default=None, metavar="NAME|PORT",
                   help="the flange's sensor when TRACKER holds several: a transform name or a port")
    p.add_argument("--out", required=True, metavar="OUT", help="output folder (robot_calibration.json, .h5)")


def robot_target_arguments(t: argparse.ArgumentParser) -> None:
    t.add_argument("--registration", required=True, metavar="R", help="registration.json (ReferenceToImage)")
    t.add_argument("--robot-calibration", required=True, metavar="C", help="robot_calibration.json (emreg handeye)")
    t.add_argument("--reference", required=True, metavar="REF",
                   help="the reference sensor now: a recording or a live source URL (trakstar:, aurora:, igtl:, "
                        "replay:), its samples averaged robustly")
    t.add_argument("--reference-sensor", type=int, default=None, metavar="PORT",
                   help="the reference sensor's port (default [sensors] reference)")
    t.add_argument("--plan", required=True, metavar="PLAN",
                   help="Slicer markups: a Line Entry -> Target, or points labelled Entry and Target")
    t.add_argument("--tool", required=True, metavar="GUIDE",
                   help="the needle guide on the flange sensor: a PLUS device set (From=NeedleGuide To=Sensor), an "
                        "ITK/Slicer transform or tool_calibration.json")
    t.add_argument("--out", required=True, metavar="OUT", help="output folder (robot_target.json)")


def robot_calibrate_arguments(c: argparse.ArgumentParser) -> None:
    c.add_argument("--robot", required=True, metavar="URL", help="the robot: franka://HOST")
    c.add_argument("--tracker", required=True, metavar="URL",
                   help="the tracker: a device URL (trakstar:, aurora:, igtl:)")
    c.add_argument("--sensor", type=int, default=None, metavar="PORT",
                   help="the flange sensor's port (default [robot] flange_sensor)")
    c.add_argument("--out", required=True, metavar="OUT", help="output folder (robot_calibration.json, .h5, .tum)")
    c.add_argument("--execute", action="store_true", help="move the robot (without it: print the planned poses)")


def robot_go_arguments(g: argparse.ArgumentParser) -> None:
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
