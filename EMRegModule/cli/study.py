"""``emreg simulate`` (a simulated case with its ground truth) and ``emreg study`` (accuracy studies on Dask).
"""

from __future__ import annotations

import argparse
from pathlib import Path

from ..errors import EMRegError
from ..pipeline.simulate import simulate
from ..studies import STUDIES, format_table, run_study
from .args import out_folder, progress_of


def cmd_simulate(args: argparse.Namespace) -> int:
    out_folder(args.out)
    simulate(Path(args.out), seed=args.seed, difficulty=args.difficulty, spacing_mm=args.spacing,
             progress=progress_of(args), probe_axis=args.probe_axis, tool_tip_mm=args.tool_tip,
             distortion_mm=args.distortion, distortion_during=args.distortion_during,
             distortion_onset_s=args.distortion_onset)
    print(f"simulated case written to {args.out}")
    return 0


def cmd_study(args: argparse.Namespace) -> int:
    summary = run_study(args.name, Path(args.out), quick=args.quick, scheduler=args.scheduler, workers=args.workers,
                        case_dir=Path(args.case) if args.case else None,
                        work=Path(args.work) if args.work else None, seed=args.seed, progress=progress_of(args),
                        only=_selection(args.only))
    print(f"{STUDIES[args.name].title}\n")
    print(format_table(summary))
    print(f"\n-> {Path(args.out) / args.name}.json, .csv, .png")
    return 0



def _selection(only: list[str]) -> dict[str, list[str]]:
    """``--only KEY=VALUE[,VALUE]`` options as KEY -> values (a key given twice: the values of both)."""
    selection: dict[str, list[str]] = {}
    for text in only:
        key, _, values = text.partition("=")
        if not key or not values:
            raise EMRegError(f"--only {text!r}: give KEY=VALUE[,VALUE] (e.g. family=clean,magpylib)")
        selection.setdefault(key.strip(), []).extend(v.strip() for v in values.split(",") if v.strip())
    return selection
