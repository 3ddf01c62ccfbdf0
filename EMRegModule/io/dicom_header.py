"""A quick reader of the few DICOM header elements series choice needs (little endian files only).

Scanning a hospital export reads the header of every file; pydicom builds a full dataset for
each (about 1-2 ms a file, most of it converting values). Here the file's first 64 KB are walked
element by element and only the elements :mod:`.dicom_series` uses are kept, as text or
numbers, top level only (sequences are skipped). Anything unusual (no preamble, big endian,
deflate, a header longer than the buffer, a malformed element) returns ``None`` and the caller
reads the file with pydicom; the tests compare both on every transfer syntax they make.
"""

from __future__ import annotations

import os
import struct
from pathlib import Path
from typing import Any

_HEAD_BYTES = 1 << 16
_FIRST_BYTES = 1 << 13  # read first: the whole header of the usual slice (its file meta and image tags)
_PIXEL_DATA = (0x7FE0, 0x0010)
_LONG_VRS = {b"OB", b"OW", b"OF", b"SQ", b"UT", b"UN", b"UC", b"UR", b"OD", b"OL", b"OV", b"SV", b"UV"}
_IMPLICIT_LE = "1.2.840.10008.1.2"
_NOT_PLAIN_LE = {"1.2.840.10008.1.2.2", "1.2.840.10008.1.2.1.99"}  # big endian, deflate
_UNDEFINED = 0xFFFFFFFF

#: The elements kept: (group, element) -> (pydicom keyword, kind); kind "us" = unsigned short.
WANTED = {
    (0x0008, 0x0008): ("ImageType", "text"), (0x0008, 0x0016): ("SOPClassUID", "text"),
    (0x0008, 0x0060): ("Modality", "text"), (0x0008, 0x103E): ("SeriesDescription", "text"),
    (0x0020, 0x000E): ("SeriesInstanceUID", "text"), (0x0020, 0x0011): ("SeriesNumber", "text"),
    (0x0020, 0x0013): ("InstanceNumber", "text"), (0x0020, 0x0032): ("ImagePositionPatient", "text"),
    (0x0020, 0x0037): ("ImageOrientationPatient", "text"), (0x0028, 0x0002): ("SamplesPerPixel", "us"),
    (0x0028, 0x0004): ("PhotometricInterpretation", "text"), (0x0028, 0x0008): ("NumberOfFrames", "text"),
    (0x0028, 0x0010): ("Rows", "us"), (0x0028, 0x0011): ("Columns", "us"), (0x0028, 0x0030): ("PixelSpacing", "text"),
    (0x0028, 0x0100): ("BitsAllocated", "us"), (0x0028, 0x0101): ("BitsStored", "us"),
    (0x0028, 0x0103): ("PixelRepresentation", "us"), (0x0028, 0x1052): ("RescaleIntercept", "text"),
    (0x0028, 0x1053): ("RescaleSlope", "text"),
}


#: The key of ``quick_header``'s values holding where Pixel Data's value starts in the file and its declared
#: length (None: undefined, an encapsulated, compressed image).
PIXEL_DATA = "PixelData"


class _UnusualError(Exception):
    """Something this reader does not handle: the caller falls back to pydicom."""


def quick_header(path: Path) -> tuple[str, dict[str, Any]] | None:
    """(transfer syntax UID, {keyword: value}) of a plain little-endian DICOM file, or None.

    Values are strings (multi-valued ones split at ``\\``, a list) or ints for unsigned shorts, and
    ``values[PIXEL_DATA]`` = (offset of the Pixel Data value, its declared length or None when undefined);
    None also for a file that has a DICOMDIR's records or no Pixel Data within the first 64 KB.

    The first :data:`_FIRST_BYTES` are walked first (a CT slice's header fits in them); only a walk they do not
    finish is made again over the first 64 KB, with the same result a walk of those would have given at once.
    """
    # the operating system's calls themselves: each lets go of the GIL and takes it back, which can wait a switch
    # interval (5 ms) while another thread holds it (the detection stage's import, during a folder scan)
    descriptor = os.open(path, os.O_RDONLY | getattr(os, "O_CLOEXEC", 0))
    try:
        head = _read_up_to(descriptor, _FIRST_BYTES)
        if len(head) < _FIRST_BYTES:
            return _parsed(head, whole=True)
        found = _parsed(head, whole=False)
        if found is not None:
            return found
        head += _read_up_to(descriptor, _HEAD_BYTES - _FIRST_BYTES)
        whole = len(head) < _HEAD_BYTES or not os.read(descriptor, 1)
    finally:
        os.close(descriptor)
    return _parsed(head, whole)


def _read_up_to(descriptor: int, count: int) -> bytes:
    """``count`` bytes from ``descriptor``, fewer only at the file's end (as a buffered read gives them)."""
    data = os.read(descriptor, count)
    while 0 < len(data) < count:
        more = os.read(descriptor, count - len(data))
        if not more:
            break
        data += more
    return data


def _parsed(head: bytes, whole: bool) -> tuple[str, dict[str, Any]] | None:
    """:func:`quick_header` of a file's first bytes ``head`` (``whole``: all of the file)."""
    try:
        if len(head) < 132 or head[128:132] != b"DICM":
            return None
        syntax, position = _meta(head)
        if syntax in _NOT_PLAIN_LE:
            return None
        values = _dataset(head, position, syntax == _IMPLICIT_LE, whole)
    except (_UnusualError, struct.error, UnicodeDecodeError, IndexError, ValueError):
        return None
    return syntax, values


def _meta(head: bytes) -> tuple[str, int]:
    """The transfer syntax and where the dataset starts (file meta: explicit VR little endian)."""
    position, syntax = 132, None
    while position + 8 <= len(head):
        group, element = struct.unpack_from("<HH", head, position)
        if group != 0x0002:
            break
        value, position = _explicit_element(head, position)
        if element == 0x0010:
            syntax = value.rstrip(b"\0 ").decode("ascii")
    if syntax is None:
        raise _UnusualError("no transfer syntax")
    return syntax, position


def _explicit_element(head: bytes, position: int) -> tuple[bytes, int]:
    length, start = _element_length(head, position, implicit=False)
    if length == _UNDEFINED:
        raise _UnusualError("undefined length in the file meta")
    return head[start:start + length], start + length


#: The tags of :data:`WANTED`, of Pixel Data and of a DICOMDIR's records as one little-endian 32-bit number each
#: (group in the low half, element in the high half: how the tag's four bytes read as one unsigned int).
_WANTED_BY_TAG = {group | element << 16: wanted for (group, element), wanted in WANTED.items()}
_PIXEL_DATA_TAG = _PIXEL_DATA[0] | _PIXEL_DATA[1] << 16
_DIRECTORY_RECORDS_TAG = 0x0004 | 0x1220 << 16
_IMPLICIT_HEAD = struct.Struct("<II")  # tag, value length
_EXPLICIT_HEAD = struct.Struct("<I2sH")  # tag, VR, 16-bit value length
_U32 = struct.Struct("<I")
_U16 = struct.Struct("<H")


def _dataset(head: bytes, position: int, implicit: bool, whole: bool) -> dict[str, Any]:
    """The :data:`WANTED` values of the dataset from ``position`` to Pixel Data (see :func:`quick_header`): one
    unpack per element header (the walk is most of a folder scan's time)."""
    values: dict[str, Any] = {}
    size = len(head)
    while True:
        if position + 8 > size:
            if whole:
                return values  # no pixel data: not an image (the caller says so)
            raise _UnusualError("header longer than the buffer")
        if implicit:
            tag, length = _IMPLICIT_HEAD.unpack_from(head, position)
            start = position + 8
        else:
            tag, vr, length = _EXPLICIT_HEAD.unpack_from(head, position)
            if vr in _LONG_VRS:
                (length,) = _U32.unpack_from(head, position + 8)
                start = position + 12
            else:
                start = position + 8
        if tag == _PIXEL_DATA_TAG:
            values[PIXEL_DATA] = (start, None if length == _UNDEFINED else length)
            return values
        if tag == _DIRECTORY_RECORDS_TAG:
            raise _UnusualError("a DICOMDIR")
        if length == _UNDEFINED:
            position = _skip_undefined(head, start, implicit)
            continue
        end = start + length
        if end > size:
            raise _UnusualError("element past the buffer")
        wanted = _WANTED_BY_TAG.get(tag)
        if wanted is not None:
            keyword, kind = wanted
            if kind == "us":
                if length != 2:
                    raise _UnusualError(f"{keyword} is not one unsigned short")
                values[keyword] = _U16.unpack_from(head, start)[0]
            else:
                text = head[start:end].decode("latin-1").rstrip("\0 ").strip()
                parts = [p.strip() for p in text.split("\\")]
                values[keyword] = parts if len(parts) > 1 else text
        position = end


def _element_length(head: bytes, position: int, implicit: bool) -> tuple[int, int]:
    """(value length, value start) of the element whose tag is at ``position`` (little endian)."""
    if implicit:
        return struct.unpack_from("<I", head, position + 4)[0], position + 8
    if head[position + 4:position + 6] in _LONG_VRS:
        return struct.unpack_from("<I", head, position + 8)[0], position + 12
    return struct.unpack_from("<H", head, position + 6)[0], position + 8


def _skip_undefined(head: bytes, position: int, implicit: bool) -> int:
    """Past a sequence (or item) of undefined length starting at ``position``: its items, to the delimiter."""
    while position + 8 <= len(head):
        group, element = struct.unpack_from("<HH", head, position)
        (length,) = struct.unpack_from("<I", head, position + 4)
        if (group, element) == (0xFFFE, 0xE0DD):  # sequence delimiter
            return position + 8
        if (group, element) != (0xFFFE, 0xE000):
            raise _UnusualError("no item in a sequence")
        position += 8
        if length != _UNDEFINED:
            position += length
            continue
        while True:  # an item of undefined length: its elements, to the item delimiter
            if position + 8 > len(head):
                raise _UnusualError("item past the buffer")
            group, element = struct.unpack_from("<HH", head, position)
            if (group, element) == (0xFFFE, 0xE00D):
                position += 8
                break
            length, start = _element_length(head, position, implicit)
            position = _skip_undefined(head, start, implicit) if length == _UNDEFINED else start + length
    raise _UnusualError("sequence past the buffer")
