"""The stage table the controller walks: each stage of :data:`EMRegModule.stages.STAGES` (what it needs, writes and
is made from) with its callables, :mod:`.steps`' functions.

Adding a stage is one entry here (and one in :data:`EMRegModule.stages.STAGES`, the graph the output folder reads
without the pipeline) plus its functions.
"""

from __future__ import annotations

from collections.abc import Callable, Mapping
from dataclasses import dataclass
from pathlib import Path

from ..io.provenance import Provenance
from ..settings import Settings
from ..stages import STAGE, STAGES, Stage
from . import steps
from .inputs import Inputs
from .job import Job, Made, Read
from .results import WorkflowResults


@dataclass(frozen=True)
class PipelineStage:
    """One stage and how it is done.

    - ``stage``: the graph's entry (its ``needs``, ``writes``, ``inputs``, ``results``).
    - ``run``: makes its result from a :class:`~.job.Job` (the inputs, the results it needs).
    - ``write``: writes its result into an output folder (the controller records its provenance); None: ``run``
      writes and records it (the report, the bundle: :class:`~.exporters.Exporter`).
    - ``read``: its result from its file (a per-stage command's ``--markers``, ``--registration``...); None: never
      read back as an input.
    - ``prepare``: in ``emreg run``, what it reads and checks of the case before any stage runs (its inputs).
    """

    stage: Stage
    run: Callable[[Job], Made]
    write: Callable[[WorkflowResults, Path, Provenance], None] | None = None
    read: Callable[[Path, Settings], Read] | None = None
    prepare: Callable[[Job], Inputs] | None = None

    @property
    def name(self) -> str:
        return self.stage.name


#: The stages in workflow order, with their callables.
PIPELINE: tuple[PipelineStage, ...] = (
    PipelineStage(STAGE["detect"], steps.run_detect, steps.write_detect, steps.read_detect),
    PipelineStage(STAGE["calibrate"], steps.run_calibrate, steps.write_calibrate, steps.read_calibrate,
                  steps.prepare_calibrate),
    PipelineStage(STAGE["register"], steps.run_register, steps.write_register, steps.read_register),
    PipelineStage(STAGE["navigate"], steps.run_navigate, steps.write_navigate),
    PipelineStage(STAGE["evaluate"], steps.run_evaluate, steps.write_evaluate),
    PipelineStage(STAGE["tre_map"], steps.run_tre_map, steps.write_tre_map_file),
    PipelineStage(STAGE["report"], steps.run_report),
    PipelineStage(STAGE["bundle"], steps.run_bundle),
)

#: The table by stage name.
PIPELINE_STAGE: Mapping[str, PipelineStage] = {entry.name: entry for entry in PIPELINE}

assert tuple(entry.stage for entry in PIPELINE) == STAGES, "every stage of the graph, in its order"
