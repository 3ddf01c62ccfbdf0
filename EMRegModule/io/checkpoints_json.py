"""``OUT/checkpoints.json``: the trust checks of a navigation (:class:`~EMRegModule.core.checkpoints.CheckpointReport`,
its JSON form ``to_json``), written atomically."""

from __future__ import annotations

import os

from ..core.checkpoints import CheckpointReport
from .atomic import atomic_write_json


def write_checkpoints(report: CheckpointReport, path: str | os.PathLike[str]) -> None:
    """Write ``checkpoints.json`` atomically."""
    atomic_write_json(path, report.to_json())
