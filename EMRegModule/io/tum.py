"""TUM trajectory files (``timestamp tx ty tz qx qy qz qw`` per line, seconds and metres, ``#`` comments), as
ROS tools and evo write them: here the robot flange's pose in the robot base frame, ``FlangeToBase``.

EMReg works in millimetres: :func:`read_tum` converts. A malformed line is an :class:`EMRegError` naming the
file and the line (exit 2).
"""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np
from scipy.spatial.transform import Rotation

from ..errors import EMRegError
from .atomic import atomic_write_text

#: A flange this far (m) from its robot's base means the file is not in metres (millimetres, most likely).
MAX_REACH_M = 20.0

#: Longest file read (bytes): a day of poses at 1 kHz is about 5 GB; a robot log for a calibration is minutes.
MAX_BYTES = 1 << 30


def _text(path: Path) -> str:
    try:
        if path.is_dir():
            raise EMRegError(f"{path}: is a folder, not a TUM trajectory file")
        if path.stat().st_size > MAX_BYTES:
            raise EMRegError(f"{path}: larger than {MAX_BYTES >> 20} MB: not a robot log for a calibration")
        return path.read_bytes().decode("utf-8-sig")
    except FileNotFoundError:
        raise EMRegError(f"{path}: TUM trajectory file not found") from None
    except UnicodeDecodeError:
        raise EMRegError(f"{path}: not a text file (a TUM trajectory is lines of 8 numbers)") from None
    except OSError as exc:
        raise EMRegError(f"{path}: cannot read the TUM trajectory ({exc.strerror or exc})") from None


def _parse_line(fields: list[str], where: str) -> list[float]:
    if len(fields) != 8:
        raise EMRegError(f"{where}: {len(fields)} fields; a TUM line is 'timestamp tx ty tz qx qy qz qw' (8 numbers)")
    try:
        values = [float(v) for v in fields]
    except ValueError:
        raise EMRegError(f"{where}: holds a non-numeric value; a TUM line is 8 numbers") from None
    if not np.all(np.isfinite(values)):
        raise EMRegError(f"{where}: holds NaN or an infinite value")
    return values


def read_tum(path: str | os.PathLike[str]) -> tuple[np.ndarray, np.ndarray]:
    """The poses of a TUM trajectory file: times (N,) in seconds as written, and poses (N, 4, 4) in millimetres
    (the file's metres x 1000; e.g. ``FlangeToBase``). Quaternions are normalised; one far from unit length, a
    time that goes back, a position beyond ``MAX_REACH_M`` or a file with no pose is refused (one line)."""
    path = Path(path)
    rows, lines = [], []
    for number, line in enumerate(_text(path).splitlines(), start=1):
        stripped = line.strip()
        if not stripped or stripped.startswith("#"):
            continue
        rows.append(_parse_line(stripped.split(), f"{path}: line {number}"))
        lines.append(number)
    if not rows:
        raise EMRegError(f"{path}: no poses (a TUM trajectory has lines 'timestamp tx ty tz qx qy qz qw')")
    data = np.asarray(rows)
    back = np.nonzero(np.diff(data[:, 0]) < 0)[0]
    if len(back):
        raise EMRegError(f"{path}: line {lines[back[0] + 1]}: the time goes back ({data[back[0] + 1, 0]:.6f} s after "
                         f"{data[back[0], 0]:.6f} s); a trajectory's lines are in time order")
    length = np.linalg.norm(data[:, 4:8], axis=1)
    bad = np.nonzero(np.abs(length - 1.0) > 0.01)[0]
    if len(bad):
        raise EMRegError(f"{path}: line {lines[bad[0]]}: the quaternion qx qy qz qw has length {length[bad[0]]:.4g}, "
                         "not 1")
    far = np.nonzero(np.linalg.norm(data[:, 1:4], axis=1) > MAX_REACH_M)[0]
    if len(far):
        raise EMRegError(f"{path}: line {lines[far[0]]}: a flange {np.linalg.norm(data[far[0], 1:4]):.0f} m from the "
                         "base; TUM positions are in metres (is this file in millimetres?)")
    poses = np.tile(np.eye(4), (len(data), 1, 1))
    poses[:, :3, :3] = Rotation.from_quat(data[:, 4:8] / length[:, None]).as_matrix()
    poses[:, :3, 3] = data[:, 1:4] * 1000.0
    return data[:, 0], poses


def format_tum(time_s: np.ndarray, poses_mm: np.ndarray, comment: str = "") -> str:
    """TUM text for times (s) and poses (N, 4, 4, mm): metres, ``qx qy qz qw``, 9 decimals."""
    quaternion = Rotation.from_matrix(np.asarray(poses_mm)[:, :3, :3]).as_quat()
    lines = [f"# {comment}"] if comment else []
    lines.append("# timestamp tx ty tz qx qy qz qw")
    for t, pose, q in zip(time_s, poses_mm, quaternion, strict=True):
        p = pose[:3, 3] / 1000.0
        lines.append(f"{t:.9f} {p[0]:.9f} {p[1]:.9f} {p[2]:.9f} {q[0]:.9f} {q[1]:.9f} {q[2]:.9f} {q[3]:.9f}")
    return "\n".join(lines) + "\n"


def write_tum(path: str | os.PathLike[str], time_s: np.ndarray, poses_mm: np.ndarray, comment: str = "") -> None:
    """Write a TUM trajectory atomically (see :func:`format_tum`)."""
    atomic_write_text(path, format_tum(time_s, poses_mm, comment))
