"""Detection settings: the ``[detection]`` table of ``case.toml``, with defaults from the marker model and HU physics.

Every threshold can be overridden; none is tuned to one simulator:

- ``low_hu`` (600): the band's lower edge, well above POM (the frame's plastic, about 340 HU),
  soft tissue (< 100) and fat; PVC markers read far higher (about 1000-1500 HU).
- ``high_hu`` (1800): the band's upper edge, the cortical-bone cut; PVC stays below it.
- ``metal_hu`` (2800): saturated / metal voxels (the reference sensor and its streaks).
- ``coarse_step_mm``: the step of the coarse candidate search, a third of the marker's narrowest
  diameter (at most 2 mm), so that every part of a marker is sampled.
- ``volume_tolerance`` (0.25): a candidate's volume must lie within +/- this fraction of
  ``MarkerModel.volume_mm3``.
- ``shape_tolerance`` (0.15): relative tolerance on each principal spread (square root of the
  principal moments) against the model's, plus 0.6 of the largest voxel side (mm).
- ``max_fit_rms_mm`` (0.35): largest RMS distance of the edge points to the fitted CAD surface.
- ``min_inlier_fraction`` (0.8): share of edge points within ``3 * max_fit_rms_mm`` of the fitted surface.
- ``bone_fraction`` (0.02): voxels above ``high_hu`` touching the blob, per blob voxel, above
  which the blob is taken for bone.
- ``metal_distance_mm`` (10): a blob with metal voxels this close is checked with halved fit
  tolerances and rejected as wrecked by metal streaks if it fails them.
- ``smoothing_sigma_mm`` (0.3) and ``opening_radius_mm`` (0.5): the Gaussian smoothing and
  binary opening applied (inside candidate regions only) before the band threshold's
  connected components, which drop noise and the thin partial-volume shells of bone.
- ``min_markers`` (1): fewer markers found is "no safe answer" (exit 3).
"""

from __future__ import annotations

from dataclasses import asdict, dataclass, fields, replace
from typing import Any

from ..errors import EMRegError
from ..io.case import check_known_keys, setting_number
from ..marker_model import MarkerModel


@dataclass(frozen=True)
class DetectionSettings:
    """Thresholds of the marker detection (HU, mm, fractions); see the module docstring."""

    low_hu: float = 600.0
    high_hu: float = 1800.0
    metal_hu: float = 2800.0
    coarse_step_mm: float = 2.0
    volume_tolerance: float = 0.25
    shape_tolerance: float = 0.15
    max_fit_rms_mm: float = 0.35
    min_inlier_fraction: float = 0.8
    bone_fraction: float = 0.02
    metal_distance_mm: float = 10.0
    smoothing_sigma_mm: float = 0.3
    opening_radius_mm: float = 0.5
    min_markers: int = 1

    def to_dict(self) -> dict[str, Any]:
        return asdict(self)


def default_settings(model: MarkerModel) -> DetectionSettings:
    """Defaults for ``model``: the coarse step resolves the narrowest part of the marker."""
    return DetectionSettings(coarse_step_mm=min(2.0, model.top_diameter_mm / 3.0))


def settings_from_dict(values: dict[str, Any] | None, model: MarkerModel) -> DetectionSettings:
    """Defaults for ``model`` overridden by the ``[detection]`` table; unknown keys or bad values are errors."""
    known = {f.name: f for f in fields(DetectionSettings)}
    table = check_known_keys(values, "detection", known)
    converted: dict[str, Any] = {}
    for key, value in table.items():
        number = setting_number("detection", key, value)
        converted[key] = int(number) if known[key].type in (int, "int") else number
    settings = replace(default_settings(model), **converted)
    _check(settings)
    return settings


def _check(s: DetectionSettings) -> None:
    def bad(message: str) -> EMRegError:
        return EMRegError(f"case.toml [detection]: {message}")

    if not s.low_hu < s.high_hu <= s.metal_hu:
        raise bad(f"need low_hu < high_hu <= metal_hu, got {s.low_hu}, {s.high_hu}, {s.metal_hu}")
    positive = ("coarse_step_mm", "volume_tolerance", "shape_tolerance", "max_fit_rms_mm", "metal_distance_mm")
    for name in positive:
        if not getattr(s, name) > 0:
            raise bad(f"{name} must be positive, got {getattr(s, name)}")
    for name in ("smoothing_sigma_mm", "opening_radius_mm", "bone_fraction"):
        if getattr(s, name) < 0:
            raise bad(f"{name} must not be negative, got {getattr(s, name)}")
    if not 0 < s.min_inlier_fraction <= 1:
        raise bad(f"min_inlier_fraction must lie in (0, 1], got {s.min_inlier_fraction}")
    if s.volume_tolerance >= 1:
        raise bad(f"volume_tolerance must be below 1, got {s.volume_tolerance}")
    if s.min_markers < 0:
        raise bad(f"min_markers must not be negative, got {s.min_markers}")
