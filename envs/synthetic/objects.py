"""Part-based shape families of the target categories, with realistic size distributions.

Every object is built in its own box frame (origin at the label box centre, x along the heading,
y to the left, z up) from analytic parts (oriented boxes, cylinders, ellipsoids) that lie inside
the label box ``(l, w, h)`` and touch its faces, so the label is the tight tracking box. Animated
categories (walking pedestrians, pedalling riders) rebuild their limbs from a phase each frame.

Sizes follow the dataset statistics (KITTI for Car / Van / Truck / Pedestrian / Cyclist, nuScenes
for Bus / Bicycle / Motorcycle): a Gaussian per dimension, clipped to +-2.5 standard deviations.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

from envs.synthetic.raycast import BOX, CYLINDER, ELLIPSOID, Parts

__all__ = [
    "CATEGORIES",
    "SIZE_STATS",
    "ObjectModel",
    "make_object",
    "sample_size",
    "segments_to_parts",
]

CATEGORIES: tuple[str, ...] = (
    "Car",
    "Van",
    "Truck",
    "Bus",
    "Pedestrian",
    "Cyclist",
    "Bicycle",
    "Motorcycle",
)

# (mean l, w, h), (std l, w, h), metres.
SIZE_STATS: dict[str, tuple[tuple[float, float, float], tuple[float, float, float]]] = {
    "Car": ((3.88, 1.63, 1.53), (0.43, 0.10, 0.14)),
    "Van": ((5.08, 1.90, 2.21), (0.50, 0.12, 0.20)),
    "Truck": ((10.1, 2.59, 3.25), (2.3, 0.15, 0.35)),
    "Bus": ((11.0, 2.90, 3.45), (1.2, 0.10, 0.25)),
    "Pedestrian": ((0.84, 0.66, 1.76), (0.12, 0.10, 0.11)),
    "Cyclist": ((1.76, 0.60, 1.74), (0.18, 0.10, 0.09)),
    # nuScenes bicycles are mostly parked (no rider); ridden ones are sampled as tall.
    "Bicycle": ((1.70, 0.60, 1.12), (0.15, 0.08, 0.08)),
    "Motorcycle": ((2.11, 0.77, 1.47), (0.20, 0.10, 0.12)),
}
_RIDDEN_BICYCLE_H = (1.72, 0.08)
_PARKED_MOTORCYCLE_H = (1.15, 0.08)

GLASS, TYRE, METAL = 0.04, 0.12, 0.55


def _default_ridden(category: str, ridden: bool | None) -> bool:
    # Bicycles are mostly parked (nuScenes statistics); motorcycles mostly ridden.
    return (category != "Bicycle") if ridden is None else ridden


def sample_size(
    category: str, rng: np.random.Generator, *, ridden: bool | None = None
) -> np.ndarray:
    """A ``(3,)`` size ``(l, w, h)`` in metres for one instance of ``category``; ``ridden``
    (two-wheelers; default: Bicycle parked, Motorcycle ridden) includes the rider's height."""
    ridden = _default_ridden(category, ridden)
    mean, std = (np.array(v) for v in SIZE_STATS[category])
    if category == "Bicycle" and ridden:
        mean[2], std[2] = _RIDDEN_BICYCLE_H
    if category == "Motorcycle" and not ridden:
        mean[2], std[2] = _PARKED_MOTORCYCLE_H
    z = np.clip(rng.standard_normal(3), -2.5, 2.5)
    return mean + z * std


# --------------------------------------------------------------------------- part helpers


def _rot_y(a: float) -> np.ndarray:
    c, s = math.cos(a), math.sin(a)
    return np.array([[c, 0.0, s], [0.0, 1.0, 0.0], [-s, 0.0, c]])


_WHEEL_ROT = np.array([[1.0, 0.0, 0.0], [0.0, 0.0, -1.0], [0.0, 1.0, 0.0]])  # local z -> y
_X_AXIS_ROT = np.array([[0.0, 0.0, 1.0], [0.0, 1.0, 0.0], [-1.0, 0.0, 0.0]])  # local z -> x


class _Builder:
    """Collects parts in the object frame."""

    def __init__(self) -> None:
        self.kind: list[int] = []
        self.center: list[np.ndarray] = []
        self.rot: list[np.ndarray] = []
        self.half: list[np.ndarray] = []
        self.refl: list[float] = []

    def add(self, kind: int, center, half, refl: float, rot: np.ndarray | None = None) -> int:
        self.kind.append(kind)
        self.center.append(np.asarray(center, dtype=np.float64))
        self.half.append(np.maximum(np.asarray(half, dtype=np.float64), 1e-3))
        self.rot.append(np.eye(3) if rot is None else rot)
        self.refl.append(refl)
        return len(self.kind) - 1

    def box_span(self, x0, x1, y0, y1, z0, z1, refl: float) -> int:
        """Axis-aligned box from its extents."""
        return self.add(
            BOX,
            ((x0 + x1) / 2, (y0 + y1) / 2, (z0 + z1) / 2),
            ((x1 - x0) / 2, (y1 - y0) / 2, (z1 - z0) / 2),
            refl,
        )

    def wheel(self, x, y, z, radius, half_width, refl: float = TYRE) -> int:
        return self.add(CYLINDER, (x, y, z), (radius, radius, half_width), refl, _WHEEL_ROT)

    def segment(self, p0, p1, radius: float, refl: float) -> int:
        """A cylinder of ``radius`` whose axis runs from ``p0`` to ``p1``."""
        center, rot, half = _segment_pose(np.asarray(p0, float), np.asarray(p1, float), radius)
        return self.add(CYLINDER, center, half, refl, rot)

    def parts(self) -> Parts:
        n = len(self.kind)
        return Parts(
            np.array(self.kind, np.int8),
            np.array(self.center).reshape(n, 3),
            np.array(self.rot).reshape(n, 3, 3),
            np.array(self.half).reshape(n, 3),
            np.array(self.refl, np.float32),
            np.zeros(n, np.int64),
        )


def _segment_pose(p0: np.ndarray, p1: np.ndarray, radius: float):
    center, rot, half = segments_to_parts(p0[None], p1[None], np.array([radius]))
    return center[0], rot[0], half[0]


def segments_to_parts(
    p0: np.ndarray, p1: np.ndarray, radius: np.ndarray
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Cylinders along segments ``p0 (K, 3) -> p1 (K, 3)`` with ``radius (K,)``: returns
    ``center (K, 3)``, ``rot (K, 3, 3)`` (local z along the segment) and ``half (K, 3)``."""
    axis = p1 - p0
    length = np.sqrt((axis * axis).sum(-1))
    a = axis / np.maximum(length, 1e-9)[:, None]
    # A perpendicular from the cross product with y (or x when the segment runs along y).
    use_y = np.abs(a[:, 1]) < 0.9
    ref = np.where(use_y[:, None], np.array([0.0, 1.0, 0.0]), np.array([1.0, 0.0, 0.0]))
    u = np.stack(
        [
            ref[:, 1] * a[:, 2] - ref[:, 2] * a[:, 1],
            ref[:, 2] * a[:, 0] - ref[:, 0] * a[:, 2],
            ref[:, 0] * a[:, 1] - ref[:, 1] * a[:, 0],
        ],
        -1,
    )
    u /= np.sqrt((u * u).sum(-1))[:, None]
    v = np.stack(
        [
            a[:, 1] * u[:, 2] - a[:, 2] * u[:, 1],
            a[:, 2] * u[:, 0] - a[:, 0] * u[:, 2],
            a[:, 0] * u[:, 1] - a[:, 1] * u[:, 0],
        ],
        -1,
    )
    rot = np.stack([u, v, a], axis=-1)
    half = np.stack([radius, radius, np.maximum(length / 2, 1e-3)], -1)
    return (p0 + p1) / 2, rot, half


def _knee(hip: np.ndarray, foot: np.ndarray, seg: float, forward: float = 1.0) -> np.ndarray:
    """Knee position of a two-link leg (links ``seg`` long) bending towards ``forward * x``."""
    d = foot - hip
    dist = float(np.linalg.norm(d))
    mid = (hip + foot) / 2
    if dist >= 2 * seg:
        return mid
    perp = np.array([-d[2], 0.0, d[0]]) / max(math.hypot(d[0], d[2]), 1e-9)
    if perp[0] * forward < 0:
        perp = -perp
    return mid + perp * math.sqrt(seg * seg - (dist / 2) ** 2)


# --------------------------------------------------------------------------- the model


@dataclass
class ObjectModel:
    """One object's shape: static parts plus, for animated ones, a limb rebuild per phase.

    Attributes:
        category: e.g. ``"Pedestrian"``.
        size: ``(3,)`` label box size ``(l, w, h)``, metres.
        parts: parts in the object (box) frame at the neutral pose.
        reflectivity: main surface reflectivity (paint / clothes).
        animate: ``"walk"``, ``"pedal"`` or ``""``.
        params: shape parameters used by the animation.
    """

    category: str
    size: np.ndarray
    parts: Parts
    reflectivity: float
    animate: str = ""
    params: dict = field(default_factory=dict)

    def limbs(self, phase: float, amplitude: float) -> tuple[np.ndarray, ...]:
        """Animated limbs in the object frame at gait/pedal ``phase`` (radians) with swing
        ``amplitude`` in [0, 1] (0 = standing still): segments ``p0 (K, 3)``, ``p1 (K, 3)``,
        ``radius (K,)``, ``refl (K,)`` (``K = 0`` for rigid objects)."""
        seg: list[tuple] = []
        if self.animate == "walk":
            _walker_limbs(seg, self.params, phase, amplitude)
        elif self.animate == "pedal":
            _rider_legs(seg, self.params, phase)
        if not seg:
            z = np.zeros((0, 3))
            return z, z, np.zeros(0), np.zeros(0, np.float32)
        p0 = np.array([s_[0] for s_ in seg], dtype=np.float64)
        p1 = np.array([s_[1] for s_ in seg], dtype=np.float64)
        return (
            p0,
            p1,
            np.array([s_[2] for s_ in seg]),
            np.array([s_[3] for s_ in seg], np.float32),
        )

    def parts_at(self, phase: float, amplitude: float) -> Parts:
        """All parts in the object frame at ``phase`` / ``amplitude`` (see :meth:`limbs`)."""
        p0, p1, radius, refl = self.limbs(phase, amplitude)
        if not len(p0):
            return self.parts
        center, rot, half = segments_to_parts(p0, p1, radius)
        limbs = Parts(
            np.full(len(p0), CYLINDER, np.int8),
            center,
            rot,
            half,
            refl,
            np.zeros(len(p0), np.int64),
        )
        return Parts.concat([self.parts, limbs])


def make_object(
    category: str, size: np.ndarray, rng: np.random.Generator, *, ridden: bool | None = None
) -> ObjectModel:
    """Build the part model of one instance of ``size (3,)`` = ``(l, w, h)`` metres; shape
    proportions vary with ``rng``; ``ridden`` as in :func:`sample_size`."""
    ridden = _default_ridden(category, ridden)
    l, w, h = (float(v) for v in size)
    b = _Builder()
    refl = float(rng.uniform(0.15, 0.7))
    animate, params = "", {}
    if category == "Car":
        _car(b, l, w, h, refl, rng)
    elif category == "Van":
        _van(b, l, w, h, refl, rng)
    elif category == "Truck":
        _truck(b, l, w, h, refl, rng)
    elif category == "Bus":
        _bus(b, l, w, h, refl, rng)
    elif category == "Pedestrian":
        refl = float(rng.uniform(0.1, 0.5))
        params = _pedestrian(b, l, w, h, refl, rng)
        animate = "walk"
    elif category in ("Cyclist", "Bicycle"):
        rider = category == "Cyclist" or ridden
        params = _bicycle(b, l, w, h, refl, rng, rider=rider)
        animate = "pedal" if rider else ""
    elif category == "Motorcycle":
        params = _motorcycle(b, l, w, h, refl, rng, rider=ridden)
    else:
        raise ValueError(f"unknown category {category!r}; valid: {', '.join(CATEGORIES)}")
    model = ObjectModel(category, np.array([l, w, h]), b.parts(), refl, animate, params)
    return model


# --------------------------------------------------------------------------- vehicles


def _car(b: _Builder, l, w, h, refl, rng) -> None:
    z0 = -h / 2
    r_w = float(np.clip(0.2 * h, 0.28, 0.36))
    clearance = 0.12 * h + rng.uniform(0.0, 0.05)
    belt = z0 + h * rng.uniform(0.52, 0.6)
    over_f = rng.uniform(0.17, 0.22) * l
    over_r = rng.uniform(0.15, 0.21) * l
    for x in (l / 2 - over_f, -l / 2 + over_r):
        # Tyres sit 3 cm inside the body side, so the body hides their upper half (arches).
        for y in (w / 2 - 0.13, -(w / 2 - 0.13)):
            b.wheel(x, y, z0 + r_w, r_w, 0.1)
    style = rng.choice(["sedan", "hatch", "wagon"])
    # Lower body, with the bumpers a little lower than the belt line at both ends.
    b.box_span(-l / 2 + 0.25, l / 2 - 0.35, -w / 2, w / 2, z0 + clearance, belt, refl)
    b.box_span(
        l / 2 - 0.35, l / 2, -w / 2 + 0.05, w / 2 - 0.05, z0 + clearance + 0.05, belt - 0.1, refl
    )
    b.box_span(
        -l / 2, -l / 2 + 0.25, -w / 2 + 0.05, w / 2 - 0.05, z0 + clearance + 0.05, belt - 0.05, refl
    )
    cab_front = l / 2 - rng.uniform(0.3, 0.36) * l
    cab_back = {"sedan": -l / 2 + 0.22 * l, "hatch": -l / 2 + 0.12, "wagon": -l / 2 + 0.1}[style]
    roof_t = 0.05
    cw = w / 2 - 0.1
    # Greenhouse: glass sides, a tilted windshield and a painted roof.
    b.box_span(cab_back + 0.2, cab_front - 0.1, -cw, cw, belt, h / 2 - roof_t, GLASS)
    # Tilted 0.9 rad; its half height is chosen so its vertical extent stays inside the box.
    hz = ((h / 2 - belt) / 2 - 0.04 * math.sin(0.9)) / math.cos(0.9)
    b.add(
        BOX,
        (cab_front - 0.1 - hz * math.sin(0.9) * 0.5, 0.0, (belt + h / 2) / 2),
        (0.04, cw, hz),
        GLASS,
        _rot_y(0.9),
    )
    b.box_span(cab_back + 0.25, cab_front - 0.35, -cw, cw, h / 2 - roof_t, h / 2, refl)


def _van(b: _Builder, l, w, h, refl, rng) -> None:
    z0 = -h / 2
    r_w = float(np.clip(0.15 * h, 0.3, 0.38))
    clearance = rng.uniform(0.16, 0.22)
    hood = rng.uniform(0.1, 0.17) * l
    for x in (l / 2 - hood - 0.1, -l / 2 + rng.uniform(0.15, 0.22) * l):
        for y in (w / 2 - 0.14, -(w / 2 - 0.14)):
            b.wheel(x, y, z0 + r_w, r_w, 0.11)
    belt = z0 + 0.5 * h
    # Hood at the front, a tall body behind it with a window band in its upper half.
    b.box_span(l / 2 - hood, l / 2, -w / 2 + 0.05, w / 2 - 0.05, z0 + clearance, belt, refl)
    b.box_span(-l / 2, l / 2 - hood, -w / 2, w / 2, z0 + clearance, belt + 0.1, refl)
    windows = rng.random() < 0.6
    top = h / 2 - 0.12
    b.box_span(-l / 2, l / 2 - hood, -w / 2, w / 2, belt + 0.1, top, GLASS if windows else refl)
    if windows:  # window pillars keep a painted rear and front
        b.box_span(-l / 2, -l / 2 + 0.3, -w / 2, w / 2, belt + 0.1, top, refl)
    b.box_span(-l / 2, l / 2 - hood - 0.05, -w / 2, w / 2, top, h / 2, refl)
    b.add(
        BOX,
        (l / 2 - hood - 0.05, 0.0, (belt + top) / 2),
        (0.04, w / 2 - 0.08, (top - belt) / 2),
        GLASS,
        _rot_y(0.5),
    )


def _truck(b: _Builder, l, w, h, refl, rng) -> None:
    z0 = -h / 2
    r_w = 0.5
    cab_len = rng.uniform(1.8, 2.4)
    cab_h = min(h, rng.uniform(2.6, 3.1))
    gap = 0.3
    chassis_top = z0 + 1.1
    b.box_span(
        l / 2 - cab_len, l / 2, -w / 2 + 0.05, w / 2 - 0.05, z0 + 0.45, z0 + cab_h * 0.62, refl
    )
    b.box_span(
        l / 2 - cab_len + 0.1,
        l / 2 - 0.15,
        -w / 2 + 0.05,
        w / 2 - 0.05,
        z0 + cab_h * 0.62,
        z0 + cab_h * 0.9,
        GLASS,
    )
    b.box_span(
        l / 2 - cab_len,
        l / 2 - 0.1,
        -w / 2 + 0.05,
        w / 2 - 0.05,
        z0 + cab_h * 0.9,
        z0 + cab_h,
        refl,
    )
    b.box_span(-l / 2 + 0.5, l / 2 - cab_len, -w * 0.3, w * 0.3, z0 + 0.5, chassis_top, METAL)
    cargo_refl = float(rng.uniform(0.3, 0.8))
    kind = rng.choice(["box", "box", "tank"])
    if kind == "tank":
        rad = min(w / 2, (h - 1.1) / 2)
        b.add(
            CYLINDER,
            (-cab_len / 2 - gap / 2, 0.0, h / 2 - rad),
            (rad, rad, (l - cab_len - gap) / 2),
            cargo_refl,
            _X_AXIS_ROT,
        )
        # Keep the label tight: a thin rail on top of the chassis reaches the full width.
        b.box_span(
            -l / 2, l / 2 - cab_len - gap, -w / 2, w / 2, chassis_top - 0.15, chassis_top, METAL
        )
        if 2 * rad < h - 1.1:
            b.box_span(-l / 2, -l / 2 + 0.3, -0.3, 0.3, chassis_top, h / 2, METAL)
    else:
        b.box_span(-l / 2, l / 2 - cab_len - gap, -w / 2, w / 2, chassis_top, h / 2, cargo_refl)
    n_rear = 2 if l > 8 else 1
    xs = [l / 2 - cab_len / 2] + [-l / 2 + 1.2 + 1.35 * i for i in range(n_rear)]
    for x in xs:
        for y in (w / 2 - 0.25, -(w / 2 - 0.25)):
            b.wheel(x, y, z0 + r_w, r_w, 0.25)


def _bus(b: _Builder, l, w, h, refl, rng) -> None:
    z0 = -h / 2
    r_w = 0.5
    lower = z0 + 0.3
    win0 = z0 + rng.uniform(1.0, 1.2)
    win1 = h / 2 - rng.uniform(0.35, 0.5)
    b.box_span(-l / 2, l / 2, -w / 2, w / 2, lower, win0, refl)
    b.box_span(-l / 2 + 0.3, l / 2 - 0.05, -w / 2, w / 2, win0, win1, GLASS)
    b.box_span(-l / 2, -l / 2 + 0.3, -w / 2, w / 2, win0, win1, refl)
    b.box_span(-l / 2, l / 2, -w / 2, w / 2, win1, h / 2, refl)
    for x in (l / 2 - 2.6, -l / 2 + 3.0):
        for y in (w / 2 - 0.33, -(w / 2 - 0.33)):
            b.wheel(x, y, z0 + r_w, r_w, 0.25)


# --------------------------------------------------------------------------- people


def _pedestrian(b: _Builder, l, w, h, refl, rng) -> dict:
    z0 = -h / 2
    r_head = 0.06 * h
    hip_z = z0 + 0.48 * h
    shoulder_z = z0 + 0.815 * h
    r_leg = 0.065 * (w / 0.66) ** 0.5
    r_arm = 0.045
    torso_depth = min(0.13, l / 2 - 0.02)
    # Torso and head (static); limbs are rebuilt each frame.
    b.add(
        ELLIPSOID,
        (0.0, 0.0, (hip_z + shoulder_z) / 2 + 0.02),
        (torso_depth, w / 2 - 2 * r_arm, (shoulder_z - hip_z) / 2 + 0.06),
        refl,
    )
    b.add(ELLIPSOID, (0.01, 0.0, h / 2 - r_head), (r_head * 0.95, r_head * 0.85, r_head), 0.3)
    if rng.random() < 0.3:  # a backpack
        depth = min(0.12, l / 2 - torso_depth - 0.01)
        if depth > 0.04:
            b.box_span(
                -torso_depth - depth,
                -torso_depth + 0.03,
                -0.15,
                0.15,
                hip_z + 0.1,
                shoulder_z - 0.02,
                float(rng.uniform(0.1, 0.5)),
            )
    leg_len = hip_z - z0
    amp = min(0.62, math.asin(min(1.0, (l / 2 - r_leg) / leg_len)))
    arm_len = 0.35 * h
    arm_amp = min(0.45, math.asin(min(1.0, (l / 2 - r_arm) / arm_len)))
    return {
        "hip_z": hip_z,
        "leg_len": leg_len,
        "leg_y": 0.17 * w,
        "r_leg": r_leg,
        "amp": amp,
        "shoulder_z": shoulder_z - 0.04,
        "arm_y": w / 2 - r_arm,
        "r_arm": r_arm,
        "arm_len": arm_len,
        "arm_amp": arm_amp,
        "refl_legs": float(rng.uniform(0.08, 0.45)),
        "refl": refl,
    }


def _walker_limbs(seg: list, p: dict, phase: float, amplitude: float) -> None:
    swing = p["amp"] * amplitude * math.sin(phase)
    for sign in (1.0, -1.0):
        a = sign * swing
        hip = (0.0, sign * p["leg_y"], p["hip_z"])
        # The foot stays on the ground (the leg stretches a little at full stride); the flat end
        # cap is lifted by its tilt so it does not dip below the box.
        foot = (
            p["leg_len"] * math.sin(a),
            sign * p["leg_y"],
            p["hip_z"] - p["leg_len"] + p["r_leg"] * abs(math.sin(a)),
        )
        seg.append((hip, foot, p["r_leg"], p["refl_legs"]))
        arm_a = -sign * swing * p["arm_amp"] / max(p["amp"], 1e-6)
        sh = (0.0, sign * p["arm_y"], p["shoulder_z"])
        hand = (p["arm_len"] * math.sin(arm_a), sh[1], sh[2] - p["arm_len"] * math.cos(arm_a))
        seg.append((sh, hand, p["r_arm"], p["refl"]))


def _bicycle(b: _Builder, l, w, h, refl, rng, *, rider: bool) -> dict:
    z0 = -h / 2
    r_w = min(0.35, 0.2 * l)
    frame_refl = float(rng.uniform(0.3, 0.7))
    rear = np.array([-l / 2 + r_w, 0.0, z0 + r_w])
    front = np.array([l / 2 - r_w, 0.0, z0 + r_w])
    b.wheel(*rear, r_w, 0.025)
    b.wheel(*front, r_w, 0.025)
    bb = np.array([-0.05 * l, 0.0, z0 + r_w - 0.02])
    frame_top = z0 + (0.85 if rider else min(h - 0.2, 0.85))
    seat = np.array([-0.17 * l, 0.0, frame_top + 0.05])
    head = np.array([0.26 * l, 0.0, frame_top])
    bar_z = z0 + min(h - 0.03, 1.05) if not rider else z0 + 1.02
    bar = np.array([0.28 * l, 0.0, bar_z])
    for p0, p1 in (
        (rear, bb),
        (bb, seat),
        (seat, head),
        (bb, head),
        (head, front),
        (rear, seat),
        (head, bar),
    ):
        b.segment(p0, p1, 0.022, frame_refl)
    b.box_span(seat[0] - 0.12, seat[0] + 0.1, -0.07, 0.07, seat[2], seat[2] + 0.06, 0.15)
    b.segment((bar[0], -w / 2 + 0.03, bar[2]), (bar[0], w / 2 - 0.03, bar[2]), 0.025, METAL)
    params: dict = {"bb": bb, "crank": 0.17, "hip": seat + np.array([0.0, 0.0, 0.1])}
    if not rider:
        return params
    # Rider: hip on the saddle, torso leaning forward to reach the bar, head touching the top.
    r_head = 0.105 * h / 1.74
    hip = seat + np.array([0.02, 0.0, 0.1])
    shoulder_z = h / 2 - 2 * r_head - 0.05
    torso_len = 0.58
    dz = shoulder_z - hip[2]
    dx = math.sqrt(max(torso_len**2 - dz**2, 0.01))
    shoulder = hip + np.array([dx, 0.0, dz])
    mid = (hip + shoulder) / 2
    lean = math.atan2(dx, dz)
    b.add(ELLIPSOID, mid, (0.12, min(0.2, w / 2 - 0.1), torso_len / 2 + 0.05), refl, _rot_y(lean))
    b.add(
        ELLIPSOID,
        shoulder + np.array([0.08, 0.0, r_head + 0.05]),
        (r_head, r_head * 0.9, r_head),
        0.3,
    )
    for sign in (1.0, -1.0):
        sh = shoulder + np.array([0.0, sign * min(0.2, w / 2 - 0.05), -0.03])
        grip = np.array([bar[0], sign * min(0.24, w / 2 - 0.05), bar[2]])
        b.segment(sh, grip, 0.045, refl)
    params.update(
        {
            "hip": hip,
            "seg": 0.46 * h / 1.74,
            "r_leg": 0.065,
            "refl_legs": float(rng.uniform(0.08, 0.45)),
        }
    )
    return params


def _rider_legs(seg: list, p: dict, phase: float) -> None:
    for sign, ph in ((1.0, phase), (-1.0, phase + math.pi)):
        pedal = p["bb"] + np.array(
            [p["crank"] * math.cos(ph), sign * 0.1, p["crank"] * math.sin(ph)]
        )
        hip = p["hip"] + np.array([0.0, sign * 0.1, 0.0])
        knee = _knee(hip, pedal, p["seg"])
        seg.append((hip, knee, p["r_leg"], p["refl_legs"]))
        seg.append((knee, pedal, p["r_leg"] * 0.8, p["refl_legs"]))


def _motorcycle(b: _Builder, l, w, h, refl, rng, *, rider: bool) -> dict:
    z0 = -h / 2
    r_w = min(0.32, 0.15 * l)
    rear = np.array([-l / 2 + r_w, 0.0, z0 + r_w])
    front = np.array([l / 2 - r_w, 0.0, z0 + r_w])
    b.wheel(*rear, r_w, 0.07)
    b.wheel(*front, r_w, 0.06)
    # Engine block, tank, seat, front fork, handlebar with mirrors at full width.
    b.box_span(-0.15 * l, 0.18 * l, -0.2, 0.2, z0 + 0.25, z0 + 0.62, METAL)
    b.add(ELLIPSOID, (0.12 * l, 0.0, z0 + 0.82), (0.25, 0.17, 0.13), refl)
    b.box_span(-0.36 * l, 0.02 * l, -0.15, 0.15, z0 + 0.7, z0 + 0.82, 0.1)
    bar = np.array([0.3 * l, 0.0, z0 + (1.05 if rider else min(h - 0.05, 1.1))])
    b.segment(front, bar, 0.04, METAL)
    b.segment((bar[0], -w / 2 + 0.03, bar[2]), (bar[0], w / 2 - 0.03, bar[2]), 0.03, METAL)
    b.segment(rear + np.array([0.0, -0.2, 0.05]), (0.0, -0.2, z0 + 0.3), 0.05, METAL)
    if not rider:
        if h - 0.05 > 1.1:
            b.box_span(bar[0] - 0.05, bar[0] + 0.05, -0.05, 0.05, bar[2], h / 2, METAL)
        return {}
    r_head = 0.14  # helmet
    hip = np.array([-0.1 * l, 0.0, z0 + 0.92])
    shoulder_z = h / 2 - 2 * r_head - 0.03
    torso_len = 0.55
    dz = shoulder_z - hip[2]
    dx = math.sqrt(max(torso_len**2 - dz**2, 0.01))
    shoulder = hip + np.array([dx, 0.0, dz])
    b.add(
        ELLIPSOID,
        (hip + shoulder) / 2,
        (0.14, min(0.22, w / 2 - 0.1), torso_len / 2 + 0.05),
        float(rng.uniform(0.05, 0.4)),
        _rot_y(math.atan2(dx, dz)),
    )
    b.add(
        ELLIPSOID,
        shoulder + np.array([0.05, 0.0, r_head + 0.02]),
        (r_head, r_head * 0.9, r_head),
        float(rng.uniform(0.2, 0.8)),
    )
    for sign in (1.0, -1.0):
        sh = shoulder + np.array([0.0, sign * min(0.2, w / 2 - 0.06), -0.03])
        b.segment(sh, (bar[0], sign * min(0.3, w / 2 - 0.05), bar[2]), 0.05, 0.2)
        knee = np.array([0.12 * l, sign * 0.24, z0 + 0.7])
        b.segment(hip + np.array([0.0, sign * 0.1, 0.0]), knee, 0.08, 0.2)
        b.segment(knee, (0.0, sign * 0.2, z0 + 0.3), 0.06, 0.2)
    return {}
