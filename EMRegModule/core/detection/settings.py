"""Detection settings: the ``[detection]`` table of ``case.toml``.

The table class, its defaults and its checks live with every other table in
:mod:`EMRegModule.settings` (:class:`~EMRegModule.settings.DetectionSettings`); this module keeps
the detection-side helpers.
"""

from __future__ import annotations

from typing import Any

from ...marker_model import MarkerModel
from ...settings import DetectionSettings
from ...tables import parse_table

__all__ = ["DetectionSettings", "default_settings", "settings_from_dict"]


def default_settings(model: MarkerModel) -> DetectionSettings:
    """Defaults for ``model``: the coarse step resolves the narrowest part of the marker."""
    return DetectionSettings.for_model(model)


def settings_from_dict(values: dict[str, Any] | None, model: MarkerModel) -> DetectionSettings:
    """Defaults for ``model`` overridden by a ``[detection]`` table; unknown keys or bad values are errors."""
    return parse_table(DetectionSettings, values, "detection", base=default_settings(model))
