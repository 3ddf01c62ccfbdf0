"""DICOM CT exports as hospitals hand them over: find the series, choose the CT volume, read it in parallel.

A CT folder (``ct/`` of a case, or any folder given to ``emreg detect``) may hold several series
(the volume, a scout/topogram, a thick reconstruction, dose reports...), in subfolders, with or
without a ``DICOMDIR``. :func:`scan_series` reads the headers only (pydicom, no pixel data) and
groups the files by Series Instance UID; :func:`choose_series` keeps the CT volumes (modality CT,
3 or more slices, not a ``LOCALIZER``, greyscale and not MONOCHROME1, one consistent, evenly
spaced, untilted geometry) and picks the one best for marker detection: finest slice spacing, then
finest in-plane spacing, then most slices. Two equally good candidates of different geometry
are an error listing both (never a silent guess); ``series=UID|NUMBER`` (``--series``,
``[ct] series``) forces a choice.

:func:`open_dicom_series` allocates the image from the headers' geometry and decodes the slices
on a thread pool (GDCM through SimpleITK, one file per task: every transfer syntax GDCM knows,
the rescale slope/intercept of each slice applied), announcing the slices in order as they are
in (:class:`~EMRegModule.io.fast_read.VolumeFill`), so that detection works on them meanwhile.

Geometry (LPS, as SimpleITK's ``ImageSeriesReader`` gives it): direction columns are the row
cosine, the column cosine and their cross product; slices are ordered along that normal; the
origin is the first slice's Image Position (Patient). Slices sheared against their plane (gantry
tilt) are refused with the tilt angle: EMReg never resamples a CT silently.
"""

from __future__ import annotations

import hashlib
import math
import mmap
import os
import threading
import warnings
from collections.abc import Callable, Iterable
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any

import numpy as np
import SimpleITK as sitk

from ..errors import EMRegError
from ..provenance import BackgroundHash, Digest, file_sha256, folder_members, folder_sha256
from .ct_stream import _HUGE_PAGE_BYTES, FixedGeometry
from .dicom_header import PIXEL_DATA, quick_header
from .fast_read import VolumeFill, _writable_bytes
from .itk_messages import quiet_itk

_PREAMBLE_PROBE_BYTES = 1 << 16  # the header of a file without its DICM marker, read to tell whether it is an image
_LOCALIZER_TYPES = {"LOCALIZER", "SCOUT", "TOPOGRAM", "SURVIEW", "SCANOGRAM"}
_TRANSFER_SYNTAX_NAMES = {
    "1.2.840.10008.1.2": "Implicit VR Little Endian",
    "1.2.840.10008.1.2.1": "Explicit VR Little Endian",
    "1.2.840.10008.1.2.1.99": "Deflated Explicit VR Little Endian",
    "1.2.840.10008.1.2.2": "Explicit VR Big Endian",
    "1.2.840.10008.1.2.4.50": "JPEG Baseline",
    "1.2.840.10008.1.2.4.51": "JPEG Extended",
    "1.2.840.10008.1.2.4.57": "JPEG Lossless",
    "1.2.840.10008.1.2.4.70": "JPEG Lossless SV1",
    "1.2.840.10008.1.2.4.80": "JPEG-LS Lossless",
    "1.2.840.10008.1.2.4.81": "JPEG-LS Near-lossless",
    "1.2.840.10008.1.2.4.90": "JPEG 2000 Lossless",
    "1.2.840.10008.1.2.4.91": "JPEG 2000",
    "1.2.840.10008.1.2.5": "RLE Lossless",
}


@dataclass
class SliceHeader:
    """What one DICOM file says about its image (LPS mm); None where the tag is absent."""

    path: Path
    series_uid: str
    series_number: int | None
    description: str
    modality: str
    image_type: tuple[str, ...]
    sop_class: str
    transfer_syntax: str
    position: np.ndarray | None
    orientation: np.ndarray | None  # row cosine (3) then column cosine (3)
    pixel_spacing: tuple[float, float] | None  # DICOM order: between rows, between columns
    rows: int
    columns: int
    frames: int
    slope: float
    intercept: float
    bits_stored: int
    signed: bool
    samples: int
    instance: int | None
    bits_allocated: int = 16
    photometric: str = "MONOCHROME2"
    frame: int | None = None  # a frame (0-based) of a multi-frame file; None for a single-image file
    pixel_data: tuple[int, int | None] | None = None  # Pixel Data's value offset and declared length (None:
    # undefined, encapsulated); None when unknown (a header read by pydicom)

    @property
    def name(self) -> str:
        """The file's name, and the frame's number (1-based, as DICOM counts them) in a multi-frame file."""
        return self.path.name if self.frame is None else f"{self.path.name} frame {self.frame + 1}"


@dataclass
class DicomSeries:
    """One series of a DICOM folder, and whether (and why not) it is a usable CT volume.

    ``files`` are ordered along the slice normal once the geometry is known. ``problem`` is
    None for a CT volume; otherwise why it cannot be one (a scout, 2 slices, a gap...).
    """

    uid: str
    number: int | None
    description: str
    modality: str
    headers: list[SliceHeader]
    problem: str | None = None
    size: tuple[int, int, int] | None = None
    spacing: tuple[float, float, float] | None = None  # x (along rows), y, slice spacing; mm
    origin: tuple[float, float, float] | None = None
    direction: tuple[float, ...] | None = None  # 9 numbers, row-major, columns = i, j, k axes
    multiframe: bool = False
    notes: list[str] = field(default_factory=list)
    frames: list[SliceHeader] = field(default_factory=list)  # a multi-frame file's frames, ordered along the normal

    @property
    def files(self) -> list[Path]:
        return [h.path for h in self.headers]

    @property
    def transfer_syntaxes(self) -> list[str]:
        return sorted({_TRANSFER_SYNTAX_NAMES.get(h.transfer_syntax, h.transfer_syntax) for h in self.headers})

    def rank(self) -> tuple[float, float, int]:
        """Smaller is better for detection: finest slice spacing, finest in-plane spacing, most slices."""
        assert self.spacing is not None and self.size is not None
        return (round(self.spacing[2], 3), round(max(self.spacing[:2]), 3), -self.size[2])

    def label(self) -> str:
        """Short human form: number, description, UID."""
        number = "?" if self.number is None else str(self.number)
        description = f" '{self.description}'" if self.description else ""
        return f"series {number}{description} ({self.uid})"

    def to_json(self) -> dict[str, Any]:
        """The block naming this series in ``markers.json`` / ``run.json``."""
        document: dict[str, Any] = {"series_instance_uid": self.uid, "series_number": self.number,
                                    "description": self.description, "modality": self.modality,
                                    "files": len(self.headers)}
        if self.size is not None and self.spacing is not None:
            document.update({"slices": self.size[2], "slice_spacing_mm": round(self.spacing[2], 6),
                             "pixel_spacing_mm": [round(self.spacing[0], 6), round(self.spacing[1], 6)],
                             "size": list(self.size)})
        document["transfer_syntaxes"] = self.transfer_syntaxes
        if self.problem is not None:
            document["not_used_because"] = self.problem
        return document


# --- scanning ---------------------------------------------------------------------------------------


def scan_series(folder: str | os.PathLike[str],
                first_image: Callable[[SliceHeader, int], None] | None = None) -> list[DicomSeries]:
    """Every image series in ``folder``, its subfolders and its ``DICOMDIR`` (headers only).

    Files that are not DICOM are ignored; a DICOM file whose header cannot be parsed, or a
    ``DICOMDIR`` entry whose file is missing, is an :class:`EMRegError` naming the file.
    ``first_image(header, count)``, when given, is called with the first image's header and the
    number of files beside it with the same suffix, as soon as it is read.
    """
    folder = Path(folder)
    if not folder.is_dir():
        raise EMRegError(f"{folder}: DICOM folder not found")
    paths = {p.resolve(): p for p in _walk(folder)}
    for dicomdir in [p for p in paths.values() if p.name.upper() == "DICOMDIR"]:
        for referenced in _dicomdir_files(dicomdir):
            paths.setdefault(referenced.resolve(), referenced)
    groups: dict[str, list[SliceHeader]] = {}
    for path in sorted(paths.values()):
        header = read_header(path)
        if header is not None:
            groups.setdefault(header.series_uid, []).append(header)
            if first_image is not None:
                first_image(header, sum(p.parent == path.parent and p.suffix == path.suffix for p in paths.values()))
                first_image = None
    series = [_describe(uid, headers) for uid, headers in groups.items()]
    series.sort(key=lambda s: (s.number if s.number is not None else 1 << 30, s.uid))
    return series


def _walk(folder: Path) -> Iterable[Path]:
    for root, dirs, names in os.walk(folder):
        dirs[:] = sorted(d for d in dirs if not d.startswith("."))
        for name in sorted(names):
            if not name.startswith("."):
                yield Path(root) / name


def _dicomdir_files(dicomdir: Path) -> list[Path]:
    """The image files a DICOMDIR refers to; a missing one is an :class:`EMRegError`."""
    import pydicom

    try:
        document = pydicom.dcmread(dicomdir)
        records = document.DirectoryRecordSequence
    except Exception as exc:  # noqa: BLE001 - pydicom raises many types for a broken file
        raise EMRegError(f"{dicomdir}: unreadable DICOMDIR ({_short(exc)})") from None
    files = []
    for record in records:
        parts = record.get("ReferencedFileID")
        if parts is None:
            continue
        parts = [parts] if isinstance(parts, str) else list(parts)
        path = dicomdir.parent.joinpath(*parts)
        if not path.is_file():
            path = _case_insensitive(dicomdir.parent, parts)
        if path is None or not path.is_file():
            raise EMRegError(f"{dicomdir}: refers to a missing file {'/'.join(parts)}; copy the whole export")
        files.append(path)
    return files


def _case_insensitive(root: Path, parts: list[str]) -> Path | None:
    """``root/parts...`` matched without regard to case (DICOMDIR names are upper case; copies may not be)."""
    path = root
    for part in parts:
        if not path.is_dir():
            return None
        match = next((p for p in path.iterdir() if p.name.upper() == part.upper()), None)
        if match is None:
            return None
        path = match
    return path


def read_header(path: Path) -> SliceHeader | None:
    """The image header of a DICOM file, or None for a file that is not a DICOM image.

    Plain little-endian files are walked by :func:`.dicom_header.quick_header`; the others (and
    anything it finds unusual) are read by pydicom. A file with the DICOM preamble whose header
    cannot be parsed, or a DICOM image after a preamble without its ``DICM`` marker, is an
    :class:`EMRegError`.
    """
    quick = quick_header(path)
    if quick is not None:
        transfer, values = quick
        return _slice_header(path, transfer, values.get)
    import pydicom
    from pydicom.errors import InvalidDicomError

    try:
        with path.open("rb") as stream:
            head = stream.read(132)
    except OSError as exc:
        raise EMRegError(f"{path}: cannot read ({exc.strerror})") from None
    has_preamble = len(head) == 132 and head[128:132] == b"DICM"
    try:
        with warnings.catch_warnings():  # pydicom's complaints ("End of file reached...") would precede EMReg's line
            warnings.simplefilter("ignore")
            dataset = pydicom.dcmread(path, stop_before_pixels=True, force=not has_preamble)
    except InvalidDicomError:
        dataset = None
    except Exception as exc:  # noqa: BLE001 - pydicom raises many types for a broken file
        if has_preamble:
            raise EMRegError(f"{path}: unreadable DICOM file ({_short(exc)})") from None
        dataset = None
    if not has_preamble and (dataset is None or dataset.get("SeriesInstanceUID") is None):
        _refuse_preamble_without_marker(path)
    if dataset is None:
        return None
    if dataset.get("DirectoryRecordSequence"):
        return None
    transfer = str(getattr(getattr(dataset, "file_meta", None), "TransferSyntaxUID", "") or "")
    return _slice_header(path, transfer, dataset.get)


def _refuse_preamble_without_marker(path: Path) -> None:
    """An :class:`EMRegError` when ``path`` is a DICOM image after a 128-byte preamble lacking its ``DICM`` marker.

    Some exports write the preamble but neither the marker nor the file meta. GDCM does not read
    such a file (its series reader leaves it out); ignoring it as "not DICOM" would silently drop
    a slice (at the end of the stack: a shorter volume, no error), so it is named instead.
    """
    import io

    import pydicom

    try:
        with path.open("rb") as stream:
            stream.seek(128)
            head = stream.read(_PREAMBLE_PROBE_BYTES)
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            dataset = pydicom.dcmread(io.BytesIO(head), stop_before_pixels=True, force=True)
        image = dataset.get("SeriesInstanceUID") is not None and dataset.get("Rows") is not None
    except Exception:  # noqa: BLE001 - not DICOM after a preamble either: the file is no DICOM image
        return
    if image:
        raise EMRegError(f"{path}: a DICOM image with a 128-byte preamble but no 'DICM' marker (a broken export "
                         f"GDCM does not read); export the series again")


def _slice_header(path: Path, transfer: str, get: Any) -> SliceHeader | None:
    """A :class:`SliceHeader` from ``get(keyword, default)`` (pydicom's or the quick reader's values)."""
    try:
        if get("SeriesInstanceUID") is None or get("Rows") is None:
            return None  # not an image (a DICOMDIR, a report, a file that is not DICOM at all)
        return SliceHeader(
            path=path, series_uid=str(get("SeriesInstanceUID")), series_number=_int(get("SeriesNumber")),
            description=str(get("SeriesDescription", "") or "").strip(),
            modality=str(get("Modality", "") or "").strip(),
            image_type=tuple(str(v).strip().upper() for v in _list(get("ImageType"))),
            sop_class=str(get("SOPClassUID", "") or ""), transfer_syntax=transfer,
            position=_vector(get("ImagePositionPatient"), 3),
            orientation=_vector(get("ImageOrientationPatient"), 6),
            pixel_spacing=_pair(get("PixelSpacing")),
            rows=int(get("Rows")), columns=int(get("Columns", 0) or 0),
            frames=_int(get("NumberOfFrames")) or 1,
            slope=float(get("RescaleSlope", 1) or 1), intercept=float(get("RescaleIntercept", 0) or 0),
            bits_stored=int(get("BitsStored", 16) or 16),
            signed=int(get("PixelRepresentation", 0) or 0) == 1,
            samples=int(get("SamplesPerPixel", 1) or 1), instance=_int(get("InstanceNumber")),
            bits_allocated=int(get("BitsAllocated", 16) or 16),
            photometric=str(get("PhotometricInterpretation", "MONOCHROME2") or "MONOCHROME2"),
            pixel_data=pixel_data if isinstance(pixel_data := get(PIXEL_DATA), tuple) else None)
    except (TypeError, ValueError, AttributeError) as exc:
        raise EMRegError(f"{path}: malformed DICOM header ({_short(exc)})") from None


def _short(exc: BaseException) -> str:
    text = " ".join(str(exc).split()) or type(exc).__name__
    return text[:160]


def _list(value: Any) -> list[Any]:
    if value is None:
        return []
    if isinstance(value, (str, bytes)):
        return [value]
    try:
        return list(value)
    except TypeError:
        return [value]


def _int(value: Any) -> int | None:
    try:
        return None if value is None or value == "" else int(value)
    except (TypeError, ValueError):
        return None


def _vector(value: Any, n: int) -> np.ndarray | None:
    values = _list(value)
    if len(values) != n:
        return None
    array = np.asarray([float(v) for v in values], dtype=float)
    return array if np.all(np.isfinite(array)) else None


def _pair(value: Any) -> tuple[float, float] | None:
    vector = _vector(value, 2)
    return None if vector is None or np.any(vector <= 0) else (float(vector[0]), float(vector[1]))


# --- geometry and suitability -------------------------------------------------------------------------


def _describe(uid: str, headers: list[SliceHeader]) -> DicomSeries:
    first = headers[0]
    series = DicomSeries(uid, first.series_number, first.description, first.modality, list(headers))
    series.problem = _volume_problem(series)
    return series


def _volume_problem(series: DicomSeries) -> str | None:
    """Why ``series`` is no CT volume for detection, or None (then its geometry is set, files ordered)."""
    headers = series.headers
    if series.modality.upper() != "CT":
        return f"modality {series.modality or 'unknown'}, not CT"
    if any(_LOCALIZER_TYPES & set(h.image_type) for h in headers):
        return "a localizer (scout/topogram)"
    colour = next((h for h in headers if h.samples != 1), None)
    if colour is not None:
        return f"{colour.name} has {colour.samples} samples per pixel (colour), not greyscale"
    inverted = next((h for h in headers if h.photometric.strip().upper() == "MONOCHROME1"), None)
    if inverted is not None:
        return f"{inverted.name} is MONOCHROME1 (GDCM inverts its values, so they are no HU); " \
               f"export it as MONOCHROME2"
    if len(headers) == 1 and headers[0].frames > 1:
        return _multiframe_geometry(series)
    if any(h.frames > 1 for h in headers):
        return f"{len(headers)} files of which some hold several frames: one multi-frame file or single slices"
    if len(headers) < 3:
        return f"{len(headers)} slice(s), a volume needs 3 or more"
    return _stack_geometry(series, headers)


def _stack_geometry(series: DicomSeries, headers: list[SliceHeader]) -> str | None:
    """Order ``headers`` (slices, or the frames of a multi-frame file) along their normal and set ``series``'
    geometry from them; or why they are no volume (missing tags, uneven or duplicate positions, tilt)."""
    missing = next((h for h in headers if h.position is None or h.orientation is None or h.pixel_spacing is None),
                   None)
    if missing is not None:
        return f"{missing.name} lacks Image Position/Orientation (Patient) or Pixel Spacing"
    first = headers[0]
    for h in headers[1:]:
        if (h.rows, h.columns) != (first.rows, first.columns):
            return f"slices of different sizes ({first.name}: {first.columns}x{first.rows}, " \
                   f"{h.name}: {h.columns}x{h.rows})"
        if np.max(np.abs(h.orientation - first.orientation)) > 1e-4:
            return f"slices of different orientations ({first.name}, {h.name})"
        if not np.allclose(h.pixel_spacing, first.pixel_spacing, rtol=1e-4, atol=1e-5):
            return f"slices of different pixel spacings ({first.name}, {h.name})"
    row, column = first.orientation[:3], first.orientation[3:]
    if abs(np.linalg.norm(row) - 1) > 1e-3 or abs(np.linalg.norm(column) - 1) > 1e-3 or abs(row @ column) > 1e-3:
        return f"{first.name}: Image Orientation (Patient) is not two orthonormal vectors"
    normal = np.cross(row, column)
    headers.sort(key=lambda h: (float(h.position @ normal), h.instance or 0))
    depth = np.array([float(h.position @ normal) for h in headers])
    steps = np.diff(depth)
    spacing = float((depth[-1] - depth[0]) / (len(depth) - 1))
    for k, step in enumerate(steps):
        if step < max(1e-3, 0.01 * spacing):
            return f"duplicate slice position: {headers[k].name} and {headers[k + 1].name} " \
                   f"are {step:.3f} mm apart"
    expected = depth[0] + spacing * np.arange(len(depth))
    tolerance = max(0.02, 0.1 * spacing)
    bad = int(np.argmax(np.abs(depth - expected)))
    if abs(depth[bad] - expected[bad]) > tolerance:
        k = int(np.argmax(steps))
        return (f"uneven slice positions (a missing slice?): {steps[k]:.3f} mm between {headers[k].name} "
                f"and {headers[k + 1].name}, {float(np.median(steps)):.3f} mm elsewhere")
    travel = headers[-1].position - headers[0].position
    sideways = travel - (travel @ normal) * normal
    tilt = math.degrees(math.atan2(float(np.linalg.norm(sideways)), abs(float(travel @ normal))))
    if tilt > 0.05 and float(np.linalg.norm(sideways)) > 0.1 * min(first.pixel_spacing):
        return f"gantry tilt of {tilt:.1f} deg (slices sheared against their plane); " \
               f"reconstruct without tilt, EMReg does not resample a CT"
    series.size = (first.columns, first.rows, len(headers))
    series.spacing = (first.pixel_spacing[1], first.pixel_spacing[0], spacing)
    series.origin = tuple(float(v) for v in headers[0].position)
    series.direction = tuple(float(v) for v in np.column_stack([row, column, normal]).ravel())
    return None


def _multiframe_geometry(series: DicomSeries) -> str | None:
    """A multi-frame file: its frames' geometry from the functional groups (Enhanced CT), checked as slices are.

    Each frame's Image Position (Patient) comes from its Per-frame Functional Groups (Plane Position),
    its orientation, pixel spacing and rescale from its own groups or the Shared ones; the frames
    must then make an evenly spaced, untilted stack, as the slices of a series must (a frame
    missing, two at one position: refused, naming the frame). GDCM decodes the pixels; a file GDCM
    cannot read, or whose frames rescale differently (GDCM applies one rescale to all), is refused.
    A multi-frame file without functional groups takes GDCM's geometry.
    """
    header = series.headers[0]
    path = header.path
    reader = sitk.ImageFileReader()
    reader.SetImageIO("GDCMImageIO")
    reader.SetFileName(str(path))
    try:
        reader.ReadImageInformation()
    except RuntimeError:
        return f"{path.name}: a multi-frame file GDCM cannot read"
    if reader.GetDimension() != 3 or reader.GetSize()[2] < 3:
        return f"{path.name}: a multi-frame file without a 3D volume"
    if tuple(reader.GetSize()) != (header.columns, header.rows, header.frames):
        return f"{path.name}: GDCM reads {list(reader.GetSize())} voxels, the header says " \
               f"{[header.columns, header.rows, header.frames]}"
    frames = _functional_group_frames(header)
    if isinstance(frames, str):
        return frames
    series.multiframe = True
    if frames is None:  # no functional groups (a legacy multi-frame file): GDCM's geometry
        series.size = tuple(int(v) for v in reader.GetSize())
        series.spacing = tuple(float(v) for v in reader.GetSpacing())
        series.origin = tuple(float(v) for v in reader.GetOrigin())
        series.direction = tuple(float(v) for v in reader.GetDirection())
        return None
    rescales = {(f.slope, f.intercept) for f in frames}
    if len(rescales) > 1:
        return f"{path.name}: frames with different rescale slopes/intercepts ({len(rescales)}), " \
               f"which GDCM does not apply frame by frame"
    problem = _stack_geometry(series, frames)
    if problem is None:
        series.frames = frames
    return problem


def _functional_group_frames(header: SliceHeader) -> list[SliceHeader] | str | None:
    """One :class:`SliceHeader` per frame of an enhanced multi-frame file (pydicom, without pixel data),
    None when it has no Per-frame Functional Groups, or why it cannot be read."""
    import pydicom

    try:
        dataset = pydicom.dcmread(header.path, stop_before_pixels=True)
        per_frame = dataset.get("PerFrameFunctionalGroupsSequence")
        if not per_frame:
            return None
        shared = (dataset.get("SharedFunctionalGroupsSequence") or [None])[0]
        if len(per_frame) != header.frames:
            return f"{header.path.name}: {len(per_frame)} per-frame functional groups for {header.frames} frames"
        frames = []
        for index, groups in enumerate(per_frame):
            def group(keyword: str, groups: Any = groups) -> Any:
                for source in (groups, shared):
                    items = source.get(keyword) if source is not None else None
                    if items:
                        return items[0]
                return None

            position, orientation = group("PlanePositionSequence"), group("PlaneOrientationSequence")
            measures, rescale = group("PixelMeasuresSequence"), group("PixelValueTransformationSequence")
            frames.append(replace(
                header, frame=index, instance=index,
                position=_vector(position.get("ImagePositionPatient") if position else None, 3),
                orientation=_vector(orientation.get("ImageOrientationPatient") if orientation else None, 6),
                pixel_spacing=_pair(measures.get("PixelSpacing") if measures else None),
                slope=float(rescale.get("RescaleSlope", 1) if rescale else dataset.get("RescaleSlope", 1) or 1),
                intercept=float(rescale.get("RescaleIntercept", 0) if rescale
                                else dataset.get("RescaleIntercept", 0) or 0)))
    except Exception as exc:  # noqa: BLE001 - pydicom raises many types for a broken file
        return f"{header.path.name}: unreadable functional groups ({_short(exc)})"
    return frames


# --- choosing -----------------------------------------------------------------------------------------


def choose_series(all_series: list[DicomSeries], folder: str | os.PathLike[str],
                  forced: str | int | None = None) -> DicomSeries:
    """The CT volume to detect markers in (see the module docstring); :class:`EMRegError` when none or a tie."""
    folder = Path(folder)
    if not all_series:
        raise EMRegError(f"{folder}: no DICOM image series found")
    if forced is not None and str(forced).strip() != "":
        return _forced(all_series, folder, str(forced).strip())
    volumes = [s for s in all_series if s.problem is None]
    if not volumes:
        listing = "; ".join(f"{s.label()}: {s.problem}" for s in all_series)
        raise EMRegError(f"{folder}: no CT volume among {len(all_series)} DICOM series ({listing})")
    best_rank = min(s.rank() for s in volumes)
    best = [s for s in volumes if s.rank() == best_rank]
    distinct = _distinct_geometries(best)
    if len(distinct) > 1:
        listing = "; ".join(f"{s.label()}: {s.size[2]} slices of {s.spacing[2]:g} mm, origin "
                            + ",".join(f"{v:.1f}" for v in s.origin) for s in distinct)
        raise EMRegError(f"{folder}: {len(distinct)} equally good CT series of different geometry ({listing}); "
                         f"choose one with --series UID|NUMBER or [ct] series")
    return best[0]


def _distinct_geometries(series: list[DicomSeries]) -> list[DicomSeries]:
    distinct: list[DicomSeries] = []
    for s in series:
        if not any(_same_geometry(s, d) for d in distinct):
            distinct.append(s)
    return distinct


def _same_geometry(a: DicomSeries, b: DicomSeries) -> bool:
    return a.size == b.size and np.allclose(a.spacing, b.spacing, atol=1e-3) \
        and np.allclose(a.origin, b.origin, atol=1e-2) and np.allclose(a.direction, b.direction, atol=1e-4)


def _forced(all_series: list[DicomSeries], folder: Path, forced: str) -> DicomSeries:
    matches = [s for s in all_series if s.uid == forced]
    if not matches and forced.lstrip("+-").isdigit():
        matches = [s for s in all_series if s.number == int(forced)]
    available = "; ".join(s.label() for s in all_series)
    if not matches:
        raise EMRegError(f"{folder}: no DICOM series {forced!r} (available: {available})")
    if len(matches) > 1:
        raise EMRegError(f"{folder}: series number {forced} names {len(matches)} series; give the UID "
                         f"({'; '.join(s.label() for s in matches)})")
    chosen = matches[0]
    if chosen.problem is not None:
        raise EMRegError(f"{folder}: {chosen.label()} cannot be used: {chosen.problem}")
    return chosen


def series_record(chosen: DicomSeries, all_series: list[DicomSeries], folder: Path) -> dict[str, Any]:
    """The ``ct_series`` block of ``markers.json`` / ``run.json``: the series used and the others."""
    record = chosen.to_json()
    record["folder"] = str(folder)
    record["others"] = [s.to_json() for s in all_series if s is not chosen]
    return record


# --- reading ------------------------------------------------------------------------------------------


# The threads that run SimpleITK (the read, the early allocation) are no daemons. A daemon thread still inside
# SimpleITK (a volume being allocated, a slice decoded) when the interpreter exits, e.g. right after a one-line
# refusal, is ended by the interpreter from within that C++ code: the process then dies of SIGABRT ("FATAL:
# exception not rethrown") or SIGSEGV instead of exiting 2. The interpreter waits for threads that are no
# daemons before it exits; these end soon (an allocation within a second, a cancelled read at its next slice).


def open_dicom_series(folder: str | os.PathLike[str], series: str | int | None = None,
                      workers: int | None = None, compact: bool = False,
                      voxels_only: bool = False) -> tuple[VolumeFill, dict[str, Any]]:
    """Start reading the chosen CT series of ``folder``; its fill and its ``ct_series`` record.

    Slices are decoded on ``workers`` threads (default: the CPU count, at most 8) and announced
    in order (``wait_for_slices``). A slice GDCM cannot decode, or whose size disagrees with its
    header, ends the read with an :class:`EMRegError` naming the file. ``fill.sha256`` is the
    folder's sha256 (:func:`~EMRegModule.provenance.file_sha256`), made from each slice's bytes
    as they are read for decoding (the first ones, read while the volume is allocated, are hashed then).

    ``compact``: voxels of :func:`compact_voxel_type` (int16 where the headers allow values beyond
    it but the CT's own values, as CTs' do, fit), half the memory to fill; a slice holding a value
    beyond it ends the read with :class:`NarrowVoxelsError` (read again without ``compact``).

    ``voxels_only``: for a caller that needs the voxels only while it works on them (``emreg detect``), integer
    voxels go into a numpy array (``fill.voxels``, k, j, i) and ``fill.image`` is only the geometry
    (:class:`~EMRegModule.io.ct_stream.FixedGeometry`): SimpleITK fills a new image with zeros before a slice can
    be decoded into it (a pass over the whole volume, on one core, that the decoding waits for), where these
    voxels are fresh memory that only the slices' decoding touches, page by page on the workers.
    """
    folder = Path(folder)
    early = None if voxels_only else _EarlyImage(compact)
    all_series = scan_series(folder, early.start if early is not None else None)
    chosen = choose_series(all_series, folder, series)
    record = series_record(chosen, all_series, folder)
    if chosen.multiframe:
        digest = BackgroundHash(folder)
        fill = VolumeFill.complete(_read_multiframe(chosen))
        fill.sha256 = digest
    else:
        fill = VolumeFill(len(chosen.headers))
        fill.sha256 = Digest()
        workers = workers or max(1, min(8, os.cpu_count() or 1))
        threading.Thread(target=_decode_series, args=(chosen, fill, workers, folder, early, compact, voxels_only),
                         name="emreg-dicom-read").start()  # no daemon: see above
    fill.series = record
    return fill, record


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
        for dtype, pixel in ((np.int16, sitk.sitkInt16), (np.uint16, sitk.sitkUInt16), (np.int32, sitk.sitkInt32)):
            info = np.iinfo(dtype)
            if info.min <= low and high <= info.max:
                return pixel
    return sitk.sitkFloat32


def compact_voxel_type(headers: list[SliceHeader]) -> int:
    """int16 where :func:`voxel_type` is int32 only because the stored bits could hold more than CT values do.

    Scanners often store 16 bits with an intercept of -1024 (unsigned: -1024 .. 64511 HU; signed:
    -33792 .. 31743), which takes int32 to hold exactly, while the CT's values (air -1000, bone a
    few thousand, metal often clipped at 3071 or at most some 30000 HU) fit int16. A compact read
    checks every slice (:class:`NarrowVoxelsError` when one does not fit).
    """
    exact = voxel_type(headers)
    if exact == sitk.sitkInt32 and all(h.bits_allocated == 16 for h in headers):
        return sitk.sitkInt16
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
    unless ``hashed``)."""
    try:
        with path.open("rb", buffering=0) as stream:
            size = os.fstat(stream.fileno()).st_size
            buffer = getattr(_buffers, "buffer", None)
            if buffer is None or len(buffer) < size:
                buffer = _buffers.buffer = bytearray(max(size, 1 << 20))
            view = memoryview(buffer)[:size]
            filled = 0
            while filled < size:
                count = stream.readinto(view[filled:])
                if not count:
                    break
                filled += count
            if stream.read(1):
                raise EMRegError(f"{path}: the file grew while it was read")
    except OSError as exc:
        raise EMRegError(f"{path}: cannot read ({exc.strerror})") from None
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


_NUMPY_TYPES = {sitk.sitkInt16: np.dtype(np.int16), sitk.sitkUInt16: np.dtype(np.uint16),
                sitk.sitkInt32: np.dtype(np.int32)}
"""The integer voxel types :func:`voxel_type` chooses, as numpy's (float32 voxels always go into a SimpleITK image,
whose values ``check_ct_image`` checks)."""


def _fresh_voxels(size: tuple[int, int, int], dtype: np.dtype) -> np.ndarray:
    """A (k, j, i) array of ``size`` (i, j, k) in fresh anonymous memory that nothing writes before the slices do:
    each page is faulted in (zeroed by the kernel) by the worker that decodes into it. Huge pages only for slices
    of 2 MB or more, as the streamed CT (:data:`~EMRegModule.io.ct_stream._HUGE_PAGE_BYTES`: smaller slices made
    the kernel's work larger with them)."""
    slice_bytes = int(size[0]) * int(size[1]) * dtype.itemsize
    mapping = mmap.mmap(-1, max(1, slice_bytes * int(size[2])), flags=mmap.MAP_PRIVATE)
    if hasattr(mmap, "MADV_HUGEPAGE") and slice_bytes >= _HUGE_PAGE_BYTES:
        mapping.madvise(mmap.MADV_HUGEPAGE)
    return np.frombuffer(mapping, dtype=dtype, count=int(np.prod(size))).reshape(size[::-1])


def _series_geometry(series: DicomSeries, pixel_type: int) -> FixedGeometry:
    """The geometry of ``series``' volume of ``pixel_type`` voxels, as the image SimpleITK would hold them gives it
    (its getters' very values), without the image."""
    probe = sitk.Image([1, 1, 1], pixel_type)
    probe.SetSpacing(series.spacing)
    probe.SetOrigin(series.origin)
    probe.SetDirection(series.direction)
    geometry = FixedGeometry.of_image(probe)
    geometry.values["GetSize"] = tuple(int(n) for n in series.size)
    return geometry


def _decode_series(series: DicomSeries, fill: VolumeFill, workers: int, folder: Path,
                   early: _EarlyImage | None = None, compact: bool = False, voxels_only: bool = False) -> None:
    """The reading thread: allocate (or take the ``early`` image), decode slices on a pool, announce the
    in-order prefix, then the sha256. ``compact``, ``voxels_only``: see :func:`open_dicom_series`.

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
        image = early.take(series) if early is not None else None  # allocated while the headers were read
        pixel_type = (compact_voxel_type if compact else voxel_type)(series.headers)
        if voxels_only and pixel_type in _NUMPY_TYPES:
            image = _series_geometry(series, pixel_type)
            voxels = fill.voxels = _fresh_voxels(series.size, _NUMPY_TYPES[pixel_type])
        else:
            if image is None:
                image = sitk.Image(list(series.size), pixel_type)
            image.SetSpacing(series.spacing)
            image.SetOrigin(series.origin)
            image.SetDirection(series.direction)
            raw = _writable_bytes(image)
            view = sitk.GetArrayViewFromImage(image)
            voxels = raw.view(view.dtype).reshape(view.shape)
        fill._set_image(image)
        expected = (series.size[1], series.size[0])
        pixel = voxel_type(series.headers)  # GDCM's output, checked where it is narrowed to the image's type

        def decode(start: int, stop: int) -> None:
            if fill._cancelled:
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
                for (_, stop), future in zip(tasks, futures, strict=True):
                    future.result()
                    if fill._cancelled:
                        raise EMRegError(f"{series.headers[0].path.parent}: reading the CT was cancelled")
                    fill._set_ready(stop)
            except BaseException:
                for future in futures:
                    future.cancel()
                raise
            _finish_digest(fill, folder, digests, pool)
    except BaseException as exc:  # handed to the waiting thread
        pool.shutdown(cancel_futures=True)
        if not fill.sha256.done():
            fill.sha256.fail(exc)
        fill._finish(exc)
    else:
        fill._finish()


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


def _finish_digest(fill: VolumeFill, folder: Path, digests: dict[str, bytes], pool: ThreadPoolExecutor) -> None:
    """``fill.sha256``: the folder's, from the slices' sha256 and those of its other files (hashed on ``pool``)."""
    try:
        members = folder_members(folder)
        others = [(name, path) for name, path in members if name not in digests]
        hashes = pool.map(lambda item: bytes.fromhex(file_sha256(item[1])), others)
        hashed = dict(zip([name for name, _ in others], hashes, strict=True))
        covered = {name: digests[name] for name, _ in members if name in digests}
        fill.sha256.set(folder_sha256({**covered, **hashed}))
    except Exception as exc:  # noqa: BLE001 - the CT is read; its provenance hash is asked again later
        fill.sha256.fail(exc)
