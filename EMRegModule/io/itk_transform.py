"""ITK transform files (``.h5``, ``.tfm``, ``.txt``) that 3D Slicer loads as linear transforms.

ITK stores the *resampling* transform, which maps points of the fixed (parent) space into
the moving (child) space, in LPS. 3D Slicer therefore loads a file holding ``BToA`` as a
linear transform node whose "to parent" transform is ``AToB``. So
:func:`write_slicer_linear_transform` writes the **inverse** of the ``AToB`` it is given:
``ReferenceToImage.h5`` holds ``ImageToReference`` (LPS); in Slicer it appears as the
transform that moves a node in Reference coordinates to its place in the CT (``ReferenceToImage``).
"""

from __future__ import annotations

import os

import numpy as np
import SimpleITK as sitk

from ..errors import EMRegError
from ..transforms import invert_rigid
from .atomic import atomic_path


def write_slicer_linear_transform(path: str | os.PathLike[str], a_to_b: np.ndarray) -> None:
    """Write ``AToB`` (4x4, LPS frames, mm) so that Slicer loads it as the A->B "to parent" transform."""
    b_to_a = invert_rigid(a_to_b)
    transform = sitk.AffineTransform(3)
    transform.SetMatrix(b_to_a[:3, :3].ravel().tolist())
    transform.SetTranslation(b_to_a[:3, 3].tolist())
    with atomic_path(path) as tmp:
        sitk.WriteTransform(transform, str(tmp))


def read_slicer_linear_transform(path: str | os.PathLike[str]) -> np.ndarray:
    """Read a file written by :func:`write_slicer_linear_transform` (or by Slicer) back as ``AToB``."""
    try:
        transform = sitk.ReadTransform(str(path))
    except RuntimeError:
        raise EMRegError(f"{path}: not a readable ITK transform file") from None
    if transform.GetDimension() != 3:
        raise EMRegError(f"{path}: expected a 3D transform")
    try:
        affine = sitk.AffineTransform(transform)
    except (RuntimeError, TypeError):
        # Composite transforms wrap the linear one.
        try:
            affine = sitk.AffineTransform(sitk.CompositeTransform(transform).GetNthTransform(0))
        except (RuntimeError, TypeError):
            raise EMRegError(f"{path}: not a linear transform") from None
    b_to_a = np.eye(4)
    b_to_a[:3, :3] = np.asarray(affine.GetMatrix()).reshape(3, 3)
    center = np.asarray(affine.GetCenter())
    b_to_a[:3, 3] = np.asarray(affine.GetTranslation()) + center - b_to_a[:3, :3] @ center
    return np.linalg.inv(b_to_a)
