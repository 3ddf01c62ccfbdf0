"""What a stage of the table is handed (:class:`Job`) and what it hands back (:class:`Made`, :class:`Read`): values,
so that a stage changes nothing it was given; the controller replaces its inputs and results with what it made.
"""

from __future__ import annotations

from collections.abc import Callable, Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any

from ..progress import QUIET, Progress
from .inputs import Inputs
from .results import WorkflowResults

if TYPE_CHECKING:
    from ..io.case import Case
    from ..io.output_folder import OutputFolder
    from .exporters import CTHold, Exporter

@dataclass(frozen=True)
class Job:
    """One stage's work.

    ``inputs`` and ``results``: what the workflow was given and has made so far; ``options``: the stage's own (a
    per-stage command's: the recording to navigate, the targets...); ``case``: within ``emreg run`` (or the 3D
    Slicer module), the case folder the stage takes its optional inputs from, a part that cannot be made then
    being skipped with its reason rather than refused; ``folder``: the output folder (the report and the bundle
    write into it); ``warn``: says a stage's warnings on stderr (the recorder's); ``exporter`` and ``ct``: the
    report's and the bundle's machinery and the CT handed to them.
    """

    inputs: Inputs
    results: WorkflowResults
    warn: Callable[[list[str]], None]
    progress: Progress = QUIET
    options: Mapping[str, Any] = field(default_factory=dict)
    case: Case | None = None
    folder: OutputFolder | None = None
    exporter: Exporter | None = None
    ct: CTHold | None = None


@dataclass(frozen=True)
class Read:
    """A stage's result read from a file: ``results`` (its fields of
    :class:`~EMRegModule.pipeline.results.WorkflowResults`), the file, and either the output it is (``output``, with
    the provenance it records) or the input role it is read as (``input_role``: fiducials)."""

    results: Mapping[str, Any]
    path: Path
    output: str | None = None
    provenance: dict[str, Any] | None = None
    input_role: str | None = None


@dataclass(frozen=True)
class Made:
    """What a stage made: ``results`` (its fields; empty: nothing made, the stage did not apply to this case),
    ``inputs`` when it changed them (the CT read with its detection, a tool's tip solved by the calibration),
    ``read`` when the result was read from a file rather than made (a fiducial case's fiducials), the ``summary``
    lines of ``emreg run``, the parts ``run.json`` records as not made (``not_evaluated``) and other entries for it
    (``manifest``)."""

    results: Mapping[str, Any] = field(default_factory=dict)
    inputs: Inputs | None = None
    read: Read | None = None
    summary: tuple[str, ...] = ()
    not_evaluated: Mapping[str, str] = field(default_factory=dict)
    manifest: Mapping[str, Any] = field(default_factory=dict)
