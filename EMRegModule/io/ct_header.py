"""Image headers read by EMReg itself (NRRD ``.nrrd`` / ``.nhdr``, MetaImage ``.mha`` / ``.mhd``, NIfTI-1): how a file
stores its voxels, the file a detached header names, and the voxel data's length against the header's sizes.

No voxel is decoded here (the readers are :mod:`.fast_read` and SimpleITK); the geometry is always SimpleITK's
own reading of the header. Provenance (:func:`~EMRegModule.io.provenance.file_sha256`) uses
:func:`detached_data_file`, the CT checks (:mod:`.ct_checks`) :func:`nrrd_header_fields`.
"""

from __future__ import annotations

import os
import zlib
from dataclasses import dataclass
from pathlib import Path
from typing import BinaryIO

import numpy as np
import SimpleITK as sitk

from ..core.pixel_types import NUMPY_NAMES
from ..errors import EMRegError
from .itk_messages import quiet_itk

try:  # a declared dependency; without it a gzip-compressed NIfTI's layout is not read here (SimpleITK reads it)
    from isal import igzip_lib
except ImportError:  # pragma: no cover - depends on the installation
    igzip_lib = None

_CHUNK_BYTES = 1 << 22  # compressed bytes read per step
_MAX_OUT_BYTES = 1 << 20  # inflated bytes per step

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


@dataclass
class VoxelStorage:
    """Where and how a file keeps its voxels (the geometry comes from SimpleITK's own header reading)."""

    dtype: np.dtype  # with its byte order
    data_offset: int  # bytes from the start of the file, or of the inflated stream when ``whole_file``
    compression: str  # "raw", "gzip" or "zlib"
    whole_file: bool = False  # the whole file is one gzip stream (``.nii.gz``)


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


def _nrrd_storage(stream: BinaryIO) -> VoxelStorage | None:
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
    return VoxelStorage(_ordered(dtype_name, _nrrd_word(fields, "endian") == "big"), offset, compression)


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


def _mha_storage(stream: BinaryIO) -> VoxelStorage | None:
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
    return VoxelStorage(_ordered(dtype_name, big), offset, _meta_compression(fields))


def _meta_flag(fields: dict[str, str], key: str, default: bool) -> bool:
    """A MetaImage yes/no field as MetaIO (hence SimpleITK) reads it: true when its value starts with
    ``T``, ``t`` or ``1`` (``True``, ``true``, ``1``), false otherwise; ``default`` when absent."""
    value = fields.get(key)
    return default if value is None else value[:1] in ("T", "t", "1")


def _meta_compression(fields: dict[str, str]) -> str:
    return "zlib" if _meta_flag(fields, "CompressedData", False) else "raw"


def _nifti_storage(stream: BinaryIO) -> VoxelStorage | None:
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
    return VoxelStorage(_ordered(dtype_name, order == ">"), int(vox_offset), "gzip" if gzip else "raw", whole_file=gzip)


def _ordered(dtype_name: str, big_endian: bool) -> np.dtype:
    dtype = np.dtype(dtype_name)
    return dtype.newbyteorder(">" if big_endian else "<") if dtype.itemsize > 1 else dtype


#: The layouts :func:`read_storage` knows, by kind, and how their files' names end.
FILE_KINDS = {"nrrd": ".nrrd", "mha": ".mha", "nifti": (".nii", ".nii.gz")}
_STORAGE_READERS = {"nrrd": _nrrd_storage, "mha": _mha_storage, "nifti": _nifti_storage}


def read_storage(kind: str, stream: BinaryIO) -> VoxelStorage | None:
    """How a file of ``kind`` (:data:`FILE_KINDS`; ``stream`` at its start) stores its voxels, when it keeps them
    in the same file without skips or scaling; None for anything else (SimpleITK then reads it)."""
    if kind == "nifti" and igzip_lib is None:
        return None
    return _STORAGE_READERS[kind](stream)


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
    dtype_name = NUMPY_NAMES.get(info.GetPixelID())
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
