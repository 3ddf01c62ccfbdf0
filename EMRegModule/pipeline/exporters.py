"""The exporters: the verification report and the 3D Slicer scene bundle of an output folder, their processes
(the bundle written in a process of its own while the report renders, a CT streamed early), and when the CT's
memory is let go (before the rendering libraries load, when nothing needs it any more).
"""

from __future__ import annotations

from pathlib import Path
from typing import TYPE_CHECKING, Any

from ..errors import EMRegError
from ..io.case import run_ct_path
from ..io.ct_handle import CTHandle
from ..io.output_folder import OutputFolder
from ..progress import Progress
from ..report.ct_memo import kept_for, memo_candidates, recorded_ct_sha256
from ..settings import Settings
from ..slicer_export.bundle import BundleProcess, start_bundle_process, write_run_bundle
from ..slicer_export.mrb import bundle_needs_ct_image
from ..stages import STAGE_OUTPUTS
from .bundle_state import KeptBundle, current_bundle
from .recorder import RunRecorder

if TYPE_CHECKING:
    import SimpleITK as sitk


class CTHold:
    """The CT in memory, handed by the controller to the stages that export it (the report, the bundle): ``take``
    lets the hold's reference go, so that a CT nothing needs any more is freed once used (before the rendering
    libraries load). ``keep``: the caller keeps the CT afterwards (the 3D Slicer Logic shows it): never let go."""

    def __init__(self, image: sitk.Image | None, keep: bool = True) -> None:
        self._image = image
        self.keep = keep

    @property
    def image(self) -> sitk.Image | None:
        return self._image

    def take(self) -> sitk.Image | None:
        image, self._image = self._image, None
        return image


class Exporter:
    """The report and the bundle of one controller. The CT in memory is handed to them in a
    :class:`CTHold`: unless the hold keeps it (the Slicer Logic shows it afterwards), it is let go before the
    rendering libraries load when nothing needs it after the report, and before the bundle when the bundle copies
    it from its file."""

    def __init__(self, recorder: RunRecorder, settings: Settings, progress: Progress) -> None:
        self.recorder = recorder
        self.settings = settings
        self.progress = progress
        self._report_image: sitk.Image | None = None  # the CT the report read, for the Slicer bundle

    def save_report(self, folder: OutputFolder, case_dir: Path | None, hold: CTHold | None = None,
                    ct_read: CTHandle | None = None) -> Path:
        """The verification report of ``folder`` (its outputs checked to belong together first); the CT
        the report read is kept for the Slicer bundle (:meth:`save_bundle`). ``ct_read``: a streamed read of the
        CT started earlier (:func:`start_report_ct`), used when it is the report's CT."""
        from ..report.writer import write_report_keeping_ct  # the page and figures: see DEFERRED_IMPORTS

        used = self.recorder.adopt_outputs(folder)
        keep = bundle_needs_ct_image(run_ct_path(folder.manifest, case_dir))  # else the report streams a CT itself
        held = None if hold is None else hold.image
        image: sitk.Image | CTHandle | None = held if held is not None else ct_read
        if held is not None and not keep and not hold.keep:  # nothing needs the CT after the report: it is
            image = CTHandle.of_image(hold.take())  # handed over: freed once used, before the rendering libraries
            # load
        page, self._report_image = write_report_keeping_ct(folder.path, case_dir=case_dir, progress=self.progress,
                                                           image=image, keep_ct=keep, settings=self.settings)
        self.recorder.record(folder, "report", self.recorder.provenance("report", tuple(used)))
        return page

    def record_report_outputs(self, folder: OutputFolder, bundle_sha256: str | None) -> None:
        """List a report written into ``folder`` by another process (``emreg report --batch``'s jobs) in its
        ``run.json``, and its scene bundle when one was written (``bundle_sha256``: its sha256)."""
        used = self.recorder.adopt_outputs(folder)
        self.recorder.record(folder, "report", self.recorder.provenance("report", tuple(used)))
        if bundle_sha256 is not None:
            self.recorder.record(folder, "bundle", self.recorder.bundle_provenance(used, folder, None),
                                 dict.fromkeys(STAGE_OUTPUTS["bundle"], bundle_sha256))
            return
        outputs = folder.manifest.get("outputs")  # an earlier bundle is gone (not renewed): no longer listed
        if isinstance(outputs, dict) and any([outputs.pop(name, None) for name in STAGE_OUTPUTS["bundle"]]):
            folder.save()

    def start_bundle(self, folder: OutputFolder, case_dir: Path | None,
                     started: BundleProcess | None = None) -> BundleProcess | None:
        """Start writing ``EMReg.mrb`` in a separate process, to go on while the report renders (pass the
        result to :meth:`save_bundle`); None when it must be written here. ``started``: a bundle process started
        earlier and held (:func:`start_report_bundle`), released here once the outputs are checked."""

        used = self.recorder.adopt_outputs(folder)
        job = started if started is not None else start_bundle_process(folder.path, case_dir)
        if job is not None:
            job.used = used
            job.release()
        return job

    def kept_bundle(self, folder: OutputFolder, case_dir: Path | None) -> KeptBundle | None:
        """``folder``'s ``EMReg.mrb`` when it is still the bundle :meth:`save_bundle` would write
        (:mod:`EMRegModule.pipeline.bundle_state`), else None."""

        kept = current_bundle(folder.path, folder.manifest, case_dir, self.settings.digest())
        return kept.start_check() if kept is not None else None

    def save_bundle(self, folder: OutputFolder, case_dir: Path | None, hold: CTHold | None = None,
                    job: BundleProcess | None = None, kept: KeptBundle | None = None) -> str:
        """``EMReg.mrb``, the 3D Slicer scene of ``folder``'s outputs; a summary line. Optional: without
        slicer-core, or when it cannot be written, the other outputs stand and a warning says why."""

        if kept is not None and kept.confirmed():
            return f"bundle: {kept.path} (up to date: kept)"
        if job is not None:
            with self.progress.step("writing the 3D Slicer scene bundle (in parallel)"):
                path, message, sha = job.result()
            used = job.used
        else:
            used = self.recorder.adopt_outputs(folder)
            held = None if hold is None else hold.image
            image = held if held is not None else self._report_image  # the CT is not read again
            self._report_image = None
            if not bundle_needs_ct_image(run_ct_path(folder.manifest, case_dir)):
                image = None  # the bundle copies the CT from its file: its memory is freed before slicer-core loads
                if hold is not None and not hold.keep:
                    hold.take()
            with self.progress.step("writing the 3D Slicer scene bundle"):
                path, message, sha = write_run_bundle(folder.path, case_dir, image)
        if path is None:
            self.recorder.warn([message])
        else:
            self.recorder.record(folder, "bundle", self.recorder.bundle_provenance(used, folder, case_dir),
                                 {path.name: sha} if sha else None)
        return f"bundle: {message}"


# --- ``emreg report OUT``: what starts before the report's libraries load ---------------------------------------


def recorded_case(run: dict[str, Any] | None) -> Path | None:
    """The case folder ``OUT/run.json`` names, when it is there."""
    case = (run or {}).get("case")
    return Path(case) if isinstance(case, str) and Path(case).is_dir() else None


def start_report_ct(out: Path, case_dir: Path | None, run: dict[str, Any] | None) -> CTHandle | None:
    """Start streaming the CT that ``OUT/run.json`` names, when the report may stream it (a plain file whose bundle
    copies it from the file) and no earlier report kept its products; None otherwise. The report checks it is its
    CT."""

    ct = run_ct_path(run, case_dir)
    if ct is None or bundle_needs_ct_image(ct) or _ct_products_kept(out, run, ct):
        return None
    from ..io.ct_stream import start_streamed_read  # SimpleITK: see DEFERRED_IMPORTS

    try:
        return start_streamed_read(ct)
    except EMRegError:
        return None  # the report reads it again and says what is wrong


def _ct_products_kept(out: Path, run: dict[str, Any] | None, ct: str) -> bool:
    """Whether an earlier report of this run kept the CT's products for this CT (then the report only hashes it)."""

    recorded = recorded_ct_sha256(run, Path(ct))
    return any(kept_for(path, recorded) for path in memo_candidates(out))


def start_report_bundle(out: Path, case_dir: Path | None, run: dict[str, Any] | None) -> BundleProcess | None:
    """The bundle's process, started held so that its start-up
    (Python, numpy, slicer-core: ~1 s of CPU) runs beside the report's own; None when it cannot be written in a
    process of its own, or when the bundle there is most likely kept (the settings are compared once read)."""
    if run is None:
        return None

    if current_bundle(out, run, case_dir, None):
        return None
    return start_bundle_process(out, case_dir, held=True)
