"""Native (uncompressed) DICOM pixels: whether a slice's Pixel Data holds all its image, and its stored 16-bit values
as voxels of a volume's type (the bits masked or sign-extended, the rescale applied), as GDCM gives them through
SimpleITK. Shared by the whole read of a series (:mod:`.dicom_read`) and its slices indexed in their files
(:mod:`.dicom_slices`)."""

from __future__ import annotations

import io
import math
import warnings
from pathlib import Path

import numpy as np

from ..errors import EMRegError
from .dicom_series import SliceHeader

#: Uncompressed transfer syntaxes and the byte order of their values.
UNCOMPRESSED = {"1.2.840.10008.1.2": "<", "1.2.840.10008.1.2.1": "<", "1.2.840.10008.1.2.2": ">"}


def native_16bit(header: SliceHeader) -> bool:
    """Whether ``header``'s slice may be an uncompressed 16-bit greyscale one that numpy reads directly."""
    return header.transfer_syntax in UNCOMPRESSED and header.bits_allocated == 16 and header.frames == 1 \
        and header.samples == 1 and header.photometric == "MONOCHROME2" and 1 <= header.bits_stored <= 16


#: Transfer syntaxes whose Pixel Data is the pixels themselves (not encapsulated): uncompressed, or deflated as a
#: whole dataset.
_NATIVE_PIXELS = {"1.2.840.10008.1.2", "1.2.840.10008.1.2.1", "1.2.840.10008.1.2.2", "1.2.840.10008.1.2.1.99"}


def check_pixel_data_length(header: SliceHeader, file_size: int, data: bytes | memoryview | None = None) -> None:
    """Refuse a file whose native Pixel Data holds fewer bytes than its image needs (rows x columns x frames x
    samples x bits allocated), declared so or cut off by the file's end: GDCM decodes such a slice without an
    error, its missing pixels made of whatever memory follows. ``data``: the file's bytes, if read already.

    The quick header walk gives where Pixel Data starts and its declared length; a header pydicom read (big
    endian, deflate, no preamble) is measured by pydicom from the file's bytes. An undefined length (an
    encapsulated, compressed image: its decoder finds a short stream) is not checked."""
    if header.pixel_data is not None:
        start, declared = header.pixel_data
        if declared is None:
            return
        held = max(0, min(declared, file_size - start))
    elif header.transfer_syntax in _NATIVE_PIXELS:
        held = _pixel_bytes_by_pydicom(header.path, data)
        if held is None:
            return
    else:
        return
    pixels = header.rows * header.columns * header.frames * header.samples
    needed = (pixels * header.bits_allocated + 7) // 8
    if held < needed:
        raise EMRegError(f"{header.path}: DICOM pixel data is cut short: {held} bytes where its {header.columns}x"
                         f"{header.rows} image of {header.bits_allocated}-bit pixels"
                         f"{f' x {header.frames} frames' if header.frames > 1 else ''} needs {needed}; export the "
                         "series again")


def _pixel_bytes_by_pydicom(path: Path, data: bytes | memoryview | None) -> int | None:
    """The bytes of ``path``'s Pixel Data value as pydicom reads them (``data``: the file's bytes, if read), or
    None when pydicom finds none (or cannot read the file: GDCM's decoding then says why)."""
    import pydicom

    try:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            source = io.BytesIO(bytes(data)) if data is not None else path
            value = pydicom.dcmread(source, force=True).get("PixelData")
    except Exception:  # noqa: BLE001 - pydicom raises many types for a broken file
        return None
    return None if value is None else len(value)


class NarrowVoxelsError(Exception):
    """A slice of a ``compact`` read holds a value beyond :func:`compact_voxel_type`: read the series again
    without ``compact`` (not an input error: nothing is wrong with the file)."""


def _stored_range(header: SliceHeader) -> tuple[int, int]:
    """The values ``header``'s stored bits can hold (before its rescale)."""
    bits = min(max(header.bits_stored, 1), 32)
    return (-(1 << (bits - 1)), (1 << (bits - 1)) - 1) if header.signed else (0, (1 << bits) - 1)


def rescaled_range(header: SliceHeader) -> tuple[float, float]:
    """The values ``header``'s slice can hold after its rescale (HU)."""
    stored = _stored_range(header)
    low, high = sorted((stored[0] * header.slope + header.intercept, stored[1] * header.slope + header.intercept))
    return low, high


def check_fits(values: np.ndarray, header: SliceHeader, dtype: np.dtype, stored: bool) -> None:
    """Raise :class:`NarrowVoxelsError` when some of ``values`` (the slice's stored values if ``stored``, else
    its rescaled ones) would not fit ``dtype`` once rescaled; nothing is checked where the header's range fits."""
    if dtype.kind not in "iu":
        return
    info = np.iinfo(dtype)
    low, high = rescaled_range(header)
    if info.min <= low and high <= info.max:
        return
    if stored:  # the stored values whose rescaled values fit (slope and intercept are integers here)
        bounds = sorted(((info.min - header.intercept) / header.slope, (info.max - header.intercept) / header.slope))
        allowed, held = (math.ceil(bounds[0]), math.floor(bounds[1])), _stored_range(header)
    else:
        allowed, held = (info.min, info.max), (low, high)
    if (held[0] < allowed[0] and values.min() < allowed[0]) or (held[1] > allowed[1] and values.max() > allowed[1]):
        raise NarrowVoxelsError(f"{header.name}: values beyond {dtype.name}")


def stored_dtype(header: SliceHeader) -> np.dtype:
    """The type of ``header``'s stored 16-bit values in its file (:func:`native_16bit` slices): signed or not, in
    its transfer syntax's byte order."""
    return np.dtype("i2" if header.signed else "u2").newbyteorder(UNCOMPRESSED[header.transfer_syntax])


def stored_to_voxels(stored: np.ndarray, header: SliceHeader, out: np.ndarray) -> None:
    """``header``'s slice's stored 16-bit values (any part of it, in the file's byte order) as voxels of ``out``'s
    type into ``out``: the stored bits masked (unsigned) or sign-extended (signed) as DICOM defines, then the slice's
    own slope and intercept applied; :class:`NarrowVoxelsError` when the values do not fit ``out``'s type."""
    stored = stored.astype(stored.dtype.newbyteorder("="), copy=False)
    unused = 16 - header.bits_stored
    if unused and header.signed:
        stored = (stored << unused) >> unused  # sign-extend the stored bits
    elif unused:
        stored = stored & ((1 << header.bits_stored) - 1)
    check_fits(stored, header, out.dtype, stored=True)
    if header.slope == 1.0 and out.dtype.kind in "iu" and float(header.intercept).is_integer():
        if out.dtype.itemsize == 2:
            # modulo 2**16 in the output's own type: the same bits as int32 sums cast to it, one pass
            intercept = np.array(int(header.intercept) % 65536, dtype=np.uint16).view(out.dtype)
            np.add(stored.view(out.dtype), intercept, out=out)
        else:
            np.add(stored, np.int32(header.intercept), out=out, casting="unsafe")  # int32 sums, then the output type
    else:
        np.copyto(out, stored * np.float32(header.slope) + np.float32(header.intercept), casting="unsafe")
