"""Small synthetic frames and tracking recordings for the calibration / pairing / registration tests.

Independent of the case simulator: a fiducial frame with markers on its top and side faces
(axes along the face normals), the true ``ReferenceToImage`` and sensor offset l, and
trakSTAR-like recordings (80 Hz, jitter, per-dwell bias, transitions, bumps, wild samples).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from EMRegModule.core.tracking import TrackingRecording
from EMRegModule.core.transforms import axis_angle_to_rotation, make_transform, random_rotation, rotation_from_y_axis


@dataclass
class SyntheticFrame:
    """Ground truth: marker origins / axes in image space, pinholes in Reference, l, ReferenceToImage."""

    origins_image: np.ndarray
    axes_image: np.ndarray
    reference_to_image: np.ndarray
    l_mm: float
    pinholes_reference: np.ndarray
    axes_reference: np.ndarray


def frame_layout(rng: np.random.Generator, n_markers: int = 28, size=(350.0, 350.0, 200.0),
                 min_spacing: float = 25.0) -> tuple[np.ndarray, np.ndarray]:
    """Marker origins (bottom-face centre, slightly sunk into the face) and axes in the frame's
    own coordinates: about half on the top face, the rest on the four sides, irregularly placed."""
    sx, sy, sz = size
    ex, ey, ez = np.eye(3)
    faces = [  # (normal, point on face, two in-face axes with half extents)
        (ez, ez * sz / 2, (ex, sx / 2), (ey, sy / 2)),
        (ex, ex * sx / 2, (ey, sy / 2), (ez, sz / 2)),
        (-ex, -ex * sx / 2, (ey, sy / 2), (ez, sz / 2)),
        (ey, ey * sy / 2, (ex, sx / 2), (ez, sz / 2)),
        (-ey, -ey * sy / 2, (ex, sx / 2), (ez, sz / 2)),
    ]
    origins: list[np.ndarray] = []
    axes: list[np.ndarray] = []
    attempts = 0
    while len(origins) < n_markers:
        attempts += 1
        if attempts > 100000:
            raise RuntimeError("cannot place markers")
        face = faces[0] if rng.random() < 0.5 else faces[1 + rng.integers(4)]
        normal, centre, (u, hu), (v, hv) = face
        point = centre + u * rng.uniform(-0.85, 0.85) * hu + v * rng.uniform(-0.85, 0.85) * hv - 4.0 * normal
        if origins and np.min(np.linalg.norm(np.asarray(origins) - point, axis=1)) < min_spacing:
            continue
        origins.append(point)
        axes.append(normal)
    return np.asarray(origins), np.asarray(axes)


def make_frame(seed: int = 0, n_markers: int = 28, l_mm: float | None = None,
               layout: tuple[np.ndarray, np.ndarray] | None = None) -> SyntheticFrame:
    """A frame with a random pose in image space and a random Reference sensor pose in the frame."""
    rng = np.random.default_rng(seed)
    origins_frame, axes_frame = layout if layout is not None else frame_layout(rng, n_markers)
    frame_to_image = make_transform(random_rotation(rng, 15.0), rng.uniform(-50, 50, 3) + [0, 0, -100])
    frame_to_reference = make_transform(random_rotation(rng), rng.uniform(-30, 30, 3) + [0, 0, -95])
    reference_to_image = frame_to_image @ np.linalg.inv(frame_to_reference)
    l_mm = float(rng.uniform(12.0, 17.5)) if l_mm is None else float(l_mm)
    origins_image = origins_frame @ frame_to_image[:3, :3].T + frame_to_image[:3, 3]
    axes_image = axes_frame @ frame_to_image[:3, :3].T
    pinholes_frame = origins_frame + l_mm * axes_frame
    pinholes_reference = pinholes_frame @ frame_to_reference[:3, :3].T + frame_to_reference[:3, 3]
    axes_reference = axes_frame @ frame_to_reference[:3, :3].T
    return SyntheticFrame(origins_image, axes_image, reference_to_image, l_mm, pinholes_reference, axes_reference)


def probe_rotation_in_hole(axis_reference: np.ndarray, rng: np.random.Generator) -> np.ndarray:
    """ProbeToReference rotation for a probe in a hole: probe +X = -axis, random roll."""
    # rotation_from_y_axis gives a rotation whose +Y column is the given direction; reorder to +X.
    base = rotation_from_y_axis(-axis_reference)
    probe = np.column_stack([base[:, 1], base[:, 2], base[:, 0]])
    return probe @ axis_angle_to_rotation([1.0, 0, 0], rng.uniform(0, 2 * np.pi))


def calibration_recording(
    points_reference: np.ndarray,
    axes_reference: np.ndarray,
    seed: int = 0,
    labels: list[str] | None = None,
    dwell_s: float = 1.5,
    rate_hz: float = 80.0,
    jitter_mm: float = 0.1,
    bias_mm: float = 0.3,
    angle_noise_deg: float = 0.5,
    bumps: bool = False,
    wild_fraction: float = 0.0,
    bad_quality_fraction: float = 0.0,
    short_stops: bool = False,
    visit_order: list[int] | None = None,
    tremor_mm: float = 0.0,
) -> tuple[TrackingRecording, np.ndarray]:
    """A two-sensor recording (reference = 1, probe = 2) visiting each pinhole in turn.

    Returns the recording and the true per-visit biased points (for checks). Between dwells
    the probe is lifted and moved at ~150 mm/s; with ``bumps`` the frame (Reference sensor)
    jumps to a new pose in the tracker between dwells; ``tremor_mm`` adds a slow hand-held
    wobble (1-3 Hz, that amplitude per axis) during the dwells.
    """
    rng = np.random.default_rng(seed)
    order = list(range(len(points_reference))) if visit_order is None else visit_order
    dt = 1.0 / rate_hz
    reference_to_tracker = make_transform(random_rotation(rng), rng.uniform(-100, 100, 3) + [0, 0, 300])
    rows_t, rows_ref, rows_probe, rows_label, rows_quality = [], [], [], [], []
    t = 0.0
    previous = None
    true_points = []
    for index in order:
        target = points_reference[index]
        axis = axes_reference[index]
        rotation = probe_rotation_in_hole(axis, rng)
        if previous is not None:
            # Transition: lift 20 mm along the old axis, travel, come down along the new axis.
            start, start_axis = previous
            waypoints = [start, start + 20 * start_axis, target + 20 * axis, target]
            path = []
            for a, b in zip(waypoints[:-1], waypoints[1:], strict=True):
                n = max(2, int(np.linalg.norm(b - a) / 150.0 * rate_hz))
                path.extend(a + (b - a) * s for s in np.linspace(0, 1, n, endpoint=False))
            if short_stops:
                # A 0.2 s pause halfway.
                mid = path[len(path) // 2]
                path[len(path) // 2:len(path) // 2] = [mid] * int(0.2 * rate_hz)
            for p in path:
                rows_t.append(t)
                rows_ref.append(reference_to_tracker)
                rows_probe.append(make_transform(rotation, p + rng.normal(0, jitter_mm, 3)))
                rows_label.append("")
                rows_quality.append(rng.uniform(0, 1))
                t += dt
            if bumps:
                tilt = axis_angle_to_rotation(rng.normal(size=3), np.radians(rng.uniform(2, 10)))
                reference_to_tracker = make_transform(tilt @ reference_to_tracker[:3, :3],
                                                      reference_to_tracker[:3, 3] + rng.uniform(-20, 20, 3))
        bias = rng.normal(0, bias_mm / np.sqrt(3), 3)
        true_points.append(target + bias)
        label = "" if labels is None else labels[index]
        frequency, phase = rng.uniform(1.0, 3.0, 3), rng.uniform(0, 2 * np.pi, 3)
        for k in range(int(dwell_s * rate_hz)):
            shake = tremor_mm * np.sin(2 * np.pi * frequency * k / rate_hz + phase)
            wobble = axis_angle_to_rotation(rng.normal(size=3), np.radians(rng.normal(0, angle_noise_deg)))
            noisy_rotation = rotation @ wobble
            position = target + bias + shake + rng.normal(0, jitter_mm, 3)
            quality = rng.uniform(0, 1)
            if rng.random() < wild_fraction:
                position = position + rng.normal(0, 5.0, 3)
            if rng.random() < bad_quality_fraction:
                position = position + rng.normal(0, 8.0, 3)
                quality = 50.0
            rows_t.append(t)
            rows_ref.append(reference_to_tracker)
            rows_probe.append(make_transform(noisy_rotation, position))
            rows_label.append(label)
            rows_quality.append(quality)
            t += dt
        previous = (target, axis)
    n = len(rows_t)
    ref = np.asarray(rows_ref)
    probe_reference = np.asarray(rows_probe)
    probe_tracker = ref @ probe_reference
    time_s = np.repeat(np.asarray(rows_t), 2)
    sensor = np.tile([1, 2], n)
    transforms = np.empty((2 * n, 4, 4))
    transforms[0::2] = ref
    transforms[1::2] = probe_tracker
    quality = np.empty(2 * n)
    quality[0::2] = 0.2
    quality[1::2] = rows_quality
    label = np.empty(2 * n, dtype=object)
    label[0::2] = ""
    label[1::2] = rows_label
    recording = TrackingRecording(time_s, sensor, transforms[:, :3, 3], transforms[:, :3, :3], quality, label,
                                  source="synthetic")
    return recording, np.asarray(true_points)


@dataclass
class PairingProblem:
    """Shuffled, noisy image markers and calibration points with missing and extra ones.

    ``image_truth[j]`` / ``calibration_truth[i]``: the true marker index of each entry, or -1
    for an extra (decoy / stray dwell); a correct pairing (j, i) has equal non-negative truths.
    """

    frame: SyntheticFrame
    origins_image: np.ndarray
    axes_image: np.ndarray
    points_reference: np.ndarray
    directions_reference: np.ndarray
    image_truth: np.ndarray
    calibration_truth: np.ndarray

    @property
    def expected_pairs(self) -> int:
        image = set(self.image_truth[self.image_truth >= 0].tolist())
        return len(image & set(self.calibration_truth[self.calibration_truth >= 0].tolist()))

    def correct(self, pairs) -> bool:
        return all(self.image_truth[j] >= 0 and self.image_truth[j] == self.calibration_truth[i] for j, i in pairs)


def pairing_problem(seed: int, n_markers: int = 28, missing_image: int = 3, extra_image: int = 3,
                    missing_calibration: int = 3, extra_calibration: int = 3, tracker_error_mm: float = 0.5,
                    image_error_mm: float = 0.2, direction_error_deg: float = 2.0, l_mm: float | None = None,
                    frame: SyntheticFrame | None = None) -> PairingProblem:
    """Image and calibration sets of one frame (RMS 3D errors as given), each missing some true
    markers (different ones) and holding extra random points near the frame."""
    frame = frame or make_frame(seed, n_markers, l_mm)
    n = len(frame.origins_image)
    rng = np.random.default_rng(seed + 1000)

    def unit(v):
        return v / np.linalg.norm(v, axis=1, keepdims=True)

    def jitter_directions(v):
        return unit(v + rng.normal(0, np.radians(direction_error_deg) / np.sqrt(2), v.shape))

    origins = frame.origins_image + rng.normal(0, image_error_mm / np.sqrt(3), (n, 3))
    axes = jitter_directions(frame.axes_image)
    points = frame.pinholes_reference + rng.normal(0, tracker_error_mm / np.sqrt(3), (n, 3))
    directions = jitter_directions(frame.axes_reference)
    image_keep = rng.permutation(n)[missing_image:]
    cal_keep = rng.permutation(n)[missing_calibration:]

    def extras(centre, spread, count):
        return centre + rng.uniform(-spread, spread, (count, 3)), unit(rng.normal(size=(count, 3)))

    extra_o, extra_a = extras(origins.mean(axis=0), 150.0, extra_image)
    extra_p, extra_d = extras(points.mean(axis=0), 150.0, extra_calibration)
    image_perm = rng.permutation(len(image_keep) + extra_image)
    cal_perm = rng.permutation(len(cal_keep) + extra_calibration)
    return PairingProblem(
        frame,
        np.vstack([origins[image_keep], extra_o])[image_perm],
        np.vstack([axes[image_keep], extra_a])[image_perm],
        np.vstack([points[cal_keep], extra_p])[cal_perm],
        np.vstack([directions[cal_keep], extra_d])[cal_perm],
        np.concatenate([image_keep, np.full(extra_image, -1)])[image_perm],
        np.concatenate([cal_keep, np.full(extra_calibration, -1)])[cal_perm],
    )


def symmetric_layout(seed: int = 5, half: int = 14) -> tuple[np.ndarray, np.ndarray]:
    """A layout with a 2-fold rotational symmetry about the frame's vertical axis."""
    origins, axes = frame_layout(np.random.default_rng(seed), half, min_spacing=30.0)
    turn = np.diag([-1.0, -1.0, 1.0])
    return np.vstack([origins, origins @ turn.T]), np.vstack([axes, axes @ turn.T])
