"""The data model of a synthetic street scene: its configuration, ground, agents, the scene
itself and one rendered frame, plus the frame rate and the labelled view.

World frame: x along the main street, y to its left, z up (metres); see
:mod:`envs.synthetic.street` for how scenes are laid out and :mod:`envs.synthetic.scene` for
how frames are rendered.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

from envs.synthetic.objects import (
    CATEGORIES,
    ObjectModel,
)
from envs.synthetic.raycast import Parts

__all__ = [
    "DT",
    "FOV_HALF_ANGLE",
    "LABEL_RANGE",
    "MOTION_VERSIONS",
    "Agent",
    "FrameResult",
    "Ground",
    "Scene",
    "SceneConfig",
    "check_motion",
]

DT = 0.1  # seconds per frame (10 Hz, as KITTI)
FOV_HALF_ANGLE = math.radians(45.0)  # labelled field of view: the front camera, as KITTI
LABEL_RANGE = 70.0  # metres; objects farther away are not labelled
MOTION_VERSIONS = ("v1", "kitti")  # see envs.synthetic.kitti_motion
_F = np.float32
_F = np.float32


def check_motion(name: str) -> str:
    """``name`` if it is a motion version; a ``ValueError`` naming the valid ones otherwise."""
    if name not in MOTION_VERSIONS:
        raise ValueError(f"unknown motion {name!r}; valid motions: {', '.join(MOTION_VERSIONS)}")
    return name


@dataclass(frozen=True)
class SceneConfig:
    """Knobs of one generated scene.

    Attributes:
        n_frames: frames to simulate (10 Hz).
        density: multiplier of the number of moving and parked agents (1 = city street).
        static_density: multiplier of trees, poles, signs and buildings' detail.
        required: categories that must appear as labelled targets (placed in view mid-scene).
        motion: the motion model, ``"v1"`` or ``"kitti"`` (:mod:`envs.synthetic.kitti_motion`).
    """

    n_frames: int
    density: float = 1.0
    static_density: float = 1.0
    required: tuple[str, ...] = CATEGORIES
    motion: str = "v1"

    def __post_init__(self) -> None:
        if self.n_frames < 2:
            raise ValueError(f"n_frames must be >= 2, got {self.n_frames}")
        if self.density < 0 or self.static_density < 0:
            raise ValueError(
                f"density and static_density must be >= 0, got {self.density}, "
                f"{self.static_density}"
            )
        bad = [c for c in self.required if c not in CATEGORIES]
        if bad:
            raise ValueError(f"unknown required categories {bad}; valid: {', '.join(CATEGORIES)}")
        check_motion(self.motion)


@dataclass
class Ground:
    """Ground surface: plane ``z = slope_x x + slope_y y`` plus roughness, and its reflectivity.

    Attributes:
        slope_x, slope_y: plane slopes (dimensionless).
        rough_amp, rough_k, rough_phase: ``(K,)``, ``(K, 2)``, ``(K,)`` sinusoidal roughness:
            ``sum_i amp_i sin(k_i . (x, y) + phase_i)`` metres.
        road_y: ``(2,)`` road edges ``(right, left)`` in world y.
        markings_y: ``(M,)`` lane-line positions in world y (dashed, 3 m on / 6 m off).
        cross_x, cross_half: cross-street centre x and half width (``nan`` when absent).
        asphalt, paint, verge: reflectivities.
    """

    slope_x: float
    slope_y: float
    rough_amp: np.ndarray
    rough_k: np.ndarray
    rough_phase: np.ndarray
    road_y: tuple[float, float]
    markings_y: np.ndarray
    cross_x: float
    cross_half: float
    asphalt: float = 0.15
    paint: float = 0.7
    verge: float = 0.22
    curb_h: float = 0.0
    sidewalk_w: float = 0.0

    def height(self, x: np.ndarray, y: np.ndarray) -> np.ndarray:
        """Plane height (no roughness) at world ``(x, y)``, metres."""
        return self.slope_x * np.asarray(x) + self.slope_y * np.asarray(y)

    def surface(self, x: np.ndarray, y: np.ndarray) -> np.ndarray:
        """Height of what one stands on at ``(x, y)``: the ground, or the top of a sidewalk
        (``curb_h`` higher) in the sidewalk bands outside the cross street."""
        x = np.asarray(x, dtype=np.float64)
        y = np.asarray(y, dtype=np.float64)
        on = ((y < self.road_y[0]) & (y >= self.road_y[0] - self.sidewalk_w)) | (
            (y > self.road_y[1]) & (y <= self.road_y[1] + self.sidewalk_w)
        )
        if math.isfinite(self.cross_x):
            on &= np.abs(x - self.cross_x) > self.cross_half
        return self.height(x, y) + np.where(on, self.curb_h, 0.0)

    def roughness(self, x: np.ndarray, y: np.ndarray) -> np.ndarray:
        out = np.zeros(np.shape(x), dtype=_F)
        for a, k, ph in zip(self.rough_amp, self.rough_k, self.rough_phase, strict=True):
            out += _F(a) * np.sin(_F(k[0]) * x + _F(k[1]) * y + _F(ph))
        return out

    def reflectivity(self, x: np.ndarray, y: np.ndarray) -> np.ndarray:
        on_road = (y >= self.road_y[0]) & (y <= self.road_y[1])
        if math.isfinite(self.cross_x):
            on_road |= np.abs(x - self.cross_x) <= self.cross_half
        refl = np.where(on_road, _F(self.asphalt), _F(self.verge)).astype(_F)
        dashed = (x % _F(9.0)) < 3.0
        for ym in self.markings_y:
            refl[(np.abs(y - ym) < 0.08) & dashed & on_road] = self.paint
        for ye in self.road_y:  # solid edge lines
            refl[np.abs(y - (ye - math.copysign(0.3, ye))) < 0.08] = self.paint
        return refl


@dataclass
class Agent:
    """A labelled object over the whole scene (moving or parked).

    Attributes:
        track_id: id written to the labels.
        category: one of :data:`~envs.synthetic.objects.CATEGORIES`.
        model: its part model.
        pose: ``(T, 3)`` world ``(x, y, yaw)`` of the box centre per frame.
        phase: ``(T,)`` gait / pedal phase, radians.
        amplitude: ``(T,)`` limb swing in [0, 1] (0 when standing).
        present: ``(T,)`` bool, the object exists in that frame (``None``: always). Replayed
            label tracks exist only in their labelled frames.
        z: ``(T,)`` world z of the box centre (``None``: standing on the ground plane).
    """

    track_id: int
    category: str
    model: ObjectModel
    pose: np.ndarray
    phase: np.ndarray
    amplitude: np.ndarray
    present: np.ndarray | None = None
    z: np.ndarray | None = None


@dataclass
class Scene:
    """A generated scene (world-frame description, rendered frame by frame).

    Attributes:
        scene_id: the KITTI-style scene number.
        n_frames: number of frames.
        ground: the ground model.
        ego: ``(T, 3)`` world ``(x, y, yaw)`` of the sensor per frame.
        static_bounds: ``(S, 7)`` world boxes of static objects (buildings, sidewalks, trees...).
        static_solid: ``(S,)`` bool, the box is the surface.
        static_refl: ``(S,)`` reflectivity of solid ones.
        static_parts: world-frame parts of the non-solid static objects (owner indexes ``S``).
        agents: the labelled objects.
    """

    scene_id: int
    n_frames: int
    ground: Ground
    ego: np.ndarray
    static_bounds: np.ndarray
    static_solid: np.ndarray
    static_refl: np.ndarray
    static_parts: Parts
    agents: list[Agent] = field(default_factory=list)


@dataclass
class FrameResult:
    """One rendered frame.

    Attributes:
        points: ``(N, 4)`` float32 scan (sensor frame, intensity in [0, 1]).
        agent_index: ``(A_f,)`` indices into ``scene.agents`` of the agents present this frame.
        boxes: ``(A_f, 7)`` their boxes in the sensor frame.
        in_fov: ``(A_f,)`` bool, inside the labelled field of view.
        n_points: ``(A_f,)`` points returned by each agent.
        bbox_rays: ``(A_f,)`` rays entering each agent's box within range (computed for agents
            in the field of view only; 0 for the others).
        clear_rays: ``(A_f,)`` of those, rays not blocked by anything before reaching the box.
    """

    points: np.ndarray
    agent_index: np.ndarray
    boxes: np.ndarray
    in_fov: np.ndarray
    n_points: np.ndarray
    bbox_rays: np.ndarray
    clear_rays: np.ndarray
