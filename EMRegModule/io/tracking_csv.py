"""Tracking recording CSV (spec: ``time_s,sensor,x_mm,y_mm,z_mm,azimuth_deg,elevation_deg,roll_deg,quality,label``).

Orientation is either the trakSTAR angles (azimuth, elevation, roll in degrees,
``R = Rz @ Ry @ Rx``) or a unit quaternion ``qw,qx,qy,qz``. ``quality`` may be empty,
``label`` may be absent or empty. Poses are ``SensorToTracker``.

A row whose orientation fields are all empty is a position-only sample (a probe reported
without angles): its rotation is NaN. A partly empty orientation is an error.
"""

from __future__ import annotations

import csv
import io
import os
from pathlib import Path

import numpy as np

from ..errors import EMRegError
from ..tracking import TrackingRecording, split_time_segments
from ..transforms import angles_to_rotation, quaternion_to_rotation, rotation_to_angles, rotation_to_quaternion
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
    numeric_idx = [columns[c] for c in numeric]
    quality_idx = columns.get("quality")
    label_idx = columns.get("label")
    body = text.split("\n", 1)[1] if "\n" in text else ""
    parsed = _parse_fast(body, len(header), numeric_idx, quality_idx, label_idx)
    if parsed is None:
        parsed = _parse_checked(reader, header, numeric_idx, quality_idx, label_idx, source)
    data, quality, labels, position_only = parsed
    if len(data) == 0:
        raise EMRegError(f"{source}: tracking recording has a header but no samples")
    finite = np.isfinite(data)
    finite[position_only, 5:] = True  # empty orientation fields: position only
    if not np.all(finite):
        bad = int(np.nonzero(~np.all(finite, axis=1))[0][0]) + 2
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
    segment, warnings = split_time_segments(data[:, 0], sensor.astype(int), source, first_line=2)
    return TrackingRecording(
        time_s=data[:, 0], sensor=sensor.astype(int), position_mm=data[:, 2:5], rotation=rotation,
        quality=quality, label=labels, source=source,
        orientation_format=orientation, segment=segment, warnings=warnings,
    )


def _parse_fast(
    body: str, n_columns: int, numeric_idx: list[int], quality_idx: int | None, label_idx: int | None
) -> tuple[np.ndarray, np.ndarray, np.ndarray] | None:
    """Vectorised parse of well-formed bodies (no quoting); None sends the caller to the checked path."""
    if '"' in body:
        return None
    lines = [line for line in body.splitlines() if line.strip(" ,\r")]
    if lines and max(map(len, lines)) > _FAST_LINE_CHARS:
        return None  # a long field: the checked parser bounds it (numpy would size every row by it)
    if not lines:
        return np.zeros((0, len(numeric_idx))), np.zeros(0), np.zeros(0, dtype=object), np.zeros(0, dtype=bool)
    if body.count(",") != len(lines) * (n_columns - 1):  # some row has a field too many or too few
        return None
    def text_column(index: int) -> np.ndarray:
        return np.char.strip(np.loadtxt(lines, delimiter=",", comments=None, usecols=[index], dtype=str, ndmin=1))

    try:
        # comments=None: numpy's default cuts every line at "#", which a label may hold ("Hole #1")
        data = np.loadtxt(lines, delimiter=",", comments=None, usecols=numeric_idx, ndmin=2)
        quality = np.full(len(lines), np.nan)
        if quality_idx is not None:
            text = text_column(quality_idx)
            given = text != ""
            quality[given] = text[given].astype(float)
        labels = text_column(label_idx) if label_idx is not None else np.full(len(lines), "")
    except ValueError:
        return None
    return data, quality, labels.astype(object), np.zeros(len(data), dtype=bool)


def _parse_checked(
    reader, header: list[str], numeric_idx: list[int], quality_idx: int | None, label_idx: int | None, source: str
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Row-by-row parse that names the first bad line; empty orientation fields mean position only."""
    values: list[list[float]] = []
    position_only: list[bool] = []
    orientation_idx = numeric_idx[5:]
    quality: list[float] = []
    labels: list[str] = []
    previous_limit = csv.field_size_limit(MAX_FIELD_CHARS)
    try:
        _read_rows(reader, header, numeric_idx, quality_idx, label_idx, source, values, quality, labels,
                   position_only, orientation_idx)
    except csv.Error as exc:
        raise EMRegError(f"{source}: line {reader.line_num}: malformed CSV ({str(exc)[:80]}; fields are at most "
                         f"{MAX_FIELD_CHARS} characters)") from None
    finally:
        csv.field_size_limit(previous_limit)
    return (np.asarray(values, dtype=float).reshape(-1, len(numeric_idx)), np.asarray(quality, dtype=float),
            np.asarray(labels, dtype=object), np.asarray(position_only, dtype=bool))


def _read_rows(reader, header: list[str], numeric_idx: list[int], quality_idx: int | None, label_idx: int | None,
               source: str, values: list[list[float]], quality: list[float], labels: list[str],
               position_only: list[bool], orientation_idx: list[int]) -> None:
    for line_no, row in enumerate(reader, start=2):
        if not row or all(not cell.strip() for cell in row):
            continue
        if len(row) < len(header) - (1 if label_idx == len(header) - 1 else 0):
            raise EMRegError(f"{source}: line {line_no} has {len(row)} fields, the header has {len(header)}")
        empty = [i >= len(row) or not row[i].strip() for i in orientation_idx]
        if any(empty) and not all(empty):
            raise EMRegError(f"{source}: line {line_no} has some orientation fields empty and others not "
                             "(leave all of them empty for a position-only sample)")
        position_only.append(all(empty))
        try:
            values.append([float(row[i]) if not (all(empty) and i in orientation_idx) else np.nan
                           for i in numeric_idx])
            q = row[quality_idx].strip() if quality_idx is not None and quality_idx < len(row) else ""
            quality.append(float(q) if q else np.nan)
        except (ValueError, IndexError):
            raise EMRegError(
                f"{source}: line {line_no} has a non-numeric value where a number is expected"
            ) from None
        labels.append(row[label_idx].strip() if label_idx is not None and label_idx < len(row) else "")


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
