"""The fiducial frame phantom: block, bed cut, marker slots, reference sensor, patient, decoys.

Everything here is in the frame's CAD frame ("Frame", mm): origin at the centre of the
block's bottom face, +X across the block (width), +Y along the bed (length), +Z up
(height). The bed is a cylindrical cut along Y through the top face. Markers sit in
cylindrical slots in the top and side faces with their +Y axis along the face's outward
normal: the bottom cylinder fills the slot, the top cylinder stands out into air.

The layout is irregular (rejection sampling with a minimum spacing, then a check that
every marker's sorted distance profile differs from every other's) and deterministic
for a given seed and geometry.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from ..core.transforms import rotation_from_y_axis
from ..marker_model import MarkerModel
from .ct import Layer
from .shapes import (
    Box,
    CapsuleY,
    CylinderY,
    Difference,
    Ellipsoid,
    InfiniteCylinderY,
    MarkerSolid,
    Posed,
    RibArc,
    Shape,
    Sphere,
    pose,
)

#: Densities (HU) of the phantom's materials.
HU = {
    "pom": 340.0, "pvc": 1100.0, "metal": 15000.0, "cable": 2200.0, "fat": -100.0, "soft_tissue": 40.0,
    "liver": 60.0, "lung": -780.0, "brain": 35.0, "marrow": 300.0, "carbon": 450.0, "foam": -930.0,
}
#: Model 800 reference sensor: a cylinder 7.9 mm x 19.8 mm (NDI data sheet).
REFERENCE_SENSOR_DIAMETER_MM = 7.9
REFERENCE_SENSOR_LENGTH_MM = 19.8

FACE_NORMALS = {
    "top": np.array([0.0, 0.0, 1.0]), "+x": np.array([1.0, 0.0, 0.0]), "-x": np.array([-1.0, 0.0, 0.0]),
    "+y": np.array([0.0, 1.0, 0.0]), "-y": np.array([0.0, -1.0, 0.0]),
}
FACE_WEIGHTS = {"top": 0.3, "+x": 0.175, "-x": 0.175, "+y": 0.175, "-y": 0.175}


@dataclass
class MarkerSlot:
    """One slot with its marker: ``marker_to_frame`` (4x4, marker CAD frame -> Frame)."""

    label: str
    face: str
    marker_to_frame: np.ndarray
    in_ct: bool = True
    calibrated: bool = True
    streaked: bool = False  # a dark streak cuts it at its shoulder in the CT (``marker_streaks``)

    @property
    def origin(self) -> np.ndarray:
        return self.marker_to_frame[:3, 3]

    @property
    def axis(self) -> np.ndarray:
        return self.marker_to_frame[:3, 1]


@dataclass
class Decoy:
    """A PVC-like object that is not a marker: ``kind`` in sphere, rod, box, disc."""

    kind: str
    shape: Shape
    centre: np.ndarray
    hu: float
    resting_on: str = "frame"  # "frame" or "patient"


@dataclass
class FrameGeometry:
    """The block and its bed cut (mm, Frame)."""

    size: np.ndarray  # (W, L, H)
    bed_radius: float
    bed_axis_z: float

    @property
    def bed_half_width(self) -> float:
        """Half width of the bed cut where it meets the top face."""
        h = self.size[2]
        return float(np.sqrt(max(self.bed_radius**2 - (self.bed_axis_z - h) ** 2, 0.0)))

    @property
    def bed_bottom_z(self) -> float:
        return float(self.bed_axis_z - self.bed_radius)

    def block_shape(self) -> Shape:
        w, length, h = self.size
        box = Posed(Box((w / 2, length / 2, h / 2)), pose(translation=[0, 0, h / 2]))
        bed = Posed(InfiniteCylinderY(self.bed_radius, extent=length), pose(translation=[0, 0, self.bed_axis_z]))
        return Difference(box, [bed])

    def inside_bed(self, x: float, z: float, clearance: float = 0.0) -> bool:
        return float(np.hypot(x, z - self.bed_axis_z)) < self.bed_radius + clearance


@dataclass
class Phantom:
    """The whole phantom in the Frame: layers to paint (in order) and the truth they carry."""

    geometry: FrameGeometry
    model: MarkerModel
    markers: list[MarkerSlot]
    reference_to_frame: np.ndarray
    layers: list[Layer] = field(default_factory=list)
    decoys: list[Decoy] = field(default_factory=list)
    targets: np.ndarray = field(default_factory=lambda: np.zeros((0, 3)))  # (n, 3) Frame
    target_normals: np.ndarray = field(default_factory=lambda: np.zeros((0, 3)))
    extent_points: np.ndarray = field(default_factory=lambda: np.zeros((0, 3)))  # what the CT must hold


def frame_geometry(size_mm) -> FrameGeometry:
    """Block of ``size_mm`` (W, L, H) with a bed cut 0.6 W wide and 0.35 H deep at the top face."""
    size = np.asarray(size_mm, dtype=float)
    half_width = 0.3 * size[0]
    depth = 0.35 * size[2]
    radius = (half_width**2 + depth**2) / (2 * depth)
    return FrameGeometry(size, radius, size[2] - depth + radius)


# --- marker layout -------------------------------------------------------------------------


def _sample_on_face(face: str, geometry: FrameGeometry, margin: float, rng: np.random.Generator,
                    z_min: float) -> np.ndarray | None:
    w, length, h = geometry.size
    if face == "top":
        lo_x = geometry.bed_half_width + margin
        if lo_x > w / 2 - margin:
            return None
        x = rng.uniform(lo_x, w / 2 - margin) * rng.choice([-1.0, 1.0])
        return np.array([x, rng.uniform(-length / 2 + margin, length / 2 - margin), h])
    if face in ("+x", "-x"):
        sign = 1.0 if face == "+x" else -1.0
        return np.array([sign * w / 2, rng.uniform(-length / 2 + margin, length / 2 - margin),
                         rng.uniform(z_min, h - margin)])
    sign = 1.0 if face == "+y" else -1.0
    for _ in range(50):
        x = rng.uniform(-w / 2 + margin, w / 2 - margin)
        z = rng.uniform(z_min, h - margin)
        if not geometry.inside_bed(x, z, clearance=margin):
            return np.array([x, sign * length / 2, z])
    return None


def _profiles_distinct(points: np.ndarray, min_difference_mm: float) -> bool:
    """Every point's sorted distances to the others differ from every other point's by ``min_difference_mm``."""
    d = np.linalg.norm(points[:, None] - points[None], axis=2)
    profiles = np.sort(d, axis=1)
    diff = np.abs(profiles[:, None, :] - profiles[None, :, :]).max(axis=2)
    np.fill_diagonal(diff, np.inf)
    return bool(diff.min() >= min_difference_mm)


def layout_markers(geometry: FrameGeometry, model: MarkerModel, n_markers: int, rng: np.random.Generator,
                   keep_out: list[tuple[np.ndarray, float]] | None = None, min_spacing_mm: float = 30.0,
                   edge_margin_mm: float = 6.0) -> list[MarkerSlot]:
    """Place ``n_markers`` markers irregularly on the top and side faces (labels M01.. by azimuth).

    Raises ``ValueError`` when the faces cannot hold that many markers with the spacing.
    """
    margin = model.bottom_diameter_mm / 2 + edge_margin_mm
    z_min = margin + 0.1 * geometry.size[2]
    faces = list(FACE_WEIGHTS)
    weights = np.array([FACE_WEIGHTS[f] for f in faces])
    spacing = min_spacing_mm
    floor = model.bottom_diameter_mm + 8.0  # slots never closer than this (4 mm of POM between them)
    for attempt in range(400):
        if attempt and attempt % 40 == 0:
            spacing = max(spacing * 0.92, floor)  # crowded: relax the spacing a little
        counts = rng.multinomial(n_markers, weights / weights.sum())
        if n_markers >= len(faces) and np.any(counts == 0):
            continue
        points: list[np.ndarray] = []
        origins: list[np.ndarray] = []
        normals: list[np.ndarray] = []
        names: list[str] = []
        ok = True
        for face, count in zip(faces, counts, strict=True):
            for _ in range(count):
                for _try in range(200):
                    p = _sample_on_face(face, geometry, margin, rng, z_min)
                    if p is None:
                        continue
                    origin = p - model.bottom_height_mm * FACE_NORMALS[face]
                    if points and (np.min(np.linalg.norm(np.asarray(points) - p, axis=1)) < spacing
                                   or np.min(np.linalg.norm(np.asarray(origins) - origin, axis=1)) < floor):
                        continue
                    if keep_out and any(np.linalg.norm(p - c) < r for c, r in keep_out):
                        continue
                    points.append(p)
                    origins.append(origin)
                    normals.append(FACE_NORMALS[face])
                    names.append(face)
                    break
                else:
                    ok = False
                    break
            if not ok:
                break
        if not ok:
            continue
        surface = np.asarray(points)
        if not _profiles_distinct(surface, 2.0):
            continue
        azimuth = np.arctan2(surface[:, 1], surface[:, 0])
        order = np.lexsort((surface[:, 2], np.round(azimuth, 6)))
        slots = []
        for rank, i in enumerate(order):
            rotation = rotation_from_y_axis(normals[i])
            origin = surface[i] - model.bottom_height_mm * normals[i]  # bottom cylinder inside the slot
            slots.append(MarkerSlot(f"M{rank + 1:02d}", names[i], pose(rotation, origin)))
        return slots
    raise ValueError(f"cannot place {n_markers} markers {min_spacing_mm:g} mm apart on a frame of "
                     f"{geometry.size.tolist()} mm; use fewer markers or a larger frame")


# --- reference sensor ---------------------------------------------------------------------------


def reference_sensor_pose(geometry: FrameGeometry, rng: np.random.Generator) -> np.ndarray:
    """``ReferenceToFrame``: the Model 800 lies in a slot of the bottom face, its +X along its length.

    The cable leaves along -X (towards the nearer side face) through a groove.
    """
    w, length, _ = geometry.size
    along_x = bool(rng.integers(2))
    x = rng.uniform(0.12, 0.3) * w * rng.choice([-1.0, 1.0])
    y = rng.uniform(0.12, 0.3) * length * rng.choice([-1.0, 1.0])
    if along_x:  # cable to the side face nearer in x
        sensor_x = np.array([-np.sign(x), 0.0, 0.0])
    else:
        sensor_x = np.array([0.0, -np.sign(y), 0.0])
    sensor_z = np.array([0.0, 0.0, -1.0]) if rng.integers(2) else np.array([0.0, 0.0, 1.0])
    sensor_y = np.cross(sensor_z, sensor_x)
    centre = np.array([x, y, REFERENCE_SENSOR_DIAMETER_MM / 2 + 1.0])
    return pose(np.column_stack([sensor_x, sensor_y, sensor_z]), centre)


def _horizontal_frame(axis: np.ndarray) -> np.ndarray:
    """Rotation whose local +Y is the horizontal ``axis`` and local +Z the Frame's +Z."""
    y = np.asarray(axis, dtype=float)
    z = np.array([0.0, 0.0, 1.0])
    return np.column_stack([np.cross(y, z), y, z])


def _reference_layers(geometry: FrameGeometry, reference_to_frame: np.ndarray) -> tuple[list[Layer], np.ndarray]:
    """Slot and cable groove (air, open to the bottom face), sensor (metal), cable; and the cable's end."""
    radius = REFERENCE_SENSOR_DIAMETER_MM / 2
    half = REFERENCE_SENSOR_LENGTH_MM / 2
    centre = reference_to_frame[:3, 3]
    sensor_axis = reference_to_frame[:3, 0]
    w, length, _ = geometry.size
    side = w / 2 if abs(sensor_axis[0]) > 0.5 else length / 2
    reach = side - abs(float(centre @ np.abs(sensor_axis)))  # centre to the side face along -axis
    outward = -sensor_axis
    top = centre[2] + radius + 0.4
    slot_rotation = _horizontal_frame(sensor_axis)
    bottom = -0.5  # open to the bottom face
    slot = Box((radius + 0.5, half + 0.5, (top - bottom) / 2))
    slot_pose = pose(slot_rotation, [centre[0], centre[1], (top + bottom) / 2])
    groove_len = reach - half + 2.0
    groove_centre = centre + outward * (half + groove_len / 2)
    groove_top = centre[2] + 2.5
    groove = Box((2.5, groove_len / 2, (groove_top - bottom) / 2))
    groove_pose = pose(_horizontal_frame(outward), [groove_centre[0], groove_centre[1], (groove_top + bottom) / 2])
    sensor = Posed(CylinderY(radius, -half, half), pose(rotation_from_y_axis(sensor_axis), centre))
    cable_length = groove_len + 25.0
    cable = Posed(CapsuleY(1.1, 0.0, cable_length), pose(rotation_from_y_axis(outward), centre + outward * half))
    layers = [
        Layer("reference slot", Posed(slot, slot_pose), -1000.0, 0),
        Layer("cable groove", Posed(groove, groove_pose), -1000.0, 0),
        Layer("reference cable", cable, HU["cable"], 3),
        Layer("reference sensor", sensor, HU["metal"], 3),
    ]
    return layers, centre + outward * (half + cable_length + 1.1)


# --- patient ------------------------------------------------------------------------------------


def _patient_layers(geometry: FrameGeometry, rng: np.random.Generator) -> tuple[list[Layer], dict]:
    """A small supine patient in the bed: body (fat, soft tissue, lungs, liver), head, arms, spine, ribs.

    Cortical bone is 1400..1900 HU (brighter than PVC), marrow about 300 HU.
    """
    w, length, h = geometry.size
    s = float(min(w / 350.0, length / 350.0, h / 200.0))
    bed_bottom = geometry.bed_bottom_z
    layers: list[Layer] = []

    def cortex() -> float:
        return float(rng.uniform(1400.0, 1900.0))

    # trunk
    ax, ay, az = 58.0 * s, 92.0 * s, 40.0 * s
    head_r = 40.0 * s
    head = 1.0 if rng.random() < 0.5 else -1.0  # the head lies at the +Y or the -Y end of the bed
    head_y = head * (length / 2 - head_r - rng.uniform(3.0, 8.0) * s)  # the skull near the end face
    body_y = head_y - head * (ay + 0.55 * head_r)
    body_c = np.array([rng.uniform(-4, 4) * s, body_y, bed_bottom + az - 6.0 * s])
    layers.append(Layer("body fat", Posed(Ellipsoid((ax, ay, az)), pose(translation=body_c)), HU["fat"]))
    inner = (ax - 4 * s, ay - 4 * s, az - 4 * s)
    layers.append(Layer("body soft tissue", Posed(Ellipsoid(inner), pose(translation=body_c)), HU["soft_tissue"]))
    for side in (-1.0, 1.0):
        lung_c = body_c + np.array([side * 0.42 * ax, head * 0.3 * ay, 0.12 * az])
        layers.append(Layer("lung", Posed(Ellipsoid((0.33 * ax, 0.33 * ay, 0.5 * az)), pose(translation=lung_c)),
                            HU["lung"]))
    liver_c = body_c + np.array([-0.25 * ax, -head * 0.15 * ay, 0.05 * az])
    layers.append(Layer("liver", Posed(Ellipsoid((0.45 * ax, 0.18 * ay, 0.5 * az)), pose(translation=liver_c)),
                        HU["liver"]))
    # head with skull
    head_c = np.array([body_c[0], head_y, bed_bottom + head_r - 4.0 * s])
    layers.append(Layer("skull", Posed(Sphere(head_r), pose(translation=head_c)), cortex()))
    layers.append(Layer("brain", Posed(Sphere(head_r - 2.6 * s), pose(translation=head_c)), HU["brain"]))
    # spine: vertebral bodies with cortex and marrow, ribs in the upper half
    spine_z = body_c[2] - 0.55 * az
    n_vertebrae = max(6, int(1.6 * ay / (15.0 * s)))
    ys = np.linspace(body_y - 0.8 * ay, body_y + 0.8 * ay, n_vertebrae)
    for i, y in enumerate(ys):
        centre = np.array([body_c[0], y, spine_z])
        outer = (8.0 * s, 6.2 * s, 6.5 * s)
        layers.append(Layer(f"vertebra {i}", Posed(Ellipsoid(outer), pose(translation=centre)), cortex()))
        inner_v = tuple(v - 1.4 * s for v in outer)
        layers.append(Layer(f"vertebra {i} marrow", Posed(Ellipsoid(inner_v), pose(translation=centre)),
                            HU["marrow"]))
        if head * (y - body_y) > -0.1 * ay:  # thoracic half
            ring = min(ax, az) * 0.82
            rib_centre = np.array([body_c[0], y, body_c[2] + 0.1 * az])
            # arc over the anterior side, leaving the posterior (spine side, -Z) open
            rib = RibArc(ring, 1.9 * s, -np.pi / 2 + 0.45, 1.5 * np.pi - 0.45)
            layers.append(Layer(f"rib {i}", Posed(rib, _rib_pose(rib_centre)), cortex()))
            marrow = RibArc(ring, 0.9 * s, -np.pi / 2 + 0.45, 1.5 * np.pi - 0.45)
            layers.append(Layer(f"rib {i} marrow", Posed(marrow, _rib_pose(rib_centre)), HU["marrow"]))
    # arms along the body, resting against the bed near its rim (bones near the top-face markers)
    arm_r = 14.0 * s
    rim_x = geometry.bed_half_width - 1.05 * arm_r
    arms: list[dict] = []
    for side in (-1.0, 1.0):
        x = side * rim_x
        dz = np.sqrt(max((geometry.bed_radius - arm_r) ** 2 - x**2, 0.0))
        z = geometry.bed_axis_z - dz
        start, end = sorted((body_y - head * 0.6 * ay, body_y + head * 0.75 * ay))
        arm_pose = pose(translation=[x, 0.0, z])
        layers.append(Layer("arm", Posed(CapsuleY(arm_r, start, end), arm_pose), HU["soft_tissue"]))
        bone_pose = pose(translation=[x + side * 1.5 * s, 0.0, z + 2.0 * s])
        layers.append(Layer("humerus", Posed(CapsuleY(4.6 * s, start + 8 * s, end - 8 * s), bone_pose), cortex()))
        layers.append(Layer("humerus marrow", Posed(CapsuleY(2.6 * s, start + 9 * s, end - 9 * s), bone_pose),
                            HU["marrow"]))
        arms.append({"x": x, "z": z, "elbow_y": body_y - head * 0.6 * ay, "radius": arm_r})
    body = {"centre": body_c, "radii": np.array([ax, ay, az]), "head_centre": head_c, "head_radius": head_r,
            "arms": arms, "scale": s}
    return layers, body


def _segment(a: np.ndarray, b: np.ndarray, radius: float) -> Shape:
    """A capsule (rod with round ends) of ``radius`` from point ``a`` to point ``b`` (Frame, mm)."""
    a, b = np.asarray(a, dtype=float), np.asarray(b, dtype=float)
    length = float(np.linalg.norm(b - a))
    return Posed(CapsuleY(radius, 0.0, length), pose(rotation_from_y_axis(b - a), a))


def _hand_layers(geometry: FrameGeometry, markers: list[MarkerSlot], model: MarkerModel, body: dict,
                 rng: np.random.Generator) -> tuple[list[Layer], list[tuple[np.ndarray, float]]]:
    """Forearms reaching over the bed's rim, hands resting on the top face beside a marker.

    Each hand lies along Y a few millimetres from a top-face marker's top cylinder, with
    four finger bones (thin cortical rods) about 8 mm from the marker: bone close to a
    marker, as on a real patient. Returns the layers and keep-out spheres (centre, radius).
    """
    w, length, h = geometry.size
    s = body["scale"]
    hand_radii = np.array([11.0, 18.0, 5.5]) * s
    gap = 4.0  # soft tissue to the marker's top cylinder
    layers: list[Layer] = []
    keep_out: list[tuple[np.ndarray, float]] = []
    tops = [m for m in markers if m.face == "top"]
    for arm in body["arms"]:
        side = np.sign(arm["x"])
        candidates = sorted((m for m in tops if np.sign(m.origin[0]) == side),
                            key=lambda m: abs(m.origin[1] - arm["elbow_y"]))
        placed = False
        for marker in candidates:
            for direction in rng.permutation([-1.0, 1.0]):
                offset = model.top_diameter_mm / 2 + gap + hand_radii[1]
                centre = np.array([marker.origin[0] + rng.uniform(-2.0, 2.0) * s, marker.origin[1] + direction * offset,
                                   h + hand_radii[2] - 1.0])
                if (abs(centre[0]) - hand_radii[0] < geometry.bed_half_width - 4.0
                        or abs(centre[0]) + hand_radii[0] > w / 2 - 2.0
                        or abs(centre[1]) + hand_radii[1] > length / 2 - 2.0
                        or abs(centre[1] - arm["elbow_y"]) > 110.0 * s):
                    continue
                others = [m for m in markers if m is not marker]
                clear = all(np.linalg.norm(m.origin + model.height_mm / 2 * m.axis - centre)
                            > hand_radii[1] + model.height_mm / 2 + gap for m in others)
                wrist = centre + np.array([0.0, direction * hand_radii[1] * 0.8, 0.0])  # away from the marker
                elbow = np.array([arm["x"], arm["elbow_y"], arm["z"]])
                forearm = elbow + np.linspace(0.0, 1.0, 30)[:, None] * (wrist - elbow)
                axis_points = np.array([m.origin + t * m.axis for m in markers for t in (0.0, 8.5, 18.5)])
                nearest = np.min(np.linalg.norm(forearm[:, None] - axis_points[None], axis=2))
                if not clear or nearest < 0.62 * arm["radius"] + model.bottom_diameter_mm / 2 + gap:
                    continue
                layers.append(Layer("forearm", _segment(elbow, wrist, 0.62 * arm["radius"]), HU["soft_tissue"]))
                layers.append(Layer("hand", Posed(Ellipsoid(tuple(hand_radii)), pose(translation=centre)),
                                    HU["soft_tissue"]))
                for dx in (-4.5, 4.5):  # radius and ulna
                    shift = np.array([dx * s * 0.5, 0.0, 0.0])
                    layers.append(Layer("forearm bone", _segment(elbow + shift, wrist + shift, 1.8 * s),
                                        float(rng.uniform(1400.0, 1900.0))))
                bone_start = centre[1] + direction * (hand_radii[1] - 4.0)  # from the wrist side ...
                bone_end = centre[1] - direction * (hand_radii[1] - 4.0 * s - 4.0)  # ... to ~8 mm from the marker
                for dx in np.linspace(-6.0, 6.0, 4) * s:
                    a = np.array([centre[0] + dx, bone_start, centre[2]])
                    b = np.array([centre[0] + dx, bone_end, centre[2]])
                    layers.append(Layer("finger bone", _segment(a, b, 1.3 * s), float(rng.uniform(1400.0, 1900.0))))
                keep_out.append((centre, hand_radii[1] + 6.0))
                placed = True
                break
            if placed:
                break
    return layers, keep_out


def _rib_pose(centre: np.ndarray) -> np.ndarray:
    """Rib arcs are defined in a local X-Z plane; in the Frame that plane is X-Z too (normal Y)."""
    return pose(np.eye(3), centre)


def patient_targets(body: dict, n_targets: int, rng: np.random.Generator, min_spacing_mm: float = 25.0):
    """``n_targets`` points on the trunk's skin (anterior half) and their outward normals (Frame)."""
    points: list[np.ndarray] = []
    normals: list[np.ndarray] = []
    spacing = min_spacing_mm
    tries = 0
    while len(points) < n_targets:
        tries += 1
        if tries % 500 == 0:
            spacing *= 0.8
        p, n = _skin_point(body, rng, 65.0)
        if points and np.min(np.linalg.norm(np.asarray(points) - p, axis=1)) < spacing:
            continue
        points.append(p)
        normals.append(n)
    return np.asarray(points), np.asarray(normals)


# --- decoys -----------------------------------------------------------------------------------


DECOY_KINDS = ("sphere", "rod", "box", "disc")


def _decoy_shape(kind: str, volume: float, rng: np.random.Generator) -> tuple[Shape, float]:
    """A decoy of ``volume`` mm^3 in a local frame whose -Y side rests on a face at y=0; returns (shape, height)."""
    if kind == "sphere":
        r = (3 * volume / (4 * np.pi)) ** (1 / 3)
        return Posed(Sphere(r), pose(translation=[0, r, 0])), 2 * r
    if kind == "rod":
        r = rng.uniform(3.0, 4.0)
        length = volume / (np.pi * r * r)
        lying = rotation_from_y_axis([1.0, 0.0, 0.0])  # the rod's axis along local X, lying on the face
        return Posed(CylinderY(r, -length / 2, length / 2), pose(lying, [0, r, 0])), 2 * r
    if kind == "box":
        a, b = rng.uniform(10.0, 14.0), rng.uniform(10.0, 14.0)
        c = volume / (a * b)
        return Posed(Box((a / 2, c / 2, b / 2)), pose(translation=[0, c / 2, 0])), c
    r = rng.uniform(7.0, 9.0)  # disc: one squat cylinder standing on the face
    height = volume / (np.pi * r * r)
    return CylinderY(r, 0.0, height), height


def _skin_point(body: dict, rng: np.random.Generator, max_polar_deg: float) -> tuple[np.ndarray, np.ndarray]:
    """A point on the trunk's skin within ``max_polar_deg`` of the anterior pole, and its outward normal."""
    centre, radii = body["centre"], body["radii"]
    polar = rng.uniform(0.0, np.radians(max_polar_deg))
    azimuth = rng.uniform(0, 2 * np.pi)
    u = np.array([np.sin(polar) * np.cos(azimuth), 0.8 * np.sin(polar) * np.sin(azimuth), np.cos(polar)])
    p = centre + radii * u / np.linalg.norm(u)
    n = (p - centre) / radii**2
    return p, n / np.linalg.norm(n)


def place_decoys(geometry: FrameGeometry, markers: list[MarkerSlot], model: MarkerModel, n_decoys: int,
                 rng: np.random.Generator, keep_out: list[tuple[np.ndarray, float]],
                 body: dict | None = None) -> list[Decoy]:
    """Marker-sized PVC-like objects of other shapes resting on the frame's faces or on the patient's skin."""
    decoys: list[Decoy] = []
    margin = 14.0
    z_min = margin + 0.1 * geometry.size[2]
    faces = list(FACE_WEIGHTS)
    occupied = [(m.origin + model.height_mm / 2 * m.axis, 24.0) for m in markers] + list(keep_out)
    for n in range(n_decoys):
        kind = DECOY_KINDS[n % len(DECOY_KINDS)]
        volume = model.volume_mm3 * rng.uniform(0.85, 1.15)
        shape, height = _decoy_shape(kind, volume, rng)
        on_patient = body is not None and n % 3 == 1  # every third decoy lies on the patient
        for attempt in range(1000):
            face = "patient" if on_patient and attempt < 500 else faces[int(rng.integers(len(faces)))]
            if face == "patient":
                p, normal = _skin_point(body, rng, 60.0)
            else:
                p = _sample_on_face(face, geometry, margin, rng, z_min)
                if p is None:
                    continue
                normal = FACE_NORMALS[face]
            centre = p + normal * height / 2
            if any(np.linalg.norm(centre - c) < r + 14.0 for c, r in occupied):
                continue
            spin = rng.uniform(0, 2 * np.pi)
            base = rotation_from_y_axis(normal)
            c, s_ = np.cos(spin), np.sin(spin)
            spin_y = np.array([[c, 0, s_], [0, 1, 0], [-s_, 0, c]])
            placed = Posed(shape, pose(base @ spin_y, p))
            resting_on = "patient" if face == "patient" else "frame"
            decoys.append(Decoy(kind, placed, centre, float(rng.uniform(1000.0, 1200.0)), resting_on))
            occupied.append((centre, 20.0))
            break
    return decoys


def _couch_layers(geometry: FrameGeometry) -> tuple[list[Layer], list[np.ndarray]]:
    """The scanner couch under the frame: carbon-fibre skins around a foam core, 40 mm thick.

    Wider and longer than the frame; the CT grid cuts it off at its edges.
    """
    w, length, _ = geometry.size
    half_w, half_l = w / 2 + 60.0, length / 2 + 60.0
    slab = Posed(Box((half_w, half_l, 20.0)), pose(translation=[0.0, 0.0, -20.0]))
    core = Posed(Box((half_w - 1.5, half_l + 1.0, 18.5)), pose(translation=[0.0, 0.0, -20.0]))
    layers = [Layer("couch skin", slab, HU["carbon"]), Layer("couch core", core, HU["foam"])]
    extent = [np.array([sx * (w / 2 + 10.0), sy * (length / 2 + 10.0), -40.0]) for sx in (-1, 1) for sy in (-1, 1)]
    return layers, extent


# --- assembly -----------------------------------------------------------------------------------


def build_phantom(rng: np.random.Generator, model: MarkerModel, size_mm=(350.0, 350.0, 200.0),
                  n_markers: int = 28, n_decoys: int = 0, absent: list[int] | None = None,
                  uncalibrated: list[int] | None = None, n_targets: int = 6, patient: bool = True,
                  couch: bool = True, pvc_hu: float = HU["pvc"]) -> Phantom:
    """The phantom in the Frame with its painting layers (patient, block, slots, sensor, markers, decoys).

    ``pvc_hu``: the markers' density (1100 HU at 120 kVp; higher on a low-kVp scan).
    ``absent``: indices of markers removed before the scan (empty slots in the CT, still
    calibrated); ``uncalibrated``: indices of markers in the CT but not calibrated.
    """
    geometry = frame_geometry(size_mm)
    reference_to_frame = reference_sensor_pose(geometry, rng)
    sensor_keep_out = [(reference_to_frame[:3, 3], 45.0 * float(min(geometry.size[:2]) / 350.0) + 20.0)]
    markers = layout_markers(geometry, model, n_markers, rng, keep_out=sensor_keep_out)
    occupied = list(sensor_keep_out)  # where decoys must not go
    for i in absent or []:
        markers[i].in_ct = False
    for i in uncalibrated or []:
        markers[i].calibrated = False
    layers: list[Layer] = []
    w, length, h = geometry.size
    extent = [np.array([sx * w / 2, sy * length / 2, z]) for sx in (-1, 1) for sy in (-1, 1) for z in (0.0, h)]
    body = None
    if patient:
        patient_layers, body = _patient_layers(geometry, rng)
        hand_layers, hand_keep_out = _hand_layers(geometry, markers, model, body, rng)
        patient_layers += hand_layers
        occupied = occupied + hand_keep_out
        layers += patient_layers
        for layer in patient_layers:
            lo, hi = layer.shape.bounds
            extent += [lo, hi]
    layers.append(Layer("POM block", geometry.block_shape(), HU["pom"]))
    reference_layers, cable_end = _reference_layers(geometry, reference_to_frame)
    extent.append(cable_end)
    solid = MarkerSolid(model)
    slot_shape = CylinderY(model.bottom_diameter_mm / 2, -0.01, model.bottom_height_mm)
    for m in markers:
        if not m.in_ct:
            layers.append(Layer(f"empty slot {m.label}", Posed(slot_shape, m.marker_to_frame), -1000.0, 3))
    layers += reference_layers
    for m in markers:
        extent.append(m.origin + model.height_mm * m.axis)
        if m.in_ct:
            hu = pvc_hu + float(rng.normal(0.0, 12.0))  # markers cut from one rod: nearly equal
            layers.append(Layer(f"marker {m.label}", Posed(solid, m.marker_to_frame), hu, 5))
    targets = np.zeros((0, 3))
    normals = np.zeros((0, 3))
    if body is not None and n_targets:
        targets, normals = patient_targets(body, n_targets, rng)
    elif n_targets:  # no patient: targets on the bed between the markers
        targets = np.column_stack([rng.uniform(-0.3, 0.3, n_targets) * geometry.size[0],
                                   rng.uniform(-0.4, 0.4, n_targets) * geometry.size[1],
                                   np.full(n_targets, geometry.bed_bottom_z)])
        normals = np.tile([0.0, 0.0, 1.0], (n_targets, 1))
    keep_out = occupied + [(t, 8.0) for t in targets]
    decoys = place_decoys(geometry, markers, model, n_decoys, rng, keep_out, body) if n_decoys else []
    for d in decoys:
        layers.append(Layer(f"decoy {d.kind}", d.shape, d.hu, 4))
        extent += [d.shape.bounds[0], d.shape.bounds[1]]
    if couch:
        couch_layers, couch_extent = _couch_layers(geometry)
        layers = couch_layers + layers
        extent += couch_extent
    return Phantom(geometry, model, markers, reference_to_frame, layers, decoys, targets, normals,
                   np.asarray(extent, dtype=float))
