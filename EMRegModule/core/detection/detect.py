"""``detect_markers``: find every marker in a CT and estimate its pose (image space, LPS mm).

Coarse-to-fine (see ``segmentation``): the volume is read through a zero-copy view, a strided
pass finds candidate regions, and only those regions are processed at full resolution, on a
few threads (the result does not depend on them). Given ``wait_for_slices``, all of this runs
while the CT is still being read, each region as soon as the slices it needs are in. Every
candidate of marker-like density and at least a third of a marker's volume ends either as a
marker or in ``rejected`` with a reason (code in brackets):

- ``edge``: cut by the image's edge;
- ``volume``: too large or too small for the marker model;
- ``bone``: touches voxels brighter than ``high_hu`` (cortical bone);
- ``shape``: principal spreads unlike the model's (rods, plates), or the CAD model does not fit
  its edges (spheres, boxes, fragments);
- ``metal``: fails a check with metal voxels nearby (the reference sensor's streaks), where the
  fit tolerances are halved.

Marker ids are ``I01, I02, ...`` ordered by origin (z, then y, then x, LPS).

Fewer than ``min_markers`` markers (default 1, ``[detection] min_markers``) is "no safe
answer" (``NoSafeAnswerError``, exit 3): the message counts the rejected candidates by reason
and nothing is written. Registration needs three or more and checks that itself.
"""

from __future__ import annotations

import os
from collections.abc import Callable
from concurrent.futures import Future
from dataclasses import replace
from typing import TYPE_CHECKING

import numpy as np

from ...errors import NoSafeAnswerError
from ...marker_model import MarkerModel
from ...progress import QUIET, Progress
from ..ct import ImageGeometry, StreamedCT, check_ct_geometry, image_geometry, index_to_physical_matrix
from ..transforms import apply_transform
from .examiners import Examiners
from .measure import measure_blob, metal_distance_mm
from .pose import fit_pose, model_moments, top_contrast
from .result import DetectedMarker, DetectionResult, RejectedCandidate
from .segmentation import Blob, CoarseScan, Region, TooLarge, blobs_in_region, region_around, with_fragments
from .settings import DetectionSettings, default_settings

if TYPE_CHECKING:  # an image handed over is SimpleITK's (its caller loaded it); a CT handle's voxels need none
    import SimpleITK as sitk

_Outcome = tuple[np.ndarray, DetectedMarker | RejectedCandidate]
"""A blob's centroid (LPS mm) and what became of it."""


def detect_markers(ct: StreamedCT | sitk.Image, model: MarkerModel | None = None,
                   settings: DetectionSettings | None = None, progress: Progress | None = None,
                   wait_for_slices: Callable[[int], None] | None = None) -> DetectionResult:
    """Markers in a scalar 3D CT in HU: origins (bottom-face centres) and +Y axes, LPS mm.

    ``ct``: a :class:`~EMRegModule.core.ct.StreamedCT` (an :class:`~EMRegModule.io.ct_handle.CTHandle`), possibly
    still being read: detection follows its slices as they arrive, working on those already read while the rest
    arrives, with the same result (voxels a forked process sees as they are written, ``shared``, let one of the
    examiners of the candidate regions be such a process: :mod:`.examiners`); or a ``SimpleITK.Image``, read in
    full or, given ``wait_for_slices``, whose slices are still arriving. ``settings`` is the ``[detection]`` table
    (None: the defaults for ``model``). Raises :class:`NoSafeAnswerError` (exit 3) when fewer than ``min_markers``
    markers are found.
    """
    model = model or MarkerModel()
    options = settings or default_settings(model)
    progress = progress or QUIET
    streamed = isinstance(ct, StreamedCT)
    image = ct.image if streamed else ct
    check_ct_geometry(image)
    shared = False
    if streamed:
        volume, wait_for_slices, shared = ct.array, ct.wait_for_slices, ct.shared
    else:
        import SimpleITK as sitk

        volume = sitk.GetArrayViewFromImage(image)
    spacing_zyx = np.asarray(image.GetSpacing(), dtype=float)[::-1]
    index_to_image = index_to_physical_matrix(image)
    with Examiners(volume, _workers(), fork=shared) as examiners:
        outcomes, too_large, options, band = _passes(volume, spacing_zyx, index_to_image, model, options, progress,
                                                     wait_for_slices, examiners)
    result = _result(outcomes, too_large, index_to_image, options, image, volume, model)
    final = _marker_hu_estimate(outcomes, model, options, markers_only=True)
    band["marker_hu"] = None if final is None else round(final, 1)
    result.band = band
    return result


def _passes(volume: np.ndarray, spacing_zyx: np.ndarray, index_to_image: np.ndarray, model: MarkerModel,
            options: DetectionSettings, progress: Progress, wait_for_slices: Callable[[int], None] | None,
            examiners: Examiners) -> tuple[list[_Outcome], list[TooLarge], DetectionSettings, dict]:
    """The detection passes: the band of ``options``, then, unless the band was set, one around the markers' own
    intensity when it suits them better; the outcomes kept, the settings of their pass and the band's record."""
    outcomes, too_large = _one_pass(volume, spacing_zyx, index_to_image, model, options, progress,
                                    wait_for_slices, examiners)
    defaults = DetectionSettings()
    explicit = not options.estimate_band or (options.low_hu, options.high_hu) != (defaults.low_hu, defaults.high_hu)
    band = {"low_hu": options.low_hu, "high_hu": options.high_hu,
            "source": "case.toml [detection]" if explicit else "default"}
    estimate = _marker_hu_estimate(outcomes, model, options)
    if not explicit and estimate is None:
        with progress.step("few markers in the default band: measuring the markers with the band's top "
                           "raised to the metal level"):
            estimate = _bright_marker_estimate(volume, spacing_zyx, index_to_image, model, options, progress,
                                               examiners)
    if not explicit and estimate is not None and not _band_suits(estimate, options):
        scaled = _band_around(estimate, options)
        with progress.step(f"markers read {estimate:.0f} HU: detecting again with the band "
                           f"{scaled.low_hu:.0f}..{scaled.high_hu:.0f} HU"):
            again, again_large = _one_pass(volume, spacing_zyx, index_to_image, model, scaled, progress,
                                           None, examiners)  # the image is whole by now
        if _marker_count(again) >= max(1, _marker_count(outcomes)):
            outcomes, too_large, options = again, again_large, scaled
            band = {"low_hu": scaled.low_hu, "high_hu": scaled.high_hu,
                    "source": f"estimated from the markers' intensity ({estimate:.0f} HU in the default band)"}
    return outcomes, too_large, options, band


def _one_pass(volume: np.ndarray, spacing_zyx: np.ndarray, index_to_image: np.ndarray, model: MarkerModel,
              options: DetectionSettings, progress: Progress, wait_for_slices: Callable[[int], None] | None,
              examiners: Examiners) -> tuple[list[_Outcome], list[TooLarge]]:
    """One detection of every marker of ``volume`` (numpy order k, j, i; ``index_to_image`` maps (i, j, k)
    to LPS mm) with the band of ``options``: the coarse scan slice block by slice block (waiting for
    them when streaming), each candidate region examined by one of ``examiners`` as soon as its slices are read."""
    slice_count = volume.shape[0]
    scan = CoarseScan(volume, spacing_zyx, model, options)
    guard = _guard_slices(model, options, index_to_image)
    queued: list[Region] = []
    too_large: list[TooLarge] = []
    examined: list[tuple[Region, Future]] = []

    def start_ready(slices: int) -> None:
        """Start the regions whose slices, and all a check of theirs may look at, are read."""
        ready: list[Region] = []
        waiting: list[Region] = []
        for region in queued:
            (ready if slices >= slice_count or region.slices[0].stop + guard <= slices else waiting).append(region)
        if ready:
            metal_zyx = scan.metal_zyx  # complete within ``guard`` of the ready regions
            examined.extend((region, examiners.submit(_examine, region, metal_zyx, index_to_image, spacing_zyx, model,
                                                      options)) for region in ready)
            queued[:] = waiting

    streaming = wait_for_slices is not None
    with progress.step("reading CT and finding candidates" if streaming else "finding candidates"):
        step_slices = _STEP_ROWS * int(scan.strides[0]) if streaming else slice_count
        for slices in range(step_slices, slice_count + step_slices, step_slices):
            slices = min(slices, slice_count)
            if streaming:
                wait_for_slices(slices)
            regions, large = scan.advance(slices)
            queued.extend(regions)
            too_large.extend(large)
            start_ready(slices)
    with progress.step("fitting markers", total=len(examined) + len(queued)) as step:
        start_ready(slice_count)
        outcomes: list[tuple[np.ndarray, DetectedMarker | RejectedCandidate]] = []
        for _, future in sorted(examined, key=lambda item: _region_key(item[0])):  # the order of a whole read
            outcomes.extend(future.result())
            step.advance()
    return outcomes, too_large


def _examine(volume: np.ndarray, region: Region, metal_zyx: np.ndarray, index_to_image: np.ndarray,
             spacing_zyx: np.ndarray, model: MarkerModel, options: DetectionSettings) -> list[_Outcome]:
    """What became of each blob of ``region`` (numpy slices of ``volume``), with its centroid (LPS mm)."""
    found = []
    for blob in blobs_in_region(volume, region, index_to_image, spacing_zyx, model, options):
        if blob.touches_region_edge:
            blob = _regrown(volume, blob, index_to_image, spacing_zyx, model, options)
        outcome = _classify(blob, metal_zyx, index_to_image, model, options)
        if isinstance(outcome, RejectedCandidate) and outcome.code in _SPLIT_CODES and not blob.touches_region_edge:
            joined = with_fragments(volume, blob, index_to_image, spacing_zyx, model, options)
            if joined is not None and not joined.touches_region_edge:
                whole = _classify(joined, metal_zyx, index_to_image, model, options)
                if isinstance(whole, DetectedMarker):
                    outcome = whole
        found.append((blob.centroid(), outcome))
    return found


def _marker_count(outcomes: list[_Outcome]) -> int:
    return sum(isinstance(outcome, DetectedMarker) for _, outcome in outcomes)


def _marker_hu_estimate(outcomes: list[_Outcome], model: MarkerModel, options: DetectionSettings,
                        markers_only: bool = False) -> float | None:
    """The markers' own intensity (HU): the median core intensity of the blobs that fit the CAD model.

    With fewer than three markers found, the marker-sized candidates turned down as bone stand in
    (markers brighter than the band's top touch "bone-density" voxels: a low-kVp scan), with the
    median of their voxels above the band's bottom, the bright ones included; None when there is
    neither. A second pass with a band around such an estimate is kept only if it finds at least
    as many markers.
    """
    markers = [o.marker_hu for _, o in outcomes if isinstance(o, DetectedMarker) and np.isfinite(o.marker_hu)]
    if len(markers) >= 3 or markers_only:
        return float(np.median(markers)) if markers else None
    bright = [o.marker_hu for _, o in outcomes if isinstance(o, RejectedCandidate) and o.code == "bone"
              and np.isfinite(o.marker_hu) and abs(o.volume_mm3 / model.volume_mm3 - 1) <= 2 * options.volume_tolerance]
    return float(np.median(bright)) if len(bright) >= 3 else None


def _bright_marker_estimate(volume: np.ndarray, spacing_zyx: np.ndarray, index_to_image: np.ndarray,
                            model: MarkerModel, options: DetectionSettings, progress: Progress,
                            examiners: Examiners) -> float | None:
    """The intensity (HU) of markers brighter than the band's top, measured with the top raised to ``metal_hu``;
    None unless at least three markers are found that way.

    With coarse voxels (about 1 mm) such a marker leaves only its thin partial-volume shell in the default
    band: the coarse search drops it as a speck, so no marker-sized candidate is turned down as bone for
    :func:`_marker_hu_estimate` to measure. Called only when the default band found too little to measure.
    """
    wide = replace(options, high_hu=options.metal_hu)
    outcomes, _ = _one_pass(volume, spacing_zyx, index_to_image, model, wide, progress, None, examiners)
    markers = [o.marker_hu for _, o in outcomes if isinstance(o, DetectedMarker) and np.isfinite(o.marker_hu)]
    return float(np.median(markers)) if len(markers) >= 3 else None


def _band_suits(marker_hu: float, options: DetectionSettings) -> bool:
    """True when the markers' intensity sits well inside the band (default band: 900..1440 HU)."""
    width = options.high_hu - options.low_hu
    return options.low_hu + 0.25 * width <= marker_hu <= options.high_hu - 0.3 * width


def _band_around(marker_hu: float, options: DetectionSettings) -> DetectionSettings:
    """The default band scaled to the markers' intensity (600..1800 HU is 0.545..1.64 of PVC's 1100 HU)."""
    defaults = DetectionSettings()
    low = marker_hu * defaults.low_hu / _PVC_HU
    high = min(marker_hu * defaults.high_hu / _PVC_HU, options.metal_hu)
    return replace(options, low_hu=low, high_hu=high)


_PVC_HU = 1100.0
"""PVC's intensity at 120 kVp, for which the default band 600..1800 HU is made."""



MIN_TOP_CONTRAST = 0.35
"""Least share of the base's contrast a fit's narrow top must show (:func:`~.pose.top_contrast`): markers show
0.71-1.0 on simulated scans at 0.5-1.5 mm voxels and 3 mm slices, a PVC cylinder as wide as the base and of the
marker's volume 0.06 (its base fits the CAD model to 0.02 mm)."""

_SPLIT_CODES = ("shape", "volume", "metal")
"""Rejections that a streak splitting a marker causes: such a blob is tried again with its fragments."""

_STEP_ROWS = 16
"""Coarse rows sampled per step while the CT is being read."""

_REGROW_ROUNDS = 2
"""Times a blob cut by its region is regrown in a larger one (``_regrown``; ``_guard_slices`` counts on it)."""


def _guard_slices(model: MarkerModel, options: DetectionSettings, index_to_image: np.ndarray) -> int:
    """Slices past a region's end that examining the region may look at.

    A blob cut by its region is regrown (``_regrown``, at most ``_REGROW_ROUNDS`` times) in its
    box grown by ``ceil(height / spacing) + 1`` voxels, so the slices read, and the blob's
    centroid, stay within that many times this past the region; the metal check then looks
    ``metal_distance_mm`` plus half the marker's diagonal around the centroid. Slices ``n``
    apart are at least ``n`` times the distance between slice planes apart (the slice spacing,
    less on a sheared grid such as a tilted gantry's).
    """
    step_i, step_j, step_k = index_to_image[:3, :3].T
    normal = np.cross(step_i, step_j)
    plane_mm = abs(float(normal @ step_k)) / float(np.linalg.norm(normal))
    regrow = _REGROW_ROUNDS * (int(np.ceil(model.height_mm / float(np.linalg.norm(step_k)))) + 1)
    metal_mm = options.metal_distance_mm + 0.5 * float(np.hypot(model.height_mm, model.bottom_diameter_mm))
    return regrow + int(np.ceil(metal_mm / plane_mm)) + 1


def _region_key(region: Region) -> tuple[int, ...]:
    return tuple(s.start for s in region.slices) + tuple(s.stop for s in region.slices)


def _result(outcomes: list[tuple[np.ndarray, DetectedMarker | RejectedCandidate]], too_large: list[TooLarge],
            index_to_image: np.ndarray, options: DetectionSettings, image: ImageGeometry, volume: np.ndarray,
            model: MarkerModel) -> DetectionResult:
    """Markers and rejected candidates, each blob once (overlapping regions can reach the same blob)."""
    markers: list[DetectedMarker] = []
    rejected = [RejectedCandidate(apply_transform(index_to_image, t.centroid_zyx[::-1].astype(float)), t.volume_mm3,
                                  f"too large for a marker (about {t.volume_mm3:.0f} mm3, {t.extent_mm:.0f} mm long)",
                                  "volume") for t in too_large]
    kept: list[np.ndarray] = []
    for key, outcome in sorted(outcomes, key=lambda item: not isinstance(item[1], DetectedMarker)):
        if any(np.linalg.norm(key - other) < 1.0 for other in kept):
            continue  # the same blob reached from two overlapping regions
        kept.append(key)
        (markers if isinstance(outcome, DetectedMarker) else rejected).append(outcome)
    markers.sort(key=lambda m: (m.origin[2], m.origin[1], m.origin[0]))
    for i, marker in enumerate(markers, start=1):
        marker.id = f"I{i:02d}"
    rejected.sort(key=lambda r: (r.centroid[2], r.centroid[1], r.centroid[0]))
    if len(markers) < options.min_markers:
        raise NoSafeAnswerError(_too_few_message(len(markers), options, rejected) + _size_hint(image, model)
                                + _intensity_hint(volume))
    return DetectionResult(markers, rejected, image_geometry(image))


def _workers() -> int:
    """Threads for the regions: the heavy parts (numpy, VTK, most of scipy.ndimage) release the GIL."""
    return max(1, min(4, os.cpu_count() or 1))


def _regrown(volume: np.ndarray, blob: Blob, index_to_image: np.ndarray, spacing_zyx: np.ndarray,
             model: MarkerModel, options: DetectionSettings) -> Blob:
    """The whole of a blob that its coarse region cut (e.g. a marker split in two by the coarse pass)."""
    reach = 1.5 * float(np.hypot(model.height_mm, model.bottom_diameter_mm))
    for _ in range(_REGROW_ROUNDS):
        extent = (blob.box_zyx[1] - blob.box_zyx[0]) * spacing_zyx
        if not blob.touches_region_edge or np.max(extent) > reach:
            return blob
        centre = blob.centroid()
        region = region_around(blob, spacing_zyx, volume.shape, margin_mm=model.height_mm)
        grown = blobs_in_region(volume, region, index_to_image, spacing_zyx, model, options)
        if not grown:
            return blob
        blob = min(grown, key=lambda b: float(np.linalg.norm(b.centroid() - centre)))
    return blob


def _classify(blob: Blob, metal_zyx: np.ndarray, index_to_image: np.ndarray, model: MarkerModel,
              options: DetectionSettings) -> DetectedMarker | RejectedCandidate:
    measures = measure_blob(blob, options)
    centroid, volume = measures.centroid, measures.volume_mm3

    marker_hu = measures.marker_hu

    def reject(reason: str, code: str) -> RejectedCandidate:
        return RejectedCandidate(centroid, volume, reason, code, marker_hu=marker_hu)

    if blob.touches_image_edge:
        return reject("cut by the edge of the image", "edge")
    reach = 0.5 * float(np.hypot(model.height_mm, model.bottom_diameter_mm))
    near_metal = metal_distance_mm(centroid, metal_zyx, index_to_image, blob, options) \
        <= options.metal_distance_mm + reach
    strict = 0.5 if near_metal else 1.0
    problem, code = None, ""
    if blob.touches_region_edge:
        problem, code = "extends beyond a marker-sized region (too large)", "volume"
    elif measures.bone_fraction > options.bone_fraction:
        problem, code = f"touches bone-density voxels (>= {options.high_hu:g} HU)", "bone"
        marker_hu = measures.bright_hu  # a marker brighter than the band (low kVp) is mostly above it
    else:
        problem, code = _size_and_shape_problem(measures.volume_mm3, measures.spreads_mm, model, options, strict,
                                                float(np.max(blob.spacing_zyx)))
    if problem is None:
        fit = fit_pose(blob.mask, blob.work_to_image, blob.full_values, blob.full_to_image, model,
                       min_contrast_hu=0.5 * (measures.marker_hu - options.low_hu),
                       min_inner_hu=options.low_hu, trim_mm=3 * options.max_fit_rms_mm,
                       good_rms_mm=strict * options.max_fit_rms_mm)
        if fit.fit_rms_mm > strict * options.max_fit_rms_mm:
            problem, code = f"the marker model does not fit (rms {fit.fit_rms_mm:.2f} mm)", "shape"
        elif fit.inlier_fraction < options.min_inlier_fraction:
            problem, code = f"the marker model fits only {100 * fit.inlier_fraction:.0f}% of its edges", "shape"
        elif (contrast := top_contrast(blob.full_values, blob.full_to_image, fit.marker_to_image, model)) \
                < MIN_TOP_CONTRAST:
            problem, code = (f"no narrow top where the marker's should be (it shows {100 * contrast:.0f}% of the "
                             "base's contrast): a solid as wide as the marker's base"), "shape"
    if problem is not None:
        if near_metal:
            return reject(f"wrecked by metal artefacts nearby ({problem})", "metal")
        return reject(problem, code)
    return DetectedMarker("", fit.origin, fit.axis, volume, fit.fit_rms_mm, marker_hu=measures.marker_hu)


def _size_and_shape_problem(volume: float, spreads: np.ndarray, model: MarkerModel, options: DetectionSettings,
                            strict: float, largest_voxel_mm: float) -> tuple[str | None, str]:
    """Why a blob's volume or principal spreads rule out a marker, or None.

    Voxels blur the marker's narrow top and its pinhole and quantise the spreads, the more the
    smaller the marker is against them (measured on simulated scans: 0.4 mm off for a 10 mm
    marker at 0.6 mm voxels, 0.95 mm for the 16 mm one at 1.25 mm, 1.2 mm at 1.5 mm): each
    spread gets 0.6 of the largest voxel side as extra tolerance. This is only a first sieve
    (rods, plates, lumps); the CAD fit that follows rejects what merely looks like a marker.
    """
    ratio = volume / model.volume_mm3
    if abs(ratio - 1) > strict * options.volume_tolerance:
        return f"volume {volume:.0f} mm3 is {100 * ratio:.0f}% of the marker's {model.volume_mm3:.0f} mm3", "volume"
    model_spreads, _ = model_moments(model)
    allowed = strict * (options.shape_tolerance * model_spreads + 0.6 * largest_voxel_mm)
    if np.any(np.abs(spreads - model_spreads) > allowed):
        return ("principal spreads " + "/".join(f"{v:.1f}" for v in spreads) + " mm unlike the marker's "
                + "/".join(f"{v:.1f}" for v in model_spreads) + " mm"), "shape"
    return None, ""


def _size_hint(image: ImageGeometry, model: MarkerModel) -> str:
    """A note for the too-few-markers message when the whole CT is smaller than two markers side by side:
    its spacing and origin are then not millimetres (metres or centimetres, e.g.). Empty otherwise."""
    extent_mm = np.asarray(image.GetSize(), dtype=float) * np.asarray(image.GetSpacing(), dtype=float)
    marker_mm = max(model.height_mm, model.bottom_diameter_mm)
    if np.max(extent_mm) >= 2 * marker_mm:
        return ""
    return (f"; the whole CT spans only {' x '.join(f'{v:.3g}' for v in extent_mm)} mm (spacing "
            f"{', '.join(f'{v:.3g}' for v in image.GetSpacing())}), less than two markers of {marker_mm:g} mm: "
            "EMReg reads spacing and origin in millimetres (is the file in metres or centimetres?)")


def _intensity_hint(volume: np.ndarray) -> str:
    """A note for the too-few-markers message when the CT's air does not read near -1000 HU (its darkest
    voxels, 2nd percentile of a sample): the values are then not Hounsfield units, typically stored pixel
    values without their rescale intercept (HU + 1024). Empty otherwise."""
    values = volume[::2, ::4, ::4]
    if values.size == 0:
        return ""
    air = float(np.percentile(values, 2))
    if air < _AIR_READS_BELOW_HU:
        return ""
    return (f"; the CT's darkest voxels read {air:.0f} where air reads -1000 HU: its values do not look like "
            "Hounsfield units (stored pixel values without their rescale intercept, e.g. HU + 1024?); convert "
            "the CT to HU")


_AIR_READS_BELOW_HU = -500.0
"""Air (around and inside the frame) reads -1000 HU; darkest voxels above this mean the values are not HU."""


def _too_few_message(found: int, options: DetectionSettings, rejected: list[RejectedCandidate]) -> str:
    counts: dict[str, int] = {}
    for r in rejected:
        counts[r.code] = counts.get(r.code, 0) + 1
    summary = ", ".join(f"{n} {code}" for code, n in sorted(counts.items())) or "none"
    return (f"{found} marker(s) found in the CT, at least {options.min_markers} needed (rejected candidates: "
            f"{summary}); check that the CT shows the frame and the [detection] thresholds "
            f"(low_hu {options.low_hu:g}, high_hu {options.high_hu:g}) bracket the markers' intensity")
