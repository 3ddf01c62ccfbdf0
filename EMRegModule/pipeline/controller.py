"""The workflow controller: walks the stage table (:data:`~EMRegModule.pipeline.stages.PIPELINE`) for the ``emreg``
command and the 3D Slicer module's Logic.

It holds two values, replaced and never changed in place: ``inputs`` (:class:`~.inputs.Inputs`: the CT, the
calibration recording, the tool, the sensor ports and the plan, given once with :meth:`EMRegController.give`) and
``results`` (:class:`~.results.WorkflowResults`: made by the table's stages with :meth:`~EMRegController.make`, or
read from their files with :meth:`~EMRegController.adopt`); a new input or result drops what it makes stale (the
stage table's graph, :mod:`EMRegModule.stages`). It holds no stage's logic: each stage's run, read and write are
the table's (:mod:`.steps`). Its parts: the provenance of every output saved (:class:`~.recorder.RunRecorder`,
``recorder``) and the report and the scene bundle (:class:`~.exporters.Exporter`, ``exporter``).

All poses are in millimetres; ``ReferenceToImage`` maps Reference-sensor coordinates into the CT's LPS image
space.
"""

from __future__ import annotations

import contextlib
import os
from pathlib import Path
from types import MappingProxyType
from typing import TYPE_CHECKING, Any

from ..errors import EMRegError, NoSafeAnswerError
from ..interrupts import interrupted_by, signals_held
from ..io.case import Case
from ..io.output_folder import OutputFolder, all_output_names, refuse_out_over_inputs
from ..names import REGISTRATION_JSON
from ..progress import QUIET, Progress
from ..settings import Settings, choose_ports
from .exporters import CTHold, Exporter
from .inputs import (
    Inputs,
    case_files,
    check_case_image_side,
    check_plan_for_case,
    read_recording,
    run_record,
    series_unused,
    with_ct,
    with_plan,
    with_ports,
    with_tool,
)
from .job import Job, Made, Read
from .recorder import RunRecorder
from .results import WorkflowResults
from .stages import PIPELINE, PIPELINE_STAGE, PipelineStage

if TYPE_CHECKING:
    import SimpleITK as sitk

    from ..core.plan import Plan
    from ..core.tool import ToolCalibration
    from ..core.tracking import TrackingRecording

#: ``tool`` and ``plan`` of :meth:`EMRegController.give` left as they are (None gives "none").
NOT_GIVEN: Any = object()


class EMRegController:
    """Sequences the EMReg workflow; usable without any GUI.

    ``settings`` is the typed, checked ``case.toml`` (:class:`~EMRegModule.settings.Settings`;
    defaults when None); each stage gets its own table. ``command`` names the command in provenance and warnings.
    """

    def __init__(self, settings: Settings | None = None, progress: Progress | None = None,
                 command: str = "emreg") -> None:
        if settings is not None and not isinstance(settings, Settings):
            raise TypeError("EMRegController takes a Settings object (EMRegModule.settings.load_settings)")
        self.settings: Settings = settings or Settings()
        self.progress = progress or QUIET
        self.inputs = Inputs.of(self.settings)
        self.results = WorkflowResults()
        self.recorder = RunRecorder(self.settings, command)
        self.exporter = Exporter(self.recorder, self.settings, self.progress)

    @classmethod
    def for_case(cls, case: Case, progress: Progress | None = None, command: str = "emreg") -> EMRegController:
        """A controller configured with a case folder's ``case.toml``."""
        return cls(case.settings, progress, command)

    # --- inputs and results made elsewhere ------------------------------------------------------------------------

    def give(self, *, sensors: tuple[int | None, int | None] | None = None,
             tool: str | os.PathLike[str] | ToolCalibration | None = NOT_GIVEN,
             calibration: str | os.PathLike[str] | TrackingRecording | None = None,
             ct: str | os.PathLike[str] | sitk.Image | None = None,
             plan: str | os.PathLike[str] | Plan | None = NOT_GIVEN) -> Inputs:
        """Give the workflow inputs, in this order (the tool names the calibration recording's transform); each
        replaces the one before and drops the results it makes stale. Returns the inputs.

        - ``sensors``: the (reference, probe) ports, None where unchanged (checked as ``[sensors]``); a change drops
          the frame calibration and what follows.
        - ``tool``: a tool file, ``auto`` or a :class:`~EMRegModule.core.tool.ToolCalibration`; None: the pinhole
          probe (:func:`~.inputs.with_tool`). Drops the navigation and the evaluation (they map its tip), and the
          frame calibration when it was made here from its touches (one read from a file stays).
        - ``calibration``: the frame-calibration recording (a file, read with the ports and the tool's transform
          name, or a recording); drops the frame calibration and what follows.
        - ``ct``: a CT file or DICOM folder, read now, or a SimpleITK image; drops the detection and what follows.
        - ``plan``: a markups file or a :class:`~EMRegModule.core.plan.Plan`; None: no plan. Refused outside the CT
          of the detected markers; drops the navigation (its guidance numbers).
        """
        inputs, stale = self.inputs, []
        if sensors is not None:
            ported = with_ports(inputs, *sensors)
            if (ported.reference_sensor, ported.probe_sensor) != (inputs.reference_sensor, inputs.probe_sensor):
                inputs, stale = ported, ["calibrate"]
        if tool is not NOT_GIVEN:
            inputs = with_tool(inputs, tool)
            stale += ["calibrate"] if self.results.calibrated_here else ["navigate", "evaluate"]
        if calibration is not None:
            recording = read_recording(calibration, inputs) if isinstance(calibration, str | os.PathLike) \
                else calibration
            inputs, stale = inputs.replace(calibration_recording=recording), [*stale, "calibrate"]
        if ct is not None:
            if isinstance(ct, str | os.PathLike):
                self.recorder.warn(series_unused(self.settings, ct))
            inputs, stale = with_ct(inputs, ct, self.progress), [*stale, "detect"]
        if plan is not NOT_GIVEN:
            inputs, stale = with_plan(inputs, plan, self.results.detection), [*stale, "navigate"]
        self.recorder.note_inputs(**{role: path for role, path in (("tool", tool), ("plan", plan))
                                     if isinstance(path, str | os.PathLike) and str(path) != "auto"})
        self.inputs, self.results = inputs, self.results.without(*stale)
        return inputs

    def adopt(self, stage: str, source: str | os.PathLike[str] | None = None, **result: Any) -> Any:
        """Use a result of ``stage`` made elsewhere: read from its file (``source``, by the table's ``read``: an
        output is checked to belong with its folder and its provenance kept for what is made from it), or given
        in memory (``result``: its fields, e.g. ``detection=...``). Drops what it makes stale; returns the result."""
        if source is not None:
            read = PIPELINE_STAGE[stage].read(Path(source), self.settings)
            self._note_read(read)
            result = dict(read.results)
        self.results = self.results.made(stage, **result)
        return next(iter(result.values()))

    def use_ports(self, reference_given: int | None, probe_given: int | None,
                  source: str = REGISTRATION_JSON) -> list[str]:
        """The ports of a consumer of the current registration (navigate, evaluate): for each sensor the port the
        user gave (command line, else ``case.toml [sensors]``; None: not given), else the port the
        registration's calibration used, else the spec's default (reference 1, probe 2). A given port that
        differs from the registration's is used (a re-cabled tracker) with a one-line warning, returned."""
        registration = self.results.registration
        self.results.require(registration=registration)
        recorded = (registration.reference_sensor, registration.probe_sensor)
        chosen, warnings = choose_ports((reference_given, probe_given), recorded, source)
        sensors = self.settings.with_sensors(*chosen).sensors  # checked as [sensors]; the registration stays
        self.inputs = self.inputs.replace(reference_sensor=sensors.reference, probe_sensor=sensors.probe)
        self.results = self.results.made("register", registration=registration)  # navigation, evaluation: stale
        return warnings

    # --- the stages -------------------------------------------------------------------------------------------

    def make(self, stage: str, case: Case | None = None, folder: OutputFolder | None = None, **options: Any) -> Any:
        """Run ``stage`` of the table on the inputs and results held (``options``: the stage's own, see
        :mod:`.steps`; ``case``: its optional inputs taken from a case folder, a part the case does not allow being
        skipped or "not evaluated"); with ``folder``, its result is saved there with its provenance. Returns the
        result (None: the case did not allow it); a missing prerequisite is refused
        (:class:`~.results.WorkflowError`, saying what is missing)."""
        entry = PIPELINE_STAGE[stage]
        hold = CTHold(self.inputs.image) if entry.stage.export else None  # the CT in memory, kept
        made = self._step(entry, case, folder, options, hold)
        return next(iter(made.results.values()), None)

    def save(self, stage: str, folder: OutputFolder) -> None:
        """Write ``stage``'s result held into ``folder`` (the table's ``write``, atomically), recorded with its
        provenance."""
        provenance = self.recorder.provenance(stage)
        PIPELINE_STAGE[stage].write(self.results, folder.path, provenance)
        self.recorder.record(folder, stage, provenance)

    def _step(self, entry: PipelineStage, case: Case | None, folder: OutputFolder | None, options: dict[str, Any],
              hold: CTHold | None = None) -> Made:
        """Run one stage of the table and take what it made (its result, inputs changed, a file read); with
        ``folder``, save it there and note what ``run.json`` records of it."""
        job = Job(self.inputs, self.results, self.recorder.warn, self.progress, MappingProxyType(options), case,
                  folder, self.exporter, hold)
        made = entry.run(job)
        if made.read is not None:
            self._note_read(made.read)
        if made.inputs is not None:
            self.inputs = made.inputs
        if made.results:
            self.results = self.results.made(entry.name, **made.results)
        if folder is not None:
            if made.results and made.read is None and entry.write is not None:
                self.save(entry.name, folder)
            folder.manifest.update(made.manifest)
            if made.not_evaluated:
                folder.manifest.setdefault("not_evaluated", {}).update(made.not_evaluated)
        return made

    def _note_read(self, read: Read) -> None:
        """A result read from a file: an output's provenance kept (checked to belong where it lies), an input
        noted by its role."""
        if read.output is not None:
            self.recorder.read_output(read.output, read.path, read.provenance)
        else:
            self.recorder.note_inputs(**{read.input_role: read.path})

    # --- a whole run ------------------------------------------------------------------------------------------

    def run(self, case: Case, out: str | os.PathLike[str], report: bool = True, keep_ct: bool = True) -> list[str]:
        """Every stage of the table the case allows, in order, into the output folder ``out``; returns summary
        lines.

        OUT is refused when it would overwrite an input of the case; the outputs of an earlier run are
        moved to ``OUT/previous/`` before anything is written; every output is written atomically and
        listed with its provenance in ``OUT/run.json``, which also records the case, the CT, the ports,
        the summary and how the run ended (``status``: finished, refused, failed, interrupted). A stage
        that refuses (no safe answer) leaves none of its own or later outputs. An evaluation that cannot
        be made does not stop the run: the reason goes to ``run.json``, ``evaluation.json`` and stderr.
        What the stages read and check of the case (the calibration recording and its ports) is read before
        the long stages run. ``report=False`` leaves out the report and the Slicer bundle (3D Slicer without
        pyvista); ``keep_ct=False`` (``emreg run``): the CT is let go as soon as nothing needs it.
        """
        check_case_image_side(case)
        files = case_files(case)
        given_settings = Path(self.settings.source) if self.settings.source else None
        refuse_out_over_inputs(out, [p for p in (*files.values(), given_settings) if p], all_output_names(),
                               case.folder)
        recorder = self.recorder
        recorder.command = recorder.command if recorder.command != "emreg" else "emreg run"
        recorder.note_inputs(**files)
        self._give_case_defaults(case)
        folder = OutputFolder(out, recorder.command)
        summary: list[str] = []
        stage = "start"
        table = [entry for entry in PIPELINE if report or not entry.stage.export]
        hold: CTHold | None = None
        try:
            folder.start_run(run_record(self.inputs, case, summary))
            for entry in (entry for entry in table if entry.prepare is not None):
                stage = entry.name  # named in run.json if this stage's inputs are refused
                self._prepare(entry, case)
            for entry in table:
                stage = entry.name  # named in run.json if this stage fails
                if entry.stage.export and hold is None:  # the CT handed to the exports: let go once used
                    hold = CTHold(self.inputs.image, keep_ct)
                    self.inputs = self.inputs if keep_ct else self.inputs.replace(image=None)
                summary.extend(self._step(entry, case, folder, {}, hold).summary)
        except NoSafeAnswerError as exc:
            folder.remove_from(stage)
            summary.append(f"{stage}: refused: {exc}")
            folder.finish("refused", f"{stage}: {exc}")
            raise
        except (EMRegError, OSError) as exc:
            with contextlib.suppress(OSError):  # on a full disk even run.json may not be written
                folder.drop_unrecorded()  # a stage's outputs written before it failed (figures without their page)
                folder.finish("failed", f"{stage}: {exc}")
            raise
        except KeyboardInterrupt as exc:
            with signals_held(redeliver=False):  # a second Ctrl-C does not cut the record short
                folder.drop_unrecorded()  # an output written as the signal came, before run.json listed it
                folder.finish("interrupted", f"{stage}: interrupted ({str(exc) or 'SIGINT'})")
            raise
        except Exception:
            signal_name = interrupted_by()  # the signal's exception was lost in a VTK callback: still an interrupt
            if signal_name is None:
                raise
            with signals_held(redeliver=False):
                folder.drop_unrecorded()
                folder.finish("interrupted", f"{stage}: interrupted ({signal_name})")
            raise
        with signals_held() as pending:  # run.json says what the exit code says, even for a signal right now
            folder.finish("finished")
            if pending:
                folder.finish("interrupted", f"{stage}: interrupted as the run recorded its end (every output "
                                             "listed is complete)")
        return summary

    def _give_case_defaults(self, case: Case) -> None:
        """Before a run: the tool of ``[tool] calibration`` and the plan of ``[navigation] plan`` unless given; a
        plan is refused (one line) when the case has no calibration recording to register with."""
        settings, defaults = self.settings, {}
        if self.inputs.tool is None and not self.inputs.tool_auto and settings.tool.calibration:
            defaults["tool"] = settings.file_path(settings.tool.calibration)
        if self.inputs.plan is None and settings.navigation.plan:
            defaults["plan"] = settings.file_path(settings.navigation.plan)
        self.give(**defaults)
        check_plan_for_case(self.inputs.plan, case)

    def _prepare(self, entry: PipelineStage, case: Case) -> None:
        """What ``entry`` reads and checks of the case before the long stages: its inputs, its result now stale."""
        inputs = entry.prepare(Job(self.inputs, self.results, self.recorder.warn, self.progress, case=case))
        if inputs is not self.inputs:
            self.inputs, self.results = inputs, self.results.without(entry.name)
