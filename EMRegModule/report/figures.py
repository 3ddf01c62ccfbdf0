"""The report's figures: one function per figure, listed in the registry :data:`FIGURES`.

Each entry says whether the figure can be drawn from what the run left (``available``), whether
it uses the CT's voxels (``uses_ct``; ``needs_ct``: left out without them) and what of it can be
prepared without them (``prepare``): the other figures and those preparations are done first,
while the CT is still being read. The CT is used twice, without any full-size copy: block-averaged
for the 3D view's context surface (:mod:`EMRegModule.rendering.context`, following the read),
and sampled on small planes around each marker for the slices.
"""

from __future__ import annotations

from collections.abc import Callable, Mapping
from concurrent.futures import Future, ThreadPoolExecutor
from dataclasses import dataclass, field
from typing import Any

import numpy as np
import SimpleITK as sitk
from scipy.ndimage import map_coordinates

from ..core.calibration import CalibrationPoint
from ..core.distortion import POWER_LEVEL, DistortionEstimate
from ..core.transforms import apply_transform
from ..errors import EMRegError
from ..io.dicom_read import NarrowVoxelsError
from ..progress import QUIET, Progress
from ..rendering.checkpoint_chart import checkpoint_chart
from ..rendering.colors import GREY, colorize, residual_range
from ..rendering.context import ContextSurface, bin_factor, binned_ct, context_surface
from ..rendering.error_views import distortion_views, error_budget_chart, tre_map_slices
from ..rendering.guidance_chart import approach_chart, plan_ct_views, plan_view_chart
from ..rendering.images import encode_png
from ..rendering.plots import bar_chart, fit_text, line_chart
from ..rendering.robot_charts import residual_panels
from ..rendering.scene3d import FrameScene, FrameSceneRenderer, SceneMarker
from ..rendering.slices import SliceMarker, StreamingMarkerViews, marker_slices_mosaic
from .checks import ReportWarning
from .derived import MarkerRow, calibration_points_in_image, finite_or_none, tre_figures
from .inputs import ReportInputs, open_report_ct
from .robot_inputs import load_robot_fit

#: The widest a pinhole's label is drawn in a marker's caption on the CT slices (pixels at the captions' font).
CAPTION_LABEL_PX = 170

#: Navigated probe positions drawn in the 3D view at most (a longer path is thinned evenly).
MAX_PATH_POINTS = 2000


@dataclass
class Figure:
    """A rendered figure: file name stem, title, caption and its PNG bytes (``png``; ``encoded``: the bytes, or
    their encoding still going on on a thread)."""

    name: str
    title: str
    caption: str
    encoded: bytes | Future[bytes]

    @property
    def png(self) -> bytes:
        if isinstance(self.encoded, Future):
            self.encoded = self.encoded.result()
        return self.encoded


_ENCODER: list[ThreadPoolExecutor] = []


def _png(image_rgb: np.ndarray) -> Future[bytes]:
    """:func:`encode_png` on a thread of its own: OpenCV lets this one draw the next figure meanwhile."""
    if not _ENCODER:
        _ENCODER.append(ThreadPoolExecutor(1, thread_name_prefix="emreg-png"))
    return _ENCODER[0].submit(encode_png, image_rgb)


@dataclass
class ReportData:
    """Everything the figures and the page draw on, derived once from the inputs."""

    inputs: ReportInputs
    rows: list[MarkerRow]
    points: dict[str, CalibrationPoint]
    curve: tuple[np.ndarray, np.ndarray] | None = None
    curve_stored: bool = False
    warnings: list[ReportWarning] = field(default_factory=list)
    surface: ContextSurface | None = None
    scene_renderer: object | None = None  # a FrameSceneRenderer built before the CT is read
    marker_views: object | None = None  # StreamingMarkerViews: the slices sampled as the CT is read
    binned: object | None = None  # the block-averaged CT (BinnedCT) the context surface is contoured from
    kept_whole: bool = False  # every CT product came from the file an earlier report kept (report.ct_memo)
    robot_fit: tuple[Any, str | None] | None = None  # (CalibrationFit or None, why not): see robot_fit()

    @property
    def l_mm(self) -> float | None:
        """The registration's sensor offset (mm), or None without a registration."""
        return None if self.inputs.registration is None else finite_or_none(self.inputs.registration.sensor_offset_l_mm)


# --- the 3D view -------------------------------------------------------------------------------


def _frame_scene(data: ReportData):
    inputs, registration = data.inputs, data.inputs.registration
    sensor_points = None
    sensor_points_name = "sensor points at the solved l"
    if registration is not None and registration.point_fit:  # no CT: the fiducials are what the points fit onto
        sensor_points = np.asarray([p["position"] for p in registration.fiducials.get("points") or []], dtype=float)
        sensor_points_name = "fiducials"
    elif data.l_mm is not None:
        paired = [r.sensor_point(data.l_mm) for r in data.rows if r.residual_mm is not None]
        sensor_points = np.stack(paired) if paired else None
    navigation = inputs.navigation_positions
    if navigation is not None and len(navigation) > MAX_PATH_POINTS:
        navigation = navigation[:: int(np.ceil(len(navigation) / MAX_PATH_POINTS))]
    return FrameScene(
        model=inputs.model,
        markers=[SceneMarker(r.id, r.marker_to_image, r.residual_mm) for r in data.rows],
        context_surface=data.surface.surface if data.surface is not None else None,
        reference_to_image=registration.reference_to_image if registration is not None else None,
        calibration_points=calibration_points_in_image(inputs, data.points),
        sensor_points=sensor_points,
        sensor_points_name=sensor_points_name,
        targets=inputs.targets_positions,
        target_labels=inputs.targets_labels,
        navigation_path=navigation,
    )


def _scene_caption(scene) -> str:
    """What the 3D view shows, as the scene holds it (a run without a registration, targets or navigation has
    no reference sensor, calibration points, targets or probe path to name)."""
    has = lambda points: points is not None and len(points) > 0  # noqa: E731
    registered = scene.reference_to_image is not None
    shown = [
        ("fitted marker models coloured by registration residual (grey: unpaired)" if registered else
         "fitted marker models (grey: no registration)") if scene.markers else "",
        "the reference sensor with its axes (red X, green Y, blue Z)" if registered else "",
        "calibration points mapped into the CT (magenta)" if has(scene.calibration_points) else "",
        f"{scene.sensor_points_name} (yellow)" if has(scene.sensor_points) else "",
        "targets (red)" if has(scene.targets) else "",
        "the navigated probe path (cyan)" if has(scene.navigation_path) and len(scene.navigation_path) > 1 else ""]
    shown = [text for text in shown if text]
    if not shown:
        return "The frame."
    text = shown[0] if len(shown) == 1 else ", ".join(shown[:-1]) + " and " + shown[-1]
    return text[0].upper() + text[1:] + "."


def prepare_context_surface(data: ReportData) -> None:
    """Bin the CT (following its read) and contour it for the 3D view; the marker slices are sampled meanwhile.

    A CT that fails to read becomes a note (and no CT figure).
    """
    prepare_ct_products(data)
    if data.binned is not None and data.surface is None:
        data.surface = context_surface(data.binned, data.inputs.settings.report.iso_value)


def prepare_ct_products(data: ReportData) -> None:
    """What the figures take from the CT's voxels: the block-averaged CT and the marker planes (made as the CT
    is read; no rendering library is needed). A CT that fails to read becomes a note (and no CT figure)."""

    if data.inputs.ct is None or data.binned is not None:
        return
    memo = data.inputs.ct.memo  # kept by an earlier report of this run (report.ct_memo)
    if memo is not None:
        if memo.matches([r.marker_to_image for r in data.rows]):
            data.binned, data.marker_views = memo.binned, memo if data.rows else None
            data.surface = memo.context_surface(data.inputs.settings.report.iso_value)  # None: made from binned
            data.kept_whole = data.surface is not None
            return

        open_report_ct(data.inputs)
        if data.inputs.ct is None:
            return
    try:
        _sample_ct(data)
    except NarrowVoxelsError:  # a compact DICOM read met a value beyond int16: the whole CT again, exactly
        _sample_ct(data, read_exactly=True)


def _sample_ct(data: ReportData, read_exactly: bool = False) -> None:
    try:
        if read_exactly:
            data.inputs.read_ct_exactly()
        ct = data.inputs.ct
        data.marker_views = None
        if data.rows:
            data.marker_views = StreamingMarkerViews(ct.image, _slice_markers(data), data.inputs.model,
                                                     array=ct.array)
        views = data.marker_views
        factor = bin_factor(ct.image.GetSize())

        def on_slices(read: int) -> None:  # slices 0 .. read-1 are in; those below read - factor are binned
            if views is not None:
                views.sample_ready(read)
            # slices used by nothing any more go back (voxels in anonymous memory: a streamed read)
            ct.release_before(min(read - factor, views.first_needed_slice() if views is not None else read))

        data.binned = binned_ct(ct, on_slices=on_slices)
    except EMRegError as exc:
        data.inputs.notes.append(str(exc))
        data.inputs.ct, data.marker_views = None, None


def prepare_scenes(data: ReportData) -> None:
    """Build the 3D scene and, while the CT is still being read, draw it once without the CT surface (the
    first frame's set-up then costs nothing later); with the CT's products at hand there is nothing to wait for."""

    data.scene_renderer = FrameSceneRenderer(_frame_scene(data), (960, 720))
    if not _ct_products_at_hand(data):
        data.scene_renderer.warm_up()


def _ct_products_at_hand(data: ReportData) -> bool:
    """Whether the CT's products need no read: kept by an earlier report (report.ct_memo), made, or no CT."""
    return data.inputs.ct is None or data.binned is not None or getattr(data.inputs.ct, "memo", None) is not None


def render_scenes(data: ReportData) -> list[Figure]:
    """The 3D view of the frame from two directions (one scene, two cameras), inside the CT surface."""
    if data.scene_renderer is None:
        prepare_scenes(data)
    renderer, data.scene_renderer = data.scene_renderer, None
    try:
        prepare_context_surface(data)
        if data.surface is not None:
            renderer.set_context_surface(data.surface.surface)
        images = renderer.screenshots(("oblique", "top"))
    finally:
        renderer.close()
    caption = _scene_caption(renderer.scene) + (" " + data.surface.description() if data.surface is not None
                                                 else "")
    return [Figure("scene_oblique", "3D view of the frame", caption, _png(images[0])),
            Figure("scene_top", "3D view from above", caption, _png(images[1]))]


# --- CT slices ------------------------------------------------------------------------------------


def _slice_markers(data: ReportData) -> list:
    """Every detected marker as drawn on the slices: caption, paired or not, sensor and calibration points."""

    registration = data.inputs.registration
    slice_markers = []
    for r in data.rows:
        caption, calibration_point = r.id, None
        if r.calibration_label is not None:
            caption += f" -> {fit_text(r.calibration_label, CAPTION_LABEL_PX, 0.42)}"  # the residual stays in view
            if r.residual_mm is not None:
                caption += f"  {r.residual_mm:.2f} mm"
            if registration is not None and r.calibration_label in data.points:
                calibration_point = apply_transform(registration.reference_to_image,
                                                    data.points[r.calibration_label].position)
        elif registration is not None:
            caption += "  (unpaired)"
        slice_markers.append(SliceMarker(
            r.id, r.marker_to_image, caption, paired=r.calibration_label is not None or registration is None,
            sensor_point=r.sensor_point(data.l_mm) if data.l_mm is not None else None,
            calibration_point=calibration_point))
    return slice_markers


def render_marker_slices(data: ReportData) -> list[Figure]:
    """Two planes along each marker's axis and one across its base, with the fitted outline."""

    prepare_context_surface(data)  # samples the slices while following the CT's read
    if data.inputs.ct is None:
        return []
    views = data.marker_views.views() if data.marker_views is not None else None
    mosaic = marker_slices_mosaic(data.inputs.image, _slice_markers(data), data.inputs.model, views=views)
    return [Figure("marker_slices", "CT slices through each marker",
                   "Per marker: two planes through the marker axis (XY, ZY) and a cross-section of its base (XZ), "
                   "with the fitted model outline (green: paired, orange: unpaired), the sensor point at the solved "
                   "l (yellow dot) and the calibration point mapped by ReferenceToImage (magenta cross). "
                   "0.2 mm per pixel.", _png(mosaic))]


# --- plots ----------------------------------------------------------------------------------------


def render_residuals(data: ReportData) -> list[Figure]:
    """The registration residual of each pair, coloured as in the 3D view, with the FRE."""
    registration = data.inputs.registration
    paired = [r for r in data.rows if r.residual_mm is not None]
    if paired:
        labels, values = [r.id for r in paired], [float(r.residual_mm) for r in paired]
    else:  # pairs name markers this report does not know: plot from the pairs alone
        labels = [f"{p['image_marker']}" for p in registration.pairs]
        values = [float(p["residual_mm"]) for p in registration.pairs]
    low, high = residual_range(np.asarray(values))
    colors = [tuple(int(c) for c in colorize([v], low, high)[0]) for v in values]
    fre_mm = finite_or_none(registration.fre_mm)
    lines = [(fre_mm, f"FRE {fre_mm:.2f} mm")] if fre_mm is not None else []
    what = "fiducial" if registration.point_fit else "marker"
    chart = bar_chart(labels, values, title=f"Registration residual per {what}", y_label="residual (mm)",
                      colors=colors or [GREY], reference_lines=lines)
    caption = ("Distance between each calibration point mapped into the fiducials' frame and its fiducial"
               if registration.point_fit else
               "Distance between each calibration point mapped into the CT and its marker's sensor point at the "
               "solved l")
    return [Figure("residuals", f"Residual per {what}", caption + "; the dashed line is the FRE (RMS).", _png(chart))]


def render_fre_curve(data: ReportData) -> list[Figure]:
    """FRE(l) over the pinhole range (paper Eq. 10) with the chosen l marked."""
    l_values, values = data.curve
    l_mm = data.l_mm
    fre_mm = finite_or_none(data.inputs.registration.fre_mm)
    if data.curve_stored and l_mm is not None and fre_mm is not None and l_values[0] <= l_mm <= l_values[-1]:
        # the stored curve is sampled every 0.25 mm: near a sharp minimum the straight line between two samples
        # passes well above the FRE at the chosen l (0.33 against 0.30 mm on a simulated case); the chosen l and
        # the registration's FRE there are a point of the same curve, so the line goes through it
        k = int(np.searchsorted(l_values, l_mm))
        l_values, values = np.insert(l_values, k, l_mm), np.insert(values, k, fre_mm)
    label = ""
    if l_mm is not None:
        label = f"chosen l = {l_mm:.2f} mm, FRE {float(np.interp(l_mm, l_values, values)):.2f} mm"
    chart = line_chart(l_values, values, "FRE(l) over the pinhole range", "sensor offset l (mm)", "FRE (mm)",
                       marker_x=l_mm, marker_label=label)
    source = "as the registration computed it" if data.curve_stored else "recomputed here from the reported pairs"
    return [Figure("fre_curve", "FRE as a function of the sensor offset l",
                   f"Paper Eq. 10, {source}: for each l in the pinhole range the rigid fit of the calibration points "
                   "to the sensor points at l; the dot marks the l the registration chose.", _png(chart))]


def render_tre_targets(data: ReportData) -> list[Figure]:
    """Measured TRE per target (mean and spread) with the predicted end-to-end RMS TRE when there is one."""
    tre = data.inputs.evaluation.tre
    labels = list(tre.targets)
    means = [np.nan if s.mean_mm is None else float(s.mean_mm) for s in tre.targets.values()]
    stds = [float(s.std_mm or 0.0) for s in tre.targets.values()]
    mean = finite_or_none(tre_figures(data.inputs.evaluation).get("mean_mm"))
    lines = [(mean, f"mean {mean:.2f} mm")] if mean is not None else []
    predicted = [finite_or_none(tre.predictions[t].predicted_rms_mm) if t in tre.predictions else None
                 for t in labels]
    overlay = [np.nan if p is None else p for p in predicted] if any(p is not None for p in predicted) else None
    chart = bar_chart(labels, means, errors=stds, title="Target registration error", y_label="TRE (mm)",
                      reference_lines=lines, overlay=overlay, overlay_label="predicted RMS" if overlay else "")
    return [Figure("tre_targets", "TRE per target",
                   "Mean and standard deviation over the dwells at each target"
                   + (", with the end-to-end RMS TRE the error model predicts (red)" if overlay else "")
                   + " (paper: 1.38 +/- 0.32 mm over 6 targets x 15 placements)."
                   + (f" {tre.invalid_poses_left_out} INVALID poses (after a failed checkpoint, or a bad tracker "
                      f"quality) were left out, {tre.dwells_left_out or 0} dwell(s) among them."
                      if tre.invalid_poses_left_out else ""), _png(chart))]


def _has_tre(data: ReportData) -> bool:
    evaluation = data.inputs.evaluation
    return evaluation is not None and evaluation.tre is not None and bool(evaluation.tre.targets)


def _has_budget(data: ReportData) -> bool:
    return _has_tre(data) and bool(data.inputs.evaluation.tre.predictions)


def render_error_budget(data: ReportData) -> list[Figure]:
    """The predicted error budget per target, stacked, beside the measured RMS TRE."""
    tre = data.inputs.evaluation.tre
    labels = [t for t in tre.targets if t in tre.predictions]
    terms = list(tre.predictions[labels[0]].budget_rms_mm)
    budget = {term: [v if (v := tre.predictions[t].budget_rms_mm.get(term, np.nan)) is not None and np.isfinite(v)
                     else np.nan for t in labels] for term in terms}
    measured = tre_figures(data.inputs.evaluation)["targets"]
    chart = error_budget_chart(labels, budget, [measured[t].get("rms_mm", np.nan) for t in labels])
    source = tre.tracking_source or "calibration"
    return [Figure("error_budget", "Error budget per target",
                   "The predicted end-to-end RMS TRE at each target split into its terms (they add in quadrature: "
                   "each segment is what its term adds): the registration (fiducial errors of both spaces through "
                   "the fit, l included), the probe's tracking error at the target (measured from the "
                   f"{source}), the reference sensor's pose error during calibration and navigation (a prior) and "
                   "the placement; the black line is the measured RMS TRE.", _png(chart))]


def _distortion(data: ReportData) -> DistortionEstimate | None:
    """The registration's distortion estimate, when it was tested (None otherwise)."""
    registration = data.inputs.registration
    error = None if registration is None else registration.error
    estimate = None if error is None else error.distortion
    return estimate if estimate is not None and estimate.tested and len(estimate.points_mm) else None


def render_distortion(data: ReportData) -> list[Figure]:
    """The residual vectors on the frame and the fitted distortion field's size (Reference frame)."""
    estimate = _distortion(data)
    verdict = (f"field distortion detected: {estimate.rms_mm:.2f} mm RMS, up to {estimate.largest()[0]:.2f} mm near "
               f"{estimate.where()}" if estimate.detected else "no field distortion detected")
    image = distortion_views(estimate.points_mm, estimate.residuals_mm, estimate.pinhole_field(),
                             lambda points: np.linalg.norm(estimate.field_at(points), axis=1),
                             f"{verdict} (p = {estimate.p_value:.2g})")
    return [Figure("distortion", "Field distortion",
                   "The registration's residual at each pinhole (black arrow: the calibration point minus its CT "
                   "pinhole, in the Reference frame, magnified) and the non-rigid field distortion fitted to them "
                   "(magenta; colour: its size on the plane through the pinholes, in two views along their "
                   "principal axes). Noise scatters the black arrows at random; a field moves neighbours alike. "
                   + _trust_words(estimate), _png(image))]


def _trust_words(estimate: DistortionEstimate) -> str:
    """Whether the predicted error can be relied on, in words for the surgeon (``prediction_trust``)."""
    trust = estimate.prediction_trust()
    size = estimate.detectable_rms_mm
    reach = ("" if estimate.detected or np.isnan(size) else
             f" With this calibration's noise and pinholes the check finds a field of {size:.2f} mm RMS or more at the "
             f"pinholes in {POWER_LEVEL:.0%} of smooth fields; a smaller one may go unseen." if np.isfinite(size) else
             " With this calibration's noise and pinholes the check cannot rule out a field of any size.")
    if trust["trusted"]:
        return ("The residuals show no sign of a distorted field: the predicted error rests on a model they agree "
                "with." + reach)
    return "Do not rely on the predicted error alone: " + "; ".join(trust["reasons"]) + "." + reach


def render_tre_map(data: ReportData) -> list[Figure]:
    """Three planes of ``tre_map.nrrd`` through the targets (or the map's centre)."""
    tre_map = sitk.ReadImage(str(data.inputs.folder.tre_map_path))
    positions = data.inputs.targets_positions if data.inputs.targets_positions is not None else np.zeros((0, 3))
    image = tre_map_slices(tre_map, positions, data.inputs.targets_labels or [])
    return [Figure("tre_map", "Predicted TRE over the CT",
                   "tre_map.nrrd: the predicted end-to-end RMS TRE (mm) on index planes of the CT's grid through the "
                   "targets' centre, with iso-lines; it grows with the distance from the markers' centroid and from "
                   "the reference sensor. Load it in 3D Slicer as a colour overlay on the CT.", _png(image))]


def read_checkpoints(data: ReportData) -> Mapping[str, object] | None:
    """``OUT/checkpoints.json`` when it holds at least one checkpoint (None otherwise, or unreadable)."""
    return data.inputs.folder.checkpoints


def render_checkpoints(data: ReportData) -> list[Figure]:
    """The error at each checkpoint during navigation over time, with the limit and the reference's jumps."""
    document = read_checkpoints(data)
    checkpoints = document["checkpoints"]
    limit = float(document["max_error_mm"])
    chart = checkpoint_chart([0.5 * (c["start_s"] + c["end_s"]) for c in checkpoints],
                             [c["error_mm"] for c in checkpoints], [bool(c["ok"]) for c in checkpoints], limit,
                             [j["time_s"] for j in document.get("reference_jumps", [])])
    failed = sum(not c["ok"] for c in checkpoints)
    by_slip = sum(not c["ok"] and bool((c.get("slip") or {}).get("fails")) for c in checkpoints)
    return [Figure("checkpoints", "Checkpoints during navigation",
                   f"Each rest of the probe in a marker's pinhole during navigation: the distance (mm) of the "
                   f"navigated probe from the pinhole at the solved l, where it must be; above the limit "
                   f"({limit:g} mm, [navigation] max_checkpoint_error_mm; red) the poses are INVALID until a "
                   f"checkpoint passes. {len(checkpoints)} checkpoint(s), {failed} failed; dotted lines: sudden jumps "
                   "of the reference sensor (a bumped frame or a slipped reference)."
                   + (f" {by_slip} failed as the reference's slip (the error the jump predicts there, larger "
                      "elsewhere on the frame), red even below the limit." if by_slip else ""), _png(chart))]


def _has_guidance(data: ReportData) -> bool:
    series = data.inputs.folder.guidance_series
    return data.inputs.folder.guidance is not None and series is not None and bool(series["ok"].any())


def render_guidance(data: ReportData) -> list[Figure]:
    """The tip's approach to the planned target (``navigation.json`` and the guidance columns of ``navigation.csv``):
    its distance to the target and to the line over time, and (with an Entry) its path beside the planned line."""

    document, series = data.inputs.folder.guidance, data.inputs.folder.guidance_series
    series = {name: values[series["ok"]] for name, values in series.items()}  # the poses shown as valid
    closest = document.get("closest_approach") or {}
    radius = (document.get("predicted_at_target") or {}).get("radius_95_mm")
    figures = [Figure("guidance_approach", "Approach to the target",
                      "The navigated tip's distance to the planned target (blue) and to the planned line (grey) over "
                      "the navigation (mm), OK poses only; red dot: the closest approach; dashed: the 95 % radius of "
                      "the error predicted at the target.",
                      _png(approach_chart(series["time_s"], series["target_distance_mm"], series["lateral_mm"],
                                          closest.get("time_s"), radius)))]
    length = (document.get("plan") or {}).get("length_mm")
    if length:
        depth = float(length) - series["to_go_mm"]
        figures.append(Figure("guidance_plan_view", "Tip path beside the planned line",
                              "Every navigated tip position in the plan's own frame: its depth along the plan from the "
                              "Entry (mm) against its distance from the planned line (mm); red: the planned line "
                              "from Entry to Target.", _png(plan_view_chart(depth, series["lateral_mm"],
                                                                            float(length)))))
    return figures


def _has_plan_in_ct(data: ReportData) -> bool:
    return _has_guidance(data) and bool((data.inputs.folder.guidance.get("plan") or {}).get("entry_mm"))


def render_plan_in_ct(data: ReportData) -> list[Figure]:
    """Two CT planes containing the planned line (from the block-averaged CT the 3D view uses), with the tip path."""

    prepare_ct_products(data)
    binned = data.binned
    if binned is None:
        return []
    image_to_index = np.linalg.inv(binned.index_to_image)

    def sample(points: np.ndarray) -> np.ndarray:
        index = apply_transform(image_to_index, points.reshape(-1, 3))
        return map_coordinates(binned.values, index[:, ::-1].T, order=1, mode="constant", cval=np.nan,
                               output=np.float32).reshape(points.shape[:-1])

    document, series = data.inputs.folder.guidance, data.inputs.folder.guidance_series
    plan, closest = document["plan"], document.get("closest_approach") or {}
    tips = data.inputs.navigation_positions[series["ok"]] if data.inputs.navigation_positions is not None else []
    views = plan_ct_views(sample, np.array(plan["entry_mm"]), np.array(plan["target_mm"]), tips,
                          None if not closest else np.array(closest["position_mm"]))
    voxel = float(np.max(np.linalg.norm(binned.index_to_image[:3, :3], axis=0)))
    return [Figure("guidance_ct", "The planned line in the CT",
                   "Two CT planes containing the planned line (red, Entry at the top), at right angles to each other: "
                   f"the block-averaged CT of the 3D view ({voxel:.1f} mm voxels), 0.5 mm per pixel; blue: the OK "
                   "tip positions within 3 mm of the plane; yellow: the closest approach.", _png(views))]


# --- the robot (issue 39) -------------------------------------------------------------------------


def robot_fit(data: ReportData) -> tuple[Any, str | None]:
    """The hand-eye calibration's fit to its recordings (:func:`~.robot_inputs.load_robot_fit`), once per report:
    (a :class:`~EMRegModule.core.handeye_profile.CalibrationFit` or None, why none)."""
    if data.robot_fit is None:
        data.robot_fit = load_robot_fit(data.inputs)
    return data.robot_fit


def _has_robot_fit(data: ReportData) -> bool:
    return data.inputs.folder.robot_calibration is not None and robot_fit(data)[0] is not None


def render_robot_calibration(data: ReportData) -> list[Figure]:
    """The hand-eye residual of every tracker sample, and the residual against the clock offset."""
    fit = robot_fit(data)[0]
    left_out = int(np.count_nonzero(fit.rejected))
    residuals = Figure(
        "robot_residuals", "Hand-eye residual per tracker sample",
        "For every sample of the flange sensor: where the robot says the sensor is (FlangeToBase @ SensorToFlange) "
        "against where the tracker says it is (TrackerToBase @ SensorToTracker), as the rotation between them "
        f"(degrees) and the distance between their origins (mm). Blue: the samples the calibration used; red: the "
        f"{left_out} it left out (glitches, distorted moments, moments the robot's log does not cover; a triangle on "
        "the top edge: beyond the scale). Fast motion spreads the residual (the clocks' jitter); still dwells sit "
        "lowest.", _png(residual_panels(fit.time_s, fit.rotation_deg, fit.translation_mm, fit.rejected)))
    shift_ms = (fit.offsets_s - fit.time_offset_s) * 1000.0
    chart = line_chart(shift_ms, fit.offset_residual_mm, "Residual against the clock offset",
                       "offset from the chosen time_offset_s (ms)", "median residual (mm)", marker_x=0.0,
                       marker_label=f"time_offset_s = {fit.time_offset_s:.4f} s")
    clock = Figure(
        "robot_clock", "Clock-offset fit",
        "The robot's log and the tracker run on different clocks (t_tracker = t_robot + time_offset_s). The curve is "
        "the median residual of the samples used (the sensor origin's distance and the rotation's at 150 mm, mm) "
        "had the clocks been offset otherwise, SensorToFlange and TrackerToBase kept; the red line is the offset "
        "the calibration chose. A clear valley there means the offset is well determined; a flat curve, that the "
        "motion was too slow to tell (still dwells do not depend on it).", _png(chart))
    return [residuals, clock]


def render_robot_go(data: ReportData) -> list[Figure]:
    """The guide's measured error after the move and after each correction of ``emreg robot-go``."""
    document = data.inputs.folder.robot_go
    steps = document["measurements"]
    labels = ["after the move" if int(m["step"]) == 0 else f"correction {int(m['step'])}" for m in steps]
    tolerance = finite_or_none(document.get("tolerance_mm"))
    chart = bar_chart(labels, [float(m["tip_mm"]) for m in steps], title="Needle tip at the planned depth to Target",
                      y_label="tip error (mm)", overlay=[float(m["exit_mm"]) for m in steps],
                      overlay_label="guide exit to Entry (mm)",
                      reference_lines=[(tolerance, f"tolerance {tolerance:g} mm")] if tolerance is not None else [])
    return [Figure("robot_go", "Guide to plan, closed loop",
                   "emreg robot-go measured the guide with the flange sensor and the live reference after moving it "
                   "onto the plan, then after each correction: bars, how far the needle tip would land from Target "
                   "at the planned depth; red ticks, how far the guide's exit is from Entry; dashed, the tolerance "
                   "([robot] tolerance_mm) it corrects down to.", _png(chart))]


def _has_robot_go(data: ReportData) -> bool:
    """``robot_go.json`` holds measurements, each with its step and errors (a file that does not is not drawn)."""
    document = data.inputs.folder.robot_go
    steps = document.get("measurements") if document is not None else None
    return bool(steps) and isinstance(steps, list) and all(
        isinstance(m, dict) and {"step", "tip_mm", "exit_mm"} <= set(m) for m in steps)


# --- the registry ---------------------------------------------------------------------------------


@dataclass(frozen=True)
class FigureSpec:
    """How to make one or more figures: their names, when they can be drawn, what they need of the CT."""

    names: tuple[str, ...]
    available: Callable[[ReportData], bool]
    render: Callable[[ReportData], list[Figure]]
    uses_ct: bool = False  # drawn after the others, once the CT is read (or known to be absent)
    needs_ct: bool = False  # left out without a CT
    prepare: Callable[[ReportData], None] | None = None  # the work that can be done before the CT is read


def _has_scene(data: ReportData) -> bool:  # calibration points alone have no place in the image
    return bool(data.rows) or bool(data.points and data.inputs.registration is not None)


FIGURES: tuple[FigureSpec, ...] = (
    FigureSpec(("scene_oblique", "scene_top"), _has_scene, render_scenes, uses_ct=True,
               prepare=prepare_scenes),
    FigureSpec(("marker_slices",), lambda d: bool(d.rows) and d.inputs.ct is not None, render_marker_slices,
               uses_ct=True, needs_ct=True),
    FigureSpec(("residuals",), lambda d: d.inputs.registration is not None and bool(d.inputs.registration.pairs),
               render_residuals),
    FigureSpec(("fre_curve",), lambda d: d.curve is not None, render_fre_curve),
    FigureSpec(("tre_targets",), _has_tre, render_tre_targets),
    FigureSpec(("error_budget",), _has_budget, render_error_budget),
    FigureSpec(("tre_map",), lambda d: d.inputs.folder.tre_map_path is not None, render_tre_map),
    FigureSpec(("checkpoints",), lambda d: read_checkpoints(d) is not None, render_checkpoints),
    FigureSpec(("guidance_approach", "guidance_plan_view"), _has_guidance, render_guidance),
    FigureSpec(("guidance_ct",), lambda d: _has_plan_in_ct(d) and d.inputs.ct is not None, render_plan_in_ct,
               uses_ct=True, needs_ct=True),
    FigureSpec(("distortion",), lambda d: _distortion(d) is not None, render_distortion),
    FigureSpec(("robot_residuals", "robot_clock"), _has_robot_fit, render_robot_calibration),
    FigureSpec(("robot_go",), _has_robot_go, render_robot_go),
)

#: Every figure name, in the order of the registry.
FIGURE_NAMES = tuple(name for spec in FIGURES for name in spec.names)


def render_figures(data: ReportData, progress: Progress = QUIET) -> list[Figure]:
    """Render every figure whose inputs exist, in the order of :data:`FIGURES`.

    While the CT is read: the figures that do not need it, and the preparation of those that
    do; then the CT's figures. A CT that fails to read leaves its slices out (with a note).
    """
    planned = [spec for spec in FIGURES if spec.available(data)]
    rendered: dict[str, list[Figure]] = {}
    with progress.step("rendering report", total=sum(len(spec.names) for spec in planned)) as step:
        try:
            for spec in planned:
                if spec.prepare is not None:
                    spec.prepare(data)
            for spec in sorted(planned, key=lambda s: s.uses_ct):
                if spec.needs_ct and data.inputs.ct is None:
                    continue
                rendered[spec.names[0]] = spec.render(data)
                step.advance(len(rendered[spec.names[0]]))
        finally:
            if data.scene_renderer is not None:
                data.scene_renderer.close()
    return [figure for spec in planned for figure in rendered.get(spec.names[0], [])]
