"""The one definition of EMReg's pipeline: each stage, what it needs, what it writes, what it is made from.

::

    CT image ──────────────> detect ─┐
                                      ├─> register ─> navigate ─┐
    calibration recording -> calibrate┘       └────> evaluate ─> tre_map ─> report ─> bundle

Everything else follows from :data:`STAGES`: the outputs of each stage (:data:`STAGE_OUTPUTS`), the stages a new
result makes stale (:data:`DEPENDENTS`, :func:`outputs_from`, used by
:class:`~EMRegModule.io.output_folder.OutputFolder`
and by :class:`~EMRegModule.pipeline.results.WorkflowResults`), the provenance of each output (``inputs``: the input
roles it is made from; :func:`uses`: the upstream outputs), and the order ``emreg run`` executes them in. File
names come from :mod:`EMRegModule.names`. How each stage runs, is read and is written is the pipeline's table
(:data:`EMRegModule.pipeline.stages.PIPELINE`, one entry per stage here), which the controller walks; this graph
stays apart so that the output folder (:mod:`EMRegModule.io.output_folder`) reads it without the pipeline. This
module imports nothing heavy: ``emreg --help`` loads it.
"""

from __future__ import annotations

from dataclasses import dataclass

from . import names


@dataclass(frozen=True)
class Stage:
    """One stage of the pipeline.

    ``needs``: the earlier stages whose results it is made from; ``writes``: its outputs in OUT (the first is the
    one later stages name in their provenance's ``uses``); ``inputs``: the input roles (``ct``, ``calibration``...)
    its provenance records; ``results``: the fields of :class:`~EMRegModule.pipeline.results.WorkflowResults` that
    hold its result; ``uses_present``: made from every output present in OUT (the report, the bundle);
    ``export``: a product of the rendering libraries, left out of a run without them (3D Slicer without pyvista).
    """

    name: str
    needs: tuple[str, ...]
    writes: tuple[str, ...]
    inputs: tuple[str, ...] = ()
    results: tuple[str, ...] = ()
    uses_present: bool = False
    export: bool = False


#: The stages in workflow order (a later stage never feeds an earlier one).
STAGES: tuple[Stage, ...] = (
    Stage("detect", (), (names.MARKERS_JSON, names.MARKERS_MRK_JSON), ("ct",),
          ("detection", "fiducials")),
    Stage("calibrate", (), (names.FRAME_CALIBRATION_JSON, names.TOOL_CALIBRATION_JSON, names.TIP_TO_PROBE_H5),
          ("calibration", "tool"), ("frame_calibration", "calibrated_here")),  # the tool's files: --tool auto
    Stage("register", ("detect", "calibrate"), (names.REGISTRATION_JSON, names.REFERENCE_TO_IMAGE_H5),
          ("targets", "fiducials"), ("registration",)),
    Stage("navigate", ("register",), (names.NAVIGATION_CSV, names.CHECKPOINTS_JSON, names.NAVIGATION_JSON),
          ("navigation", "tool", "plan"), ("navigation", "checkpoints", "guidance")),
    Stage("evaluate", ("register",), (names.EVALUATION_JSON,), ("navigation", "targets", "board"), ("evaluation",)),
    Stage("tre_map", ("register", "evaluate"), (names.TRE_MAP_NRRD,), results=("tre_map",)),
    Stage("report", ("detect", "calibrate", "register", "navigate", "evaluate", "tre_map"),
          (names.REPORT_HTML, names.REPORT_FIGURES), uses_present=True, export=True),
    Stage("bundle", ("report",), (names.BUNDLE_MRB,), uses_present=True, export=True),
)

STAGE: dict[str, Stage] = {stage.name: stage for stage in STAGES}

#: The outputs of each stage, in workflow order.
STAGE_OUTPUTS: dict[str, tuple[str, ...]] = {stage.name: stage.writes for stage in STAGES}


def _made_from(stage: Stage) -> set[str]:
    """Every stage ``stage`` is made from, directly or not."""
    found: set[str] = set()
    for name in stage.needs:
        found |= {name, *_made_from(STAGE[name])}
    return found


#: The stages whose results are made from each stage's (directly or not): stale when it has a new result.
DEPENDENTS: dict[str, tuple[str, ...]] = {
    stage.name: tuple(later.name for later in STAGES if stage.name in _made_from(later)) for stage in STAGES}


def outputs_from(stage: str) -> list[str]:
    """The outputs of ``stage`` and of every stage made from its result (stale once it has a new one)."""
    return [name for later in (stage, *DEPENDENTS[stage]) for name in STAGE_OUTPUTS[later]]


def all_output_names() -> list[str]:
    """Every output a run may write, in workflow order."""
    return [name for stage in STAGES for name in stage.writes]


def uses(stage: str) -> tuple[str, ...]:
    """The upstream outputs named in the provenance of ``stage``'s outputs: the first output of each stage it
    needs (the report and the bundle: every output present, :attr:`Stage.uses_present`)."""
    return tuple(STAGE[name].writes[0] for name in STAGE[stage].needs)


def made_before_export() -> list[str]:
    """The outputs the report and the bundle are made from (every output of the stages before them)."""
    return [name for stage in STAGES if not stage.export for name in stage.writes]
