"""``emreg run`` (every stage of a case) and ``emreg demo`` (the built-in sample case, simulated and run).
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path

from ..io.case import open_case
from ..pipeline.simulate import simulate
from ..settings import with_series
from .args import (
    controller_of,
    out_folder,
    progress_of,
    settings_of,
)


def cmd_run(args: argparse.Namespace) -> int:
    out_folder(args.out)
    case = open_case(args.case, settings_of(args) if args.settings else None)
    case.settings = with_series(case.settings, args.series)
    case.settings = case.settings.with_sensors(args.reference_sensor, args.probe_sensor)  # a sequence file's too
    controller = controller_of(args, case.settings)
    controller.give(**{name: value for name, value in (("tool", args.tool), ("plan", args.plan)) if value})
    # nothing uses the CT after the run: freed as soon as nothing needs it
    for line in controller.run(case, Path(args.out), keep_ct=False):
        print(line)
    return 0


def cmd_demo(args: argparse.Namespace) -> int:
    out = out_folder(args.out)
    case_dir = out / "case"
    progress = progress_of(args)
    start = time.perf_counter()
    progress.message(f"[emreg] demo: simulating the sample case into {case_dir}")
    simulate(case_dir, seed=args.seed, spacing_mm=args.spacing, progress=progress)
    case = open_case(case_dir)
    controller = controller_of(args, case.settings)
    for line in controller.run(case, out / "result"):
        print(line)
    print(f"demo finished in {time.perf_counter() - start:.1f} s; outputs in {out / 'result'}")
    return 0
