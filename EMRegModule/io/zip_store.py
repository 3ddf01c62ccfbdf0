"""A ZIP archive of stored (uncompressed) entries, written in one forward pass and hashed as it is written.

3D Slicer's scene bundles (``.mrb``) are such archives. :class:`StoredZipWriter` knows every entry's
CRC-32 and size before it writes the entry's local header, so it never seeks back: the sha256 of the
archive is computed from the bytes as they go out (no second read of a bundle of hundreds of MB), a
file's bytes are copied by the kernel (``os.copy_file_range``; read and written in chunks where that is
not available) and checksummed by ISA-L's CRC-32 (zlib's when ISA-L is missing). ZIP64 records are
written where sizes or offsets need them (APPNOTE 6.3.10, sections 4.3.7-4.3.16, 4.5.3), as
:mod:`zipfile` writes them.
"""

from __future__ import annotations

import hashlib
import mmap
import os
import struct
import time
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path

try:
    from isal.isal_zlib import crc32
except ImportError:  # pragma: no cover - ISA-L is a dependency; zlib's CRC-32 is the same function, slower
    from zlib import crc32

#: Bytes of a file mapped at a time (bounded memory whatever the size of a file).
_CHUNK_BYTES = 16 << 20
#: Sizes and offsets from this on need ZIP64 fields (a module attribute so that tests can lower it).
ZIP64_LIMIT = 0xFFFFFFFF
_UTF8_NAMES = 0x800


@dataclass(frozen=True)
class FileRegion:
    """``length`` bytes of the file ``path`` from ``offset`` on (an entry's content copied as it is)."""

    path: Path
    offset: int
    length: int


@dataclass
class _Entry:
    name: bytes
    flags: int
    dos_time: int
    dos_date: int
    crc: int
    size: int
    offset: int
    external_attr: int


def _dos_stamp(seconds: float) -> tuple[int, int]:
    """MS-DOS time and date of a POSIX time (local time; 1980 at the earliest, as :mod:`zipfile` does)."""
    t = time.localtime(seconds)
    year = max(t.tm_year, 1980)
    return (t.tm_hour << 11) | (t.tm_min << 5) | (t.tm_sec // 2), ((year - 1980) << 9) | (t.tm_mon << 5) | t.tm_mday


class StoredZipWriter:
    """Write ``path`` as a ZIP of stored entries, in order; :meth:`close` returns the archive's sha256 (hex).

    Entries are made of parts: ``bytes`` and :class:`FileRegion` s (a large file's bytes never pass
    through Python when the kernel can copy them). Use as a context manager; an exception leaves the
    file incomplete (the caller writes to a temporary name and renames it once closed).
    """

    def __init__(self, path: str | os.PathLike[str]) -> None:
        self._fd = os.open(path, os.O_WRONLY | os.O_CREAT | os.O_TRUNC, 0o666)
        self._sha = hashlib.sha256()
        self._position = 0
        self._entries: list[_Entry] = []
        self._closed = False

    def __enter__(self) -> StoredZipWriter:
        return self

    def __exit__(self, *exc: object) -> None:
        if not self._closed:
            os.close(self._fd)
            self._closed = True

    def add_directory(self, name: str, mtime: float | None = None, mode: int = 0o40755) -> None:
        """A folder entry ``name/`` (``mode``: its ``st_mode``, recorded as ``zipfile.ZipFile.write`` records it)."""
        self.add(name.rstrip("/") + "/", [], mtime, ((mode & 0xFFFF) << 16) | 0x10)

    def add(self, name: str, parts: list[bytes | FileRegion], mtime: float | None = None,
            external_attr: int = 0o100644 << 16) -> None:
        """The entry ``name`` (POSIX path in the archive): its parts in order; ``mtime`` POSIX seconds (now by
        default)."""
        crc, size = 0, 0
        for part in parts:
            crc = self._crc_of(part, crc)
            size += part.length if isinstance(part, FileRegion) else len(part)
        encoded = name.encode("ascii", "ignore")
        flags = 0
        if encoded.decode("ascii") != name:
            encoded, flags = name.encode("utf-8"), _UTF8_NAMES
        dos_time, dos_date = _dos_stamp(time.time() if mtime is None else mtime)
        entry = _Entry(encoded, flags, dos_time, dos_date, crc, size, self._position, external_attr)
        zip64 = size >= ZIP64_LIMIT
        extra = struct.pack("<HHQQ", 1, 16, size, size) if zip64 else b""
        shown = 0xFFFFFFFF if zip64 else size
        self._emit(struct.pack("<IHHHHHIIIHH", 0x04034B50, 45 if zip64 else 20, flags, 0, dos_time, dos_date, crc,
                               shown, shown, len(encoded), len(extra)) + encoded + extra)
        for part in parts:
            if isinstance(part, FileRegion):
                self._copy(part)
            else:
                self._emit(part)
        self._entries.append(entry)

    def close(self) -> str:
        """Write the central directory (and the ZIP64 end records when needed); the sha256 of the whole archive."""
        start = self._position
        for e in self._entries:
            extra_values = [v for v in (e.size, e.size) if v >= ZIP64_LIMIT]
            if e.offset >= ZIP64_LIMIT:
                extra_values.append(e.offset)
            extra = struct.pack(f"<HH{len(extra_values)}Q", 1, 8 * len(extra_values), *extra_values) \
                if extra_values else b""
            version = 45 if extra else 20
            size = 0xFFFFFFFF if e.size >= ZIP64_LIMIT else e.size
            offset = 0xFFFFFFFF if e.offset >= ZIP64_LIMIT else e.offset
            self._emit(struct.pack("<IBBHHHHHIIIHHHHHII", 0x02014B50, version, 3, version, e.flags, 0, e.dos_time,
                                   e.dos_date, e.crc, size, size, len(e.name), len(extra), 0, 0, 0, e.external_attr,
                                   offset) + e.name + extra)
        count, directory_size = len(self._entries), self._position - start
        if count >= 0xFFFF or start >= ZIP64_LIMIT or directory_size >= ZIP64_LIMIT:
            end64 = self._position
            self._emit(struct.pack("<IQBBHIIQQQQ", 0x06064B50, 44, 45, 3, 45, 0, 0, count, count, directory_size,
                                   start))
            self._emit(struct.pack("<IIQI", 0x07064B50, 0, end64, 1))
        self._emit(struct.pack("<IHHHHIIH", 0x06054B50, 0, 0, min(count, 0xFFFF), min(count, 0xFFFF),
                               min(directory_size, 0xFFFFFFFF), min(start, 0xFFFFFFFF), 0))
        os.close(self._fd)
        self._closed = True
        return self._sha.hexdigest()

    # --- bytes out ------------------------------------------------------------------------------

    def _emit(self, data: bytes) -> None:
        self._sha.update(data)
        self._write_all(data)
        self._position += len(data)

    def _write_all(self, data: bytes | memoryview) -> None:
        with memoryview(data) as view:
            done = 0
            while done < len(view):
                done += os.write(self._fd, view[done:])

    def _crc_of(self, part: bytes | FileRegion, crc: int) -> int:
        if not isinstance(part, FileRegion):
            return crc32(part, crc)
        with open(part.path, "rb", buffering=0) as source:
            for _, window in _windows(source, part):
                crc = crc32(window, crc)
        return crc

    def _copy(self, region: FileRegion) -> None:
        """The region's bytes into the archive: hashed where the file is mapped, copied by the kernel when it can."""
        with open(region.path, "rb", buffering=0) as source:
            for offset, window in _windows(source, region):
                self._sha.update(window)
                copied = _kernel_copy(source.fileno(), self._fd, offset, len(window))
                if copied < len(window):
                    with window[copied:] as rest:  # released even when the write fails (a full disk): else
                        self._write_all(rest)  # the mapping cannot be closed (BufferError)
        self._position += region.length


def _windows(source, region: FileRegion) -> Iterator[tuple[int, memoryview]]:
    """The region's bytes as (file offset, view) of at most :data:`_CHUNK_BYTES`, each mapped from the file
    (no copy) and unmapped after use (a view is released when the next is asked for; the caller keeps no view
    derived from it): the process's memory stays one window whatever the region's size."""
    grain = mmap.ALLOCATIONGRANULARITY  # where a mapping may start
    step = max(grain, _CHUNK_BYTES - _CHUNK_BYTES % grain)
    end = region.offset + region.length
    position = region.offset - region.offset % grain
    while position < end:
        length = min(step, end - position)
        try:
            mapped = mmap.mmap(source.fileno(), length, offset=position, access=mmap.ACCESS_READ)
        except ValueError:  # the file ends before the region does
            raise OSError(f"{region.path}: shorter than expected while copying it into the archive") from None
        with mapped:
            start = max(region.offset - position, 0)
            view = memoryview(mapped)[start:]
            try:
                yield position + start, view
            finally:
                view.release()
        position += length


def _kernel_copy(source_fd: int, target_fd: int, offset: int, count: int) -> int:
    """Copy ``count`` bytes of ``source_fd`` from ``offset`` to ``target_fd``'s position in the kernel; the bytes
    copied (fewer, down to 0, where the kernel cannot: the caller writes the rest)."""
    copy = getattr(os, "copy_file_range", None)
    done = 0
    while copy is not None and done < count:
        try:
            n = copy(source_fd, target_fd, count - done, offset + done)
        except OSError:
            break
        if n <= 0:
            break
        done += n
    return done
