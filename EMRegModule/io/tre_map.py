"""``OUT/tre_map.nrrd``: the predicted TRE over the CT (:class:`~EMRegModule.core.tre_map.TreMap`, computed by
:func:`~EMRegModule.core.tre_map.predicted_tre_map`) as a float32 volume in mm, in the CT's LPS space (its origin and
direction cosines, a coarser spacing), which 3D Slicer loads as a scalar volume aligned with the CT."""

from __future__ import annotations

import os

import SimpleITK as sitk

from ..core.tre_map import TreMap
from .image import write_image


def write_tre_map(path: str | os.PathLike[str], tre_map: TreMap) -> None:
    """Write the map atomically as NRRD (gzip), float32 mm, LPS."""
    image = sitk.GetImageFromArray(tre_map.values_mm)
    image.SetOrigin(tuple(float(v) for v in tre_map.origin))
    image.SetSpacing(tuple(float(v) for v in tre_map.spacing))
    image.SetDirection(tuple(float(v) for v in tre_map.direction.ravel()))
    write_image(image, path)
