"""Reading a DICOM CT series chosen by :mod:`.dicom_series`: its slices decoded in parallel into a
:class:`~EMRegModule.io.ct_handle.CTHandle`, announced in order as they are in, so that detection works on them
meanwhile.

Uncompressed 16-bit greyscale slices are read whole (one read, which also gives their sha256) and converted by
numpy straight into the volume; every other transfer syntax is decoded by GDCM through SimpleITK, a run of
consecutive slices per ``ImageSeriesReader`` call, the rescale slope/intercept of each slice applied. The volume is
allocated while the folder's headers are read (a SimpleITK image), or, for a caller that needs the voxels only
while it works on them, is fresh anonymous memory that only the slices' decoding touches. A multi-frame file is
decoded whole by GDCM.

Frames: the voxels are numpy (k, j, i); the geometry (LPS mm) is the series' (:class:`.dicom_series.DicomSeries`),
as SimpleITK's ``ImageSeriesReader`` gives it.
"""

from __future__ import annotations

import hashlib
import math
import os
import threading
import warnings
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from ..errors import EMRegError
from ..provenance import BackgroundHash, Digest, file_sha256, folder_members, folder_sha256
from .ct_handle import CTGeometry, CTHandle, writable_bytes
from .dicom_series import DicomSeries, SliceHeader, choose_series, scan_series, series_record
from .itk_messages import quiet_itk
from .pixel_types import FLOAT32, FLOATS, INT16, INT32, NAMES, NUMPY_NAMES, UINT16
from .read_process import can_fork_reader, fork_reader

if TYPE_CHECKING:  # SimpleITK is imported where an image is made or GDCM decodes: an uncompressed series read
    import SimpleITK as sitk  # into numpy memory (emreg detect) needs none (its library takes 50 ms of CPU to load)

# The threads that run SimpleITK (the read, the early allocation) are no daemons. A daemon thread still inside
# SimpleITK (a volume being allocated, a slice decoded) when the interpreter exits, e.g. right after a one-line
# refusal, is ended by the interpreter from within that C++ code: the process then dies of SIGABRT ("FATAL:
# exception not rethrown") or SIGSEGV instead of exiting 2. The interpreter waits for threads that are no
# daemons before it exits; these end soon (an allocation within a second, a cancelled read at its next slice).


def open_dicom_series(folder: str | os.PathLike[str], series: str | int | None = None,
                      workers: int | None = None, compact: bool = False,
                      voxels_only: bool = False) -> tuple[CTHandle, dict[str, Any]]:
    """Start reading the chosen CT series of ``folder``; its handle and its ``ct_series`` record.

    Slices are decoded on ``workers`` threads (default: the CPU count, at most 8) and announced
    in order (``wait_for_slices``). A slice GDCM cannot decode, or whose size disagrees with its
    header, ends the read with an :class:`EMRegError` naming the file. ``handle.sha256`` is the
    folder's sha256 (:func:`~EMRegModule.provenance.file_sha256`), made from each slice's bytes
    as they are read for decoding (the first ones, read while the volume is allocated, are hashed then).

    ``compact``: voxels of :func:`compact_voxel_type` (int16 where the headers allow values beyond
    it but the CT's own values, as CTs' do, fit), half the memory to fill; a slice holding a value
    beyond it ends the read with :class:`NarrowVoxelsError` (read again without ``compact``).

    ``voxels_only``: for a caller that needs the voxels only while it works on them (``emreg detect``), integer
    voxels go into anonymous memory (:meth:`CTHandle.in_anonymous_memory`: ``handle.voxels``, k, j, i;
    ``handle.image`` is only the geometry and ``result()`` None): SimpleITK fills a new image with zeros before a
    slice can be decoded into it (a pass over the whole volume, on one core, that the decoding waits for), where
    these voxels are fresh memory that only the slices' decoding touches, page by page on the workers. Where this
    process may fork (:func:`~.read_process.can_fork_reader`: the command, alone on its thread), the slices are read
    by a process of its own into memory shared with this one, so that the caller's work meanwhile (the detection
    stage's import) does not hold up the read's threads.
    """
    folder = Path(folder)
    early = None if voxels_only else _EarlyImage(compact)
    all_series = scan_series(folder, early.start if early is not None else None)
    chosen = choose_series(all_series, folder, series)
    record = series_record(chosen, all_series, folder)
    if chosen.multiframe:
        digest = BackgroundHash(folder)
        handle = CTHandle.of_image(_read_multiframe(chosen))
        handle.sha256 = digest
    else:
        pixel_type = (compact_voxel_type if compact else voxel_type)(chosen.headers)
        in_memory = voxels_only and pixel_type not in FLOATS  # float32 voxels go into an image (check_ct_image)
        in_process = in_memory and can_fork_reader()
        if in_memory:
            handle = CTHandle.in_anonymous_memory(_series_geometry(chosen, pixel_type),
                                                  np.dtype(NUMPY_NAMES[pixel_type]), shared=in_process)
        else:
            handle = CTHandle(len(chosen.headers))
        handle.sha256 = Digest()
        workers = workers or max(1, min(8, os.cpu_count() or 1))
        if in_process:  # read beside the caller's work, not sharing its interpreter lock (see read_process)
            try:
                fork_reader(handle, lambda side: _decode_series(chosen, side, pixel_type, workers, folder), folder,
                            (NarrowVoxelsError,))
            except OSError:  # the system refuses a process: threads
                in_process = False
        if not in_process:
            threading.Thread(target=_decode_series, args=(chosen, handle, pixel_type, workers, folder, early),
                             name="emreg-dicom-read").start()  # no daemon: see above
    handle.series = record
    return handle, record


class _EarlyImage:
    """The volume allocated on a thread while the rest of the folder's headers are read.

    Allocating (and so zeroing) a CT of a few hundred MB takes about as long as reading all the
    headers; it does not hold the GIL. The size is guessed from the first image read and the
    files beside it (a folder holding one series: the usual case); the image is used only when
    the chosen series has exactly that size and voxel type, and dropped otherwise.
    """

    _MAX_SLICES = 4096

    def __init__(self, compact: bool = False) -> None:
        self._thread: threading.Thread | None = None
        self._image: sitk.Image | None = None
        self._voxel_type = compact_voxel_type if compact else voxel_type

    def start(self, header: SliceHeader, count: int) -> None:
        if header.frames != 1 or header.samples != 1 or not 3 <= count <= self._MAX_SLICES \
                or header.modality.upper() != "CT" or header.rows < 1 or header.columns < 1:
            return
        size, pixel = [header.columns, header.rows, count], self._voxel_type([header])
        import SimpleITK as sitk

        def allocate() -> None:
            self._image = sitk.Image(size, pixel)

        self._thread = threading.Thread(target=allocate, name="emreg-dicom-allocate")  # no daemon (see above)
        self._thread.start()

    def allocating(self) -> bool:
        """Whether the early image is still being allocated."""
        return self._thread is not None and self._thread.is_alive()

    def take(self, series: DicomSeries) -> sitk.Image | None:
        """The early image if it fits ``series`` (size, voxel type), else None (it is let go)."""
        if self._thread is None:
            return None
        self._thread.join()
        image, self._image = self._image, None
        if image is None or series.multiframe or series.size is None or tuple(image.GetSize()) != series.size \
                or image.GetPixelID() != self._voxel_type(series.headers):
            return None
        return image


def _read_multiframe(series: DicomSeries) -> sitk.Image:
    """A multi-frame file's volume: GDCM's pixels, frames in the order along the normal, the functional groups'
    geometry (:func:`_multiframe_geometry`); GDCM's own image for a file without functional groups."""
    import SimpleITK as sitk

    path = series.headers[0].path
    check_pixel_data_length(series.headers[0], path.stat().st_size)
    if not series.frames:
        return _read_one(path)
    decoded = _read_one(path, voxel_type(series.frames))
    values = sitk.GetArrayViewFromImage(decoded)
    order = [f.frame for f in series.frames]
    image = sitk.GetImageFromArray(values[order] if order != sorted(order) else values)
    image.SetSpacing(series.spacing)
    image.SetOrigin(series.origin)
    image.SetDirection(series.direction)
    return image


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
    import io

    import pydicom

    try:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            source = io.BytesIO(bytes(data)) if data is not None else path
            value = pydicom.dcmread(source, force=True).get("PixelData")
    except Exception:  # noqa: BLE001 - pydicom raises many types for a broken file
        return None
    return None if value is None else len(value)


def _read_one(path: Path, pixel: int | None = None) -> sitk.Image:
    import SimpleITK as sitk

    reader = sitk.ImageFileReader()
    reader.SetImageIO("GDCMImageIO")
    reader.SetFileName(str(path))
    if pixel is not None:
        reader.SetOutputPixelType(pixel)
    try:
        with quiet_itk():
            return reader.Execute()
    except RuntimeError as exc:
        lines = [line.strip() for line in str(exc).splitlines() if line.strip()]
        detail = lines[-1][:160] if lines else "unreadable"
        raise EMRegError(f"{path}: cannot decode the DICOM image ({detail})") from None


class NarrowVoxelsError(Exception):
    """A slice of a ``compact`` read holds a value beyond :func:`compact_voxel_type`: read the series again
    without ``compact`` (not an input error: nothing is wrong with the file)."""


def _stored_range(header: SliceHeader) -> tuple[int, int]:
    """The values ``header``'s stored bits can hold (before its rescale)."""
    bits = min(max(header.bits_stored, 1), 32)
    return (-(1 << (bits - 1)), (1 << (bits - 1)) - 1) if header.signed else (0, (1 << bits) - 1)


def _rescaled_range(header: SliceHeader) -> tuple[float, float]:
    """The values ``header``'s slice can hold after its rescale (HU)."""
    stored = _stored_range(header)
    low, high = sorted((stored[0] * header.slope + header.intercept, stored[1] * header.slope + header.intercept))
    return low, high


def _integral(header: SliceHeader) -> bool:
    return float(header.slope).is_integer() and float(header.intercept).is_integer()


def voxel_type(headers: list[SliceHeader]) -> int:
    """The SimpleITK pixel type holding every slice's rescaled values exactly (int16 if it can)."""
    ranges = [_rescaled_range(h) for h in headers]
    low, high = min(r[0] for r in ranges), max(r[1] for r in ranges)
    if all(_integral(h) for h in headers):
        for pixel in (INT16, UINT16, INT32):
            info = np.iinfo(NUMPY_NAMES[pixel])
            if info.min <= low and high <= info.max:
                return pixel
    return FLOAT32


def compact_voxel_type(headers: list[SliceHeader]) -> int:
    """int16 where :func:`voxel_type` is int32 only because the stored bits could hold more than CT values do.

    Scanners often store 16 bits with an intercept of -1024 (unsigned: -1024 .. 64511 HU; signed:
    -33792 .. 31743), which takes int32 to hold exactly, while the CT's values (air -1000, bone a
    few thousand, metal often clipped at 3071 or at most some 30000 HU) fit int16. A compact read
    checks every slice (:class:`NarrowVoxelsError` when one does not fit).
    """
    exact = voxel_type(headers)
    if exact == INT32 and all(h.bits_allocated == 16 for h in headers):
        return INT16
    return exact


def _check_fits(values: np.ndarray, header: SliceHeader, dtype: np.dtype, stored: bool) -> None:
    """Raise :class:`NarrowVoxelsError` when some of ``values`` (the slice's stored values if ``stored``, else
    its rescaled ones) would not fit ``dtype`` once rescaled; nothing is checked where the header's range fits."""
    if dtype.kind not in "iu":
        return
    info = np.iinfo(dtype)
    low, high = _rescaled_range(header)
    if info.min <= low and high <= info.max:
        return
    if stored:  # the stored values whose rescaled values fit (slope and intercept are integers here)
        bounds = sorted(((info.min - header.intercept) / header.slope, (info.max - header.intercept) / header.slope))
        allowed, held = (math.ceil(bounds[0]), math.floor(bounds[1])), _stored_range(header)
    else:
        allowed, held = (info.min, info.max), (low, high)
    if (held[0] < allowed[0] and values.min() < allowed[0]) or (held[1] > allowed[1] and values.max() > allowed[1]):
        raise NarrowVoxelsError(f"{header.name}: values beyond {dtype.name}")


_UNCOMPRESSED = {"1.2.840.10008.1.2": "<", "1.2.840.10008.1.2.1": "<", "1.2.840.10008.1.2.2": ">"}
_PIXEL_DATA_TAG = {"<": b"\xe0\x7f\x10\x00", ">": b"\x7f\xe0\x00\x10"}
_CHUNK_SLICES = 8  # compressed slices decoded by one ImageSeriesReader call
_buffers = threading.local()


def _direct(header: SliceHeader) -> bool:
    """Whether ``header``'s slice may be an uncompressed 16-bit greyscale one that numpy reads directly."""
    return header.transfer_syntax in _UNCOMPRESSED and header.bits_allocated == 16 and header.frames == 1 \
        and header.samples == 1 and header.photometric == "MONOCHROME2" and 1 <= header.bits_stored <= 16


def _file_bytes(path: Path, hashed: bool = True) -> tuple[memoryview, bytes | None]:
    """The whole file in this thread's reusable buffer, and its sha256 (one read, no allocation per slice; None
    unless ``hashed``).

    Read with the operating system's calls themselves (open, fstat, one read asking one byte more than the file
    holds, close): each call lets go of the GIL and must take it back, which costs up to a switch interval (5 ms)
    while the detection stage's import holds it, so a slice is read with as few as it takes."""
    try:
        descriptor = os.open(path, os.O_RDONLY | getattr(os, "O_CLOEXEC", 0))
    except OSError as exc:
        raise EMRegError(f"{path}: cannot read ({exc.strerror})") from None
    try:
        size = os.fstat(descriptor).st_size
        buffer = getattr(_buffers, "buffer", None)
        if buffer is None or len(buffer) <= size:
            buffer = _buffers.buffer = bytearray(max(size + 1, 1 << 20))
        view = memoryview(buffer)[:size + 1]
        filled = 0
        while filled <= size:
            count = os.readv(descriptor, [view[filled:]])
            if not count:
                break  # the end, before the size fstat gave
            filled += count
            if filled == size:
                break  # all of it: a read asked for one byte more stops short only at a regular file's end
        if filled > size:
            raise EMRegError(f"{path}: the file grew while it was read")
    except OSError as exc:
        raise EMRegError(f"{path}: cannot read ({exc.strerror})") from None
    finally:
        os.close(descriptor)
    view = view[:filled]
    return view, hashlib.sha256(view).digest() if hashed else None


def _read_uncompressed(header: SliceHeader, data: memoryview, out: np.ndarray) -> bool:
    """Decode an uncompressed 16-bit slice from its file's bytes into ``out`` (HU after its rescale); False if
    not that simple; :class:`NarrowVoxelsError` when its values do not fit ``out``'s type.

    Taken only when the file ends with its Pixel Data element (checked from its tag) holding
    exactly rows x columns 16-bit values of a MONOCHROME2 image; the stored bits are masked
    (unsigned) or sign-extended (signed) as DICOM defines, then the slice's own slope and
    intercept applied. Anything else is decoded by GDCM. The tests compare both with
    ``SimpleITK.ImageSeriesReader``.
    """
    if not _direct(header):
        return False
    order = _UNCOMPRESSED[header.transfer_syntax]
    count = header.rows * header.columns
    explicit = header.transfer_syntax != "1.2.840.10008.1.2"
    start = len(data) - 2 * count
    element = bytes(data[start - (12 if explicit else 8):start]) if start >= 12 else b""
    if len(element) < 8:
        return False
    length = int.from_bytes(element[-4:], "little" if order == "<" else "big")
    if element[:4] != _PIXEL_DATA_TAG[order] or length != 2 * count \
            or (explicit and element[4:6] not in (b"OW", b"OB")):
        return False
    stored = np.frombuffer(data, dtype=np.dtype("i2" if header.signed else "u2").newbyteorder(order), count=count,
                           offset=start)
    stored = stored.astype(stored.dtype.newbyteorder("="), copy=False).reshape(header.rows, header.columns)
    unused = 16 - header.bits_stored
    if unused and header.signed:
        stored = (stored << unused) >> unused  # sign-extend the stored bits
    elif unused:
        stored = stored & ((1 << header.bits_stored) - 1)
    _check_fits(stored, header, out.dtype, stored=True)
    if header.slope == 1.0 and out.dtype.kind in "iu" and float(header.intercept).is_integer():
        if out.dtype.itemsize == 2:
            # modulo 2**16 in the output's own type: the same bits as int32 sums cast to it, one pass
            intercept = np.array(int(header.intercept) % 65536, dtype=np.uint16).view(out.dtype)
            np.add(stored.view(out.dtype), intercept, out=out)
        else:
            np.add(stored, np.int32(header.intercept), out=out, casting="unsafe")  # int32 sums, then the output type
    else:
        np.copyto(out, stored * np.float32(header.slope) + np.float32(header.intercept), casting="unsafe")
    return True


def _slice_tasks(headers: list[SliceHeader]) -> list[tuple[int, int]]:
    """Runs of slices decoded by one task: one uncompressed slice, or up to ``_CHUNK_SLICES`` compressed ones."""
    tasks: list[tuple[int, int]] = []
    k = 0
    while k < len(headers):
        stop = k + 1
        if not _direct(headers[k]):
            while stop < len(headers) and stop - k < _CHUNK_SLICES and not _direct(headers[stop]):
                stop += 1
        tasks.append((k, stop))
        k = stop
    return tasks


def _series_geometry(series: DicomSeries, pixel_type: int) -> CTGeometry:
    """The geometry of ``series``' volume of ``pixel_type`` voxels as the image SimpleITK would hold them gives it,
    without the image (nor SimpleITK): ITK keeps the spacing, origin and direction it is given, number for number
    (the tests compare both)."""
    return CTGeometry(tuple(int(n) for n in series.size), tuple(float(v) for v in series.spacing),
                      tuple(float(v) for v in series.origin), tuple(float(v) for v in series.direction), pixel_type,
                      3, 1, NAMES[pixel_type])


def _decode_series(series: DicomSeries, handle: CTHandle, pixel_type: int, workers: int, folder: Path,
                   early: _EarlyImage | None = None) -> None:
    """The reading thread: allocate the volume of ``pixel_type`` voxels (or take the ``early`` image) unless the
    handle holds its voxels already, decode slices on a pool, announce the in-order prefix, then the sha256.

    Uncompressed slices are read whole (one read, which also gives their sha256) and converted by
    numpy; compressed ones are decoded by GDCM, a run of consecutive slices per
    ``SimpleITK.ImageSeriesReader`` call (one header parse per file fewer than ``ImageFileReader``,
    and SimpleITK releases the GIL, so the workers decode in parallel).
    """
    digests: dict[str, bytes] = {}
    names = {h.path: _relative(h.path, folder) for h in series.headers}
    pool = ThreadPoolExecutor(max_workers=workers, thread_name_prefix="emreg-dicom-decode")
    try:
        if early is not None:
            _hash_while_allocating(series.headers, early, pool, workers, names, digests)
        voxels = handle.voxels if handle.provided else _allocate(series, handle, pixel_type, early)
        expected = (series.size[1], series.size[0])
        pixel = voxel_type(series.headers)  # GDCM's output, checked where it is narrowed to the image's type

        def decode(start: int, stop: int) -> None:
            if handle.cancelled:
                return
            headers = series.headers[start:stop]
            direct = False
            for k, header in enumerate(headers, start):
                hashed = names[header.path] not in digests
                data, digest = _file_bytes(header.path, hashed)
                if hashed:
                    digests[names[header.path]] = digest
                check_pixel_data_length(header, len(data), data)
                if stop - start == 1:
                    direct = _read_uncompressed(header, data, voxels[k])
            if not direct:
                _decode_gdcm(headers, voxels[start:stop], expected, pixel)

        with pool:
            tasks = _slice_tasks(series.headers)
            futures = [pool.submit(decode, start, stop) for start, stop in tasks]
            try:
                for k, ((_, stop), future) in enumerate(zip(tasks, futures, strict=True)):
                    future.result()
                    if handle.cancelled:
                        raise EMRegError(f"{series.headers[0].path.parent}: reading the CT was cancelled")
                    if k + 1 == len(futures) or not futures[k + 1].done():
                        # the slices in order so far, told once before waiting for the next: a reader waiting
                        # for slices is woken (and takes the GIL) once per run of them, not once per slice
                        handle.announce(stop)
            except BaseException:
                for future in futures:
                    future.cancel()
                raise
            _finish_digest(handle, folder, digests, pool)
    except BaseException as exc:  # handed to the waiting thread
        pool.shutdown(cancel_futures=True)
        if not handle.sha256.done():
            handle.sha256.fail(exc)
        handle.finish(exc)
    else:
        handle.finish()


def _allocate(series: DicomSeries, handle: CTHandle, pixel_type: int, early: _EarlyImage | None) -> np.ndarray:
    """The SimpleITK image of ``series``' volume (the ``early`` one if it fits), provided to ``handle``; its
    voxels (k, j, i) as a writable array."""
    import SimpleITK as sitk

    image = early.take(series) if early is not None else None  # allocated while the headers were read
    if image is None:
        image = sitk.Image(list(series.size), pixel_type)
    image.SetSpacing(series.spacing)
    image.SetOrigin(series.origin)
    image.SetDirection(series.direction)
    raw = writable_bytes(image)
    handle.provide(image=image)
    view = handle.array
    return raw.view(view.dtype).reshape(view.shape)


def _hash_while_allocating(headers: list[SliceHeader], early: _EarlyImage, pool: ThreadPoolExecutor, workers: int,
                           names: dict[Path, str | None], digests: dict[str | None, bytes]) -> None:
    """While the early volume is being allocated (zeroed, which keeps one core busy without the GIL), hash the
    first slices' files on the pool into ``digests``: the decoding, which waits for the volume, then reads them
    without hashing them (the slices' sha256 is the largest share of an uncompressed series' CPU)."""
    k, width = 0, max(1, workers - 1)  # a core is zeroing the volume
    while k < len(headers) and early.allocating():
        batch = headers[k:k + width]
        for header, digest in zip(batch, pool.map(lambda h: _file_bytes(h.path)[1], batch), strict=True):
            digests[names[header.path]] = digest
        k += len(batch)


def _decode_gdcm(headers: list[SliceHeader], out: np.ndarray, expected: tuple[int, int], pixel: int) -> None:
    """Decode consecutive slices with GDCM as ``pixel`` into ``out`` (one ImageSeriesReader call; file by file on
    an error, to name the file); :class:`NarrowVoxelsError` when a slice's values do not fit ``out``'s type."""
    import SimpleITK as sitk

    if len(headers) > 1:
        reader = sitk.ImageSeriesReader()
        reader.SetImageIO("GDCMImageIO")
        reader.SetFileNames([str(h.path) for h in headers])
        reader.SetOutputPixelType(pixel)
        reader.SetNumberOfThreads(1)  # the pool's workers are the parallelism
        try:
            with quiet_itk():
                chunk = reader.Execute()
        except RuntimeError:
            chunk = None  # one of the files is bad: decoded one by one below, which names it
        if chunk is not None and chunk.GetNumberOfComponentsPerPixel() == 1:
            values = sitk.GetArrayViewFromImage(chunk)
            if values.shape == (len(headers), *expected):
                for header, slice_values in zip(headers, values, strict=True):
                    _check_fits(slice_values, header, out.dtype, stored=False)
                np.copyto(out, values, casting="unsafe")
                return
    for k, header in enumerate(headers):
        slice_image = _read_one(header.path, pixel)
        values = sitk.GetArrayViewFromImage(slice_image)
        values = values.reshape(values.shape[-2:]) if values.ndim == 3 and values.shape[0] == 1 else values
        if values.shape != expected or slice_image.GetNumberOfComponentsPerPixel() != 1:
            raise EMRegError(f"{header.path}: the decoded image ({values.shape[-1]}x{values.shape[-2]}) disagrees "
                             f"with its header ({expected[1]}x{expected[0]})")
        _check_fits(values, header, out.dtype, stored=False)
        np.copyto(out[k], values, casting="unsafe")


def _relative(path: Path, folder: Path) -> str | None:
    try:
        return path.relative_to(folder).as_posix()
    except ValueError:
        return None


def _finish_digest(handle: CTHandle, folder: Path, digests: dict[str, bytes], pool: ThreadPoolExecutor) -> None:
    """``handle.sha256``: the folder's, from the slices' sha256 and those of its other files (hashed on ``pool``)."""
    try:
        members = folder_members(folder)
        others = [(name, path) for name, path in members if name not in digests]
        hashes = pool.map(lambda item: bytes.fromhex(file_sha256(item[1])), others)
        hashed = dict(zip([name for name, _ in others], hashes, strict=True))
        covered = {name: digests[name] for name, _ in members if name in digests}
        handle.sha256.set(folder_sha256({**covered, **hashed}))
    except Exception as exc:  # noqa: BLE001 - the CT is read; its provenance hash is asked again later
        handle.sha256.fail(exc)
