"""The output folder of a command: its files, its manifest ``run.json``, and what makes it never mix two runs.

Every file EMReg writes into an output folder OUT goes through an :class:`OutputFolder`:

- it is written atomically (temporary name, then rename), and then listed in ``OUT/run.json``
  (``outputs``: name -> sha256 and provenance, :mod:`EMRegModule.io.provenance`), so a consumer can
  tell this run's files from anything else;
- ``emreg run`` starts by moving every output of an earlier run (and ``run.json`` itself) into
  ``OUT/previous/`` (replacing what an even earlier run left there), before it writes anything:
  whether the new run finishes, is refused (exit 3), fails (exit 2) or is interrupted, OUT then
  only holds files of the new run, and its ``run.json`` says how the run ended (``status``);
- a per-stage command (``emreg detect``, ``register``...) moves aside the outputs of its own
  stage and of every later stage, which its new result makes stale, and keeps the others;
- OUT may not be, or lie inside, an input folder (the case) unless nothing it writes could
  overwrite an input (:func:`refuse_out_over_inputs`).
"""

from __future__ import annotations

import contextlib
import datetime
import os
import shutil
from collections.abc import Iterable, Mapping
from pathlib import Path
from typing import Any

from .. import __version__
from ..errors import EMRegError
from ..interrupts import signals_held
from ..names import CASE_INPUT_NAMES, PREVIOUS_FOLDER, RUN_JSON
from ..stages import all_output_names, outputs_from
from .atomic import atomic_write_json
from .provenance import Provenance, file_sha256, read_manifest


def _now() -> str:
    return datetime.datetime.now(datetime.UTC).isoformat(timespec="seconds")


def _resolved(path: str | os.PathLike[str]) -> Path:
    """``path`` made absolute with its links followed; a symbolic-link loop is an :class:`EMRegError` naming it."""
    try:
        return Path(path).resolve()
    except (RuntimeError, OSError):  # RuntimeError: Python < 3.13's "Symlink loop"; OSError (ELOOP) after
        raise EMRegError(f"{path}: is a symbolic-link loop; give the file or folder itself") from None


def refuse_out_over_inputs(out: str | os.PathLike[str], inputs: Iterable[str | os.PathLike[str]],
                           written: Iterable[str], case_folder: str | os.PathLike[str] | None = None) -> None:
    """Refuse (exit 2) an output folder that could overwrite an input: one equal to or inside an input
    folder (a DICOM ``ct/``), or one equal to the folder of an input where a name it writes (``written``,
    plus ``run.json`` and ``previous``) is an input, or, for the case folder, a name a case is read from
    (``--out CASE`` would replace the patient's ``navigation.csv``)."""
    out = _resolved(out)
    paths = [_resolved(p) for p in inputs]
    names = {*written, RUN_JSON, PREVIOUS_FOLDER}
    for path in paths:
        if path.is_dir() and (out == path or path in out.parents):
            raise EMRegError(f"--out {out}: lies inside the input {path}; choose an output folder outside it")
    case = Path(case_folder).resolve() if case_folder is not None else None
    if out not in {p.parent for p in paths} and out != case:
        return
    clash = sorted(n for n in names if out / n in paths or (out == case and n in CASE_INPUT_NAMES))
    if clash:
        raise EMRegError(f"--out {out}: would overwrite {', '.join(clash)}, an input of this command; "
                         "choose an output folder outside the case folder")


class OutputFolder:
    """OUT, its manifest ``run.json`` and the atomic, recorded writes of one command (see module docstring)."""

    def __init__(self, path: str | os.PathLike[str], made_by: str) -> None:
        self.path = Path(path)
        self.made_by = made_by
        if self.path.exists() and not self.path.is_dir():
            raise EMRegError(f"--out {self.path}: exists and is not a folder")
        try:
            self.path.mkdir(parents=True, exist_ok=True)
        except OSError as exc:
            raise EMRegError(f"--out {self.path}: cannot create the output folder ({exc.strerror or exc})") from None
        self.damaged: EMRegError | None = None  # a run.json there but damaged: only ``emreg run`` replaces it
        try:
            self.manifest: dict[str, Any] = read_manifest(self.path) or {}
        except EMRegError as exc:
            self.damaged, self.manifest = exc, {}

    # --- starting -------------------------------------------------------------------------------

    def start_run(self, record: Mapping[str, Any]) -> None:
        """Begin ``emreg run``: the previous run's outputs go to ``OUT/previous/``; ``run.json`` says "running".
        An interrupt waits until this is done (OUT never holds a previous run's file beside this run.json)."""
        with signals_held():
            self._start_run(record)

    def _start_run(self, record: Mapping[str, Any]) -> None:
        old = dict(self.manifest)
        self.damaged = None  # a damaged run.json goes to previous/ with the rest; nothing in OUT is trusted
        stale = self._present(set(all_output_names()) | set(old.get("outputs") or {}))
        previous = self.path / PREVIOUS_FOLDER
        if stale or (self.path / RUN_JSON).is_file():
            if previous.is_dir():
                shutil.rmtree(previous)
            previous.mkdir()
            if (self.path / RUN_JSON).is_file():
                shutil.copy2(self.path / RUN_JSON, previous / RUN_JSON)
        self.manifest = {**record, "status": "running", "started_utc": _now(), "made_by": self.made_by,
                         "outputs": {}}
        self.save()  # from here on, no earlier file in OUT is listed: consumers refuse it
        for name in stale:
            os.replace(self.path / name, previous / name)
        self._remove_temporaries()

    def start_stage(self, stage: str, keep: Iterable[str] = ()) -> None:
        """Begin a per-stage command: the outputs of ``stage`` and of the stages made from it move to
        ``previous/``, except those in ``keep`` (still up to date: they stay, listed as they are)."""
        self._refuse_damaged()
        kept = set(keep)
        names = [name for name in outputs_from(stage) if name not in kept]
        stale = self._present(names)
        if stale:
            previous = self.path / PREVIOUS_FOLDER
            previous.mkdir(exist_ok=True)
            for name in stale:
                target = previous / name
                if target.is_dir():
                    shutil.rmtree(target)
                os.replace(self.path / name, target)
        outputs = self.manifest.get("outputs")
        if isinstance(outputs, dict):
            for name in names:
                outputs.pop(name, None)
        else:  # a folder without a manifest (hand-made, or an older EMReg): what is there is adopted as is
            outputs = {name: {"sha256": file_sha256(self.path / name), "adopted": True}
                       for name in self._present(all_output_names()) if (self.path / name).is_file()}
        if not self.manifest and not outputs:
            return  # an empty folder: nothing to record until something is written
        self.manifest.setdefault("emreg_version", __version__)
        self.manifest["outputs"] = outputs
        self.save()

    def _refuse_damaged(self) -> None:
        """A per-stage command never adopts the outputs beside a damaged ``run.json`` (nor overwrites it)."""
        if self.damaged is not None:
            raise EMRegError(str(self.damaged))

    def _present(self, names: Iterable[str]) -> list[str]:
        return sorted(n for n in names if n and "/" not in n and n not in (RUN_JSON, PREVIOUS_FOLDER)
                      and (self.path / n).exists())

    def _remove_temporaries(self) -> None:
        """Temporary files an earlier, killed process left behind (``.name-XXXX.suffix``)."""
        for name in [*all_output_names(), RUN_JSON]:
            stem = name.split(".")[0]
            for leftover in self.path.glob(f".{stem}-*"):
                with contextlib.suppress(OSError):
                    leftover.unlink()

    # --- writing --------------------------------------------------------------------------------

    def record(self, names: Iterable[str], provenance: Provenance, sha256: dict[str, str] | None = None) -> None:
        """List files just written (atomically, by their stage's writer) in ``run.json`` with their sha256
        (``sha256``: those already computed by their writer, by name)."""
        self._refuse_damaged()
        outputs = self.manifest.setdefault("outputs", {})
        known = sha256 or {}
        for name in names:
            if (self.path / name).exists():
                digest = known.get(name) or file_sha256(self.path / name)
                outputs[name] = {"sha256": digest, "provenance": provenance.to_json()}
        inputs = self.manifest.setdefault("inputs", {})
        for role, entry in provenance.inputs.items():
            inputs.setdefault(role, dict(entry))
        self.save()

    def remove_from(self, stage: str) -> None:
        """Delete the outputs of ``stage`` and of the stages made from it (a refusal: nothing misleading stays)."""
        outputs = self.manifest.get("outputs") or {}
        for name in outputs_from(stage):
            self._delete(name)
            outputs.pop(name, None)
        self.save()

    def sha256(self, name: str) -> str:
        """The sha256 of an output as listed in ``run.json`` (computed when not listed)."""
        entry = (self.manifest.get("outputs") or {}).get(name)
        if isinstance(entry, Mapping) and entry.get("sha256"):
            return str(entry["sha256"])
        return file_sha256(self.path / name)

    def drop_unrecorded(self) -> list[str]:
        """Remove the outputs present in OUT but not listed in ``run.json`` (written in the instant an interrupt
        came, before they could be listed, or a report's figures without their page); their names."""
        listed = self.manifest.get("outputs") or {}
        dropped = [name for name in self._present(all_output_names()) if name not in listed]
        for name in dropped:
            self._delete(name)
        return dropped

    def _delete(self, name: str) -> None:
        """Delete the output ``name`` of OUT: a file, a folder (the report's figures), or a link (itself only)."""
        target = self.path / name
        if target.is_dir() and not target.is_symlink():
            shutil.rmtree(target, ignore_errors=True)
        else:
            with contextlib.suppress(FileNotFoundError):
                target.unlink()

    def finish(self, status: str, message: str | None = None) -> None:
        """Record how the run ended: ``finished``, ``refused`` (exit 3), ``failed`` (exit 2), ``interrupted``."""
        self.manifest["status"] = status
        if message:
            self.manifest["message"] = message
        self.manifest["finished_utc"] = _now()
        self.save()

    def save(self) -> None:
        atomic_write_json(self.path / RUN_JSON, self.manifest)
