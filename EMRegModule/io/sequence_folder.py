"""A tracking recording given as a folder of sequence files, one transform each, as 3D Slicer saves them.

3D Slicer's Sequences module keeps each recorded transform in a sequence node of its own and saves each
node to a file of its own (``vtkMRMLLinearTransformSequenceStorageNode``: ``ReferenceToTracker.seq.nrrd``,
``ProbeToTracker.seq.nrrd``, or ``.seq.mha``), every file in the PLUS sequence-metafile layout with one
transform (:mod:`EMRegModule.io.sequence_metafile`). EMReg reads such a recording from a folder holding
those files (``CASE/calibration/``, ``CASE/navigation/``, ``CASE/board/``, or any folder given where a
recording file is expected):

- each sequence file of the folder is read; a transform takes the role whose name it carries
  (``[sensors] reference_transform`` / ``probe_transform``, default ``ReferenceToTracker`` /
  ``ProbeToTracker``; a Slicer node-name ending ``-Sequence`` / ``_Sequence`` is ignored) and, for a
  file holding a single transform of another name (``Unknown1ToUnknown2``), the role its file name
  carries;
- the reference and probe frames are matched by timestamp (within 1 ms, never across a clock reset);
  frames without a partner are dropped with a warning that counts them;
- refused with one line (exit 2): no sequence file, a role found in no file (the partner file is
  missing) or in two, or files that do not hold the same frames (fewer than half of the frames of the
  longer file find a partner: two different recordings).

Statuses, rigidity and time resets are handled as for a single file.
"""

from __future__ import annotations

import os
import re
from pathlib import Path

import numpy as np

from ..core.tracking import SAME_MOMENT_LIMIT_S, SAME_MOMENT_S, TrackingRecording
from ..errors import EMRegError
from ..names import DEFAULT_PROBE_PORT, DEFAULT_REFERENCE_PORT
from .sequence_metafile import (
    DEFAULT_PROBE_TRANSFORM,
    DEFAULT_REFERENCE_TRANSFORM,
    SEQUENCE_SUFFIXES,
    SequenceFrames,
    is_sequence_file,
    read_sequence_frames,
    recording_from_frames,
)

#: A sequence node name's ending that 3D Slicer may add to the transform's own name.
_NODE_SUFFIX = re.compile(r"[-_ ]?sequence$", re.IGNORECASE)
#: Fewer matched frames than this fraction of the longer file's: the two files are not one recording.
MIN_MATCHED_FRACTION = 0.5


def sequence_files(folder: str | os.PathLike[str]) -> list[Path]:
    """The sequence files (by name) directly in ``folder``, sorted by name."""
    folder = Path(folder)
    return sorted(p for p in folder.iterdir() if p.is_file() and is_sequence_file(p) and not p.name.startswith("."))


def is_sequence_folder(path: str | os.PathLike[str]) -> bool:
    """True for a folder holding at least one sequence file (a recording saved by 3D Slicer, one file per transform)."""
    path = Path(path)
    return path.is_dir() and bool(sequence_files(path))


def _base(name: str) -> str:
    for suffix in SEQUENCE_SUFFIXES:
        if name.lower().endswith(suffix):
            name = name[: -len(suffix)]
            break
    name = _NODE_SUFFIX.sub("", name)
    return name[: -len("Transform")] if name.endswith("Transform") and name != "Transform" else name


def read_sequence_folder(
    folder: str | os.PathLike[str],
    reference_transform: str = DEFAULT_REFERENCE_TRANSFORM,
    probe_transform: str = DEFAULT_PROBE_TRANSFORM,
    reference_port: int = DEFAULT_REFERENCE_PORT,
    probe_port: int = DEFAULT_PROBE_PORT,
) -> TrackingRecording:
    """The recording of a folder of single-transform sequence files (see module docstring): the reference
    and probe transforms as rows of the given ports, their frames matched by timestamp."""
    folder = Path(folder)
    if not folder.is_dir():
        raise EMRegError(f"{folder}: tracking recording folder not found")
    files = sequence_files(folder)
    if not files:
        suffixes = ", ".join(SEQUENCE_SUFFIXES)
        raise EMRegError(f"{folder}: is a folder with no sequence file ({suffixes}); give a tracking recording file, "
                         "or a folder of 3D Slicer sequence files (one per transform)")
    roles: dict[str, list[tuple[Path, SequenceFrames, str]]] = {reference_transform: [], probe_transform: []}
    held = []
    for path in files:
        frames = read_sequence_frames(path)
        held.append(f"{path.name}: {', '.join(frames.names) or 'no transform'}")
        for name in frames.names:
            role = _base(name) if _base(name) in roles else None
            if role is None and len(frames.names) == 1 and _base(path.name) in roles:
                role = _base(path.name)
            if role is not None:
                roles[role].append((path, frames, name))
    for role, found in roles.items():
        if len(found) > 1:
            names = ", ".join(p.name for p, _, _ in found)
            raise EMRegError(f"{folder}: {role}Transform is in more than one file ({names}); keep the files of one "
                             "recording per folder")
    missing = [role for role, found in roles.items() if not found]
    if missing:
        raise EMRegError(f"{folder}: no {' or '.join(m + 'Transform' for m in missing)} in the recording folder (its "
                         f"partner file missing?); it holds {'; '.join(held)}; name the transforms with [sensors] "
                         "reference_transform / probe_transform in case.toml")
    (ref_path, ref_frames, ref_name), = roles[reference_transform]
    (probe_path, probe_frames, probe_name), = roles[probe_transform]
    if ref_path == probe_path:  # both transforms in one file: as a single sequence file
        return recording_from_frames(ref_frames, {ref_name: reference_port, probe_name: probe_port})
    merged, notes = _match_frames(folder, (ref_path, ref_frames, ref_name, reference_transform),
                                  (probe_path, probe_frames, probe_name, probe_transform))
    recording = recording_from_frames(merged, {reference_transform: reference_port, probe_transform: probe_port})
    recording.warnings = notes + list(recording.warnings)
    return recording


def _segments(time_s: np.ndarray) -> np.ndarray:
    """Segment number of each frame: a new segment where the time goes back (a clock reset)."""
    return np.concatenate([[0], np.cumsum(np.diff(time_s) < 0)]).astype(int)


def _match_frames(folder: Path, reference: tuple[Path, SequenceFrames, str, str],
                  probe_file: tuple[Path, SequenceFrames, str, str]) -> tuple[SequenceFrames, list[str]]:
    """One SequenceFrames (transforms named by role) holding the reference frames that have a probe frame
    within ``SAME_MOMENT_S`` (the nearest, in the same clock segment), with that probe frame; and a warning
    counting the frames left out. Each argument: (file, its frames, transform name in it, role name)."""
    ref_path, ref, ref_name, ref_role = reference
    probe_path, probe, probe_name, probe_role = probe_file
    ref_segment, probe_segment = _segments(ref.time_s), _segments(probe.time_s)
    ref_index, probe_index = [], []
    for segment in np.intersect1d(ref_segment, probe_segment):
        r = np.flatnonzero(ref_segment == segment)
        p = np.flatnonzero(probe_segment == segment)
        order = np.argsort(ref.time_s[r], kind="stable")
        r_sorted = r[order]
        times = ref.time_s[r_sorted]
        right = np.clip(np.searchsorted(times, probe.time_s[p]), 0, len(times) - 1)
        left = np.clip(right - 1, 0, len(times) - 1)
        nearest = np.where(np.abs(times[left] - probe.time_s[p]) <= np.abs(times[right] - probe.time_s[p]),
                           left, right)
        ok = np.abs(times[nearest] - probe.time_s[p]) <= SAME_MOMENT_LIMIT_S
        used: set[int] = set()
        for k in np.flatnonzero(ok):  # one probe frame per reference frame (the first, in file order)
            candidate = int(r_sorted[nearest[k]])
            if candidate not in used:
                used.add(candidate)
                ref_index.append(candidate)
                probe_index.append(int(p[k]))
    order = np.argsort(ref_index, kind="stable")
    ri = np.asarray(ref_index, dtype=int)[order]
    pi = np.asarray(probe_index, dtype=int)[order]
    n_ref, n_probe, matched = len(ref.time_s), len(probe.time_s), len(ri)
    if matched < MIN_MATCHED_FRACTION * max(n_ref, n_probe):
        raise EMRegError(f"{folder}: {ref_path.name} and {probe_path.name} do not hold the same frames: only {matched} "
                         f"of {n_ref} {ref_name} and {n_probe} {probe_name} frames share a timestamp (within "
                         f"{SAME_MOMENT_S * 1000:g} ms); give the two files of one recording")
    notes = []
    if matched < max(n_ref, n_probe):
        notes.append(f"{folder}: {n_ref - matched} of {n_ref} frames of {ref_path.name} and {n_probe - matched} of "
                     f"{n_probe} of {probe_path.name} have no partner frame at their timestamp: left out")

    tables = {}
    for table in ("matrices", "valid", "quality", "position_only"):
        tables[table] = {ref_role: getattr(ref, table)[ref_name][ri], probe_role: getattr(probe, table)[probe_name][pi]}
    merged = SequenceFrames(source=str(folder), time_s=ref.time_s[ri], **tables,
                            index=(np.arange(n_ref) if ref.index is None else np.asarray(ref.index))[ri])
    return merged, notes
