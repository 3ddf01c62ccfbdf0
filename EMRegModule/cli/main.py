"""The ``emreg`` command: the table of commands, signal handling and :func:`main`; each command's arguments are
declared in :mod:`.options` and its handler lives in :mod:`EMRegModule.cli` (one module per family), which parses,
calls the pipeline and prints.

Exit codes (spec): 0 success; 2 bad input or usage (one line naming the file and what is
wrong); 3 the data do not allow a safe answer. Every output file is written atomically.
"""

from __future__ import annotations

import argparse
import gc
import importlib
import os
import signal
import sys
import threading
from collections.abc import Callable, Sequence
from typing import NamedTuple

from .. import __version__
from ..errors import EXIT_BAD_INPUT, EMRegError
from ..interrupts import interrupted_by, note_interrupt
from . import options


class Command(NamedTuple):
    """An ``emreg`` command: its handler (``"module:function"``, imported when the command runs), its help line and
    the declaration of its arguments."""

    handler: str
    help: str
    arguments: Callable[[argparse.ArgumentParser], None]


_CLI = "EMRegModule.cli."

#: Every ``emreg`` command, in the order of ``--help``: its handler as ``"module:function"``, imported only when the
#: command runs (the one import a command makes on demand: ``emreg --help`` and the parser of every command load
#: no command's libraries), its help line, and the declaration of its arguments (:mod:`.options`).
COMMANDS: dict[str, Command] = {
    "simulate": Command(_CLI + "study:cmd_simulate",
                        "write a simulated case folder with its ground truth (truth.json)", options.simulate_arguments),
    "detect": Command(_CLI + "stages:cmd_detect", "find the markers in a CT: OUT/markers.json and markers.mrk.json",
                      options.detect_arguments),
    "calibrate": Command(_CLI + "stages:cmd_calibrate",
                         "frame calibration from a tracking recording: OUT/frame_calibration.json",
                         options.calibrate_arguments),
    "pivot": Command(_CLI + "stages:cmd_pivot",
                     "pivot calibration of a tool's tip: OUT/tool_calibration.json and TipToProbe.h5",
                     options.pivot_arguments),
    "register": Command(_CLI + "stages:cmd_register", "pair, solve the sensor offset, register: OUT/registration.json",
                        options.register_arguments),
    "navigate": Command(_CLI + "stages:cmd_navigate", "map probe samples into image space (replay or live)",
                        options.navigate_arguments),
    "evaluate": Command(_CLI + "stages:cmd_evaluate", "TRE at targets and the board table: OUT/evaluation.json",
                        options.evaluate_arguments),
    "convert": Command(_CLI + "convert:cmd_convert", "convert a tracking recording between CSV and a PLUS sequence "
                       "metafile (.seq.mha, .mha, .seq.nrrd)", options.convert_arguments),
    "report": Command(_CLI + "report:cmd_report", "render the verification report: OUT/report.html",
                      options.report_arguments),
    "run": Command(_CLI + "run:cmd_run", "run every stage on a case folder", options.run_arguments),
    "demo": Command(_CLI + "run:cmd_demo", "simulate the built-in sample case and run it", options.demo_arguments),
    "study": Command(_CLI + "study:cmd_study",
                     "an accuracy study on simulated data, run on Dask: OUT/NAME.json, .csv, .png",
                     options.study_arguments),
    "record": Command(_CLI + "live:run_record",
                      "record a tracking CSV from a trakSTAR, an OpenIGTLink server or a replay",
                      options.record_arguments),
    "sim-tracker": Command(_CLI + "live:run_sim_tracker",
                           "run a simulated trakSTAR on a pseudo-terminal (RS-232 protocol, fault injection)",
                           options.sim_tracker_arguments),
    "serve": Command(_CLI + "live:run_serve",
                     "publish every tracker sensor over OpenIGTLink (ReferenceToTracker, ProbeToTracker, STATUS)",
                     options.serve_arguments),
    "handeye": Command(_CLI + "robot:cmd_handeye", "hand-eye (SensorToFlange) and robot-world (TrackerToBase) "
                       "calibration with the EM tracker, from a robot's log and a tracker recording on two clocks",
                       options.handeye_arguments),
    "robot-target": Command(_CLI + "robot:cmd_robot_target", "the flange pose (FlangeToBase) that puts the needle "
                            "guide on a trajectory planned in the CT", options.robot_target_arguments),
    "robot-calibrate": Command(_CLI + "robot_live:cmd_robot_calibrate", "move the robot through calibration poses "
                               "it plans itself and solve SensorToFlange and TrackerToBase (dry run without "
                               "--execute)", options.robot_calibrate_arguments),
    "robot-go": Command(_CLI + "robot_live:cmd_robot_go", "move the needle guide onto the plan and correct it with "
                        "the EM tracker until it is within tolerance (dry run without --execute)",
                        options.robot_go_arguments),
}


class _Parser(argparse.ArgumentParser):
    """argparse with the spec's exit code 2 and a one-line message for usage errors."""

    def error(self, message: str) -> None:  # type: ignore[override]
        self.print_usage(sys.stderr)
        self.exit(EXIT_BAD_INPUT, f"{self.prog}: error: {message}\n")

def build_parser() -> argparse.ArgumentParser:
    """The ``emreg`` argument parser: a subcommand per entry of :data:`COMMANDS`, each with the common options."""
    parser = _Parser(prog="emreg", description="Automatic patient-to-image registration for EM navigation.")
    parser.add_argument("--version", action="version", version=f"emreg {__version__}")
    common = argparse.ArgumentParser(add_help=False)
    common.add_argument("--quiet", action="store_true", help="no progress output")
    common.add_argument("--settings", metavar="case.toml", help="settings file (default: the case's case.toml)")
    sub = parser.add_subparsers(dest="command", required=True, parser_class=_Parser)
    for name, command in COMMANDS.items():
        p = sub.add_parser(name, parents=[common], help=command.help, description=command.help)
        p.set_defaults(handler=command.handler)
        command.arguments(p)
    return parser


def handler_of(args: argparse.Namespace) -> Callable[[argparse.Namespace], int]:
    """The function that runs the parsed command (``args.handler``, ``"module:function"``), its module imported now:
    the lazy command table is the one place the command line imports inside a function
    (``scripts/architecture.py``'s ``DEFERRED_IMPORTS`` lists the other, optional, libraries)."""
    module, function = args.handler.split(":")
    return getattr(importlib.import_module(module), function)


class Terminated(KeyboardInterrupt):
    """SIGTERM, raised in the main thread like Ctrl-C so that every ``finally`` and atomic write cleans up."""

def _on_sigterm(signum: int, frame: object) -> None:
    note_interrupt("SIGTERM")
    raise Terminated("SIGTERM")

def _on_sigint(signum: int, frame: object) -> None:
    note_interrupt("SIGINT")
    raise KeyboardInterrupt

def main(argv: Sequence[str] | None = None) -> int:
    """Entry point of the ``emreg`` console script.

    SIGINT and SIGTERM end a command with one line on stderr and exit code 130 / 143; temporary
    files are removed on the way out and an interrupted ``emreg run`` says so in ``OUT/run.json``. The
    handlers are the command's only: the process's own are put back when it returns (a test, the Slicer
    module or a script calling it goes on with what it had).
    """
    parser = build_parser()
    args = parser.parse_args(argv)
    if threading.current_thread() is not threading.main_thread():
        return _command(args)
    previous = {signum: signal.getsignal(signum) for signum in (signal.SIGINT, signal.SIGTERM)}
    try:
        signal.signal(signal.SIGTERM, _on_sigterm)
        if previous[signal.SIGINT] is signal.default_int_handler:
            signal.signal(signal.SIGINT, _on_sigint)
        return _command(args)
    finally:
        for signum, handler in previous.items():
            if handler is not None:  # None: installed outside Python, nothing to put back
                signal.signal(signum, handler)


def _command(args: argparse.Namespace) -> int:
    """Run the parsed command; its errors, interrupts and file-system failures end as one line and an exit code."""
    note_interrupt(None)
    try:
        try:
            return int(handler_of(args)(args) or 0)
        except (EMRegError, KeyboardInterrupt, OSError):
            raise
        except Exception:  # a signal's exception lost in a VTK callback (the filter then fails): the interrupt
            if interrupted_by() is None:
                raise
            raise (Terminated("SIGTERM") if interrupted_by() == "SIGTERM" else KeyboardInterrupt()) from None
    except EMRegError as exc:
        print(f"emreg {args.command}: error: {exc}", file=sys.stderr)
        return exc.exit_code
    except KeyboardInterrupt as exc:
        terminated = isinstance(exc, Terminated)
        # CPython marks a KeyboardInterrupt that ends any string exec() (a dataclass or namedtuple being made
        # while Ctrl-C lands) as unhandled even once caught, and `python -m` then kills itself with SIGINT
        # instead of exiting 130 (bpo-41602's check in Py_RunMain). A string exec that ends normally clears it.
        exec("")
        print(f"emreg {args.command}: interrupted ({'SIGTERM' if terminated else 'SIGINT'}); no partial file "
              "was left in place of a complete one", file=sys.stderr)
        return 143 if terminated else 130
    except OSError as exc:  # a file-system failure no specific check foresaw: still one line, exit 2
        where = f"{exc.filename}: " if getattr(exc, "filename", None) else ""
        print(f"emreg {args.command}: error: {where}{exc.strerror or exc}", file=sys.stderr)
        return EXIT_BAD_INPUT

def run() -> int:
    """The ``emreg`` console script (and ``python -m EMRegModule``): :func:`main`, in a process that ends with it.

    Every object the command made is frozen out of the garbage collector before the interpreter exits: its
    final collection would otherwise walk them all (0.12 s after a report with pyvista and VTK loaded, measured)
    only to free memory the process is about to give back. Not in :func:`main`, which callers in a longer-lived
    process (tests, the Slicer module) run too.
    """
    # OpenBLAS (numpy's and scipy's) starts a worker thread per core that busy-waits after each call it splits.
    # EMReg's linear algebra is on tiny matrices (3 x 3 to a few thousand x 6) beside threads of its own that
    # already use every core, so those workers only spin: 0.07 s of CPU per `emreg detect` on 2 cores, the same
    # results. Read by OpenBLAS when numpy loads it, i.e. before any command imports numpy; a value the user set
    # is kept.
    os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")
    code = main()
    gc.freeze()
    return code


if __name__ == "__main__":
    sys.exit(run())
