"""The two recordings of a hand-eye calibration, read into arrays:

- the robot's log, ``FlangeToBase`` over time: a TUM trajectory (:mod:`.tum`) or a PLUS sequence file with the
  flange's transform (``[handeye] flange_transform``, default ``FlangeToBase``);
- the tracker's recording of the flange's sensor, ``SensorToTracker`` over time: a PLUS sequence file or EMReg's
  tracking CSV; a file holding one transform (one port) uses it, otherwise ``--sensor NAME|PORT`` picks.

Poses in millimetres, times in seconds on each recording's own clock. Problems are one-line
:class:`EMRegError` (exit 2) naming the file.
"""

from __future__ import annotations

import os
from dataclasses import dataclass, field
from pathlib import Path
from xml.etree import ElementTree

import numpy as np

from ..core.transforms import mean_rigid
from ..errors import EMRegError
from .recording import read_recording
from .sequence_metafile import is_sequence_file, read_sequence_frames
from .tum import read_tum


@dataclass(frozen=True)
class PoseStream:
    """Poses over time from one file: ``time_s`` (N,), ``poses`` (N, 4, 4, mm), the transform or port they are
    (``name``), and what reading left out (``warnings``)."""

    time_s: np.ndarray
    poses: np.ndarray
    name: str
    warnings: list[str] = field(default_factory=list)


def _sequence_transform(path: Path, name: str) -> PoseStream:
    frames = read_sequence_frames(path)
    key = name[:-len("Transform")] if name.endswith("Transform") else name
    if key not in frames.matrices:
        raise EMRegError(f"{path}: no {key}Transform in the file; it holds "
                         f"{', '.join(n + 'Transform' for n in frames.names) or 'no transforms'}")
    ok = frames.valid[key] & ~frames.position_only[key]
    warnings = [frames.notes[key]] if key in frames.notes else []
    if not np.all(ok):
        warnings.append(f"{path}: {np.count_nonzero(~ok)} of {len(ok)} frames of {key} have no valid full pose "
                        "(status other than OK, or no orientation): left out")
    if not np.any(ok):
        raise EMRegError(f"{path}: no frame holds a valid {key}Transform")
    order = np.argsort(frames.time_s[ok], kind="stable")
    return PoseStream(frames.time_s[ok][order], frames.matrices[key][ok][order], key, warnings)


def read_robot_poses(path: str | os.PathLike[str], flange_transform: str = "FlangeToBase") -> PoseStream:
    """The robot's ``FlangeToBase`` poses (mm) over time (s): a PLUS sequence file's ``flange_transform``, or
    else a TUM trajectory file (s, m)."""
    path = Path(path)
    if is_sequence_file(path):
        return _sequence_transform(path, flange_transform)
    time_s, poses = read_tum(path)
    return PoseStream(time_s, poses, "FlangeToBase (TUM)")


def _choose(available: list[str], sensor: str | int | None, path: Path, what: str) -> str:
    if sensor is None:
        if len(available) == 1:
            return available[0]
        raise EMRegError(f"{path}: holds {len(available)} {what} ({', '.join(available)}); choose the flange's "
                         "sensor with --sensor NAME|PORT (or [handeye] sensor)")
    wanted = str(sensor)
    for name in available:
        if wanted in (name, f"{name}Transform", f"Sensor{name}ToTracker") or wanted == f"{name}ToTracker":
            return name
    raise EMRegError(f"{path}: no sensor {wanted!r} in the file; it holds {what} {', '.join(available)}")


def read_sensor_poses(path: str | os.PathLike[str], sensor: str | int | None = None) -> PoseStream:
    """The flange sensor's ``SensorToTracker`` poses (mm) over time (s) from a PLUS sequence file (a transform
    name) or EMReg's tracking CSV (a port); ``sensor`` None: the file's only one."""
    path = Path(path)
    if is_sequence_file(path):
        frames = read_sequence_frames(path)
        name = _choose(list(frames.names), sensor, path, "transforms")
        return _sequence_transform(path, name)
    recording = read_recording(path)
    ports = [str(p) for p in recording.sensors]
    wanted = sensor
    if isinstance(sensor, str) and sensor.startswith("Sensor") and sensor.endswith("ToTracker"):
        wanted = sensor[len("Sensor"):-len("ToTracker")]
    port = int(_choose(ports, wanted, path, "sensor ports"))
    rows = (recording.sensor == port) & np.all(np.isfinite(recording.rotation), axis=(1, 2))
    warnings = list(recording.warnings)
    if np.count_nonzero(rows) < np.count_nonzero(recording.sensor == port):
        warnings.append(f"{path}: samples of port {port} without an orientation (position only): left out")
    if not np.any(rows):
        raise EMRegError(f"{path}: port {port} has no sample with a full pose (position and orientation)")
    chosen = recording.select(rows)
    order = np.argsort(chosen.timeline_s, kind="stable")
    return PoseStream(chosen.timeline_s[order], chosen.transforms()[order], f"port {port}", warnings)


def read_device_set_transform(path: str | os.PathLike[str], source: str, target: str) -> np.ndarray:
    """The 4x4 (mm) of ``<Transform From="source" To="target" Matrix="...">`` in a PLUS device set's
    ``CoordinateDefinitions`` (e.g. ``NeedleGuide`` -> ``Sensor``); one line (exit 2) when absent or malformed."""
    path = Path(path)
    try:
        root = ElementTree.parse(path).getroot()
    except (ElementTree.ParseError, OSError, UnicodeDecodeError) as exc:
        raise EMRegError(f"{path}: not a readable XML file ({exc!s:.80})") from None
    found = [e for e in root.iter("Transform") if e.get("From") == source and e.get("To") == target]
    if not found:
        raise EMRegError(f'{path}: no <Transform From="{source}" To="{target}" Matrix="..."/> in the device set')
    try:
        numbers = np.array([float(v) for v in found[0].get("Matrix", "").split()])
    except ValueError:
        raise EMRegError(f'{path}: the Matrix of From="{source}" To="{target}" holds a non-number') from None
    if numbers.size != 16:
        raise EMRegError(f'{path}: the Matrix of From="{source}" To="{target}" has {numbers.size} numbers, 16 expected')
    return numbers.reshape(4, 4)


def robust_mean_pose(poses: np.ndarray) -> np.ndarray:
    """The mean (4x4, mm) of a still sensor's poses (N, 4, 4), samples farther than 3 robust standard deviations
    from the median position left out (a glitch)."""
    distance = np.linalg.norm(poses[:, :3, 3] - np.median(poses[:, :3, 3], axis=0), axis=1)
    keep = distance <= max(3.0 * 1.4826 * float(np.median(distance)), 1e-6)
    return mean_rigid(poses[keep])
