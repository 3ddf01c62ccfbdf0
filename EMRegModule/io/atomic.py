"""Atomic file writing: a temporary file in the target's folder, then ``os.replace``.

An interrupted run never leaves a half-written file in place of a good one.
"""

from __future__ import annotations

import contextlib
import errno
import json
import locale
import os
import tempfile
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import numpy as np

from ..errors import EMRegError


@contextlib.contextmanager
def atomic_path(path: str | os.PathLike[str]) -> Iterator[Path]:
    """Yield a temporary path beside ``path``; on success rename it onto ``path``.

    The temporary name keeps the final suffix(es) so writers that choose the format by
    extension (SimpleITK, VTK, PNG) still work. On any exception the temporary is removed
    and ``path`` is left untouched; a file-system error (a full disk, a folder made read-only)
    becomes an :class:`~EMRegModule.errors.EMRegError` naming ``path`` (the OS names none, or the
    temporary).
    """
    path = Path(path)
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
        suffix = "".join(path.suffixes) or ".tmp"
        fd, tmp_name = tempfile.mkstemp(prefix=f".{path.stem.split('.')[0]}-", suffix=suffix, dir=path.parent)
        os.close(fd)
    except OSError as exc:
        raise cannot_write(path, exc) from None
    tmp = Path(tmp_name)
    try:
        yield tmp
        if tmp.exists():  # mkstemp makes the file private; give it the usual umask-based mode
            os.chmod(tmp, 0o666 & ~_current_umask())
        os.replace(tmp, path)
    except BaseException as exc:
        with contextlib.suppress(OSError):
            tmp.unlink()
        if isinstance(exc, OSError):
            raise cannot_write(path, exc) from None
        raise


def cannot_write(path: Path, exc: OSError) -> Exception:
    """The one-line error for a file-system failure writing ``path`` (the OS names no file, or the temporary)."""
    return EMRegError(f"{path}: cannot write ({exc.strerror or exc})")


@contextlib.contextmanager
def locale_kept() -> Iterator[None]:
    """The process's C locale as it was before the block, put back after it. GDCM's DICOM writer (SimpleITK's,
    for ``.dcm`` files) sets every category to "C" and leaves it there: Python's default text encoding then
    became ASCII for the rest of the process, and any later ``open()`` or ``read_text()`` without an explicit
    encoding failed on the first non-ASCII character."""
    kept = locale.setlocale(locale.LC_ALL)
    try:
        yield
    finally:
        if locale.setlocale(locale.LC_ALL) != kept:
            locale.setlocale(locale.LC_ALL, kept)


@contextlib.contextmanager
def itk_write_errors() -> Iterator[None]:
    """Inside :func:`atomic_path`: a SimpleITK writer's failure (it raises RuntimeError, e.g. "couldn't write gzip
    data" on a full disk, where the OS would raise OSError) is treated as the file-system error it is, so that it
    ends as one line naming the file; the writer leaves the process's locale as it found it (:func:`locale_kept`)."""
    try:
        with locale_kept():
            yield
    except RuntimeError:
        raise OSError(errno.EIO, "the ITK image writer failed: disk full or no permission?") from None


def _current_umask() -> int:
    mask = os.umask(0)
    os.umask(mask)
    return mask


def atomic_write_text(path: str | os.PathLike[str], text: str) -> None:
    """Write ``text`` (UTF-8) to ``path`` atomically."""
    with atomic_path(path) as tmp:
        tmp.write_text(text, encoding="utf-8")


def atomic_write_bytes(path: str | os.PathLike[str], data: bytes) -> None:
    """Write ``data`` to ``path`` atomically."""
    with atomic_path(path) as tmp:
        tmp.write_bytes(data)


def to_jsonable(value: Any) -> Any:
    """Convert numpy scalars/arrays (recursively) into plain JSON types; NaN becomes None."""
    if isinstance(value, dict):
        return {str(k): to_jsonable(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [to_jsonable(v) for v in value]
    if isinstance(value, np.ndarray):
        return to_jsonable(value.tolist())
    if isinstance(value, np.generic):
        value = value.item()
    if isinstance(value, float) and not np.isfinite(value):
        return None
    if isinstance(value, Path):
        return str(value)
    return value


def atomic_write_json(path: str | os.PathLike[str], obj: Any) -> None:
    """Write ``obj`` as indented JSON atomically (numpy values converted)."""
    atomic_write_text(path, json.dumps(to_jsonable(obj), indent=2) + "\n")


def read_json(path: str | os.PathLike[str], what: str = "JSON file") -> Any:
    """Read a JSON file; a missing, unreadable or malformed file (or a folder, a FIFO under its name) raises
    :class:`EMRegError` naming it."""
    path = Path(path)
    try:
        if path.exists() and not path.is_file():  # a FIFO would block the read for ever
            raise EMRegError(f"{path}: {what} is {'a folder' if path.is_dir() else 'not a regular file'}")
        return json.loads(path.read_text(encoding="utf-8"))
    except FileNotFoundError:
        raise EMRegError(f"{path}: {what} not found") from None
    except OSError as exc:
        raise EMRegError(f"{path}: cannot read the {what} ({exc.strerror or exc})") from None
    except (json.JSONDecodeError, UnicodeDecodeError) as exc:
        raise EMRegError(f"{path}: not a valid {what} ({exc})") from None
