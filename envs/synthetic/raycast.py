"""Vectorised ray casting against analytic primitives (the synthetic LiDAR's hot path).

Everything is in the sensor frame with the sensor at the origin, so a ray is ``t * d`` with ``d`` a
unit direction and ``t`` the range in metres.

A frame is a flat list of primitives (:class:`Parts`): oriented boxes, finite elliptic cylinders
(axis = the part's local z) and ellipsoids, each with a general 3x3 rotation, half extents, a
reflectivity and an ``owner`` (the object it belongs to; returned per point). Solid scenery such
as buildings is a single box part.

The cast is fully vectorised, never looping over rays in Python:

1. Each primitive is paired only with the rays of its angular window: the azimuth columns and
   beams that its axis-aligned bounding box can cover (a conservative window from the box
   corners). This is what keeps the work near ~200k pairs for a 131k-ray frame with 40 agents.
2. Every primitive is mapped to a unit shape (cube ``[-1, 1]^3``, unit cylinder, unit sphere) by
   the affine map ``M = diag(1 / half) @ R.T``; a linear map keeps the ray parameter ``t``, so
   the unit-shape hit distance is the metric range. Pairs are tested per shape kind.
3. Occlusion is the nearest hit per ray (``np.minimum.at``), including the ground.
4. Returns get dropout (more for dark surfaces such as glass and tyres, and at long range),
   Gaussian range noise, and an intensity from the surface reflectivity.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from envs.synthetic.sensor import SensorModel

__all__ = [
    "BOX",
    "CYLINDER",
    "ELLIPSOID",
    "CastResult",
    "Parts",
    "box_parts",
    "cast",
    "cast_single_box",
]

BOX, CYLINDER, ELLIPSOID = 0, 1, 2
_F = np.float32


@dataclass
class Parts:
    """A batch of primitives.

    Attributes:
        kind: ``(P,)`` int, :data:`BOX`, :data:`CYLINDER` or :data:`ELLIPSOID`.
        center: ``(P, 3)`` float64 centres, metres.
        rot: ``(P, 3, 3)`` float64 rotations, part frame -> parent frame (columns = part axes).
        half: ``(P, 3)`` float64 half extents (box), radii (ellipsoid) or
            ``(radius_x, radius_y, half_height)`` (cylinder), metres.
        refl: ``(P,)`` float32 reflectivity in [0, 1] (glass ~0.05, paint ~0.4, markings ~0.7).
        owner: ``(P,)`` int object index (meaningful once the parts of a frame are assembled).
    """

    kind: np.ndarray
    center: np.ndarray
    rot: np.ndarray
    half: np.ndarray
    refl: np.ndarray
    owner: np.ndarray

    def __len__(self) -> int:
        return len(self.kind)

    @staticmethod
    def empty() -> Parts:
        return Parts(
            np.zeros(0, np.int8),
            np.zeros((0, 3)),
            np.zeros((0, 3, 3)),
            np.zeros((0, 3)),
            np.zeros(0, _F),
            np.zeros(0, np.int64),
        )

    @staticmethod
    def concat(items: list[Parts]) -> Parts:
        if not items:
            return Parts.empty()
        return Parts(
            np.concatenate([p.kind for p in items]),
            np.concatenate([p.center for p in items]),
            np.concatenate([p.rot for p in items]),
            np.concatenate([p.half for p in items]),
            np.concatenate([p.refl for p in items]),
            np.concatenate([p.owner for p in items]),
        )

    def transformed(self, rot: np.ndarray, trans: np.ndarray) -> Parts:
        """Parts moved by the rigid transform ``p -> rot @ p + trans`` (``rot (3, 3)``) or, with
        ``rot (P, 3, 3)`` and ``trans (P, 3)``, one transform per part."""
        rot = np.asarray(rot, dtype=np.float64)
        trans = np.asarray(trans, dtype=np.float64)
        if rot.ndim == 2:
            center = self.center @ rot.T + trans
            new_rot = np.einsum("ij,pjk->pik", rot, self.rot)
        else:
            center = np.einsum("pij,pj->pi", rot, self.center) + trans
            new_rot = np.einsum("pij,pjk->pik", rot, self.rot)
        return Parts(self.kind, center, new_rot, self.half, self.refl, self.owner)


@dataclass
class CastResult:
    """One simulated scan.

    Attributes:
        points: ``(N, 4)`` float32 ``(x, y, z, intensity)`` in the sensor frame.
        owner: ``(N,)`` int32 object index of each point, ``-1`` for the ground.
        bbox_rays: ``(O,)`` int number of rays whose line of sight enters each object's bounds
            within range (the returns an unoccluded object would give, before dropout).
        clear_rays: ``(O,)`` int of those, the rays along which nothing else (another object or
            the ground) is hit before the ray enters the bounds: the object's unoccluded view.
    """

    points: np.ndarray
    owner: np.ndarray
    bbox_rays: np.ndarray
    clear_rays: np.ndarray


def _expand(counts: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Ragged enumeration: for ``counts (K,)`` return ``(group (S,), k (S,))`` int32 with ``k``
    running ``0..counts[g]-1`` inside each group, ``S = counts.sum()``."""
    counts = counts.astype(np.int64)
    total = int(counts.sum())
    group = np.repeat(np.arange(len(counts), dtype=np.int32), counts)
    starts = (np.cumsum(counts) - counts).astype(np.int32)
    k = np.arange(total, dtype=np.int32) - np.repeat(starts, counts)
    return group, k


def _windows(sensor: SensorModel, bounds: np.ndarray) -> tuple[np.ndarray, ...]:
    """Conservative ray windows of yaw-oriented boxes ``(O, 7)``.

    Returns ``(col0, n_col, beam0, n_beam)`` int64 ``(O,)``: columns ``col0 .. col0+n_col-1``
    (modulo ``n_columns``) and beams ``beam0 .. beam0+n_beam-1`` (beam index, top beam 0).
    """
    x, y, z = bounds[:, 0], bounds[:, 1], bounds[:, 2]
    l2, w2, h2 = bounds[:, 3] / 2, bounds[:, 4] / 2, bounds[:, 5] / 2
    c, s = np.cos(bounds[:, 6]), np.sin(bounds[:, 6])
    sl = np.array([1.0, -1.0, -1.0, 1.0])
    sw = np.array([1.0, 1.0, -1.0, -1.0])
    cx = x[:, None] + c[:, None] * l2[:, None] * sl - s[:, None] * w2[:, None] * sw
    cy = y[:, None] + s[:, None] * l2[:, None] * sl + c[:, None] * w2[:, None] * sw
    ang_c = np.arctan2(y, x)
    rel = np.arctan2(cy, cx) - ang_c[:, None]
    rel = (rel + np.pi) % (2 * np.pi) - np.pi
    step = sensor.azimuth_step
    lo = ang_c + rel.min(1) - step
    hi = ang_c + rel.max(1) + step
    # Distance from the sensor (origin) to the footprint rectangle, in the box frame.
    px, py = -(c * x + s * y), -(-s * x + c * y)
    d_min = np.hypot(np.maximum(np.abs(px) - l2, 0.0), np.maximum(np.abs(py) - w2, 0.0))
    d_max = np.sqrt(cx**2 + cy**2).max(1)
    inside = d_min <= 1e-6
    n_cols = sensor.n_columns
    col0 = np.floor((lo + np.pi) / step - 0.5).astype(np.int64)
    col1 = np.ceil((hi + np.pi) / step - 0.5).astype(np.int64)
    n_col = np.minimum(col1 - col0 + 1, n_cols)
    col0 = np.where(inside, 0, col0 % n_cols)
    n_col = np.where(inside, n_cols, n_col)
    z_top, z_bot = z + h2, z - h2
    el_hi = np.arctan2(z_top, np.where(z_top > 0, d_min, d_max)) + 1e-4
    el_lo = np.arctan2(z_bot, np.where(z_bot < 0, d_min, d_max)) - 1e-4
    el_asc = np.deg2rad(np.asarray(sensor.elevations_deg, dtype=np.float64))[::-1]
    a0 = np.searchsorted(el_asc, el_lo, side="left")
    a1 = np.searchsorted(el_asc, el_hi, side="right")
    n_beam = np.maximum(a1 - a0, 0)
    beam0 = sensor.n_beams - a1
    n_beam = np.where(d_min < sensor.max_range, n_beam, 0)
    return col0, n_col, beam0, n_beam


def _unit_box(o: tuple, d: tuple) -> tuple[np.ndarray, np.ndarray]:
    """Slab test of rays ``o + t d`` (tuples of three ``(S,)`` arrays) against ``[-1, 1]^3``.
    Returns ``(t_near, t_far)``; a hit is ``t_far >= max(t_near, 0)``."""
    t_near = None
    t_far = None
    for oi, di in zip(o, d, strict=True):
        inv = 1.0 / di
        ta = (-1.0 - oi) * inv
        tb = (1.0 - oi) * inv
        lo = np.minimum(ta, tb)
        hi = np.maximum(ta, tb)
        t_near = lo if t_near is None else np.maximum(t_near, lo)
        t_far = hi if t_far is None else np.minimum(t_far, hi)
    return t_near, t_far


def _unit_sphere(o: tuple, d: tuple) -> np.ndarray:
    """Nearest positive hit of rays with the unit sphere (``inf`` for a miss)."""
    a = d[0] * d[0] + d[1] * d[1] + d[2] * d[2]
    b = o[0] * d[0] + o[1] * d[1] + o[2] * d[2]
    c = o[0] * o[0] + o[1] * o[1] + o[2] * o[2] - 1.0
    disc = b * b - a * c
    t = (-b - np.sqrt(np.maximum(disc, 0.0))) / a
    return np.where((disc >= 0) & (t > 0), t, np.inf)


def _unit_cylinder(o: tuple, d: tuple) -> np.ndarray:
    """Nearest positive hit with the unit cylinder ``x^2 + y^2 <= 1, |z| <= 1`` (caps included)."""
    a = d[0] * d[0] + d[1] * d[1]
    b = o[0] * d[0] + o[1] * d[1]
    c = o[0] * o[0] + o[1] * o[1] - 1.0
    disc = b * b - a * c
    t_side = (-b - np.sqrt(np.maximum(disc, 0.0))) / np.maximum(a, 1e-12)
    z_side = o[2] + t_side * d[2]
    side_ok = (disc >= 0) & (t_side > 0) & (np.abs(z_side) <= 1.0)
    # The cap facing the ray: z = -sign(dz).
    t_cap = (-np.sign(d[2]) - o[2]) / np.where(d[2] == 0, 1e-12, d[2])
    xc = o[0] + t_cap * d[0]
    yc = o[1] + t_cap * d[1]
    cap_ok = (t_cap > 0) & (xc * xc + yc * yc <= 1.0)
    return np.minimum(np.where(side_ok, t_side, np.inf), np.where(cap_ok, t_cap, np.inf))


def _part_aabb(parts: Parts) -> np.ndarray:
    """Axis-aligned bounding boxes ``(P, 7)`` (yaw 0) of parts, for their ray windows."""
    r = parts.rot
    h = parts.half
    ext = np.empty((len(parts), 3))
    box = parts.kind == BOX
    ell = parts.kind == ELLIPSOID
    cyl = parts.kind == CYLINDER
    ext[box] = np.einsum("pij,pj->pi", np.abs(r[box]), h[box])
    ext[ell] = np.sqrt(np.einsum("pij,pj->pi", r[ell] ** 2, h[ell] ** 2))
    rad = np.sqrt(
        r[cyl, :, 0] ** 2 * h[cyl, None, 0] ** 2 + r[cyl, :, 1] ** 2 * h[cyl, None, 1] ** 2
    )
    ext[cyl] = rad + np.abs(r[cyl, :, 2]) * h[cyl, None, 2]
    out = np.zeros((len(parts), 7))
    out[:, :3] = parts.center
    out[:, 3:6] = 2 * ext
    return out


def _pairs(sensor: SensorModel, bounds: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The rays of each primitive's window: ``counts (K,)`` and ``ray (S,)`` int32, grouped by
    primitive (``counts[k]`` consecutive entries each). Built by two ragged expansions
    (primitive -> columns -> beams), so there is no per-pair integer division."""
    col0, n_col, beam0, n_beam = _windows(sensor, bounds)
    n_columns = sensor.n_columns
    cprim, ck = _expand(n_col)
    col = col0.astype(np.int32)[cprim] + ck
    col[col >= n_columns] -= n_columns
    base = beam0.astype(np.int32)[cprim] * n_columns + col  # top beam of the window
    nb = n_beam[cprim]
    _, bk = _expand(nb)
    ray = np.repeat(base, nb) + bk * np.int32(n_columns)
    return n_col * n_beam, ray


class _Rays:
    """Per-sensor contiguous float32 direction components (1-D gathers are the fast ones)."""

    def __init__(self, dirs: np.ndarray) -> None:
        self.x = np.ascontiguousarray(dirs[:, 0], _F)
        self.y = np.ascontiguousarray(dirs[:, 1], _F)
        self.z = np.ascontiguousarray(dirs[:, 2], _F)


def _unit_maps(parts: Parts) -> tuple[np.ndarray, np.ndarray]:
    """Per part the unit-shape map ``M = diag(1/half) R^T`` as ``(9, P)`` float32 rows and the
    ray origin (the sensor) in unit-shape coordinates ``(3, P)``."""
    m = np.swapaxes(parts.rot, 1, 2) / parts.half[:, :, None]
    o = -np.einsum("pij,pj->pi", m, parts.center)
    return np.ascontiguousarray(m.reshape(-1, 9).T, _F), np.ascontiguousarray(o.T, _F)


def _hit_distance(
    kind: int,
    counts: np.ndarray,
    sel: np.ndarray,
    ray: np.ndarray,
    rays: _Rays,
    m: np.ndarray,
    o: np.ndarray,
    yaw_only: bool = False,
) -> np.ndarray:
    """Range of the first hit of each (primitive, ray) pair (``inf`` for a miss).

    Pairs are grouped by primitive: primitive ``sel[k]`` owns ``counts[k]`` consecutive rays,
    so its constants are expanded with ``np.repeat`` (sequential, cheaper than a gather).
    ``yaw_only``: the primitives only turn about z (most boxes), so ``M`` has five non-zeros.
    """
    dx, dy, dz = rays.x.take(ray), rays.y.take(ray), rays.z.take(ray)

    def rep(row: np.ndarray) -> np.ndarray:
        return np.repeat(row[sel], counts)

    if yaw_only:
        du = (rep(m[0]) * dx + rep(m[1]) * dy, rep(m[3]) * dx + rep(m[4]) * dy, rep(m[8]) * dz)
    else:
        mm = [rep(row) for row in m]
        du = (
            mm[0] * dx + mm[1] * dy + mm[2] * dz,
            mm[3] * dx + mm[4] * dy + mm[5] * dz,
            mm[6] * dx + mm[7] * dy + mm[8] * dz,
        )
    ou = (rep(o[0]), rep(o[1]), rep(o[2]))
    with np.errstate(divide="ignore", invalid="ignore", over="ignore"):
        if kind == BOX:
            tn, tf = _unit_box(ou, du)
            return np.where((tf >= tn) & (tn > 0), tn, np.inf)
        if kind == CYLINDER:
            return _unit_cylinder(ou, du)
        return _unit_sphere(ou, du)


_RAYS_CACHE: dict[int, _Rays] = {}

# Drawing ~250k Gaussian samples per frame costs ~4 ms; a fixed table of iid standard normals
# read from a random offset drawn from the frame's generator costs ~0.2 ms and keeps every
# frame deterministic. Within a frame the samples are iid; frames use random (rarely
# overlapping) windows of the table.
_NORMAL_TABLE = np.random.default_rng(20240611).standard_normal(1 << 21).astype(_F)


def _normals(rng: np.random.Generator, n: int) -> np.ndarray:
    """``(n,)`` float32 standard normal samples, deterministic given ``rng``."""
    start = int(rng.integers(0, len(_NORMAL_TABLE)))
    return _NORMAL_TABLE.take(np.arange(start, start + n), mode="wrap")


def cast(
    sensor: SensorModel,
    parts: Parts,
    ground_t: np.ndarray,
    ground_refl: np.ndarray,
    rng: np.random.Generator,
    dirs: np.ndarray | None = None,
    stat_bounds: np.ndarray | None = None,
    stat_owner: np.ndarray | None = None,
) -> CastResult:
    """Simulate one scan.

    Args:
        sensor: the beam layout, range limits and noise model.
        parts: all primitives of the frame in the sensor frame; ``owner`` names the object each
            belongs to (returned per point).
        ground_t: ``(n_rays,)`` range of each ray's ground hit (``inf`` where it misses).
        ground_refl: ``(n_rays,)`` reflectivity of the ground at that hit.
        rng: noise and dropout.
        dirs: ``(n_rays, 3)`` ray directions (default: ``sensor.ray_directions()``).
        stat_bounds: optional ``(B, 7)`` boxes (sensor frame) to report ray statistics for
            (``bbox_rays``, ``clear_rays``), typically the labelled objects' boxes.
        stat_owner: ``(B,)`` the owner id of each of those boxes' parts (a ray blocked only by
            the object's own parts still counts as clear).

    Returns:
        :class:`CastResult` with points in the sensor frame.
    """
    if dirs is None:
        dirs = sensor.ray_directions()
    key = id(dirs)
    rays = _RAYS_CACHE.get(key)
    if rays is None or len(rays.x) != len(dirs):
        rays = _Rays(dirs)
        _RAYS_CACHE.clear()
        _RAYS_CACHE[key] = rays
    n_rays = len(dirs)
    best = np.asarray(ground_t, dtype=_F).copy()
    best[best < sensor.min_range] = np.inf
    best_refl = np.asarray(ground_refl, dtype=_F).copy()
    best_owner = np.full(n_rays, -1, dtype=np.int64)

    if len(parts):
        m, o = _unit_maps(parts)
        aabb = _part_aabb(parts)
        cand_ray, cand_t, cand_prim = [], [], []
        yaw_only = np.abs(parts.rot[:, 2, 2] - 1.0) < 1e-9
        groups = (
            (BOX, (parts.kind == BOX) & yaw_only),
            (BOX, (parts.kind == BOX) & ~yaw_only),
            (CYLINDER, parts.kind == CYLINDER),
            (ELLIPSOID, parts.kind == ELLIPSOID),
        )
        for g, (kind, mask) in enumerate(groups):
            sel = np.flatnonzero(mask)
            if not len(sel):
                continue
            if g == 0:  # yaw-only boxes: the oriented box gives a tighter window than its AABB
                win = np.concatenate(
                    [
                        parts.center[sel],
                        2 * parts.half[sel],
                        np.arctan2(parts.rot[sel, 1, 0], parts.rot[sel, 0, 0])[:, None],
                    ],
                    axis=1,
                )
            else:
                win = aabb[sel]
            counts, ray = _pairs(sensor, win)
            if not len(ray):
                continue
            t = _hit_distance(kind, counts, sel, ray, rays, m, o, yaw_only=g == 0)
            ok = (t < best.take(ray)) & (t >= sensor.min_range)
            cand_ray.append(ray[ok])
            cand_t.append(t[ok].astype(_F, copy=False))
            cand_prim.append(np.repeat(sel.astype(np.int32), counts)[ok])
        if cand_ray:
            ray_c = np.concatenate(cand_ray)
            t_c = np.concatenate(cand_t)
            prim_c = np.concatenate(cand_prim)
            np.minimum.at(best, ray_c, t_c)
            win = t_c <= best.take(ray_c)
            best_refl[ray_c[win]] = parts.refl.take(prim_c[win])
            best_owner[ray_c[win]] = parts.owner.take(prim_c[win])

    n_stat = 0 if stat_bounds is None else len(stat_bounds)
    bbox_rays = np.zeros(n_stat, dtype=np.int64)
    clear_rays = np.zeros(n_stat, dtype=np.int64)
    if n_stat:
        sb = np.asarray(stat_bounds, dtype=np.float64)
        unit = Parts(
            np.zeros(n_stat, np.int8),
            sb[:, :3],
            _rot_z(sb[:, 6]),
            sb[:, 3:6] / 2,
            np.zeros(n_stat, _F),
            np.asarray(stat_owner, dtype=np.int64),
        )
        m, o = _unit_maps(unit)
        counts, ray = _pairs(sensor, sb)
        if len(ray):
            sel = np.arange(n_stat)
            prim = np.repeat(sel, counts)
            with np.errstate(divide="ignore", invalid="ignore", over="ignore"):
                dx, dy, dz = rays.x.take(ray), rays.y.take(ray), rays.z.take(ray)
                rep = [np.repeat(row, counts) for row in (m[0], m[1], m[3], m[4], m[8])]
                du = (rep[0] * dx + rep[1] * dy, rep[2] * dx + rep[3] * dy, rep[4] * dz)
                ou = tuple(np.repeat(o[i], counts) for i in range(3))
                tn, tf = _unit_box(ou, du)
            t_enter = np.maximum(tn, 0.0)
            hit = (tf >= t_enter) & (t_enter < sensor.max_range) & (tf > sensor.min_range)
            prim, ray, t_enter = prim[hit], ray[hit], t_enter[hit]
            bbox_rays = np.bincount(prim, minlength=n_stat)
            clear = (best.take(ray) >= t_enter - 1e-3) | (
                best_owner.take(ray) == unit.owner.take(prim)
            )
            clear_rays = np.bincount(prim[clear], minlength=n_stat)

    idx = np.flatnonzero(best <= sensor.max_range)
    t = best[idx]
    refl = best_refl[idx]
    owner = best_owner[idx]
    # Losses: a base dropout, dark surfaces (glass, tyres) returning rarely, and weak far returns.
    p_drop = sensor.dropout + 0.75 * (refl < 0.08) + 0.15 * (t / sensor.max_range) ** 2
    keep = rng.random(len(idx), dtype=_F) >= p_drop
    idx, t, refl, owner = idx[keep], t[keep], refl[keep], owner[keep]
    noise = _normals(rng, 2 * len(t)).reshape(2, len(t))
    t = t + _F(sensor.range_noise) * noise[0]
    pts = np.empty((len(idx), 4), dtype=_F)
    pts[:, 0] = rays.x[idx] * t
    pts[:, 1] = rays.y[idx] * t
    pts[:, 2] = rays.z[idx] * t
    # Intensity: reflectivity, mildly weaker with range, with a little speckle.
    inten = refl * (1.0 - _F(0.35 / sensor.max_range) * t) + _F(0.02) * noise[1]
    pts[:, 3] = np.clip(inten, 0.0, 1.0)
    return CastResult(points=pts, owner=owner, bbox_rays=bbox_rays, clear_rays=clear_rays)


def _rot_z(yaw: np.ndarray) -> np.ndarray:
    c, s = np.cos(yaw), np.sin(yaw)
    z, one = np.zeros_like(c), np.ones_like(c)
    return np.stack(
        [np.stack([c, -s, z], -1), np.stack([s, c, z], -1), np.stack([z, z, one], -1)], -2
    )


def box_parts(boxes: np.ndarray, refl: np.ndarray, owner: np.ndarray) -> Parts:
    """Yaw-oriented boxes ``(B, 7)`` as :data:`BOX` parts (solid objects such as buildings)."""
    boxes = np.asarray(boxes, dtype=np.float64).reshape(-1, 7)
    return Parts(
        np.zeros(len(boxes), np.int8),
        boxes[:, :3].copy(),
        _rot_z(boxes[:, 6]),
        boxes[:, 3:6] / 2,
        np.asarray(refl, dtype=_F).reshape(-1),
        np.asarray(owner, dtype=np.int64).reshape(-1),
    )


def cast_single_box(sensor: SensorModel, box: np.ndarray, rng: np.random.Generator) -> CastResult:
    """Convenience for tests: one box of reflectivity 0.5, no ground; ``owner`` is 0."""
    box = np.asarray(box, dtype=np.float64).reshape(1, 7)
    n = sensor.n_rays
    parts = box_parts(box, np.array([0.5]), np.array([0]))
    return cast(
        sensor,
        parts,
        np.full(n, np.inf, _F),
        np.zeros(n, _F),
        rng,
        stat_bounds=box,
        stat_owner=np.array([0]),
    )
