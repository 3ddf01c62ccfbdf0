"""The run recorder: every output a stage saves goes through it, into an
:class:`~EMRegModule.io.output_folder.OutputFolder`
and listed in ``run.json`` with its provenance (the inputs by role and sha256, the upstream outputs it was made
from, the settings' digest, the command). What each stage writes and is made from is the stage table's
(:mod:`EMRegModule.stages`).
"""

from __future__ import annotations

import dataclasses
import os
import sys
from pathlib import Path
from typing import Any

from ..io.case import Case
from ..io.output_folder import OutputFolder
from ..io.provenance import InputDigest, Provenance, check_belongs, check_inputs_match, file_sha256
from ..io.run_folder import check_outputs
from ..settings import Settings
from ..stages import STAGE, STAGE_OUTPUTS, uses
from .bundle_state import bundle_inputs


class RunRecorder:
    """The provenance ledger of one controller: the inputs noted, and for each output held or read the
    provenance of the result and the sha256 of its file. ``command`` names the command in provenance and
    warnings (``emreg run``, ``EMReg (3D Slicer)``)."""

    def __init__(self, settings: Settings, command: str = "emreg") -> None:
        self.settings = settings
        self.command = command
        self._inputs: dict[str, tuple[str, str | InputDigest]] = {}  # role -> (path, sha256)
        self._made_from: dict[str, Provenance] = {}  # output name -> provenance of the result held
        self._output_sha: dict[str, str] = {}  # output name -> sha256 of the file written or read

    def warn(self, warnings: list[str]) -> None:
        """A stage's warnings (also kept in its output) on stderr, one line each (even when quiet)."""
        for warning in warnings:
            print(f"{self.command}: warning: {warning}", file=sys.stderr)

    def note_inputs(self, **paths: str | os.PathLike[str] | None) -> None:
        """Record input files by role (``ct``, ``calibration``, ``navigation``, ``targets``, ``board``) for the
        provenance of the outputs made from them; a CT's sha256 is the one its read computes in the same pass
        (:class:`~EMRegModule.io.provenance.InputDigest`)."""
        for role, path in paths.items():
            if path is None:
                continue
            path = Path(path)
            digest: str | InputDigest = InputDigest(path) if role == "ct" else file_sha256(path)
            self._inputs[role] = (str(path), digest)

    def provenance(self, stage: str, used: tuple[str, ...] | None = None) -> Provenance:
        """The provenance of ``stage``'s outputs: made from its input roles and the upstream outputs it uses
        (:func:`~.stages.uses`; ``used``: those present, for the report and the bundle)."""
        inputs: dict[str, dict[str, str]] = {}
        names_used = uses(stage) if used is None else used
        for name in names_used:
            if name in self._made_from:
                inputs.update(self._made_from[name].inputs)
        for role in STAGE[stage].inputs:
            if role in self._inputs:
                path, digest = self._inputs[role]
                inputs[role] = {"path": path, "sha256": digest if isinstance(digest, str) else digest.result()}
        sha = {name: self._output_sha[name] for name in names_used if name in self._output_sha}
        return Provenance(inputs, sha, self.settings.digest(), self.settings.source, made_by=self.command)

    def record(self, folder: OutputFolder, stage: str, provenance: Provenance,
               sha256: dict[str, str] | None = None) -> None:
        """List ``stage``'s outputs just written into ``folder`` in its ``run.json``; remembered for later stages."""
        folder.record(STAGE_OUTPUTS[stage], provenance, sha256)
        for name in STAGE_OUTPUTS[stage]:
            if (folder.path / name).exists():
                self._made_from[name] = provenance
                self._output_sha[name] = folder.sha256(name)

    def read_output(self, name: str, path: Path, document_provenance: dict[str, Any] | None) -> None:
        """An upstream output read from a file: checked to belong where it lies, remembered for provenance."""
        check_belongs(path)
        provenance = Provenance.from_json(document_provenance)
        if provenance is not None:
            self._made_from[name] = provenance
        self._output_sha[name] = file_sha256(path)

    def check_case_inputs(self, name: str, path: str | os.PathLike[str], case: Case) -> None:
        """Refuse an upstream output (read from its file) made from another calibration recording, CT or
        fiducials file than ``case``'s own."""
        check_inputs_match(path, self._made_from.get(name), {"calibration": case.calibration, "ct": case.ct,
                                                             "fiducials": case.fiducials})

    def adopt_outputs(self, folder: OutputFolder) -> list[str]:
        """The outputs present in ``folder``, checked to belong together; their sha256 kept for provenance."""
        used = check_outputs(folder.path)
        for name in used:
            self._output_sha.setdefault(name, folder.sha256(name))
        return used

    def bundle_provenance(self, used: list[str], folder: OutputFolder, case_dir: Path | None) -> Provenance:
        """A bundle is made from the CT and the targets too: named, a later report keeps it while none of what
        it was made from changed (:mod:`EMRegModule.pipeline.bundle_state`)."""
        provenance = self.provenance("bundle", tuple(used))
        return dataclasses.replace(provenance, inputs={**provenance.inputs, **bundle_inputs(folder.manifest, case_dir)})
