"""Tracking recording CSV (spec: ``time_s,sensor,x_mm,y_mm,z_mm,azimuth_deg,elevation_deg,roll_deg,quality,label``).

Orientation is either the trakSTAR angles (azimuth, elevation, roll in degrees,
``R = Rz @ Ry @ Rx``) or a unit quaternion ``qw,qx,qy,qz``. ``quality`` may be empty,
``label`` may be absent or empty. Poses are ``SensorToTracker``.

An optional ``status`` column follows PLUS's transform status (as ``.seq.mha`` files carry it):
``OK`` is a valid pose, anything else (``MISSING``, ``INVALID``, empty, ...) is none. Such rows
are left out (their pose fields may be empty or stale) and counted in the recording's warnings.

A row whose orientation fields are all empty is a position-only sample (a probe reported
without angles): its rotation is NaN. A partly empty orientation is an error.
"""

from __future__ import annotations

import csv
import io
import os
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from ..core.tracking import TrackingRecording, split_time_segments
from ..core.transforms import angles_to_rotation, quaternion_to_rotation, rotation_to_angles, rotation_to_quaternion
from ..errors import EMRegError
from .atomic import atomic_path

ANGLE_COLUMNS = ("azimuth_deg", "elevation_deg", "roll_deg")
QUATERNION_COLUMNS = ("qw", "qx", "qy", "qz")
POSITION_COLUMNS = ("x_mm", "y_mm", "z_mm")
HEADER_ANGLES = ("time_s", "sensor", *POSITION_COLUMNS, *ANGLE_COLUMNS, "quality", "label")
HEADER_QUATERNION = ("time_s", "sensor", *POSITION_COLUMNS, *QUATERNION_COLUMNS, "quality", "label")


#: Longest line (bytes) of a tracking CSV: a row of numbers and a label takes under 300; a longer line is
#: refused while reading, before it is held in memory (a 2 GB line never is).
MAX_LINE_BYTES = 1 << 16

#: Longest field (characters, e.g. a label): refused before any array is sized by it.
MAX_FIELD_CHARS = 4096

#: Lines longer than this (characters) send the body to the row-by-row parser (no fixed-width arrays).
_FAST_LINE_CHARS = 512

_READ_CHUNK = 1 << 20


@dataclass
class _Parsed:
    """The samples a parser read: numeric fields (N, len(numeric)), quality (NaN: none), labels, which rows are
    position only, each row's line in the file, and how many rows were left out for their status."""

    data: np.ndarray
    quality: np.ndarray
    labels: np.ndarray
    position_only: np.ndarray
    lines: np.ndarray
    not_ok: int = 0

    @classmethod
    def empty(cls, n_numeric: int, not_ok: int = 0) -> _Parsed:
        return cls(np.zeros((0, n_numeric)), np.zeros(0), np.zeros(0, dtype=object), np.zeros(0, dtype=bool),
                   np.zeros(0, dtype=int), not_ok)


@dataclass(frozen=True)
class _Columns:
    """Where the fields are in a row: the numeric ones (time, sensor, position, orientation, in that order)
    and the optional text ones (None: no such column)."""

    numeric: list[int]
    quality: int | None
    label: int | None
    status: int | None


def read_tracking_csv(path: str | os.PathLike[str]) -> TrackingRecording:
    """Read a tracking recording; a malformed file raises :class:`EMRegError` naming file and line."""
    if str(path).strip() == "":
        raise EMRegError("tracking recording: no file given")
    path = Path(path)
    try:
        if path.is_dir():
            raise EMRegError(f"{path}: is a folder, not a tracking recording (give the .csv file)")
        data = _read_bounded_lines(path)
        text = data.decode("utf-8-sig")
    except FileNotFoundError:
        raise EMRegError(f"{path}: tracking recording not found") from None
    except UnicodeDecodeError:
        raise EMRegError(f"{path}: not a text CSV file") from None
    except OSError as exc:
        raise EMRegError(f"{path}: cannot read the tracking recording ({exc.strerror or exc})") from None
    return parse_tracking_csv(text, source=str(path))


def _read_bounded_lines(path: Path) -> bytes:
    """The file's bytes, read in chunks; a line longer than ``MAX_LINE_BYTES`` stops the read with an error."""
    chunks: list[bytes] = []
    line_length, line_no = 0, 1
    with path.open("rb") as stream:
        while True:
            chunk = stream.read(_READ_CHUNK)
            if not chunk:
                return b"".join(chunks)
            last = chunk.rfind(b"\n")
            if last < 0:
                line_length += len(chunk)
            else:
                first = chunk.find(b"\n")
                longest_inside = max((len(part) for part in chunk[first + 1:last].split(b"\n")), default=0) \
                    if first != last else 0
                if line_length + first > MAX_LINE_BYTES:
                    _too_long(path, line_no)
                if longest_inside > MAX_LINE_BYTES:
                    parts = chunk[first + 1:last].split(b"\n")
                    offset = next(k for k, part in enumerate(parts) if len(part) > MAX_LINE_BYTES)
                    _too_long(path, line_no + 1 + offset)
                line_no += chunk.count(b"\n")
                line_length = len(chunk) - last - 1
            if line_length > MAX_LINE_BYTES:
                _too_long(path, line_no)
            chunks.append(chunk)


def _too_long(path: Path, line_no: int) -> None:
    raise EMRegError(f"{path}: line {line_no} is longer than {MAX_LINE_BYTES} bytes: not a tracking recording "
                     "(rows of numbers and a short label)")


def parse_tracking_csv(text: str, source: str = "recording") -> TrackingRecording:
    """Parse tracking CSV text (see module docstring)."""
    reader = csv.reader(io.StringIO(text))
    try:
        header = [h.strip() for h in next(reader)]
    except StopIteration:
        raise EMRegError(f"{source}: empty tracking recording (no header row)") from None
    except csv.Error as exc:
        raise EMRegError(f"{source}: line 1: malformed CSV header ({str(exc)[:80]})") from None
    columns = {name.lower(): i for i, name in reversed(list(enumerate(header)))}  # Time_s reads as time_s
    if header and header[0].startswith("#"):
        raise EMRegError(f"{source}: line 1 is a comment ({','.join(header)[:40]!r}); a tracking CSV starts with its "
                         "header row (time_s,sensor,x_mm,...) and holds no comment lines: remove them")
    if len(header) == 1 and any(sep in header[0] for sep in ";\t"):
        word = "semicolons" if ";" in header[0] else "tabs"
        raise EMRegError(f"{source}: line 1: the fields are separated by {word}; a tracking CSV separates them by "
                         "commas (time_s,sensor,x_mm,...)")
    read = {"time_s", "sensor", *POSITION_COLUMNS, *ANGLE_COLUMNS, *QUATERNION_COLUMNS, "quality", "label", "status"}
    names = [h.lower() for h in header if h.lower() in read]
    repeated = sorted({n for n in names if names.count(n) > 1})
    if repeated:  # which of the two holds the data? Never guessed
        raise EMRegError(f"{source}: line 1: the header names column(s) {', '.join(repeated)} more than once; "
                         "each column must appear once")
    missing = [c for c in ("time_s", "sensor", *POSITION_COLUMNS) if c not in columns]
    if all(c in columns for c in ANGLE_COLUMNS):
        orientation, orientation_columns = "angles", ANGLE_COLUMNS
    elif all(c in columns for c in QUATERNION_COLUMNS):
        orientation, orientation_columns = "quaternion", QUATERNION_COLUMNS
    else:
        missing.append("azimuth_deg,elevation_deg,roll_deg (or qw,qx,qy,qz)")
    if missing:
        raise EMRegError(f"{source}: tracking CSV header lacks column(s) {', '.join(missing)}")
    numeric = ["time_s", "sensor", *POSITION_COLUMNS, *orientation_columns]
    fields = _Columns([columns[c] for c in numeric], columns.get("quality"), columns.get("label"),
                      columns.get("status"))
    body = text.split("\n", 1)[1] if "\n" in text else ""
    parsed = _parse_fast(body, len(header), fields)
    if parsed is None:
        parsed = _parse_checked(reader, header, fields, source)
    data, position_only, lines, not_ok = parsed.data, parsed.position_only, parsed.lines, parsed.not_ok
    if len(data) == 0:
        if not_ok:
            raise EMRegError(f"{source}: none of its {not_ok} samples has the status OK (a valid pose)")
        raise EMRegError(f"{source}: tracking recording has a header but no samples")
    finite = np.isfinite(data)
    finite[position_only, 5:] = True  # empty orientation fields: position only
    if not np.all(finite):
        bad = int(lines[np.nonzero(~np.all(finite, axis=1))[0][0]])
        raise EMRegError(f"{source}: line {bad} holds a non-finite number")
    sensor = data[:, 1]
    if np.any(sensor != np.round(sensor)) or np.any(sensor < 1):
        raise EMRegError(f"{source}: the sensor column must hold port numbers 1, 2, 3, ...")
    if orientation == "angles":
        rotation = angles_to_rotation(data[:, 5], data[:, 6], data[:, 7])
    else:
        norms = np.linalg.norm(data[:, 5:9], axis=1)
        if np.any(norms[~position_only] < 1e-6):
            raise EMRegError(f"{source}: a quaternion of zero length")
        quaternions = data[:, 5:9].copy()
        quaternions[position_only] = [1.0, 0.0, 0.0, 0.0]
        rotation = quaternion_to_rotation(quaternions)
    rotation[position_only] = np.nan
    segment, warnings = split_time_segments(data[:, 0], sensor.astype(int), source,
                                            where=lambda row: f"line {lines[row]}")
    if not_ok:
        warnings.insert(0, f"{source}: {not_ok} of {not_ok + len(data)} samples have a status other than OK "
                           "(no valid pose): left out")
    return TrackingRecording(
        time_s=data[:, 0], sensor=sensor.astype(int), position_mm=data[:, 2:5], rotation=rotation,
        quality=parsed.quality, label=parsed.labels, source=source,
        orientation_format=orientation, segment=segment, warnings=warnings,
    )


def _parse_fast(body: str, n_columns: int, fields: _Columns) -> _Parsed | None:
    """Vectorised parse of well-formed bodies (no quoting); None sends the caller to the checked path."""
    if '"' in body:
        return None
    every_line = body.splitlines()
    lines = [line for line in every_line if line.strip(" ,\r")]
    if lines and max(map(len, lines)) > _FAST_LINE_CHARS:
        return None  # a long field: the checked parser bounds it (numpy would size every row by it)
    if not lines:
        return _Parsed.empty(len(fields.numeric))
    if body.count(",") != len(lines) * (n_columns - 1):  # some row has a field too many or too few
        return None

    def text_column(index: int) -> np.ndarray:
        return np.char.strip(np.loadtxt(lines, delimiter=",", comments=None, usecols=[index], dtype=str, ndmin=1))

    try:
        line_numbers = np.arange(2, len(lines) + 2) if len(lines) == len(every_line) else \
            np.array([n for n, line in enumerate(every_line, start=2) if line.strip(" ,\r")])  # blank lines left out
        not_ok = 0
        if fields.status is not None:
            ok = np.char.upper(text_column(fields.status)) == "OK"
            not_ok = int(np.count_nonzero(~ok))
            lines, line_numbers = [line for line, keep in zip(lines, ok, strict=True) if keep], line_numbers[ok]
            if not lines:
                return _Parsed.empty(len(fields.numeric), not_ok)
        # comments=None: numpy's default cuts every line at "#", which a label may hold ("Hole #1")
        data = np.loadtxt(lines, delimiter=",", comments=None, usecols=fields.numeric, ndmin=2)
        quality = np.full(len(lines), np.nan)
        if fields.quality is not None:
            text = text_column(fields.quality)
            given = text != ""
            quality[given] = text[given].astype(float)
        labels = text_column(fields.label) if fields.label is not None else np.full(len(lines), "")
    except ValueError:
        return None
    return _Parsed(data, quality, labels.astype(object), np.zeros(len(data), dtype=bool), line_numbers, not_ok)


def _parse_checked(reader, header: list[str], fields: _Columns, source: str) -> _Parsed:
    """Row-by-row parse that names the first bad line; empty orientation fields mean position only."""
    rows = _Rows()
    previous_limit = csv.field_size_limit(MAX_FIELD_CHARS)
    try:
        _read_rows(reader, header, fields, source, rows)
    except csv.Error as exc:
        raise EMRegError(f"{source}: line {reader.line_num}: malformed CSV ({str(exc)[:80]}; fields are at most "
                         f"{MAX_FIELD_CHARS} characters)") from None
    finally:
        csv.field_size_limit(previous_limit)
    return _Parsed(np.asarray(rows.values, dtype=float).reshape(-1, len(fields.numeric)),
                   np.asarray(rows.quality, dtype=float), np.asarray(rows.labels, dtype=object),
                   np.asarray(rows.position_only, dtype=bool), np.asarray(rows.lines, dtype=int), rows.not_ok)


@dataclass
class _Rows:
    """What the checked parser has read so far, a list per column."""

    values: list[list[float]] = field(default_factory=list)
    quality: list[float] = field(default_factory=list)
    labels: list[str] = field(default_factory=list)
    position_only: list[bool] = field(default_factory=list)
    lines: list[int] = field(default_factory=list)
    not_ok: int = 0


def _read_rows(reader, header: list[str], fields: _Columns, source: str, rows: _Rows) -> None:
    orientation_idx = fields.numeric[5:]
    label_idx = fields.label

    def text(row: list[str], index: int | None) -> str:
        return row[index].strip() if index is not None and index < len(row) else ""

    for line_no, row in enumerate(reader, start=2):
        if not row or all(not cell.strip() for cell in row):
            continue
        if len(row) < len(header) - (1 if label_idx == len(header) - 1 else 0):
            raise EMRegError(f"{source}: line {line_no} has {len(row)} fields, the header has {len(header)}")
        if fields.status is not None and text(row, fields.status).upper() != "OK":
            rows.not_ok += 1  # no valid pose: whatever its pose fields hold is not read
            continue
        empty = [i >= len(row) or not row[i].strip() for i in orientation_idx]
        if any(empty) and not all(empty):
            raise EMRegError(f"{source}: line {line_no} has some orientation fields empty and others not "
                             "(leave all of them empty for a position-only sample)")
        try:
            values = [float(row[i]) if not (all(empty) and i in orientation_idx) else np.nan for i in fields.numeric]
            q = text(row, fields.quality)
            quality = float(q) if q else np.nan
        except (ValueError, IndexError):
            raise EMRegError(
                f"{source}: line {line_no} has a non-numeric value where a number is expected"
            ) from None
        rows.values.append(values)
        rows.quality.append(quality)
        rows.position_only.append(all(empty))
        rows.labels.append(text(row, label_idx))
        rows.lines.append(line_no)


def format_tracking_csv(recording: TrackingRecording, orientation: str | None = None) -> str:
    """CSV text for a recording; ``orientation`` 'angles' (default as read) or 'quaternion'."""
    orientation = orientation or recording.orientation_format
    out = io.StringIO()
    writer = csv.writer(out, lineterminator="\n")
    if orientation == "quaternion":
        writer.writerow(HEADER_QUATERNION)
        orient = rotation_to_quaternion(recording.rotation)
    else:
        writer.writerow(HEADER_ANGLES)
        orient = rotation_to_angles(recording.rotation)
    for i in range(len(recording)):
        q = recording.quality[i]
        writer.writerow([
            f"{recording.time_s[i]:.4f}", int(recording.sensor[i]),
            *(f"{v:.4f}" for v in recording.position_mm[i]),
            *(f"{v:.6f}" if np.isfinite(v) else "" for v in orient[i]),
            "" if np.isnan(q) else f"{q:g}",
            recording.label[i] or "",
        ])
    return out.getvalue()


def write_tracking_csv(
    recording: TrackingRecording, path: str | os.PathLike[str], orientation: str | None = None
) -> None:
    """Write a recording as tracking CSV atomically."""
    with atomic_path(path) as tmp:
        tmp.write_text(format_tracking_csv(recording, orientation), encoding="utf-8")
