"""Synthetic street scenes: the public face of the generator, and frame rendering.

A scene (:mod:`envs.synthetic.scene_types`) is laid out by :func:`build_scene`
(:mod:`envs.synthetic.street`: layout, static clutter, agents, their motion from
:mod:`envs.synthetic.motion`); this module renders its frames: agent boxes in the world and
sensor frames, the sensor's pose, and :func:`render_frame` (ray casting against the ground, the
static parts and the agents' parts placed at frame ``t``).
"""

from __future__ import annotations

import math

import numpy as np

from envs.synthetic.objects import segments_to_parts
from envs.synthetic.raycast import CYLINDER, CastResult, Parts, box_parts, cast
from envs.synthetic.scene_types import (
    FOV_HALF_ANGLE,
    LABEL_RANGE,
    FrameResult,
    Ground,
    Scene,
    SceneConfig,
)
from envs.synthetic.sensor import SensorModel
from envs.synthetic.street import build_scene

# re-exported: what a caller needs to build and render a scene (SceneConfig, build_scene) and
# the labelled view (FOV_HALF_ANGLE, LABEL_RANGE)
__all__ = [
    "FOV_HALF_ANGLE",
    "LABEL_RANGE",
    "SceneConfig",
    "agent_boxes_world",
    "build_scene",
    "render_frame",
    "sensor_pose",
    "world_to_sensor_boxes",
]

_F = np.float32


def _rot_z(yaw: np.ndarray) -> np.ndarray:
    c, s = np.cos(yaw), np.sin(yaw)
    z, o = np.zeros_like(c), np.ones_like(c)
    return np.stack(
        [np.stack([c, -s, z], -1), np.stack([s, c, z], -1), np.stack([z, z, o], -1)], -2
    )


def _rigid_agent_parts(scene: Scene) -> Parts:
    """The rigid parts of every agent in its object frame, concatenated (owner = agent index);
    cached on the scene."""
    cached = getattr(scene, "_rigid_parts", None)
    if cached is None:
        items = []
        for i, a in enumerate(scene.agents):
            p = a.model.parts
            items.append(
                Parts(p.kind, p.center, p.rot, p.half, p.refl, np.full(len(p), i, np.int64))
            )
        cached = Parts.concat(items)
        scene._rigid_parts = cached  # type: ignore[attr-defined]
    return cached


def _to_sensor(points: np.ndarray, boxes: np.ndarray) -> np.ndarray:
    """Object-frame points ``(K, 3)`` of boxes ``(K, 7)`` (sensor frame) -> sensor frame."""
    c, s = np.cos(boxes[:, 6]), np.sin(boxes[:, 6])
    out = np.empty_like(points)
    out[:, 0] = c * points[:, 0] - s * points[:, 1] + boxes[:, 0]
    out[:, 1] = s * points[:, 0] + c * points[:, 1] + boxes[:, 1]
    out[:, 2] = points[:, 2] + boxes[:, 2]
    return out


def _place(parts: Parts, sel: np.ndarray, boxes: np.ndarray) -> Parts:
    """Object-frame parts (``owner`` indexing ``boxes (A, 7)``, sensor frame) moved into the
    sensor frame; only parts with ``sel`` true are kept."""
    owner = parts.owner[sel]
    b = boxes[owner]
    center = _to_sensor(parts.center[sel], b)
    c, s = np.cos(b[:, 6])[:, None], np.sin(b[:, 6])[:, None]
    r = parts.rot[sel]
    rot = np.empty_like(r)
    rot[:, 0, :] = c * r[:, 0, :] - s * r[:, 1, :]
    rot[:, 1, :] = s * r[:, 0, :] + c * r[:, 1, :]
    rot[:, 2, :] = r[:, 2, :]
    return Parts(parts.kind[sel], center, rot, parts.half[sel], parts.refl[sel], owner)


def agent_boxes_world(scene: Scene, t: int) -> np.ndarray:
    """``(A, 7)`` world boxes of all agents at frame ``t`` (bottom on the ground plane)."""
    if not scene.agents:
        return np.zeros((0, 7))
    pose = np.array([a.pose[t] for a in scene.agents])
    size = np.array([a.model.size for a in scene.agents])
    # Standing on the road or on a sidewalk (pedestrians, parked bicycles).
    z = scene.ground.surface(pose[:, 0], pose[:, 1]) + size[:, 2] / 2
    fixed = [i for i, a in enumerate(scene.agents) if a.z is not None]
    if fixed:
        z[fixed] = [scene.agents[i].z[t] for i in fixed]
    return np.column_stack([pose[:, 0], pose[:, 1], z, size, pose[:, 2]])


def sensor_pose(scene: Scene, t: int, sensor: SensorModel) -> tuple[np.ndarray, float]:
    """World position ``(3,)`` and yaw of the sensor at frame ``t``."""
    x, y, yaw = scene.ego[t]
    return np.array([x, y, float(scene.ground.height(x, y)) + sensor.height]), float(yaw)


def world_to_sensor_boxes(boxes: np.ndarray, origin: np.ndarray, yaw: float) -> np.ndarray:
    """World boxes ``(..., 7)`` -> sensor-frame boxes for a sensor at ``origin`` with ``yaw``."""
    c, s = math.cos(yaw), math.sin(yaw)
    d = boxes[..., :3] - origin
    out = np.array(boxes, dtype=np.float64, copy=True)
    out[..., 0] = c * d[..., 0] + s * d[..., 1]
    out[..., 1] = -s * d[..., 0] + c * d[..., 1]
    out[..., 2] = d[..., 2]
    out[..., 6] = (boxes[..., 6] - yaw + np.pi) % (2 * np.pi) - np.pi
    return out


def ground_hits(
    ground: Ground, dirs: np.ndarray, origin: np.ndarray, yaw: float
) -> tuple[np.ndarray, np.ndarray]:
    """Range ``(R,)`` and reflectivity ``(R,)`` of each sensor ray's ground hit (``inf`` above
    the horizon)."""
    c, s = math.cos(yaw), math.sin(yaw)
    # Ray directions in the world (sensor is level; yaw only).
    wx = c * dirs[:, 0] - s * dirs[:, 1]
    wy = s * dirs[:, 0] + c * dirs[:, 1]
    wz = dirs[:, 2]
    denom = wz - ground.slope_x * wx - ground.slope_y * wy
    f0 = origin[2] - ground.slope_x * origin[0] - ground.slope_y * origin[1]
    with np.errstate(divide="ignore", invalid="ignore"):
        t0 = np.where(denom < -1e-4, -f0 / denom, np.inf).astype(_F)
        finite = np.isfinite(t0)
        hx = np.where(finite, origin[0] + t0 * wx, 0.0).astype(_F)
        hy = np.where(finite, origin[1] + t0 * wy, 0.0).astype(_F)
    # Roughness (first-order correction of the range along the ray) and reflectivity only for
    # the rays that actually return from the ground.
    idx = np.flatnonzero(finite & (t0 < 150.0))
    t = np.full(len(dirs), np.inf, dtype=_F)
    hx, hy = hx[idx], hy[idx]
    t[idx] = t0[idx] + ground.roughness(hx, hy) / denom[idx].astype(_F)
    refl = np.zeros(len(dirs), dtype=_F)
    refl[idx] = ground.reflectivity(hx, hy)
    return t, refl


def render_frame(
    scene: Scene, t: int, sensor: SensorModel, rng: np.random.Generator
) -> FrameResult:
    """Ray-cast frame ``t`` of ``scene`` with ``sensor``; noise and dropout from ``rng``."""
    origin, yaw = sensor_pose(scene, t, sensor)
    dirs = sensor.ray_directions()
    g_t, g_refl = ground_hits(scene.ground, dirs, origin, yaw)
    reach = sensor.max_range + 20.0

    # Static objects near enough (the cast culls by angle; this only trims the far world).
    sb = world_to_sensor_boxes(scene.static_bounds, origin, yaw)
    s_keep = np.hypot(sb[:, 0], sb[:, 1]) - 0.5 * np.hypot(sb[:, 3], sb[:, 4]) < reach
    s_idx = np.flatnonzero(s_keep)
    # Agents near enough.
    ab_world = agent_boxes_world(scene, t)
    ab = world_to_sensor_boxes(ab_world, origin, yaw) if len(ab_world) else np.zeros((0, 7))
    a_keep = np.hypot(ab[:, 0], ab[:, 1]) < reach if len(ab) else np.zeros(0, bool)
    for i, a in enumerate(scene.agents):
        if a.present is not None and not a.present[t]:
            a_keep[i] = False
    a_idx = np.flatnonzero(a_keep)

    # Static primitives (owner -2): solid boxes directly, composite objects through their parts.
    c, s_ = math.cos(yaw), math.sin(yaw)
    r_t = np.array([[c, s_, 0.0], [-s_, c, 0.0], [0.0, 0.0, 1.0]])  # R_ego^T
    solid_idx = s_idx[scene.static_solid[s_idx]]
    items: list[Parts] = [
        box_parts(sb[solid_idx], scene.static_refl[solid_idx], np.full(len(solid_idx), -2))
    ]
    sp = scene.static_parts
    if len(sp):
        sp_keep = s_keep[sp.owner]
        kept = Parts(
            sp.kind[sp_keep],
            sp.center[sp_keep],
            sp.rot[sp_keep],
            sp.half[sp_keep],
            sp.refl[sp_keep],
            np.full(int(sp_keep.sum()), -2, np.int64),
        )
        items.append(kept.transformed(r_t, -r_t @ origin))
    # Agent parts: object frame -> sensor frame; owner = agent index. Rigid parts of all agents
    # are transformed in one vectorised step; animated limbs are rebuilt as segments.
    if len(a_idx):
        rigid = _rigid_agent_parts(scene)
        sel = a_keep[rigid.owner]
        items.append(_place(rigid, sel, ab))
        p0s, p1s, rads, refls, owners = [], [], [], [], []
        for ai in a_idx:
            agent = scene.agents[ai]
            if not agent.model.animate:
                continue
            p0, p1, rad, refl_l = agent.model.limbs(
                float(agent.phase[t]), float(agent.amplitude[t])
            )
            p0s.append(p0)
            p1s.append(p1)
            rads.append(rad)
            refls.append(refl_l)
            owners.append(np.full(len(p0), ai, np.int64))
        if p0s:
            owner = np.concatenate(owners)
            p0 = _to_sensor(np.concatenate(p0s), ab[owner])
            p1 = _to_sensor(np.concatenate(p1s), ab[owner])
            center, rot, half = segments_to_parts(p0, p1, np.concatenate(rads))
            items.append(
                Parts(
                    np.full(len(owner), CYLINDER, np.int8),
                    center,
                    rot,
                    half,
                    np.concatenate(refls),
                    owner,
                )
            )
    parts = Parts.concat(items)

    boxes = ab[a_idx]
    az = np.arctan2(boxes[:, 1], boxes[:, 0])
    dist = np.hypot(boxes[:, 0], boxes[:, 1])
    in_fov = (np.abs(az) <= FOV_HALF_ANGLE) & (dist <= LABEL_RANGE) & (boxes[:, 0] > 0)
    res: CastResult = cast(
        sensor, parts, g_t, g_refl, rng, dirs, stat_bounds=boxes[in_fov], stat_owner=a_idx[in_fov]
    )
    n_pts_all = np.bincount(res.owner[res.owner >= 0], minlength=len(scene.agents))
    bbox_rays = np.zeros(len(a_idx), np.int64)
    clear_rays = np.zeros(len(a_idx), np.int64)
    bbox_rays[in_fov] = res.bbox_rays
    clear_rays[in_fov] = res.clear_rays
    return FrameResult(
        points=res.points,
        agent_index=a_idx,
        boxes=boxes,
        in_fov=in_fov,
        n_points=n_pts_all[a_idx],
        bbox_rays=bbox_rays,
        clear_rays=clear_rays,
    )
