"""A registration's files: ``OUT/registration.json`` (:class:`~EMRegModule.core.registration.RegistrationResult`,
its JSON form ``to_json`` / ``from_json``) and ``OUT/ReferenceToImage.h5`` (the same transform as 3D Slicer loads
it), each written atomically; :func:`read_registration` reads the JSON back and checks that it can be trusted."""

from __future__ import annotations

import os
from pathlib import Path

from ..core.registration import RegistrationResult
from ..errors import NoSafeAnswerError
from ..names import REFERENCE_TO_IMAGE_H5, REGISTRATION_JSON
from ..settings import RegistrationSettings
from .atomic import atomic_write_json, read_json
from .itk_transform import write_slicer_linear_transform


def write_registration(result: RegistrationResult, out_dir: str | os.PathLike[str]) -> None:
    """Write ``registration.json`` and ``ReferenceToImage.h5`` (both atomically) into ``out_dir``."""
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    write_slicer_linear_transform(out / REFERENCE_TO_IMAGE_H5, result.reference_to_image)
    atomic_write_json(out / REGISTRATION_JSON, result.to_json())


def read_registration(path: str | os.PathLike[str], max_fre_mm: float | None = None) -> RegistrationResult:
    """Read ``registration.json`` (a folder holding one is accepted too) and check it can be trusted.

    Every consumer (navigate, evaluate, report, live navigation, the Slicer Logic) reads through
    here: the numbers must be finite, ``ReferenceToImage`` rigid (:func:`~EMRegModule.core.transforms.check_rigid`),
    and ``fre_mm`` at most ``max_fre_mm`` (default: the ``[registration] max_fre_mm`` default,
    2 mm). A malformed file raises :class:`EMRegError` (exit 2); an FRE above the limit raises
    :class:`NoSafeAnswerError` (exit 3), as ``emreg register`` does.
    """
    path = Path(path)
    if path.is_dir():
        path = path / REGISTRATION_JSON
    result = RegistrationResult.from_json(read_json(path, "registration JSON"), str(path))
    limit = RegistrationSettings().max_fre_mm if max_fre_mm is None else float(max_fre_mm)
    if result.fre_mm > limit:
        raise NoSafeAnswerError(f"{path}: registration FRE {result.fre_mm:.2f} mm is above the limit of {limit:g} mm "
                                "([registration] max_fre_mm): not used")
    return result
