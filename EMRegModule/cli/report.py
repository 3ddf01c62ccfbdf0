"""``emreg report OUT`` and ``emreg report --batch DIR``: the verification report and the scene bundle of run
folders (:mod:`EMRegModule.pipeline.reporting` does the work).
"""

from __future__ import annotations

import argparse
from pathlib import Path

from ..errors import EMRegError
from ..pipeline.reporting import write_report, write_report_batch
from .args import controller_of, out_folder, progress_of, settings_of, warn


def cmd_report(args: argparse.Namespace) -> int:
    if args.batch and (args.out or args.case):  # one of them would be ignored: never guessed
        raise EMRegError(f"give an output folder (emreg report OUT [--case CASE]) or --batch DIR, not "
                         f"both ({args.out or '--case ' + args.case} and --batch {args.batch})")

    def controller_for(case_dir: Path | None):
        return controller_of(args, settings_of(args, case_dir))

    if args.batch:
        if not Path(args.batch).is_dir():
            raise EMRegError(f"{Path(args.batch)}: folder of run outputs not found")
        if args.settings:
            settings_of(args)  # a settings file that cannot be read is refused once, before any report
        write_report_batch(args.batch, args.jobs, progress_of(args), args.settings, controller_for, print, warn)
        return 0
    if not args.out:
        raise EMRegError("report: give an output folder (emreg report OUT) or --batch DIR")
    report = write_report(args.out, Path(args.case) if args.case else None, controller_for,
                          lambda out: out_folder(out, create=False))
    print(f"report -> {report.path}")
    print(report.save_bundle())
    return 0
