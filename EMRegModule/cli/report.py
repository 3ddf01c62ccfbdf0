"""``emreg report OUT`` and ``emreg report --batch DIR``: the verification report and the scene bundle of run
folders (:mod:`EMRegModule.pipeline.exporters` does the work).
"""

from __future__ import annotations

import argparse
from pathlib import Path

from ..errors import EMRegError
from .args import AddCommand, controller_of, out_folder, progress_of, settings_of, warn


def cmd_report(args: argparse.Namespace) -> int:
    if args.batch and (args.out or args.case):  # one of them would be ignored: never guessed
        raise EMRegError(f"give an output folder (emreg report OUT [--case CASE]) or --batch DIR, not "
                         f"both ({args.out or '--case ' + args.case} and --batch {args.batch})")
    from ..io.run_folder import recorded_run
    from ..pipeline.exporters import recorded_case, start_report_bundle, start_report_ct

    out, case = (Path(args.out) if args.out else None), (Path(args.case) if args.case else None)
    run = recorded_run(out) if not args.batch else None
    early = start_report_ct(out, case, run) if out is not None else None  # read while the report's libraries load
    bundle = early_bundle = start_report_bundle(out, case, run)  # held: writes nothing into OUT until released below
    folder = kept = None
    try:
        from ..io.output_folder import OutputFolder

        if args.batch:
            return _report_batch(args)
        if not args.out:
            raise EMRegError("report: give an output folder (emreg report OUT) or --batch DIR")
        out_folder(args.out, create=False)  # the run's folder: the report is written into it
        from ..report.inputs import require_report_inputs

        require_report_inputs(args.out)  # before run.json is written: a case folder is left as it is
        # the case's settings (those the figures use), so that the report's provenance names them
        controller = controller_of(args, settings_of(args, case or recorded_case(run)))
        stage = OutputFolder(args.out, "emreg report")
        kept = controller.exporter.kept_bundle(stage, case)  # still the scene this report would write: it stays
        stage.start_stage("report", keep=[kept.path.name] if kept is not None else ())
        folder = stage
        if kept is None:
            bundle = controller.exporter.start_bundle(folder, case, early_bundle)  # goes on while the report renders
        elif early_bundle is not None:
            early_bundle.cancel()
            bundle = None
        path = controller.exporter.save_report(folder, case, ct_read=early)
    except BaseException:
        if bundle is not None:
            bundle.cancel()
        if early is not None:
            early.cancel()
        if folder is not None:  # the bundle (released by then) or figures this failed report wrote: not left in OUT
            if kept is not None:  # nor the kept bundle: as a report that fails leaves none, it goes to previous/
                folder.start_stage("bundle")
            folder.drop_unrecorded()
        raise
    print(f"report -> {path}")
    print(controller.exporter.save_bundle(folder, case, job=bundle, kept=kept))
    return 0


def _report_batch(args: argparse.Namespace) -> int:
    """``emreg report --batch DIR``: every run folder under DIR, each with its bundle."""
    from ..report.batch import write_reports_batch

    batch = Path(args.batch)
    if not batch.is_dir():
        raise EMRegError(f"{batch}: folder of run outputs not found")
    if args.settings:
        settings_of(args)  # a settings file that cannot be read is refused once, before any report
    folders = sorted(p for p in batch.iterdir() if p.is_dir())
    # each job checks that its folder's outputs belong together: one mixed folder fails alone, the others are reported
    bundles: list = []  # each job writes its case's bundle (with the CT its report read, if it needs it)
    try:
        pages = write_reports_batch(folders, jobs=args.jobs, progress=progress_of(args), bundles=bundles,
                                    settings_file=getattr(args, "settings", None))
        print(f"{len(pages)} reports written under {args.batch}")
    finally:  # the cases that did get their report and bundle say so even when others failed
        for folder, (path, message, sha) in bundles:
            _record_batch_report(args, Path(folder), sha if path is not None else None)
            print(_bundle_line(path, message))
    return 0


def _record_batch_report(args: argparse.Namespace, folder: Path, bundle_sha256: str | None) -> None:
    """The report (and bundle, whose sha256 its job computed as it wrote it) a batch job wrote into ``folder``,
    listed in its ``run.json``."""
    from ..io.output_folder import OutputFolder
    from ..io.run_folder import recorded_run
    from ..pipeline.exporters import recorded_case

    case_dir = recorded_case(recorded_run(folder))
    try:
        controller = controller_of(args, settings_of(args, case_dir))
        controller.recorder.command = "emreg report --batch"
        controller.exporter.record_report_outputs(OutputFolder(folder, controller.recorder.command), bundle_sha256)
    except EMRegError as exc:
        warn("report", [f"{folder}: not recorded in run.json ({exc})"])


def _bundle_line(path, message: str) -> str:
    """The summary line of a scene bundle; one that could not be written is also a warning."""
    if path is None:
        warn("bundle", [message])
    return f"bundle: {message}"


def add_parsers(add: AddCommand) -> None:
    """The subcommands of this module (``add``: :data:`~EMRegModule.cli.args.AddCommand`)."""
    p = add("report", cmd_report, "render the verification report: OUT/report.html")
    p.add_argument("out", nargs="?", metavar="OUT")
    p.add_argument("--case", metavar="CASE", help="the case folder (for the CT), when not recorded in OUT")
    p.add_argument("--batch", metavar="DIR", help="render a report in every output folder under DIR")
    p.add_argument("--jobs", type=int, default=1,
                   help="reports rendered at a time with --batch (lowered to what the available memory holds)")
