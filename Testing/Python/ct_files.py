"""CT files written by hand as other tools write them, for the tests: an NRRD as 3D Slicer writes one (RAS or LPS
space, either byte order, raw or gzip, attached or detached), from a ``SimpleITK.Image`` in LPS.

Frames: the image's index (i, j, k) to LPS mm (SimpleITK's); RAS = diag(-1, -1, 1) LPS.
"""

from __future__ import annotations

import gzip
from pathlib import Path

import numpy as np
import SimpleITK as sitk

RAS_FROM_LPS = np.diag([-1.0, -1.0, 1.0])


def index_to_lps(image: sitk.Image) -> np.ndarray:
    """4x4 voxel index (i, j, k) -> LPS mm."""
    matrix = np.eye(4)
    matrix[:3, :3] = np.asarray(image.GetDirection()).reshape(3, 3) * np.asarray(image.GetSpacing())[None, :]
    matrix[:3, 3] = image.GetOrigin()
    return matrix


def _vector(values) -> str:
    return "(" + ",".join(f"{v:.17g}" for v in values) + ")"


def write_nrrd(path: Path, image: sitk.Image, space: str = "RAS", endian: str = "big", encoding: str = "gzip",
               data_file: str | None = None) -> Path:
    """An NRRD as 3D Slicer writes one (``space``: "RAS" or "LPS"), by hand; ``data_file``: a detached
    ``.nhdr`` whose voxels are in that file beside it (``.raw`` or ``.raw.gz``)."""
    to_space = RAS_FROM_LPS if space == "RAS" else np.eye(3)
    matrix = index_to_lps(image)
    columns = to_space @ matrix[:3, :3]
    voxels = sitk.GetArrayViewFromImage(image).astype(">i2" if endian.lower() == "big" else "<i2").tobytes()
    if encoding.lower() == "gzip":
        voxels = gzip.compress(voxels, compresslevel=1)
    header = [
        "NRRD0004", "# Complete NRRD file format specification at:", "type: short", "dimension: 3",
        "space: " + {"RAS": "right-anterior-superior", "LPS": "left-posterior-superior"}[space],
        "sizes: " + " ".join(map(str, image.GetSize())),
        "space directions: " + " ".join(_vector(columns[:, a]) for a in range(3)),
        "kinds: domain domain domain", f"endian: {endian}", f"encoding: {encoding}",
        "space origin: " + _vector(to_space @ matrix[:3, 3]),
    ]
    if data_file is None:
        path.write_bytes(("\n".join(header) + "\n\n").encode("ascii") + voxels)
    else:
        (path.parent / data_file).write_bytes(voxels)
        path.write_text("\n".join([*header, f"data file: {data_file}"]) + "\n")
    return path
