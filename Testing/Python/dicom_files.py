"""Test helpers: DICOM series as scanners export them (several series, scouts, rescales, transfer syntaxes).

Files are written by SimpleITK's GDCM writer (uncompressed) and converted with GDCM's and
dcmtk's own command-line tools (``gdcmconv``, ``dcmconv``), never by EMReg's code.
"""

from __future__ import annotations

import shutil
import subprocess
from collections.abc import Sequence
from pathlib import Path

import numpy as np
import SimpleITK as sitk

_UID_ROOT = "1.2.826.0.1.3680043.8.498.77"

#: Transfer syntaxes and how to make them: (tool arguments, lossless).
TRANSFER_SYNTAXES = {
    "jpeg-lossless": (["gdcmconv", "--jpeg"], True),
    "jpeg-ls": (["gdcmconv", "--jpegls"], True),
    "jpeg2000-lossless": (["gdcmconv", "--j2k"], True),
    "jpeg2000-lossy": (["gdcmconv", "--j2k", "--lossy", "-q", "70"], False),
    "rle": (["gdcmconv", "--rle"], True),
    "deflate": (["dcmconv", "+td"], True),
    "big-endian": (["dcmconv", "+tb"], True),
}


def uid(*parts: int) -> str:
    return ".".join([_UID_ROOT, *(str(p) for p in parts)])


def write_series(image: sitk.Image, folder: Path, series_uid: str, number: int | None = 1,
                 description: str = "volume", modality: str = "CT", image_type: str = "ORIGINAL\\PRIMARY\\AXIAL",
                 positions: Sequence[Sequence[float]] | None = None,
                 rescale: Sequence[tuple[float, float]] | None = None, prefix: str = "IM",
                 bits_stored: int | None = None) -> list[Path]:
    """Write ``image`` (3D) as one file per k slice; the geometry tags from the image unless ``positions`` given.

    The image's values are stored as they are; ``rescale`` gives the (slope, intercept) written
    into each slice (set with pydicom afterwards, so nothing is rescaled on the way): the slice's
    HU are then ``stored * slope + intercept``.
    """
    folder.mkdir(parents=True, exist_ok=True)
    direction = np.asarray(image.GetDirection()).reshape(3, 3)
    iop = "\\".join(f"{v:.10g}" for v in (*direction[:, 0], *direction[:, 1]))
    spacing = image.GetSpacing()
    writer = sitk.ImageFileWriter()
    writer.KeepOriginalImageUIDOn()
    files = []
    values = sitk.GetArrayFromImage(image)
    for k in range(image.GetSize()[2]):
        slice_k = sitk.GetImageFromArray(values[k])
        slice_k.SetSpacing(spacing[:2])
        position = positions[k] if positions is not None else image.TransformIndexToPhysicalPoint((0, 0, k))
        tags = {
            "0008|0016": "1.2.840.10008.5.1.4.1.1.2", "0008|0018": f"{series_uid}.{k + 1}", "0008|0060": modality,
            "0008|0008": image_type, "0008|103e": description, "0010|0010": "Test^Frame", "0010|0020": "EMREG-T1",
            "0008|0020": "20261201", "0008|0030": "120000", "0020|0010": "1", "0020|000d": uid(1),
            "0020|000e": series_uid,
            "0020|0052": uid(2), "0020|0013": str(k + 1), "0020|0037": iop,
            "0020|0032": "\\".join(f"{v:.6f}" for v in position),
            "0028|0030": f"{spacing[1]:.6g}\\{spacing[0]:.6g}", "0018|0050": f"{spacing[2]:.6g}",
        }
        if number is not None:
            tags["0020|0011"] = str(number)
        for tag, value in tags.items():
            slice_k.SetMetaData(tag, value)
        path = folder / f"{prefix}{k + 1:05d}.dcm"
        writer.SetFileName(str(path))
        writer.Execute(slice_k)
        if rescale is not None or bits_stored is not None:
            import pydicom

            dataset = pydicom.dcmread(path)
            if rescale is not None:
                dataset.RescaleSlope, dataset.RescaleIntercept = (f"{v:.6g}" for v in rescale[k])
            if bits_stored is not None:
                dataset.BitsStored, dataset.HighBit = bits_stored, bits_stored - 1
            dataset.save_as(path)
        files.append(path)
    return files


def convert(files: Sequence[Path], syntax: str) -> None:
    """Re-encode ``files`` in place to a transfer syntax of ``TRANSFER_SYNTAXES`` with GDCM/dcmtk tools."""
    command, _ = TRANSFER_SYNTAXES[syntax]
    for path in files:
        tmp = path.with_suffix(".tmp")
        subprocess.run([*command, str(path), str(tmp)], check=True, capture_output=True)
        tmp.replace(path)


def tools_available() -> list[str]:
    """The DICOM tools missing on this machine (``scripts/setup`` installs them)."""
    return [tool for tool in ("gdcmconv", "dcmconv", "dcmdjpeg", "gdcminfo") if shutil.which(tool) is None]


def transfer_syntax_uid(path: Path) -> str:
    import pydicom

    return str(pydicom.dcmread(path, stop_before_pixels=True).file_meta.TransferSyntaxUID)


def make_volume(size=(48, 40, 12), spacing=(0.5, 0.6, 0.8), seed: int = 0, pixel=sitk.sitkInt16,
                smooth: bool = False) -> sitk.Image:
    """A small oblique CT-like volume of random HU values (-1000 .. 2000) with a bright block.

    ``smooth`` blurs the noise in plane (an image a lossy codec can keep close, as real CTs).
    """
    rng = np.random.default_rng(seed)
    values = rng.integers(-1000, 2000, size=size[::-1]).astype(np.int32)
    if smooth:
        from scipy import ndimage

        values = np.rint(ndimage.gaussian_filter(values.astype(float), (0, 3, 3)) * 8 - 3500).astype(np.int32)
    values[3:6, 10:20, 10:25] = 1400
    if pixel == sitk.sitkUInt16:
        values = values + 1000
    image = sitk.GetImageFromArray(values.astype(sitk.GetArrayViewFromImage(sitk.Image(1, 1, pixel)).dtype))
    image.SetSpacing(spacing)
    image.SetOrigin((-12.0, 30.5, -101.25))
    angle = 0.2
    direction = np.array([[np.cos(angle), -np.sin(angle), 0], [np.sin(angle), np.cos(angle), 0], [0, 0, 1]])
    image.SetDirection(direction.ravel().tolist())
    return image


def write_enhanced_ct(image: sitk.Image, path: Path, series_uid: str, number: int = 7,
                      frame_order: Sequence[int] | None = None, positions: Sequence[Sequence[float]] | None = None,
                      rescale: tuple[float, float] = (1.0, -1024.0)) -> Path:
    """``image`` (3D, int16 stored values) as one Enhanced CT Image Storage file written with pydicom.

    Geometry in the functional groups only, as scanners write them: Pixel Measures, Plane Orientation
    and Pixel Value Transformation (``rescale``: slope, intercept) shared, Plane Position per frame;
    frames stored in ``frame_order`` (k indices of ``image``; default 0, 1, ...), each at its
    ``positions[k]`` (default: where ``image`` puts slice k). Stored values are ``image``'s.
    """
    import pydicom
    from pydicom.dataset import Dataset, FileMetaDataset
    from pydicom.sequence import Sequence as DicomSequence
    from pydicom.uid import ExplicitVRLittleEndian

    values = sitk.GetArrayFromImage(image).astype("<i2")
    count, rows, columns = values.shape
    order = list(range(count)) if frame_order is None else list(frame_order)
    direction = np.asarray(image.GetDirection()).reshape(3, 3)
    spacing = image.GetSpacing()
    meta = FileMetaDataset()
    meta.MediaStorageSOPClassUID = "1.2.840.10008.5.1.4.1.1.2.1"
    meta.MediaStorageSOPInstanceUID = f"{series_uid}.1"
    meta.TransferSyntaxUID = ExplicitVRLittleEndian
    dataset = Dataset()
    dataset.file_meta = meta
    dataset.SOPClassUID, dataset.SOPInstanceUID = meta.MediaStorageSOPClassUID, meta.MediaStorageSOPInstanceUID
    dataset.Modality, dataset.SeriesInstanceUID, dataset.SeriesNumber = "CT", series_uid, number
    dataset.StudyInstanceUID, dataset.FrameOfReferenceUID = uid(1), uid(2)
    dataset.SeriesDescription, dataset.ImageType = "enhanced", ["ORIGINAL", "PRIMARY", "AXIAL", "NONE"]
    dataset.PatientName, dataset.PatientID = "Test^Frame", "EMREG-T1"
    dataset.Rows, dataset.Columns, dataset.NumberOfFrames = rows, columns, len(order)
    dataset.SamplesPerPixel, dataset.PhotometricInterpretation = 1, "MONOCHROME2"
    dataset.BitsAllocated, dataset.BitsStored, dataset.HighBit, dataset.PixelRepresentation = 16, 16, 15, 1
    measures = Dataset()
    measures.PixelSpacing = [f"{spacing[1]:.6g}", f"{spacing[0]:.6g}"]
    measures.SliceThickness = f"{spacing[2]:.6g}"
    orientation = Dataset()
    orientation.ImageOrientationPatient = [f"{v:.10g}" for v in (*direction[:, 0], *direction[:, 1])]
    transformation = Dataset()
    transformation.RescaleSlope, transformation.RescaleIntercept = (f"{v:.6g}" for v in rescale)
    transformation.RescaleType = "HU"
    shared = Dataset()
    shared.PixelMeasuresSequence = DicomSequence([measures])
    shared.PlaneOrientationSequence = DicomSequence([orientation])
    shared.PixelValueTransformationSequence = DicomSequence([transformation])
    dataset.SharedFunctionalGroupsSequence = DicomSequence([shared])
    frames = []
    for k in order:
        plane = Dataset()
        position = positions[k] if positions is not None else image.TransformIndexToPhysicalPoint((0, 0, k))
        plane.ImagePositionPatient = [f"{v:.6f}" for v in position]
        content = Dataset()
        content.StackID, content.InStackPositionNumber = "1", k + 1
        frame = Dataset()
        frame.PlanePositionSequence = DicomSequence([plane])
        frame.FrameContentSequence = DicomSequence([content])
        frames.append(frame)
    dataset.PerFrameFunctionalGroupsSequence = DicomSequence(frames)
    dataset.PixelData = np.ascontiguousarray(values[order]).tobytes()
    path.parent.mkdir(parents=True, exist_ok=True)
    pydicom.dcmwrite(path, dataset, enforce_file_format=True)
    return path
