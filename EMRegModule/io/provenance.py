"""Provenance: what every output was made from, and the check that outputs read together belong together.

Each output records a :class:`Provenance`: EMReg's version, the sha256 of the settings
(:meth:`EMRegModule.settings.Settings.digest`), the sha256 of every input file it was made from
(the CT, the tracking recordings, the targets: ``inputs``, by role) and of every upstream output
it used (``uses``, by file name). JSON outputs carry it under a ``"provenance"`` key (the spec's
keys are unchanged); every output of a folder is also listed, with its sha256 and provenance, in
the folder's manifest ``run.json`` (``outputs``), which is how ``navigation.csv`` and the other
non-JSON files carry theirs.

:func:`check_belongs` is what every consumer calls before using an output: the file must be the
one the folder's ``run.json`` lists (a stale file left from an earlier run, or one copied in, is
not), the upstream outputs it used must be the ones beside it, and its inputs must be the run's.
A mismatch is an :class:`EMRegError` (exit 2) naming both sides.
"""

from __future__ import annotations

import hashlib
import os
import threading
from collections.abc import Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from .. import __version__
from ..errors import EMRegError
from ..names import RUN_JSON
from .atomic import read_json

#: The manifest of an output folder (and the record of the last ``emreg run`` into it).
_CHUNK = 1 << 22


#: Image headers whose voxels may be in a file of their own (``.nhdr``, ``.mhd``, ``.hdr`` + ``.img``).
_DETACHED_HEADERS = (".nhdr", ".mhd", ".hdr")


def file_sha256(path: str | os.PathLike[str]) -> str:
    """sha256 of a file's bytes; of a folder (a DICOM series), :func:`folder_sha256` of its files' sha256; of
    an image header whose voxels are in a file beside it, :func:`folder_sha256` of the two (a change to the
    voxels is a change to the image).

    Unreadable inputs are an :class:`EMRegError`.
    """
    path = Path(path)
    try:
        if path.is_dir():
            return folder_sha256({name: _digest(member) for name, member in folder_members(path)})
        if path.name.lower().endswith(_DETACHED_HEADERS):
            from .ct_header import detached_data_file

            data = detached_data_file(path)
            if data is not None:
                return folder_sha256({path.name: _digest(path), data.name: _digest(data)})
        return _digest(path).hex()
    except OSError as exc:
        raise EMRegError(f"{path}: cannot be read to record its provenance ({exc.strerror or exc})") from None


def folder_members(folder: Path) -> list[tuple[str, Path]]:
    """The files a folder's sha256 covers: (relative POSIX name, path), sorted by name (hidden ones too)."""
    return sorted((p.relative_to(folder).as_posix(), p) for p in folder.rglob("*") if p.is_file())


def folder_sha256(digests: Mapping[str, bytes]) -> str:
    """The sha256 of a folder from its files' own: over each relative name (sorted), a NUL, its 32-byte sha256.

    Each file's sha256 can so be computed where its bytes are read anyway (a DICOM slice as it is
    decoded, on any thread, in any order): no second pass over the folder.
    """
    digest = hashlib.sha256()
    for name in sorted(digests):
        digest.update(name.encode("utf-8") + b"\0" + digests[name])
    return digest.hexdigest()


def _digest(path: Path) -> bytes:
    digest = hashlib.sha256()
    with path.open("rb") as f:
        while chunk := f.read(_CHUNK):
            digest.update(chunk)
    return digest.digest()


class Digest:
    """A sha256 (hex) that another thread delivers: the one computed while reading a CT in a single pass."""

    def __init__(self) -> None:
        self._event = threading.Event()
        self._value: str | None = None
        self._error: BaseException | None = None

    def set(self, value: str) -> None:
        self._value = value
        self._event.set()

    def fail(self, error: BaseException) -> None:
        self._error = error
        self._event.set()

    def done(self) -> bool:
        return self._event.is_set()

    def result(self) -> str:
        self._event.wait()
        if self._error is not None:
            raise self._error
        assert self._value is not None
        return self._value


class BackgroundHash(Digest):
    """:func:`file_sha256` of a (large) input computed on a thread while other work goes on."""

    def __init__(self, path: str | os.PathLike[str]) -> None:
        super().__init__()
        self.path = Path(path)
        threading.Thread(target=self._run, name=f"sha256 {self.path.name}", daemon=True).start()

    def _run(self) -> None:
        try:
            self.set(file_sha256(self.path))
        except BaseException as exc:  # noqa: BLE001 - handed to the caller of result()
            self.fail(exc)


_READ_DIGESTS: dict[Path, Digest] = {}
_READ_DIGESTS_LOCK = threading.Lock()


def note_read_digest(path: str | os.PathLike[str], digest: Digest) -> None:
    """Say that a read of ``path`` (a CT file or DICOM folder) computes its sha256 as it goes (the latest read wins)."""
    with _READ_DIGESTS_LOCK:
        _READ_DIGESTS[Path(path).resolve()] = digest


class InputDigest:
    """The sha256 of an input CT for provenance: the one its read computed in the same pass over the bytes
    (:func:`note_read_digest`, looked up when asked, so the read may start after this is made), else a
    pass of its own over the file."""

    def __init__(self, path: str | os.PathLike[str]) -> None:
        self.path = Path(path)

    def result(self) -> str:
        with _READ_DIGESTS_LOCK:
            read = _READ_DIGESTS.get(self.path.resolve())
        if read is not None:
            try:
                return read.result()
            except Exception:  # noqa: BLE001 - the read failed (or was cancelled): hash the file on its own
                pass
        return file_sha256(self.path)


@dataclass
class Provenance:
    """What one output was made from: ``inputs`` (role -> {"path", "sha256"}), ``uses`` (upstream output
    name -> sha256), the settings' sha256 and file, EMReg's version, and the command that made it."""

    inputs: dict[str, dict[str, str]] = field(default_factory=dict)
    uses: dict[str, str] = field(default_factory=dict)
    settings_sha256: str = ""
    settings_file: str = ""
    emreg_version: str = __version__
    made_by: str = ""

    def to_json(self) -> dict[str, Any]:
        return {"emreg_version": self.emreg_version, "made_by": self.made_by,
                "settings_sha256": self.settings_sha256, "settings_file": self.settings_file,
                "inputs": {k: dict(v) for k, v in self.inputs.items()}, "uses": dict(self.uses)}

    @classmethod
    def from_json(cls, document: Any) -> Provenance | None:
        """The provenance of a document (None when it has none: a file made elsewhere, or before 0.2)."""
        if not isinstance(document, Mapping):
            return None
        inputs = document.get("inputs") or {}
        uses = document.get("uses") or {}
        if not isinstance(inputs, Mapping) or not isinstance(uses, Mapping):
            return None
        return cls({str(k): {"path": str(v.get("path", "")), "sha256": str(v.get("sha256", ""))}
                    for k, v in inputs.items() if isinstance(v, Mapping)},
                   {str(k): str(v) for k, v in uses.items()}, str(document.get("settings_sha256", "")),
                   str(document.get("settings_file", "")), str(document.get("emreg_version", "")),
                   str(document.get("made_by", "")))

    def input_hashes(self) -> dict[str, str]:
        return {role: entry["sha256"] for role, entry in self.inputs.items() if entry.get("sha256")}


def read_manifest(folder: str | os.PathLike[str]) -> dict[str, Any] | None:
    """A folder's ``run.json`` (None when absent).

    A ``run.json`` that is there but damaged (not JSON, not an object, or its ``outputs`` / ``inputs`` not
    objects) is an :class:`EMRegError`: it is what tells a run's own files from stale, copied or edited ones,
    so it is never treated as absent (that would turn the check off).
    """
    path = Path(folder) / RUN_JSON
    if not os.path.lexists(path):
        return None
    if not path.is_file():
        raise EMRegError(f"{path}: the run record is not a file; the outputs beside it cannot be checked")
    try:
        document = read_json(path, "run record")
    except OSError as exc:
        raise EMRegError(f"{path}: the run record cannot be read ({exc.strerror or exc}); "
                         "the outputs beside it cannot be checked") from None
    except EMRegError as exc:
        raise EMRegError(f"{exc}; the outputs beside it cannot be checked: run again into a fresh --out") from None
    if not isinstance(document, dict):
        raise EMRegError(f"{path}: damaged run record (not a JSON object); the outputs beside it cannot be "
                         "checked: run again into a fresh --out")
    for key in ("outputs", "inputs"):
        if key in document and not isinstance(document[key], Mapping):
            raise EMRegError(f"{path}: damaged run record ({key!r} is not an object); the outputs beside it "
                             "cannot be checked: run again into a fresh --out")
    return document


def check_belongs(path: str | os.PathLike[str], provenance: Provenance | None = None) -> None:
    """Refuse (:class:`EMRegError`, exit 2) an output that does not belong with what surrounds it.

    ``path`` is an output file (``registration.json``, ``markers.json``...); ``provenance`` its own
    (default: read from the file's ``"provenance"`` key, or from the folder's manifest).
    Checked against the folder's ``run.json`` when it lists its outputs: the file must be listed
    with the same sha256, the outputs it used must be the ones beside it, and its inputs must be the
    run's. A file without any provenance or manifest cannot be checked and is accepted.
    """
    path = Path(path)
    folder = path.parent
    manifest = read_manifest(folder)
    outputs = (manifest or {}).get("outputs")
    sha = file_sha256(path)
    recorded = [provenance, _embedded(path)]
    if isinstance(outputs, Mapping):
        entry = outputs.get(path.name)
        if not isinstance(entry, Mapping):
            raise EMRegError(f"{path}: not an output of the run recorded in {folder / RUN_JSON} "
                             f"({_describe_run(manifest)}): a stale or copied file; run again into a fresh --out")
        if entry.get("sha256") != sha:
            raise EMRegError(f"{path}: changed since the run recorded in {folder / RUN_JSON} wrote it "
                             f"({_describe_run(manifest)}); run again")
        recorded.append(Provenance.from_json(entry.get("provenance")))
    run_inputs = (manifest or {}).get("inputs")
    for found in (p for p in recorded if p is not None):
        _check_uses(path, found)
        if isinstance(run_inputs, Mapping):
            _check_inputs(path, found, run_inputs, folder / RUN_JSON)


def _check_inputs(path: Path, provenance: Provenance, run_inputs: Mapping[str, Any], run_json: Path) -> None:
    for role, recorded in provenance.input_hashes().items():
        entry = run_inputs.get(role)
        if isinstance(entry, Mapping) and entry.get("sha256") and entry.get("sha256") != recorded:
            raise EMRegError(f"{path}: made from another {role} ({provenance.inputs[role].get('path')}) "
                             f"than the run recorded in {run_json} ({entry.get('path')}); "
                             "outputs of two runs must not be mixed")


def check_inputs_match(path: str | os.PathLike[str], provenance: Provenance | None,
                       inputs: Mapping[str, str | os.PathLike[str] | None]) -> None:
    """Refuse an output made from other input files than ``inputs`` (role -> path) of the case at hand."""
    if provenance is None:
        return
    recorded = provenance.input_hashes()
    for role, input_path in inputs.items():
        if input_path is None or role not in recorded:
            continue
        if file_sha256(input_path) != recorded[role]:
            raise EMRegError(f"{path}: made from another {role} ({provenance.inputs[role].get('path')}) than "
                             f"{input_path}; use the outputs of this case")


def _check_uses(path: Path, provenance: Provenance) -> None:
    for name, used_sha in provenance.uses.items():
        beside = path.parent / name
        if beside.is_file() and beside != path and file_sha256(beside) != used_sha:
            raise EMRegError(f"{path}: made from another {name} than {beside}; the folder mixes outputs of "
                             "two runs: run again into a fresh --out")


def _embedded(path: Path) -> Provenance | None:
    if path.suffix != ".json":
        return None
    try:
        document = read_json(path, "output")
    except EMRegError:
        return None
    return Provenance.from_json(document.get("provenance")) if isinstance(document, dict) else None


def _describe_run(manifest: Mapping[str, Any] | None) -> str:
    if not manifest:
        return "no run"
    status = manifest.get("status")
    case = manifest.get("case") or manifest.get("made_by") or "?"
    return f"case {case}" + (f", {status}" if status else "")
