"""The ``emreg`` command: the parser wiring, signal handling and :func:`main`; the commands live in
:mod:`EMRegModule.cli` (one module per family).

Exit codes (spec): 0 success; 2 bad input or usage (one line naming the file and what is
wrong); 3 the data do not allow a safe answer. Every output file is written atomically.
"""

from __future__ import annotations

import argparse
import signal
import sys
import threading
from collections.abc import Callable, Sequence

from .. import __version__
from ..errors import EXIT_BAD_INPUT, EMRegError


class _Parser(argparse.ArgumentParser):
    """argparse with the spec's exit code 2 and a one-line message for usage errors."""

    def error(self, message: str) -> None:  # type: ignore[override]
        self.print_usage(sys.stderr)
        self.exit(EXIT_BAD_INPUT, f"{self.prog}: error: {message}\n")

def build_parser() -> argparse.ArgumentParser:
    """The ``emreg`` argument parser: each command family adds its own subcommands, in the order of ``--help``."""
    from . import convert, live, report, robot, robot_live, run, stages, study

    parser = _Parser(prog="emreg", description="Automatic patient-to-image registration for EM navigation.")
    parser.add_argument("--version", action="version", version=f"emreg {__version__}")
    common = argparse.ArgumentParser(add_help=False)
    common.add_argument("--quiet", action="store_true", help="no progress output")
    common.add_argument("--settings", metavar="case.toml", help="settings file (default: the case's case.toml)")
    sub = parser.add_subparsers(dest="command", required=True, parser_class=_Parser)

    def add(name: str, func: Callable[[argparse.Namespace], int], help_text: str) -> argparse.ArgumentParser:
        p = sub.add_parser(name, parents=[common], help=help_text, description=help_text)
        p.set_defaults(func=func)
        return p

    for add_parsers in (study.add_simulate_parser, stages.add_parsers, convert.add_parsers, report.add_parsers,
                        run.add_parsers, study.add_parsers, live.add_parsers, robot.add_parsers,
                        robot_live.add_parsers):
        add_parsers(add)
    return parser


class Terminated(KeyboardInterrupt):
    """SIGTERM, raised in the main thread like Ctrl-C so that every ``finally`` and atomic write cleans up."""

def _on_sigterm(signum: int, frame: object) -> None:
    from ..interrupts import note_interrupt

    note_interrupt("SIGTERM")
    raise Terminated("SIGTERM")

def _on_sigint(signum: int, frame: object) -> None:
    from ..interrupts import note_interrupt

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
    from ..interrupts import interrupted_by, note_interrupt

    note_interrupt(None)
    try:
        try:
            return int(args.func(args) or 0)
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
    import gc
    import os

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
