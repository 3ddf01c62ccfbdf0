"""PLUS / 3D Slicer sequence metafiles of tracked poses (``.seq.mha``, ``.mha``, ``.seq.nrrd``, ``.igs.nrrd``).

The PLUS "SequenceMetafile" layout (MetaIO text header; the image part is empty for a
tracking-only file, ``DimSize = 0 0 N``), one group of fields per frame::

    Seq_Frame0000_ProbeToTrackerTransform = r00 r01 r02 tx r10 ... 0 0 0 1   (row-major 4x4, mm)
    Seq_Frame0000_ProbeToTrackerTransformStatus = OK                         (anything else: no valid pose)
    Seq_Frame0000_Timestamp = 12.3375                                        (s)
    ...
    ElementDataFile = LOCAL                                                  (last header line)

Every transform name of the file is read (3D Slicer's own reader keeps only the first), and the
status is honoured: a frame whose status is not ``OK`` gives no pose for that transform; such
frames are dropped and counted (``TrackingRecording.warnings``). The NRRD variant with
``key:=value`` fields (PLUS ``.igs.nrrd``) is read too; 3D Slicer writes ``.seq.nrrd`` with the
MetaIO text above, which is what :func:`write_sequence_metafile` writes for that suffix.

EMReg extras, ignored by PLUS and Slicer: ``Seq_FrameNNNN_<Name>TransformQuality`` (the
tracker's quality number) and ``Seq_FrameNNNN_<Name>TransformOrientation = MISSING`` for a
position-only pose (the rotation written is the identity).

Transform status as PLUS and 3D Slicer read it: PLUS (IGSIO's ``igsioTrackedFrame::GetFrameTransformStatus``)
marks a transform whose ``...TransformStatus`` field is missing ``TOOL_INVALID`` (with an error), 3D Slicer's
sequence reader ignores the status field altogether. A transform that has no status field in *any* frame (files
written by tools that never record it, e.g. PLUS's own ``TransformInterpolationTest.igs.mha``) is read as Slicer
reads it, every pose valid, with a warning; a frame without the status where other frames of the same transform
have one is refused (one line), as an inconsistent file.

Transform names: with no ``<probe>Transform`` in the file but exactly two transforms, one the reference, the
other is taken as the tool (with a warning): ``ReferenceToTracker`` + ``StylusToTracker`` as PLUS records them.

Bad input (a broken header, a frame without its timestamp, a matrix that is not rigid
within :data:`~EMRegModule.core.transforms.RIGID_TOLERANCE`, NaN values, a sensor's time repeated) raises
:class:`EMRegError`
with one line naming the file and the frame. Timestamps that go back (a clock reset) or pause for
more than 2 s split the recording into time segments with a warning naming the frame, by the same
rule as a tracking CSV (:func:`EMRegModule.core.tracking.split_time_segments`): nothing is dropped and
samples are never matched across a reset. Writing keeps the segments in order, each with its own
timestamps, so a reset survives a conversion either way.
"""

from __future__ import annotations

import os
import re
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from ..core.tracking import SAME_MOMENT_LIMIT_S, TrackingRecording, split_time_segments
from ..core.transforms import RIGID_TOLERANCE, check_rigid
from ..errors import EMRegError
from ..names import DEFAULT_PROBE_PORT, DEFAULT_REFERENCE_PORT
from .atomic import atomic_path

#: File name endings read and written as sequence metafiles.
SEQUENCE_SUFFIXES = (".seq.mha", ".mha", ".seq.nrrd", ".igs.nrrd")
DEFAULT_REFERENCE_TRANSFORM = "ReferenceToTracker"
DEFAULT_PROBE_TRANSFORM = "ProbeToTracker"
#: Header lines longer than this are not a sequence metafile header (binary data reached).
_MAX_LINE = 1 << 16
_FRAME_FIELD = re.compile(r"^Seq_Frame(\d+)_(\S+)$")


def is_sequence_file(path: str | os.PathLike[str]) -> bool:
    """True when the file name ends like a sequence metafile (``.seq.mha``, ``.mha``, ``.seq.nrrd``, ``.igs.nrrd``)."""
    name = Path(path).name.lower()
    return any(name.endswith(s) for s in SEQUENCE_SUFFIXES)


@dataclass
class SequenceFrames:
    """The transforms of a sequence metafile: per name, (F, 4, 4) matrices, a validity mask (F,),
    the quality (F,) (NaN: unknown) and a position-only mask (F,); ``time_s`` (F,) in file order
    (it may go back: a clock reset); ``index`` (F,) the frame numbers of the file (None: 0..F-1)."""

    source: str
    time_s: np.ndarray
    matrices: dict[str, np.ndarray]
    valid: dict[str, np.ndarray]
    quality: dict[str, np.ndarray] = field(default_factory=dict)
    position_only: dict[str, np.ndarray] = field(default_factory=dict)
    index: np.ndarray | None = None
    #: per transform name, what reading found and kept (one line: a transform without any status field)
    notes: dict[str, str] = field(default_factory=dict)

    @property
    def names(self) -> list[str]:
        """Transform names without the ``Transform`` suffix (e.g. ``ProbeToTracker``), in file order."""
        return list(self.matrices)


def _read_header(path: Path) -> tuple[dict[str, str], str]:
    """Header fields up to ``ElementDataFile`` (kept in file order) and the separator style."""
    fields: dict[str, str] = {}
    try:
        handle = path.open("rb")
    except FileNotFoundError:
        raise EMRegError(f"{path}: tracking recording not found") from None
    except OSError as exc:
        raise EMRegError(f"{path}: cannot be read ({exc.strerror})") from None
    with handle:
        first = True
        nrrd = False
        line_no = 0
        while True:
            raw = handle.readline(_MAX_LINE)
            line_no += 1
            if not raw:
                raise EMRegError(f"{path}: broken sequence metafile header: it ends before 'ElementDataFile' "
                                 "(truncated file?)")
            try:
                line = raw.decode("utf-8").strip()
            except UnicodeDecodeError:
                raise EMRegError(f"{path}: broken sequence metafile header: line {line_no} is not text") from None
            if first:
                first = False
                if line.startswith("NRRD"):
                    nrrd = True
                    continue
            if not line or line.startswith("#"):
                if nrrd and not line:
                    break  # the NRRD header ends at the first empty line
                continue
            if nrrd and ":=" in line:
                key, value = line.split(":=", 1)
            elif nrrd and ": " in line:
                key, value = line.split(": ", 1)
            elif "=" in line:
                key, value = line.split("=", 1)
            else:
                raise EMRegError(f"{path}: broken sequence metafile header: line {line_no} is not 'key = value' "
                                 f"({line[:60]!r})")
            key = key.strip()
            if key in fields:
                raise EMRegError(f"{path}: broken sequence metafile header: field {key} appears twice")
            fields[key] = value.strip()
            if key == "ElementDataFile":
                break
    if not nrrd and "ObjectType" not in fields and "NDims" not in fields:
        raise EMRegError(f"{path}: not a sequence metafile (no ObjectType / NDims header fields)")
    return fields, "nrrd" if nrrd else "metaio"


def read_sequence_frames(path: str | os.PathLike[str]) -> SequenceFrames:
    """Every transform of a sequence metafile with its status (see module docstring)."""
    path = Path(path)
    fields, _ = _read_header(path)
    per_frame: dict[int, dict[str, str]] = {}
    for key, value in fields.items():
        match = _FRAME_FIELD.match(key)
        if match:
            per_frame.setdefault(int(match.group(1)), {})[match.group(2)] = value
    if not per_frame:
        raise EMRegError(f"{path}: the sequence metafile holds no frames (no Seq_FrameNNNN_... fields)")
    indices = sorted(per_frame)
    dim_size = fields.get("DimSize", "").split()
    if len(dim_size) == 3 and dim_size[2].isdigit() and int(dim_size[2]) not in (0, len(indices)):
        raise EMRegError(f"{path}: the header says {dim_size[2]} frames (DimSize) but holds {len(indices)}")
    names: list[str] = []
    for index in indices:
        for key in per_frame[index]:
            if key.endswith("Transform") and key[:-len("Transform")] not in names:
                names.append(key[:-len("Transform")])
    n = len(indices)
    never_status = [name for name in names if not any(f"{name}TransformStatus" in per_frame[i] for i in indices)]
    time_s = np.empty(n)
    matrices = {name: np.tile(np.eye(4), (n, 1, 1)) for name in names}
    valid = {name: np.zeros(n, dtype=bool) for name in names}
    quality = {name: np.full(n, np.nan) for name in names}
    position_only = {name: np.zeros(n, dtype=bool) for name in names}
    for k, index in enumerate(indices):
        frame = per_frame[index]
        where = f"{path}: frame {index}"
        stamp = frame.get("Timestamp")
        if stamp is None:
            raise EMRegError(f"{where} has no Seq_Frame{index:04d}_Timestamp")
        try:
            time_s[k] = float(stamp)
        except ValueError:
            raise EMRegError(f"{where}: Timestamp {stamp[:30]!r} is not a number") from None
        if not np.isfinite(time_s[k]):
            raise EMRegError(f"{where}: Timestamp is not a finite number")
        for name in names:
            text = frame.get(f"{name}Transform")
            status = frame.get(f"{name}TransformStatus")
            if text is None and status is None:
                continue  # this transform is not recorded in this frame
            if status is None:
                if name not in never_status:
                    raise EMRegError(f"{where} has {name}Transform but no {name}TransformStatus (the other frames "
                                     f"give {name}'s status: a frame without it is not a valid pose to PLUS)")
                status = "OK"  # the file never records this transform's status: read as 3D Slicer reads it
            if text is None:
                raise EMRegError(f"{where} has {name}TransformStatus but no {name}Transform")
            ok = status.strip().upper() == "OK"
            try:
                numbers = np.array([float(v) for v in text.split()])
            except ValueError:
                if not ok:
                    continue
                raise EMRegError(f"{where}: {name}Transform holds a non-numeric value") from None
            if not ok:
                continue  # not a valid pose: dropped (counted by the caller), whatever its numbers
            if numbers.size != 16:
                raise EMRegError(f"{where}: {name}Transform has {numbers.size} numbers, 16 expected (4x4 row-major)")
            if not np.all(np.isfinite(numbers)):
                raise EMRegError(f"{where}: {name}Transform holds NaN or infinite values")
            matrix = numbers.reshape(4, 4)
            no_orientation = frame.get(f"{name}TransformOrientation", "").strip().upper() == "MISSING"
            if not no_orientation:
                check_rigid(matrix, f"{where}: {name}Transform")
            elif np.max(np.abs(matrix[3] - [0, 0, 0, 1])) > RIGID_TOLERANCE:
                raise EMRegError(f"{where}: {name}Transform's last row is not 0 0 0 1")
            matrices[name][k] = matrix
            valid[name][k] = True
            position_only[name][k] = no_orientation
            q = frame.get(f"{name}TransformQuality")
            if q:
                try:
                    quality[name][k] = float(q)
                except ValueError:
                    raise EMRegError(f"{where}: {name}TransformQuality {q[:20]!r} is not a number") from None
    frames = SequenceFrames(str(path), time_s, matrices, valid, quality, position_only, np.asarray(indices))
    frames.notes = {name: f"{path}: {name}Transform has no {name}TransformStatus in any frame: every pose of it is "
                    "read as valid, as 3D Slicer reads it (PLUS would take none of them)" for name in never_status}
    return frames


def read_sequence_metafile(
    path: str | os.PathLike[str],
    reference_transform: str = DEFAULT_REFERENCE_TRANSFORM,
    probe_transform: str | None = None,
    reference_port: int = DEFAULT_REFERENCE_PORT,
    probe_port: int = DEFAULT_PROBE_PORT,
) -> TrackingRecording:
    """A tracking recording from a sequence metafile: the reference and probe transforms
    (``<Name>Transform`` without the suffix, e.g. ``ProbeToTracker``) become rows of the given
    ports; frames whose status is not OK are dropped and counted in ``warnings``. No labels.
    ``probe_transform`` None: ``ProbeToTracker``, else the tool of a file with two transforms
    (:func:`tool_transform`, with a warning); a name given must be in the file."""
    frames = read_sequence_frames(path)
    chosen = None if probe_transform is not None else tool_transform(frames, reference_transform,
                                                                      DEFAULT_PROBE_TRANSFORM)
    probe_transform = probe_transform or DEFAULT_PROBE_TRANSFORM
    note = None
    if chosen is not None:
        note = (f"{path}: no {probe_transform}Transform; the file holds two transforms and {reference_transform} "
                f"is the reference, so {chosen}Transform is taken as the tool")
        probe_transform = chosen
    missing = [n for n in (reference_transform, probe_transform) if n not in frames.matrices]
    if missing:
        raise EMRegError(
            f"{path}: no {' or '.join(n + 'Transform' for n in missing)} in the file; it holds "
            f"{', '.join(n + 'Transform' for n in frames.names) or 'no transforms'}; name them with [sensors] "
            "reference_transform / probe_transform in case.toml"
        )
    recording = recording_from_frames(frames, {reference_transform: reference_port, probe_transform: probe_port})
    if note:
        recording.warnings.insert(0, note)
    return recording


def tool_transform(frames: SequenceFrames, reference_transform: str, probe_transform: str) -> str | None:
    """The tool's transform name when the probe's is not in the file but the choice is plain: exactly two
    transforms, one of them the reference (as PLUS writes ``ReferenceToTracker`` and ``StylusToTracker``).
    None when ``probe_transform`` is in the file or the choice is not plain."""
    if probe_transform in frames.matrices or len(frames.names) != 2 or reference_transform not in frames.names:
        return None
    return next(n for n in frames.names if n != reference_transform)


def recording_from_frames(frames: SequenceFrames, ports: dict[str, int]) -> TrackingRecording:
    """Rows (sensor = the port of each transform name in ``ports``) of the frames' valid poses, in frame
    order; time resets and long pauses split them into segments (with a warning naming the frame)."""
    time_parts, sensor_parts, matrix_parts, quality_parts, only_parts, frame_parts = [], [], [], [], [], []
    notes = [frames.notes[name] for name in ports if name in frames.notes]  # one line each, naming the file
    for name, port in ports.items():
        ok = frames.valid[name]
        frame_parts.append(np.nonzero(ok)[0])
        time_parts.append(frames.time_s[ok])
        sensor_parts.append(np.full(int(ok.sum()), port))
        matrix_parts.append(frames.matrices[name][ok])
        quality_parts.append(frames.quality[name][ok])
        only_parts.append(frames.position_only[name][ok])
        dropped = len(ok) - int(np.count_nonzero(ok))
        if dropped:
            notes.append(f"{frames.source}: {dropped} of {len(ok)} frames of {name} have a status other than OK "
                         "(no valid pose): dropped")
    time_s = np.concatenate(time_parts)
    sensor = np.concatenate(sensor_parts)
    matrices = np.concatenate(matrix_parts)
    quality = np.concatenate(quality_parts)
    position_only = np.concatenate(only_parts)
    frame = np.concatenate(frame_parts)
    if len(time_s) == 0:
        raise EMRegError(f"{frames.source}: no frame has a valid (OK) pose")
    sort = np.lexsort((sensor, frame))  # the file's frame order, ports in order within a frame
    numbers = np.arange(len(frames.time_s)) if frames.index is None else np.asarray(frames.index)
    frame_number = numbers[frame[sort]]
    segment, time_notes = split_time_segments(time_s[sort], sensor[sort], frames.source,
                                              where=lambda row: f"frame {int(frame_number[row])}")
    rotation = matrices[sort, :3, :3].copy()
    rotation[position_only[sort]] = np.nan
    return TrackingRecording(time_s[sort], sensor[sort], matrices[sort, :3, 3], rotation, quality[sort],
                             np.full(len(sort), "", dtype=object), source=frames.source, segment=segment,
                             warnings=notes + time_notes)


def _frames_of(recording: TrackingRecording) -> tuple[np.ndarray, np.ndarray]:
    """Frame number of each row (rows within ``SAME_MOMENT_S`` of a frame's first row share it, one
    row per sensor: a sensor seen again starts a new frame) and each frame's time. Time segments (a
    clock reset) follow each other in order, each with its own times, never interleaved."""
    order = np.lexsort((recording.time_s, recording.segment))
    times = recording.time_s[order]
    sensors = recording.sensor[order]
    segments = recording.segment[order]
    frame = np.empty(len(times), dtype=int)
    starts: list[float] = []
    seen: set[int] = set()
    previous_segment = None
    for k, (t, s, g) in enumerate(zip(times.tolist(), sensors.tolist(), segments.tolist(), strict=True)):
        if not starts or g != previous_segment or abs(t - starts[-1]) > SAME_MOMENT_LIMIT_S or s in seen:
            starts.append(float(t))
            seen = set()
        seen.add(s)
        previous_segment = g
        frame[k] = len(starts) - 1
    out = np.empty(len(times), dtype=int)
    out[order] = frame
    return out, np.asarray(starts)


def _number(value: float) -> str:
    return f"{value:.12g}"


def format_sequence_metafile(
    recording: TrackingRecording,
    reference_transform: str = DEFAULT_REFERENCE_TRANSFORM,
    probe_transform: str = DEFAULT_PROBE_TRANSFORM,
    reference_port: int = DEFAULT_REFERENCE_PORT,
    probe_port: int = DEFAULT_PROBE_PORT,
    statuses: dict[str, np.ndarray] | None = None,
) -> str:
    """Sequence metafile text: one frame per moment (rows within 1 ms), the reference and probe
    transforms (status ``OK``; ``INVALID`` with an identity matrix where a sensor has no row at
    that moment), other ports as ``Sensor<N>ToTracker``; quality and position-only as EMReg extras."""
    frame_of_row, frame_times = _frames_of(recording)
    ports = [reference_port, probe_port] + [p for p in recording.sensors if p not in (reference_port, probe_port)]
    names = {reference_port: reference_transform, probe_port: probe_transform}
    for port in ports[2:]:
        names[port] = f"Sensor{port}ToTracker"
    n_frames = len(frame_times)
    row_of = {port: np.full(n_frames, -1, dtype=int) for port in ports}
    for row in range(len(recording)):
        row_of[int(recording.sensor[row])][frame_of_row[row]] = row
    lines = [
        "ObjectType = Image", "NDims = 3", "AnatomicalOrientation = RAI", "BinaryData = True",
        "BinaryDataByteOrderMSB = False", "CompressedData = False", f"DimSize = 0 0 {n_frames}",
        "ElementSpacing = 1 1 1", "Offset = 0 0 0", "TransformMatrix = 1 0 0 0 1 0 0 0 1",
        "ElementType = MET_UCHAR", "Kinds = domain domain list",
    ]
    identity = " ".join(_number(v) for v in np.eye(4).ravel())
    transforms = recording.transforms()
    for f in range(n_frames):
        prefix = f"Seq_Frame{f:04d}_"
        for port in ports:
            name = names[port]
            row = row_of[port][f]
            if row < 0:
                lines.append(f"{prefix}{name}Transform = {identity}")
                lines.append(f"{prefix}{name}TransformStatus = INVALID")
                continue
            matrix = transforms[row].copy()
            status = "OK" if statuses is None or port not in statuses else str(statuses[port][row])
            if status != "OK" and not np.all(np.isfinite(matrix)):
                matrix = np.eye(4)  # no pose: PLUS writes the identity with the status
            position_only = not np.all(np.isfinite(matrix[:3, :3]))
            if position_only:
                matrix[:3, :3] = np.eye(3)
            lines.append(f"{prefix}{name}Transform = " + " ".join(_number(v) for v in matrix.ravel()))
            lines.append(f"{prefix}{name}TransformStatus = {status}")
            if np.isfinite(recording.quality[row]):
                lines.append(f"{prefix}{name}TransformQuality = {_number(recording.quality[row])}")
            if position_only:
                lines.append(f"{prefix}{name}TransformOrientation = MISSING")
        lines.append(f"{prefix}Timestamp = {frame_times[f]:.6f}")
    lines.append("ElementDataFile = LOCAL")
    return "\n".join(lines) + "\n"


def write_sequence_metafile(recording: TrackingRecording, path: str | os.PathLike[str], **names) -> None:
    """Write a recording as a sequence metafile atomically (see :func:`format_sequence_metafile`)."""
    with atomic_path(path) as tmp:
        tmp.write_text(format_sequence_metafile(recording, **names), encoding="utf-8")
