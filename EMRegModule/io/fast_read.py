"""A fast path for compressed CT files: NRRD, MetaImage (``.mha``) and NIfTI-1 (``.nii``, ``.nii.gz``).

SimpleITK inflates gzip/zlib voxel data with plain zlib, which makes reading the slowest part of
``emreg detect`` on a full-frame scan. Here SimpleITK reads only the header (so origin,
spacing, direction cosines and pixel type are exactly those of ``sitk.ReadImage``), allocates
the image, and the voxel bytes are inflated with ISA-L (``isal``, faster than zlib: see ``scripts/bench_read_ct.py``)
straight into that image's buffer, a bounded chunk at a time: peak memory is the volume plus a
few MB, with no second copy. This runs on a background thread that announces whole slices as
they are filled (:class:`VolumeFill`), so that marker detection can work on them meanwhile.

Only the plain layouts are taken: 3D, scalar, the voxels in the same file, raw or gzip/zlib,
no intensity rescaling. Anything else (detached data, a NIfTI slope, NIfTI-2, a pixel type the
header and SimpleITK disagree on, a missing ``isal``) returns ``None`` and the caller reads
the file with SimpleITK. The tests compare both readers voxel for voxel.

The file's sha256 (for provenance) is computed from the bytes as they are read, in that same single
pass: ``fill.sha256``.
"""

from __future__ import annotations

import ctypes
import hashlib
import os
import queue
import threading
from collections.abc import Callable, Iterable, Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import BinaryIO

import numpy as np
import SimpleITK as sitk

from ..errors import EMRegError
from ..provenance import Digest
from .ct_checks import NonFiniteCounter
from .itk_messages import quiet_itk

try:  # a declared dependency; without it SimpleITK reads the file (slower, same result)
    from isal import igzip_lib
except ImportError:  # pragma: no cover - depends on the installation
    igzip_lib = None

_CHUNK_BYTES = 1 << 22  # compressed bytes read per step
_MAX_OUT_BYTES = 1 << 20  # inflated bytes per step: small enough that malloc reuses its heap for each block
# (16 MB blocks were fresh memory every time: 2.8 GB of page faults, ~1 s of kernel time, reading a 0.32 mm CT)

_NRRD_TYPES = {
    "signed char": "int8", "int8": "int8", "int8_t": "int8",
    "uchar": "uint8", "unsigned char": "uint8", "uint8": "uint8", "uint8_t": "uint8",
    "short": "int16", "short int": "int16", "signed short": "int16", "signed short int": "int16",
    "int16": "int16", "int16_t": "int16",
    "ushort": "uint16", "unsigned short": "uint16", "unsigned short int": "uint16", "uint16": "uint16",
    "uint16_t": "uint16",
    "int": "int32", "signed int": "int32", "int32": "int32", "int32_t": "int32",
    "uint": "uint32", "unsigned int": "uint32", "uint32": "uint32", "uint32_t": "uint32",
    "float": "float32", "double": "float64",
}
_MET_TYPES = {
    "MET_CHAR": "int8", "MET_UCHAR": "uint8", "MET_SHORT": "int16", "MET_USHORT": "uint16",
    "MET_INT": "int32", "MET_UINT": "uint32", "MET_FLOAT": "float32", "MET_DOUBLE": "float64",
}
_NIFTI_TYPES = {2: "uint8", 4: "int16", 8: "int32", 16: "float32", 64: "float64", 256: "int8", 512: "uint16",
                768: "uint32"}
_SITK_TYPES = {
    "int8": sitk.sitkInt8, "uint8": sitk.sitkUInt8, "int16": sitk.sitkInt16, "uint16": sitk.sitkUInt16,
    "int32": sitk.sitkInt32, "uint32": sitk.sitkUInt32, "float32": sitk.sitkFloat32, "float64": sitk.sitkFloat64,
}


@dataclass
class _Storage:
    """Where and how a file keeps its voxels (the geometry comes from SimpleITK's own header reading)."""

    dtype: np.dtype  # with its byte order
    data_offset: int  # bytes from the start of the file, or of the inflated stream when ``whole_file``
    compression: str  # "raw", "gzip" or "zlib"
    whole_file: bool = False  # the whole file is one gzip stream (``.nii.gz``)


class VolumeFill:
    """A CT image whose voxels are being read on a background thread, whole slices at a time.

    Slices are numpy axis 0 of ``sitk.GetArrayViewFromImage(image)`` (the image's k index),
    in the order the file stores them. ``wait_for_slices(n)`` returns once slices ``0 .. n-1``
    hold their final values, so that work on them (marker detection) can go on while the rest
    is inflated. ``result()`` waits for the whole image. An error of the read is raised by
    whichever of the two is waiting.
    """

    def __init__(self, slice_count: int) -> None:
        self.slice_count = slice_count
        self._image: sitk.Image | None = None
        self._ready = 0
        self._error: BaseException | None = None
        self._finished = False
        self._cancelled = False
        self._condition = threading.Condition()
        self.series: dict | None = None  # a DICOM folder: the series read and the others (``dicom_series``)
        self.is_complete = False  # True when made by ``complete`` (read in full before it existed)
        self.sha256: Digest | None = None  # the source's sha256 (provenance), computed as it is read
        # the voxels (k, j, i) when they are not in a SimpleITK image: ``image`` is then only their geometry
        # (a DICOM series read ``voxels_only``, :func:`~EMRegModule.io.dicom_series.open_dicom_series`)
        self.voxels: np.ndarray | None = None

    @classmethod
    def complete(cls, image: sitk.Image) -> VolumeFill:
        """An image read in full already (by SimpleITK)."""
        size = image.GetSize()
        fill = cls(size[2] if len(size) > 2 else 1)  # a 2D image is refused by ``check_ct`` later
        fill._image, fill._ready, fill._finished = image, fill.slice_count, True
        fill.is_complete = True
        return fill

    @property
    def image(self) -> sitk.Image:
        """The image (allocated with its geometry; its voxels may still be arriving)."""
        with self._condition:
            self._condition.wait_for(lambda: self._image is not None or self._finished)
            self._raise_error()
            return self._image

    def wait_for_slices(self, stop: int) -> None:
        """Block until slices ``0 .. stop-1`` are read (``stop`` is clipped to the slice count)."""
        stop = min(stop, self.slice_count)
        with self._condition:
            self._condition.wait_for(lambda: self._ready >= stop or self._finished)
            self._raise_error()

    def result(self) -> sitk.Image:
        """The whole image, once read and its checksum verified."""
        with self._condition:
            self._condition.wait_for(lambda: self._finished)
            self._raise_error()
            return self._image

    def read_error(self) -> BaseException | None:
        """Wait for the read to end; its own error (not a cancellation), or ``None``."""
        with self._condition:
            self._condition.wait_for(lambda: self._finished)
            error = self._error
        return None if isinstance(error, _CancelledReadError) else error

    def cancel(self) -> None:
        """Stop reading (the image is then incomplete and must not be used)."""
        self._cancelled = True

    def _raise_error(self) -> None:
        if self._error is not None:
            raise self._error

    def _set_image(self, image: sitk.Image) -> None:
        with self._condition:
            self._image = image
            self._condition.notify_all()

    def _set_ready(self, slices: int) -> None:
        with self._condition:
            self._ready = slices
            self._condition.notify_all()

    def _finish(self, error: BaseException | None = None) -> None:
        with self._condition:
            self._error = error
            self._finished = True
            self._condition.notify_all()


def plain_storage(path: Path, kinds: tuple[str, ...] | None = None
                  ) -> tuple[sitk.ImageFileReader, _Storage] | None:
    """SimpleITK's header reading of ``path`` (origin, spacing, direction, size, pixel type: those of
    ``sitk.ReadImage``) and how the file stores its voxels, when it is a 3D scalar file of one of ``kinds`` (all)
    whose voxel type SimpleITK agrees on; ``None`` for anything else (then SimpleITK's full read judges it)."""
    name = path.name.lower()
    kind = next((k for k in kinds or _KINDS if name.endswith(_KINDS[k])), None)
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
            storage = _STORAGE_READERS[kind](stream)
    except (RuntimeError, OSError):
        return None
    if storage is None or _SITK_TYPES.get(storage.dtype.newbyteorder("=").name) != info.GetPixelID():
        return None
    return info, storage


def start_fast_read(path: Path) -> VolumeFill | None:
    """Start reading ``path`` on a background thread, or ``None`` when the file is not a plain layout.

    The returned fill raises :class:`EMRegError` (one line) when the voxel data turns out
    truncated or corrupt.
    """
    plain = plain_storage(path)
    if plain is None:
        return None
    info, storage = plain
    fill = VolumeFill(info.GetSize()[2])
    fill.sha256 = Digest()
    threading.Thread(target=_read_voxels, args=(path, info, storage, fill), name="emreg-ct-read").start()
    return fill


def stored_nrrd_voxels(path: Path) -> tuple[sitk.ImageFileReader, np.dtype, int, str] | None:
    """How a plain NRRD file stores its voxels, for copying them without decoding (the 3D Slicer bundle).

    Returns SimpleITK's header reading (geometry, size, pixel type: those of ``sitk.ReadImage``), the
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
    return info, storage.dtype.newbyteorder("="), storage.data_offset, storage.compression


def _read_voxels(path: Path, info: sitk.ImageFileReader, storage: _Storage, fill: VolumeFill) -> None:
    """The reading thread: allocate the image, then :func:`read_and_hash` the file into it."""
    try:
        image, voxels = _new_image(info)  # SimpleITK allocates without the GIL: the imports go on meanwhile
    except BaseException as exc:  # handed to the waiting thread
        _hand_over(fill, path, exc)
        return
    fill._set_image(image)
    read_and_hash(path, info, storage, voxels, fill)


def read_and_hash(path: Path, info: sitk.ImageFileReader, storage: _Storage, voxels: np.ndarray,
                  fill: VolumeFill) -> None:
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
                fill._finish()
                fill.sha256.set(stream.hexdigest())  # its last chunks may still be being hashed
            finally:
                stream.close()
    except BaseException as exc:  # handed to the waiting thread
        _hand_over(fill, path, exc)


def _hand_over(fill: VolumeFill, path: Path, exc: BaseException) -> None:
    """End ``fill`` (and its sha256) with the read's error; a cancel is said as such."""
    if isinstance(exc, _CancelledError):
        exc = _CancelledReadError(f"{path}: reading the CT was cancelled")
    fill.sha256.fail(exc)
    fill._finish(exc)


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
    pass


class _CancelledReadError(EMRegError):
    """The read was cancelled by its user (detection failed first)."""


def _too_much_data(path: Path, info: sitk.ImageFileReader, expected: int, extra: int) -> str:
    return (f"{path}: cannot read CT (the file holds {extra} voxel bytes more than its header's size "
            f"{list(info.GetSize())} needs ({expected} bytes): the header does not describe the data)")


class _SliceAnnouncer:
    """Called with the bytes filled so far: swaps the byte order of newly whole slices, announces them."""

    def __init__(self, voxels: np.ndarray, dtype: np.dtype, fill: VolumeFill) -> None:
        self.voxels, self.dtype, self.fill = voxels, dtype, fill
        self.slice_bytes = voxels.nbytes // max(1, fill.slice_count)
        self.done = 0
        self.non_finite = NonFiniteCounter()
        self.native = dtype.newbyteorder("=")
        self.check_finite = self.native.kind == "f"

    def __call__(self, filled: int) -> None:
        if self.fill._cancelled:
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
            self.fill._set_ready(whole)


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
    return image, _writable_bytes(image)


def _writable_bytes(image: sitk.Image) -> np.ndarray:
    """The voxel buffer of a freshly made (unshared) ``image`` as a writable flat uint8 array.

    SimpleITK only hands out read-only views; the buffer itself is the image's own, so it is
    written through its address. The returned array must not outlive ``image``.
    """
    view = sitk.GetArrayViewFromImage(image)  # also makes the buffer unique to this image
    address = view.__array_interface__["data"][0]
    return np.frombuffer((ctypes.c_char * view.nbytes).from_address(address), dtype=np.uint8)


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


# --- headers --------------------------------------------------------------------------------------


def _header_lines(stream: BinaryIO, limit: int = 1 << 16) -> tuple[list[str], int] | None:
    """Lines up to the first empty one (NRRD) or ``ElementDataFile`` (MetaImage), and the data offset."""
    head = stream.read(limit)
    lines, offset = [], 0
    while True:
        end = head.find(b"\n", offset)
        if end < 0 and len(head) < limit and offset < len(head):
            end = len(head)  # a detached header (``.nhdr``, ``.mhd``) may end without a newline
        elif end < 0:
            return (lines, offset) if len(head) < limit and lines else None
        raw = head[offset:end]
        offset = end + 1
        try:
            line = raw.decode("ascii").rstrip("\r")
        except UnicodeDecodeError:
            return None
        if not line:
            return lines, offset
        lines.append(line)
        if line.split("=")[0].strip() == "ElementDataFile":
            return lines, offset


def _nrrd_fields(stream: BinaryIO) -> tuple[dict[str, str], int] | None:
    """The NRRD header's fields (lower-case keys) and the data offset, or ``None`` when not plain NRRD."""
    parsed = _header_lines(stream)
    if parsed is None or not parsed[0] or not parsed[0][0].startswith("NRRD000"):
        return None
    lines, offset = parsed
    fields: dict[str, str] = {}
    for line in lines[1:]:
        if line.startswith("#") or ":=" in line:
            continue  # comments and key/value pairs
        key, sep, value = line.partition(": ")
        if not sep:
            return None
        fields[key.strip().lower()] = value.strip()
    return fields, offset


def _header_fields(path: Path) -> tuple[str, dict[str, str], int] | None:
    """The kind (``"nrrd"``: ``.nrrd``, ``.nhdr``; ``"mha"``: ``.mha``, ``.mhd``), fields and data offset of an
    image header read by name; None for another file, one that cannot be read or a header not read here."""
    name = path.name.lower()
    kind = "nrrd" if name.endswith((".nrrd", ".nhdr")) else "mha" if name.endswith((".mha", ".mhd")) else None
    if kind is None:
        return None
    try:
        with path.open("rb") as stream:
            parsed = (_nrrd_fields if kind == "nrrd" else _mha_fields)(stream)
    except OSError:
        return None
    return None if parsed is None else (kind, *parsed)


def nrrd_header_fields(path: Path) -> dict[str, str] | None:
    """The fields of a NRRD header (``.nrrd`` or ``.nhdr``; lower-case keys), None when ``path`` is not one."""
    header = _header_fields(path)
    return header[1] if header is not None and header[0] == "nrrd" else None


def _nrrd_storage(stream: BinaryIO) -> _Storage | None:
    parsed = _nrrd_fields(stream)
    if parsed is None:
        return None
    fields, offset = parsed
    if {"data file", "datafile", "line skip", "lineskip", "byte skip", "byteskip"} & set(fields):
        return None  # detached or offset data: SimpleITK handles those
    dtype_name = _NRRD_TYPES.get(_nrrd_word(fields, "type"))
    compression = _nrrd_compression(fields)
    if dtype_name is None or compression is None:
        return None
    return _Storage(_ordered(dtype_name, _nrrd_word(fields, "endian") == "big"), offset, compression)


def _nrrd_word(fields: dict[str, str], key: str) -> str:
    """A field whose value is a word of a fixed set (type, encoding, endian), in lower case: NRRD readers (teem,
    hence SimpleITK and 3D Slicer) take ``endian: BIG`` or ``encoding: GZIP`` as ``big`` and ``gzip``."""
    return fields.get(key, "").lower()


def _nrrd_compression(fields: dict[str, str]) -> str | None:
    """"raw" or "gzip" for the encodings read here, ``None`` for others (text, hex, bzip2)."""
    return {"raw": "raw", "gzip": "gzip", "gz": "gzip"}.get(_nrrd_word(fields, "encoding"))


def _mha_fields(stream: BinaryIO) -> tuple[dict[str, str], int] | None:
    """The MetaImage header's fields and the data offset (after ``ElementDataFile``), or ``None``."""
    parsed = _header_lines(stream)
    if parsed is None:
        return None
    lines, offset = parsed
    fields: dict[str, str] = {}
    for line in lines:
        key, sep, value = line.partition("=")
        if not sep:
            return None
        fields[key.strip()] = value.strip()
    return fields, offset


def _mha_storage(stream: BinaryIO) -> _Storage | None:
    parsed = _mha_fields(stream)
    if parsed is None:
        return None
    fields, offset = parsed
    if fields.get("ElementDataFile") != "LOCAL" or not _meta_flag(fields, "BinaryData", True):
        return None
    dtype_name = _MET_TYPES.get(fields.get("ElementType", ""))
    if dtype_name is None:
        return None
    big = _meta_flag(fields, "BinaryDataByteOrderMSB", _meta_flag(fields, "ElementByteOrderMSB", False))
    return _Storage(_ordered(dtype_name, big), offset, _meta_compression(fields))


def _meta_flag(fields: dict[str, str], key: str, default: bool) -> bool:
    """A MetaImage yes/no field as MetaIO (hence SimpleITK) reads it: true when its value starts with
    ``T``, ``t`` or ``1`` (``True``, ``true``, ``1``), false otherwise; ``default`` when absent."""
    value = fields.get(key)
    return default if value is None else value[:1] in ("T", "t", "1")


def _meta_compression(fields: dict[str, str]) -> str:
    return "zlib" if _meta_flag(fields, "CompressedData", False) else "raw"


def _nifti_storage(stream: BinaryIO) -> _Storage | None:
    """NIfTI-1 (``.nii`` or ``.nii.gz``) without intensity scaling; others return ``None``."""
    start = stream.read(2)
    stream.seek(0)
    gzip = start == b"\x1f\x8b"
    if gzip:
        head = igzip_lib.IgzipDecompressor(flag=igzip_lib.DECOMP_GZIP).decompress(stream.read(1 << 12), 352)
    else:
        head = stream.read(352)
    if len(head) < 352:
        return None
    for order in "<>":
        if np.frombuffer(head, dtype=order + "i4", count=1)[0] == 348:
            break
    else:
        return None  # NIfTI-2 or not NIfTI
    datatype = int(np.frombuffer(head, dtype=order + "i2", count=1, offset=70)[0])
    vox_offset, slope, intercept = np.frombuffer(head, dtype=order + "f4", count=3, offset=108)
    dtype_name = _NIFTI_TYPES.get(datatype)
    if dtype_name is None or slope not in (0.0, 1.0) or intercept != 0.0 or vox_offset < 352:
        return None  # a rescaled or unusual file: SimpleITK applies its rules
    return _Storage(_ordered(dtype_name, order == ">"), int(vox_offset), "gzip" if gzip else "raw", whole_file=gzip)


def _ordered(dtype_name: str, big_endian: bool) -> np.dtype:
    dtype = np.dtype(dtype_name)
    return dtype.newbyteorder(">" if big_endian else "<") if dtype.itemsize > 1 else dtype


_KINDS = {"nrrd": ".nrrd", "mha": ".mha", "nifti": (".nii", ".nii.gz")}
_STORAGE_READERS = {"nrrd": _nrrd_storage, "mha": _mha_storage, "nifti": _nifti_storage}


# --- the data length against the header, for files SimpleITK reads ---------------------------------


def check_data_length(path: Path) -> None:
    """Refuse an NRRD / MetaImage whose voxel data is longer or shorter than its header's sizes say.

    SimpleITK reads as many bytes as the header asks for and ignores the rest, so a header whose
    ``sizes`` / ``DimSize`` is smaller than the data silently drops slices. Checked for the layouts
    SimpleITK reads when the fast path does not (detached data files, no ``isal``): raw or
    gzip/zlib data in one file, attached or detached. Other layouts are left to SimpleITK.
    """
    header = _header_fields(path)
    if header is None:
        return
    kind, fields, offset = header
    info = sitk.ImageFileReader()
    info.SetFileName(str(path))
    try:
        with quiet_itk(capture=True):
            info.ReadImageInformation()
    except RuntimeError:
        return  # SimpleITK's full read reports the problem
    dtype_name = next((k for k, v in _SITK_TYPES.items() if v == info.GetPixelID()), None)
    if dtype_name is None:
        return
    expected = int(np.prod(info.GetSize(), dtype=np.int64)) * info.GetNumberOfComponents() \
        * np.dtype(dtype_name).itemsize
    if kind == "nrrd":
        if {"line skip", "lineskip", "byte skip", "byteskip"} & set(fields):
            return
        detached = fields.get("data file", fields.get("datafile"))
        compression = _nrrd_compression(fields)
    else:
        if "HeaderSize" in fields or not _meta_flag(fields, "BinaryData", True):
            return
        detached = fields.get("ElementDataFile")
        detached = None if detached == "LOCAL" else detached
        compression = _meta_compression(fields)
    if compression is None:
        return
    if detached is not None:
        data_path, offset = _one_data_file(path, detached), 0
        if data_path is None:
            return  # a file list or pattern (SimpleITK's business), or missing
    else:
        data_path = path
    available = _data_bytes(data_path, offset, compression)
    if available is None or available == expected:
        return
    if available > expected:
        raise EMRegError(f"{path}: cannot read CT (the file holds {available - expected} voxel bytes more than its "
                         f"header's size {list(info.GetSize())} needs ({expected} bytes): the header does not "
                         f"describe the data)")
    raise EMRegError(f"{path}: cannot read CT (file is truncated: {available} of {expected} voxel bytes)")


def detached_data_file(path: str | os.PathLike[str]) -> Path | None:
    """The file holding the voxels of a detached header (NRRD ``data file``, MetaImage ``ElementDataFile``, the
    ``.img`` beside an Analyze / NIfTI ``.hdr``) when it is one existing file; None for an image in one file."""
    path = Path(path)
    name = path.name.lower()
    if name.endswith(".hdr"):
        data = path.with_name(path.name[:-4] + (".IMG" if path.name.endswith(".HDR") else ".img"))
        return data if data.is_file() else None
    header = _header_fields(path) if name.endswith((".nhdr", ".mhd")) else None
    if header is None:
        return None
    fields = header[1]
    detached = fields.get("data file", fields.get("datafile", fields.get("ElementDataFile")))
    return None if detached is None or detached == "LOCAL" else _one_data_file(path, detached)


def _one_data_file(header: Path, detached: str) -> Path | None:
    """The data file a header names, when it names one that exists (not a list or a pattern of files)."""
    if " " in detached.strip() or "%" in detached or detached.upper().startswith("LIST"):
        return None
    data = header.parent / detached
    return data if data.is_file() else None


def _data_bytes(path: Path, offset: int, compression: str) -> int | None:
    """The voxel bytes stored from ``offset`` (inflated when compressed), or ``None`` when undecidable."""
    import zlib

    if compression == "raw":
        return path.stat().st_size - offset
    total = 0
    with path.open("rb") as stream:
        stream.seek(offset)
        inflater = zlib.decompressobj(47)  # gzip or zlib, detected from the stream
        try:
            while True:
                chunk = inflater.unconsumed_tail or stream.read(_CHUNK_BYTES)
                if not chunk:
                    return total
                total += len(inflater.decompress(chunk, _MAX_OUT_BYTES))
                if inflater.eof:
                    rest = inflater.unused_data + stream.read(_CHUNK_BYTES)
                    if not rest:
                        return total
                    inflater = zlib.decompressobj(47)  # another gzip member
                    total += len(inflater.decompress(rest, _MAX_OUT_BYTES))
        except zlib.error:
            return None  # corrupt: SimpleITK's read reports it
