"""ITK transform files (``.h5``, ``.tfm``, ``.txt``) that 3D Slicer loads as linear transforms.

Two conventions meet in such a file:

- ITK stores the *resampling* transform (it maps points of the fixed/parent space into the
  moving/child space) and works in LPS. 3D Slicer, reading an ITK file holding ``T``, converts
  both sides to RAS and sets the node's "to parent" transform to ``F @ inv(T) @ F`` with
  ``F = diag(-1, -1, 1)``.
- In 3D Slicer (as in PLUS and SlicerIGT) the coordinates of tracker-side frames — Tracker,
  Reference, Probe — are used as they are: a ``ProbeToReference`` streamed by a tracker server is
  applied unchanged, and a registration node maps raw Reference coordinates to RAS
  (``ReferenceToRAS = F @ ReferenceToImage``). EMReg's Slicer module and live navigation use
  that same node.

So :func:`write_slicer_linear_transform` stores ``T = F @ ImageToReference`` for a given
``ReferenceToImage`` (Reference = a tracker-side frame, Image = LPS): loaded in Slicer, the node's
"to parent" transform is exactly ``F @ ReferenceToImage``, and a model or stream in Reference
coordinates placed under it lands where it is in the CT. Read in SimpleITK or ITK, ``T`` maps an
LPS image point to its Reference-frame coordinates with x and y negated; for plain numpy work
use ``registration.json``'s ``ReferenceToImage`` matrix instead.
"""

from __future__ import annotations

import os

import numpy as np

from ..core.frames import LPS_TO_RAS
from ..core.transforms import invert_rigid
from ..errors import EMRegError
from .atomic import atomic_path, itk_write_errors


def write_slicer_linear_transform(path: str | os.PathLike[str], tracker_side_to_image: np.ndarray) -> None:
    """Write ``AToImage`` (4x4, mm; A a tracker-side frame, Image LPS) for 3D Slicer (module docstring)."""
    write_itk_linear_matrix(path, LPS_TO_RAS @ invert_rigid(tracker_side_to_image))


def read_slicer_linear_transform(path: str | os.PathLike[str]) -> np.ndarray:
    """Read a file written by :func:`write_slicer_linear_transform` back as ``AToImage`` (4x4, mm)."""
    return np.linalg.inv(LPS_TO_RAS @ read_itk_linear_matrix(path))


def write_itk_linear_matrix(path: str | os.PathLike[str], stored: np.ndarray) -> None:
    """Write the 4x4 ``stored`` as it is (an ``AffineTransform``, ITK's own convention) atomically."""
    import SimpleITK as sitk  # loaded when a transform is written, not with the registration module

    transform = sitk.AffineTransform(3)
    transform.SetMatrix(np.asarray(stored, dtype=float)[:3, :3].ravel().tolist())
    transform.SetTranslation(np.asarray(stored, dtype=float)[:3, 3].tolist())
    with atomic_path(path) as tmp, itk_write_errors():
        sitk.WriteTransform(transform, str(tmp))


def read_itk_linear_matrix(path: str | os.PathLike[str]) -> np.ndarray:
    """The 4x4 an ITK transform file stores (a 3D linear transform, or a composite wrapping one), as it is."""
    import SimpleITK as sitk

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
    stored = np.eye(4)
    stored[:3, :3] = np.asarray(affine.GetMatrix()).reshape(3, 3)
    center = np.asarray(affine.GetCenter())
    stored[:3, 3] = np.asarray(affine.GetTranslation()) + center - stored[:3, :3] @ center
    return stored


def write_slicer_frame_transform(path: str | os.PathLike[str], a_to_b: np.ndarray) -> None:
    """Write ``AToB`` (4x4, mm) between two frames that 3D Slicer uses as they are (tracker or robot side:
    ``SensorToFlange``, ``TrackerToBase``), so that Slicer loads it as a linear transform node whose "to
    parent" is exactly ``AToB``: ITK stores the inverse in LPS, Slicer converts it to RAS on reading, so the
    file holds ``F @ inv(AToB) @ F`` with ``F = diag(-1, -1, 1)``."""
    write_itk_linear_matrix(path, LPS_TO_RAS @ invert_rigid(a_to_b) @ LPS_TO_RAS)


def read_slicer_frame_transform(path: str | os.PathLike[str]) -> np.ndarray:
    """Read a file written by :func:`write_slicer_frame_transform` back as ``AToB`` (4x4, mm)."""
    return np.linalg.inv(LPS_TO_RAS @ read_itk_linear_matrix(path) @ LPS_TO_RAS)
