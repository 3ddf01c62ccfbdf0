"""``OUT/evaluation.json``: the accuracy at the targets (:class:`~EMRegModule.core.evaluation.Evaluation`, its JSON
form ``to_json`` / ``from_json``), written atomically and read back."""

from __future__ import annotations

import os

from ..core.evaluation import Evaluation
from ..errors import EMRegError
from .atomic import atomic_write_json, read_json


def write_evaluation(result: Evaluation, path: str | os.PathLike[str]) -> None:
    """Write ``evaluation.json`` atomically."""
    atomic_write_json(path, result.to_json())


def read_evaluation(path: str | os.PathLike[str]) -> Evaluation:
    """Read an ``evaluation.json``; a missing or malformed file is an :class:`EMRegError`."""
    document = read_json(path, "evaluation JSON")
    if not isinstance(document, dict):
        raise EMRegError(f"{path}: not an evaluation file (not a JSON object)")
    return Evaluation.from_json(document, str(path))
