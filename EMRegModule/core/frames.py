"""The one home of the image-frame conventions: EMReg's image space is the CT's **LPS** (DICOM, ITK,
SimpleITK), 3D Slicer's world is **RAS**. The two differ by a flip of the first two axes.

- A *point* (or a transform whose output side is the image) goes LPS -> RAS by ``LPS_TO_RAS @ ...``
  (:func:`lps_to_ras_points`; e.g. ``ReferenceToRAS = LPS_TO_RAS @ ReferenceToImage``).
- A transform whose *both* sides are image-like frames goes LPS -> RAS by conjugation
  (:func:`lps_to_ras`; the same formula maps RAS -> LPS).

All values in millimetres; the matrices are 4x4 homogeneous (``LPS_TO_RAS_3X3`` for directions and NIfTI).
"""

from __future__ import annotations

import numpy as np
from numpy.typing import ArrayLike

#: LPS -> RAS (and RAS -> LPS: the flip is its own inverse), 4x4 homogeneous.
LPS_TO_RAS: np.ndarray = np.diag([-1.0, -1.0, 1.0, 1.0])
#: The same flip for 3-vectors and 3x3 direction matrices.
LPS_TO_RAS_3X3: np.ndarray = np.diag([-1.0, -1.0, 1.0])


def lps_to_ras(transform_lps: ArrayLike) -> np.ndarray:
    """A 4x4 transform between two LPS-based frames, expressed between their RAS counterparts (and back)."""
    return LPS_TO_RAS @ np.asarray(transform_lps, dtype=float) @ LPS_TO_RAS


def lps_to_ras_points(points_lps: ArrayLike) -> np.ndarray:
    """Points in LPS mm as an (N, 3) array in RAS mm (and back: the same flip)."""
    points = np.array(points_lps, dtype=float).reshape(-1, 3)
    points[:, :2] *= -1.0
    return points
