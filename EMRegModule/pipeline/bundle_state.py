"""Whether ``OUT/EMReg.mrb`` is still the scene bundle a new report of OUT would write (then it is kept).

The bundle is made from the run's outputs (``markers.json`` ... ``tre_map.nrrd``), the CT ``run.json``
names and the case's ``targets.mrk.json``; its entry in ``run.json`` records their sha256 (provenance
``uses`` and ``inputs``), the settings' digest and the EMReg version. When all of these are what they are
now and the file is the one recorded (its sha256, computed on a thread while the report renders), writing it
again would give the same scene: ``emreg report`` keeps it instead of copying the CT into a new one (a second
of CPU and the CT's size written at 0.6 mm, several at 0.3 mm). The CT itself is checked by the report against
``run.json`` (:func:`~EMRegModule.report.writer._check_run_ct`), before anything is kept. Without slicer-core
nothing is kept: a bundle that could not be renewed is removed, as before, and the report says why.
"""

from __future__ import annotations

import importlib.util
from pathlib import Path
from typing import Any

from .. import __version__
from ..errors import EMRegError
from ..io.provenance import BackgroundHash, file_sha256
from ..names import BUNDLE_MRB, TARGETS_FILE
from ..stages import made_before_export

BUNDLE_NAME = BUNDLE_MRB


def bundle_inputs(run: dict[str, Any], case_dir: Path | None) -> dict[str, dict[str, str]]:
    """The inputs a bundle of this run is made from besides its outputs: the CT ``run.json`` records (path and
    sha256) and the case's targets file (path and sha256), where there are any."""
    inputs: dict[str, dict[str, str]] = {}
    recorded = run.get("inputs")
    ct = recorded.get("ct") if isinstance(recorded, dict) else None
    if isinstance(ct, dict) and ct.get("path") == run.get("ct") and isinstance(ct.get("sha256"), str):
        inputs["ct"] = {"path": str(ct["path"]), "sha256": str(ct["sha256"])}
    case = case_dir if case_dir is not None else (Path(run["case"]) if isinstance(run.get("case"), str) else None)
    targets = case / TARGETS_FILE if case is not None else None
    if targets is not None and targets.is_file():
        try:
            inputs["targets"] = {"path": str(targets), "sha256": file_sha256(targets)}
        except EMRegError:
            pass
    return inputs


class KeptBundle:
    """An up-to-date ``EMReg.mrb`` a new report keeps; :meth:`start_check` hashes its file on a thread and
    :meth:`confirmed` waits for that."""

    def __init__(self, path: Path, sha256: str) -> None:
        self.path = path
        self.sha256 = sha256
        self._digest: BackgroundHash | None = None

    def start_check(self) -> KeptBundle:
        self._digest = BackgroundHash(self.path)
        return self

    def confirmed(self) -> bool:
        """Whether the file is still the one ``run.json`` lists (not edited or replaced since)."""
        if self._digest is None:
            self.start_check()
        try:
            return self._digest.result() == self.sha256
        except EMRegError:
            return False


def current_bundle(out: Path, run: dict[str, Any], case_dir: Path | None,
                   settings_sha256: str | None) -> KeptBundle | None:
    """The bundle in ``out`` when a new one would be the same (see the module's docstring), else None.
    ``settings_sha256`` None: the settings are not compared (a first look, before they are read)."""
    path = out / BUNDLE_NAME
    if not _slicer_core_installed():  # the bundle cannot be renewed here: it goes, and the report says why
        return None
    outputs = run.get("outputs") if isinstance(run, dict) else None
    if not isinstance(outputs, dict):
        return None
    entry = outputs.get(BUNDLE_NAME)
    if not path.is_file() or not isinstance(entry, dict) or not isinstance(entry.get("sha256"), str):
        return None
    provenance = entry.get("provenance")
    if not isinstance(provenance, dict) or provenance.get("emreg_version") != __version__ or (
            settings_sha256 is not None and provenance.get("settings_sha256") != settings_sha256):
        return None
    listed = {name: outputs[name].get("sha256") for name in made_before_export()
              if (out / name).is_file() and isinstance(outputs.get(name), dict)}
    if provenance.get("uses") != listed or len(listed) != sum(
            1 for name in made_before_export() if (out / name).is_file()):
        return None
    inputs, recorded = bundle_inputs(run, case_dir), provenance.get("inputs")
    if "ct" not in inputs or not isinstance(recorded, dict) or any(
            recorded.get(role) != inputs.get(role) for role in ("ct", "targets")):
        return None
    return KeptBundle(path, entry["sha256"])


def _slicer_core_installed() -> bool:
    """Whether the slicer-core wheel is importable (found, not imported: its libraries stay out of this process)."""
    try:
        return importlib.util.find_spec("slicer") is not None
    except (ImportError, ValueError):
        return False
