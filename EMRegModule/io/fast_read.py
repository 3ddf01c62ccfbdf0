"""A fast path for compressed CT files: NRRD, MetaImage (``.mha``) and NIfTI-1 (``.nii``, ``.nii.gz``).

SimpleITK inflates gzip/zlib voxel data with plain zlib, which makes reading the slowest part of
``emreg detect`` on a full-frame scan. Here SimpleITK reads only the header (so origin,
spacing, direction cosines and pixel type are exactly those of ``sitk.ReadImage``), allocates
the image, and the voxel bytes are inflated with ISA-L (``isal``, faster than zlib: see ``scripts/bench_read_ct.py``)
straight into that image's buffer, a bounded chunk at a time: peak memory is the volume plus a
few MB, with no second copy. This runs on a background thread that announces whole slices as
they are filled (a :class:`~EMRegModule.io.ct_handle.CTHandle`), so that marker detection can work on them
meanwhile.

Only the plain layouts are taken: 3D, scalar, the voxels in the same file, raw or gzip/zlib,
no intensity rescaling. Anything else (detached data, a NIfTI slope, NIfTI-2, a pixel type the
header and SimpleITK disagree on, a missing ``isal``) returns ``None`` and the caller reads
the file with SimpleITK. The tests compare both readers voxel for voxel.

The file's sha256 (for provenance) is computed from the bytes as they are read, in that same single
pass: ``handle.sha256``. The NRRD / MetaImage / NIfTI headers are read by :mod:`.ct_header`.
"""

from __future__ import annotations

import hashlib
import queue
import threading
from collections.abc import Callable, Iterable, Iterator
from pathlib import Path
from typing import BinaryIO

import numpy as np
import SimpleITK as sitk

from ..core.pixel_types import BY_NUMPY_NAME
from ..errors import EMRegError
from .ct_checks import NonFiniteCounter
from .ct_handle import CancelledReadError, CTGeometry, CTHandle, writable_bytes
from .ct_header import FILE_KINDS, VoxelStorage, read_storage
from .itk_messages import quiet_itk
from .provenance import Digest

try:  # a declared dependency; without it SimpleITK reads the file (slower, same result)
    from isal import igzip_lib
except ImportError:  # pragma: no cover - depends on the installation
    igzip_lib = None

_CHUNK_BYTES = 1 << 22  # compressed bytes read per step
_MAX_OUT_BYTES = 1 << 20  # inflated bytes per step: small enough that malloc reuses its heap for each block
# (16 MB blocks were fresh memory every time: 2.8 GB of page faults, ~1 s of kernel time, reading a 0.32 mm CT)


def plain_storage(path: Path, kinds: tuple[str, ...] | None = None
                  ) -> tuple[sitk.ImageFileReader, VoxelStorage] | None:
    """SimpleITK's header reading of ``path`` (origin, spacing, direction, size, pixel type: those of
    ``sitk.ReadImage``) and how the file stores its voxels, when it is a 3D scalar file of one of ``kinds`` (all)
    whose voxel type SimpleITK agrees on; ``None`` for anything else (then SimpleITK's full read judges it)."""
    name = path.name.lower()
    kind = next((k for k in kinds or FILE_KINDS if name.endswith(FILE_KINDS[k])), None)
    if igzip_lib is None or kind is None or not path.is_file():
        return None
    info = sitk.ImageFileReader()
    info.SetFileName(str(path))
    try:
        with quiet_itk(capture=True):  # a failure is judged (and said) by SimpleITK's full read
            info.ReadImageInformation()
        if info.GetDimension() != 3 or info.GetNumberOfComponents() != 1:
            return None
        with path.open("rb") as stream:
            storage = read_storage(kind, stream)
    except (RuntimeError, OSError):
        return None
    if storage is None or BY_NUMPY_NAME.get(storage.dtype.newbyteorder("=").name) != info.GetPixelID():
        return None
    return info, storage


def start_fast_read(path: Path) -> CTHandle | None:
    """Start reading ``path`` into a SimpleITK image on a background thread, or ``None`` when the file is not a
    plain layout.

    The returned handle raises :class:`EMRegError` (one line) when the voxel data turns out
    truncated or corrupt.
    """
    plain = plain_storage(path)
    if plain is None:
        return None
    info, storage = plain
    fill = CTHandle(info.GetSize()[2])
    fill.sha256 = Digest()
    threading.Thread(target=_read_voxels, args=(path, info, storage, fill), name="emreg-ct-read").start()
    return fill


def stored_nrrd_voxels(path: Path) -> tuple[CTGeometry, np.dtype, int, str] | None:
    """How a plain NRRD file stores its voxels, for copying them without decoding (the 3D Slicer bundle).

    Returns the geometry (SimpleITK's header reading: size, spacing, origin, direction, pixel type), the
    voxel type, the data offset and the encoding ("raw" or "gzip") when the file is a 3D scalar NRRD
    with attached data in the machine's byte order (or one byte per voxel), no skips,
    and a pixel type SimpleITK agrees on: then its data bytes are exactly the voxels the readers give
    (raw, or their gzip stream). ``None`` for anything else.
    """
    plain = plain_storage(Path(path), ("nrrd",))
    if plain is None:
        return None
    info, storage = plain
    if storage.compression not in ("raw", "gzip") or not storage.dtype.isnative:
        return None
    return CTGeometry.of(info), storage.dtype.newbyteorder("="), storage.data_offset, storage.compression


def _read_voxels(path: Path, info: sitk.ImageFileReader, storage: VoxelStorage, fill: CTHandle) -> None:
    """The reading thread: allocate the image, then :func:`read_and_hash` the file into it."""
    try:
        image, voxels = _new_image(info)  # SimpleITK allocates without the GIL: the imports go on meanwhile
    except BaseException as exc:  # handed to the waiting thread
        _hand_over(fill, path, exc)
        return
    fill.provide(image=image)
    read_and_hash(path, info, storage, voxels, fill)


def read_and_hash(path: Path, info: sitk.ImageFileReader, storage: VoxelStorage, voxels: np.ndarray,
                  fill: CTHandle) -> None:
    """Fill ``voxels`` (the image's bytes) from the file, announcing whole slices to ``fill``, then finish it and
    set ``fill.sha256``: every byte of the file goes through one :class:`_HashingReader`, in order, so that its
    sha256 comes out of this same pass. A truncated, corrupt or over-long file (or a cancel) ends ``fill`` with
    the error, for the thread waiting on it."""
    try:
        slices = _SliceAnnouncer(voxels, storage.dtype, fill)
        with path.open("rb") as file:
            stream = _HashingReader(file, in_place=storage.compression == "raw" and not storage.dtype.isnative)
            try:
                if storage.compression == "raw" or not storage.whole_file:
                    stream.skip(storage.data_offset)  # the header: hashed, not used
                if storage.compression == "raw":
                    filled = _read_raw(stream, voxels, slices)
                    if filled == voxels.nbytes and stream.read(1):
                        extra = path.stat().st_size - storage.data_offset - voxels.nbytes
                        raise EMRegError(_too_much_data(path, info, voxels.nbytes, extra))
                else:
                    skip = storage.data_offset if storage.whole_file else 0
                    blocks = _inflated(stream, storage.compression == "gzip", path, skip + voxels.nbytes)
                    filled, extra = _fill(voxels, blocks, skip, slices)
                    if extra:
                        raise EMRegError(_too_much_data(path, info, voxels.nbytes, extra))
                if filled != voxels.nbytes:
                    raise EMRegError(f"{path}: cannot read CT (file is truncated: {filled} of {voxels.nbytes} voxel "
                                     f"bytes)")
                slices(filled)
                slices.non_finite.check(path)
                stream.skip(None)  # whatever follows the data (nothing, normally): hashed too
                fill.finish()
                fill.sha256.set(stream.hexdigest())  # its last chunks may still be being hashed
            finally:
                stream.close()
    except BaseException as exc:  # handed to the waiting thread
        _hand_over(fill, path, exc)


def _hand_over(fill: CTHandle, path: Path, exc: BaseException) -> None:
    """End ``fill`` (and its sha256) with the read's error; a cancel is said as such."""
    if isinstance(exc, _CancelledError):
        exc = CancelledReadError(f"{path}: reading the CT was cancelled")
    fill.sha256.fail(exc)
    fill.finish(exc)


class _HashingReader:
    """A file read front to back once: ``read``/``readinto`` as the file's, and the sha256 of every byte read.

    The bytes are hashed on a thread of their own as they come (hashlib lets go of the GIL), so the
    hash costs the read no time where a second core is free. ``in_place``: the caller rewrites
    what ``readinto`` filled (a byte swap), so the bytes are hashed at once, before that.
    """

    _QUEUED = 8  # chunks waiting to be hashed at most (a few tens of MB)

    def __init__(self, file: BinaryIO, in_place: bool = False) -> None:
        self.file = file
        self.digest = hashlib.sha256()
        self._chunks: queue.Queue | None = None
        self._thread: threading.Thread | None = None
        if not in_place:
            self._chunks = queue.Queue(self._QUEUED)
            self._thread = threading.Thread(target=self._hash, name="emreg-ct-sha256", daemon=True)
            self._thread.start()

    def _hash(self) -> None:
        while (chunk := self._chunks.get()) is not None:
            self.digest.update(chunk)

    def _add(self, data: bytes | np.ndarray) -> None:
        if self._chunks is None:
            self.digest.update(data)
        else:
            self._chunks.put(data)  # not written again: hashed while the next chunk is read

    def read(self, size: int = -1) -> bytes:
        data = self.file.read(size)
        if data:
            self._add(data)
        return data

    def readinto(self, buffer: np.ndarray) -> int:
        count = self.file.readinto(buffer)
        if count:
            self._add(buffer[:count])
        return count

    def skip(self, size: int | None) -> None:
        """Read (and hash) ``size`` bytes, or everything left when None."""
        while size is None or size > 0:
            chunk = self.read(_CHUNK_BYTES if size is None else min(size, _CHUNK_BYTES))
            if not chunk:
                return
            if size is not None:
                size -= len(chunk)

    def close(self) -> None:
        """Wait until every byte read so far is hashed; the hashing thread ends."""
        if self._thread is not None:
            self._chunks.put(None)
            self._thread.join()
            self._thread = None

    def hexdigest(self) -> str:
        self.close()
        return self.digest.hexdigest()


class _CancelledError(Exception):
    """Raised within the reading thread when the handle's user cancelled the read."""


def _too_much_data(path: Path, info: sitk.ImageFileReader, expected: int, extra: int) -> str:
    return (f"{path}: cannot read CT (the file holds {extra} voxel bytes more than its header's size "
            f"{list(info.GetSize())} needs ({expected} bytes): the header does not describe the data)")


class _SliceAnnouncer:
    """Called with the bytes filled so far: swaps the byte order of newly whole slices, announces them."""

    def __init__(self, voxels: np.ndarray, dtype: np.dtype, fill: CTHandle) -> None:
        self.voxels, self.dtype, self.fill = voxels, dtype, fill
        self.slice_bytes = voxels.nbytes // max(1, fill.slice_count)
        self.done = 0
        self.non_finite = NonFiniteCounter()
        self.native = dtype.newbyteorder("=")
        self.check_finite = self.native.kind == "f"

    def __call__(self, filled: int) -> None:
        if self.fill.cancelled:
            raise _CancelledError
        whole = filled // self.slice_bytes if self.slice_bytes else self.fill.slice_count
        if whole <= self.done:
            return
        part = self.voxels[self.done * self.slice_bytes:whole * self.slice_bytes]
        if not self.dtype.isnative:
            part.view(self.native).byteswap(inplace=True)
        if self.check_finite:
            self.non_finite.add(part.view(self.native))
        self.done = whole
        if not self.non_finite.count:  # slices after a non-finite voxel are not handed to detection
            self.fill.announce(whole)


def _read_raw(stream: _HashingReader, out: np.ndarray, announce: Callable[[int], None]) -> int:
    """Read uncompressed voxels into ``out`` chunk by chunk; the bytes read."""
    filled = 0
    while filled < out.nbytes:
        count = stream.readinto(out[filled:filled + _MAX_OUT_BYTES])
        if not count:
            break
        filled += count
        announce(filled)
    return filled


def _new_image(info: sitk.ImageFileReader) -> tuple[sitk.Image, np.ndarray]:
    """An image with the header's size, pixel type and geometry, and its buffer as writable bytes."""
    image = sitk.Image(list(info.GetSize()), info.GetPixelID())
    image.SetSpacing(info.GetSpacing())
    image.SetOrigin(info.GetOrigin())
    image.SetDirection(info.GetDirection())
    return image, writable_bytes(image)


def _inflated(stream: _HashingReader, gzip: bool, path: Path, expected: int) -> Iterator[bytes]:
    """The inflated rest of ``stream``, block by block (at most ``_MAX_OUT_BYTES`` each).

    The stream is inflated to its end, so that its checksums (gzip CRC-32, zlib Adler-32) are
    verified: a corrupt file is an error even when its damage still inflates. A stream that
    ends early is an error too; gzip members that follow one another are read in turn.
    ``IgzipDecompressor`` is used rather than ``isal_zlib``: it keeps the GIL far less, so the
    imports running beside the read are not slowed down.
    """
    flag = igzip_lib.DECOMP_GZIP if gzip else igzip_lib.DECOMP_ZLIB
    inflater = igzip_lib.IgzipDecompressor(flag=flag)
    produced = 0
    try:
        while True:
            if inflater.eof:
                rest = inflater.unused_data or stream.read(_CHUNK_BYTES)
                if not (gzip and rest):
                    return
                inflater = igzip_lib.IgzipDecompressor(flag=flag)  # the next gzip member
                pending = rest
            elif inflater.needs_input:
                pending = stream.read(_CHUNK_BYTES)
                if not pending:
                    raise EMRegError(f"{path}: cannot read CT (file is truncated: its compressed data ends after "
                                     f"{produced} of {expected} bytes)")
            else:
                pending = b""
            block = inflater.decompress(pending, _MAX_OUT_BYTES)
            produced += len(block)
            yield block
    except igzip_lib.IsalError as exc:
        raise EMRegError(f"{path}: cannot read CT (voxel data is corrupt: {exc})") from None


def _fill(out: np.ndarray, blocks: Iterable[bytes], skip: int,
          announce: Callable[[int], None]) -> tuple[int, int]:
    """Copy ``blocks`` into ``out`` after dropping their first ``skip`` bytes.

    Returns the bytes written and the bytes left over after ``out`` was full (the data is longer
    than the header says). ``announce`` gets the bytes written so far after each block.
    """
    position = -skip  # where the next block starts in ``out``
    for block in blocks:
        lo, hi = max(0, -position), min(len(block), out.nbytes - position)
        if lo < hi:
            out[position + lo:position + hi] = np.frombuffer(block, dtype=np.uint8)[lo:hi]
        position += len(block)
        announce(min(max(position, 0), out.nbytes))
    return min(max(position, 0), out.nbytes), max(0, position - out.nbytes)

