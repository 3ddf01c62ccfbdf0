"""The verification report and the scene bundle of a run folder (``emreg report OUT``), or of every run folder
under one (``emreg report --batch DIR``); :mod:`.exporters` writes them, this sequences them.

A report starts what it can before its libraries load (the CT streamed from the file ``OUT/run.json`` names, the
bundle's process held), keeps a bundle that is still the scene it would write, and leaves nothing of a failed
report in OUT. The settings are the case's (those the figures use), so that the report's provenance names them.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass
from pathlib import Path

from ..errors import EMRegError
from ..io.output_folder import OutputFolder
from ..io.run_folder import recorded_run
from ..progress import Progress
from ..report.batch import write_reports_batch
from ..report.inputs import require_report_inputs
from .controller import EMRegController
from .exporters import recorded_case, start_report_bundle, start_report_ct

#: The controller a report is made with, for the case folder given (None: none known), with the settings the
#: command line names.
ControllerFor = Callable[[Path | None], EMRegController]


@dataclass
class Report:
    """A report written into its run folder, its bundle still being written (:meth:`save_bundle`)."""

    path: Path
    folder: OutputFolder
    case: Path | None
    controller: EMRegController
    bundle: object
    kept: object

    def save_bundle(self) -> str:
        """Wait for the scene bundle (or keep the one there); the line that says what became of it."""
        return self.controller.exporter.save_bundle(self.folder, self.case, job=self.bundle, kept=self.kept)


def write_report(out: str, case: Path | None, controller_for: ControllerFor,
                 check_out: Callable[[str], object]) -> Report:
    """The report of the run folder ``out`` (``case``: the case folder, for the CT, when ``OUT/run.json`` does not
    name it), ``out`` checked by ``check_out`` once the early reads have started; the bundle goes on meanwhile."""
    run = recorded_run(Path(out))
    early = start_report_ct(Path(out), case, run)  # read while the report's libraries load
    # held: writes nothing into OUT until released below
    bundle = early_bundle = start_report_bundle(Path(out), case, run)
    folder = kept = None
    try:
        check_out(out)  # the run's folder: the report is written into it
        require_report_inputs(out)  # before run.json is written: a case folder is left as it is
        controller = controller_for(case or recorded_case(run))
        stage = OutputFolder(out, "emreg report")
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
    return Report(path, folder, case, controller, bundle, kept)


def write_report_batch(batch: str, jobs: int, progress: Progress, settings_file: str | None,
                       controller_for: ControllerFor, say: Callable[[str], None],
                       warn: Callable[[str, Sequence[str]], None]) -> None:
    """A report and its bundle in every run folder under the folder ``batch``, ``jobs`` at a time; each job checks
    that its folder's outputs belong together, so one mixed folder fails alone. What became of each bundle is said
    (``say``) and recorded in its folder's ``run.json`` even when others failed."""
    folders = sorted(p for p in Path(batch).iterdir() if p.is_dir())
    bundles: list = []  # each job writes its case's bundle (with the CT its report read, if it needs it)
    try:
        pages = write_reports_batch(folders, jobs=jobs, progress=progress, bundles=bundles,
                                    settings_file=settings_file)
        say(f"{len(pages)} reports written under {batch}")
    finally:  # the cases that did get their report and bundle say so even when others failed
        for folder, (path, message, sha) in bundles:
            _record_batch_report(Path(folder), sha if path is not None else None, controller_for, warn)
            if path is None:
                warn("bundle", [message])
            say(f"bundle: {message}")


def _record_batch_report(folder: Path, bundle_sha256: str | None, controller_for: ControllerFor,
                         warn: Callable[[str, Sequence[str]], None]) -> None:
    """The report (and bundle, whose sha256 its job computed as it wrote it) a batch job wrote into ``folder``,
    listed in its ``run.json``."""
    case_dir = recorded_case(recorded_run(folder))
    try:
        controller = controller_for(case_dir)
        controller.recorder.command = "emreg report --batch"
        controller.exporter.record_report_outputs(OutputFolder(folder, controller.recorder.command), bundle_sha256)
    except EMRegError as exc:
        warn("report", [f"{folder}: not recorded in run.json ({exc})"])
