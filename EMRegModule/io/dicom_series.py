"""DICOM CT exports as hospitals hand them over: find the series and choose the CT volume.

A CT folder (``ct/`` of a case, or any folder given to ``emreg detect``) may hold several series
(the volume, a scout/topogram, a thick reconstruction, dose reports...), in subfolders, with or
without a ``DICOMDIR``. :func:`scan_series` reads the headers only (pydicom, no pixel data) and
groups the files by Series Instance UID; :func:`choose_series` keeps the CT volumes (modality CT,
3 or more slices, not a ``LOCALIZER``, greyscale and not MONOCHROME1, one consistent, evenly
spaced, untilted geometry) and picks the one best for marker detection: finest slice spacing, then
finest in-plane spacing, then most slices. Two equally good candidates of different geometry
are an error listing both (never a silent guess); ``series=UID|NUMBER`` (``--series``,
``[ct] series``) forces a choice.

:func:`~EMRegModule.io.dicom_read.open_dicom_series` then reads the chosen series' voxels.

Geometry (LPS, as SimpleITK's ``ImageSeriesReader`` gives it): direction columns are the row
cosine, the column cosine and their cross product; slices are ordered along that normal; the
origin is the first slice's Image Position (Patient). Slices sheared against their plane (gantry
tilt) are refused with the tilt angle: EMReg never resamples a CT silently.
"""

from __future__ import annotations

import io
import math
import os
import warnings
from collections.abc import Callable, Iterable
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any

import numpy as np

from ..errors import EMRegError
from .dicom_header import PIXEL_DATA, quick_header

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
    import SimpleITK as sitk

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

