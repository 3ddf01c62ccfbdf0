"""``emreg simulate`` (a simulated case with its ground truth) and ``emreg study`` (accuracy studies on Dask).
"""

from __future__ import annotations

import argparse
from pathlib import Path

from .args import AddCommand, out_folder, progress_of


def cmd_simulate(args: argparse.Namespace) -> int:
    out_folder(args.out)
    from ..simulation.case import simulate_case

    options = {"probe_axis": args.probe_axis} if args.probe_axis else {}
    if args.tool_tip:
        options["tool_tip_mm"] = tuple(args.tool_tip)
    if args.distortion:
        options.update(distortion_mm=args.distortion, distortion_during=args.distortion_during,
                       distortion_onset_s=args.distortion_onset)
    simulate_case(
        Path(args.out), seed=args.seed, difficulty=args.difficulty, spacing_mm=args.spacing,
        progress=progress_of(args), **options,
    )
    print(f"simulated case written to {args.out}")
    return 0


def cmd_study(args: argparse.Namespace) -> int:
    from ..studies import STUDIES, format_table, run_study

    summary = run_study(args.name, Path(args.out), quick=args.quick, scheduler=args.scheduler, workers=args.workers,
                        case_dir=Path(args.case) if args.case else None,
                        work=Path(args.work) if args.work else None, seed=args.seed, progress=progress_of(args))
    print(f"{STUDIES[args.name].title}\n")
    print(format_table(summary))
    print(f"\n-> {Path(args.out) / args.name}.json, .csv, .png")
    return 0


def _add_study_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("name", metavar="NAME", help="calibration, board, tre, noise, markers, prediction, tool or trust")
    p.add_argument("--out", required=True, metavar="DIR")
    p.add_argument("--quick", action="store_true", help="a small frame and few sessions (a smoke-sized run)")
    p.add_argument("--scheduler", metavar="tcp://HOST:PORT", help="an existing Dask scheduler (default: a local one)")
    p.add_argument("--workers", type=int, default=None, metavar="N", help="local worker processes (default 2)")
    p.add_argument("--case", metavar="CASE", help="a simulated case folder with truth.json (default: simulate one)")
    p.add_argument("--work", metavar="DIR", help="where the simulated case and its detection are kept (OUT/work)")
    p.add_argument("--seed", type=int, default=1, help="seed of the simulated case")


def add_simulate_parser(add: AddCommand) -> None:
    """``emreg simulate`` (``add``: :data:`~EMRegModule.cli.args.AddCommand`)."""
    p = add("simulate", cmd_simulate, "write a simulated case folder with its ground truth (truth.json)")
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


def add_parsers(add: AddCommand) -> None:
    """``emreg study`` (``add``: :data:`~EMRegModule.cli.args.AddCommand`)."""
    _add_study_arguments(add("study", cmd_study,
                             "an accuracy study on simulated data, run on Dask: OUT/NAME.json, .csv, .png"))
