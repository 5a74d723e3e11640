"""Box geometry in the LiDAR frame, vectorised over any leading dimensions.

Box convention (docs/design.md): ``(x, y, z, l, w, h, yaw)`` with ``(x, y, z)`` the geometric
centre, ``l`` along the heading, ``w`` across it, ``h`` up, ``yaw`` about +z counter-clockwise
from +x, wrapped to ``[-pi, pi)``. The box-local (canonical) frame of a box is reached by
translating by ``-centre`` and rotating by ``-yaw``.

All functions take numpy arrays and broadcast their leading dimensions. A few torch twins used by
the trackers live at the end of the module (suffix ``_torch``).
"""

from __future__ import annotations

import math
from collections.abc import Sequence

import numpy as np
import torch

__all__ = [
    "apply_offset",
    "apply_offset_pair",
    "box_corners",
    "box_corners_torch",
    "box_to_world",
    "box_to_world_torch",
    "boxes_in_frame",
    "center_distance",
    "iou_3d",
    "iou_bev",
    "iou_pair",
    "invert_rigid",
    "map_points",
    "offset_between",
    "offset_between_pair",
    "points_in_box",
    "rotation_z",
    "wrap_yaw",
    "world_to_box",
    "world_to_box_torch",
]

# Unit corner signs (l, w, h) in the box frame: bottom face counter-clockwise seen from above,
# starting front-left, then the top face in the same order.
_CORNER_SIGNS = np.array(
    [
        [0.5, 0.5, -0.5],
        [-0.5, 0.5, -0.5],
        [-0.5, -0.5, -0.5],
        [0.5, -0.5, -0.5],
        [0.5, 0.5, 0.5],
        [-0.5, 0.5, 0.5],
        [-0.5, -0.5, 0.5],
        [0.5, -0.5, 0.5],
    ]
)
_EPS = 1e-9


def wrap_yaw(yaw: np.ndarray | float) -> np.ndarray:
    """Wrap angles in radians to ``[-pi, pi)``."""
    yaw = np.asarray(yaw, dtype=np.float64)
    return (yaw + np.pi) % (2.0 * np.pi) - np.pi


def rotation_z(yaw: np.ndarray | float) -> np.ndarray:
    """Rotation matrices about +z: ``(...,)`` -> ``(..., 3, 3)``."""
    yaw = np.asarray(yaw, dtype=np.float64)
    c, s = np.cos(yaw), np.sin(yaw)
    zeros, ones = np.zeros_like(c), np.ones_like(c)
    return np.stack(
        [
            np.stack([c, -s, zeros], -1),
            np.stack([s, c, zeros], -1),
            np.stack([zeros, zeros, ones], -1),
        ],
        -2,
    )


def box_corners(boxes: np.ndarray) -> np.ndarray:
    """Corners of boxes ``(..., 7)`` -> ``(..., 8, 3)``; order as ``_CORNER_SIGNS``."""
    boxes = np.asarray(boxes, dtype=np.float64)
    local = boxes[..., None, 3:6] * _CORNER_SIGNS
    return box_to_world(local, boxes)


def map_points(points: np.ndarray, rigid: np.ndarray) -> np.ndarray:
    """``(N, C >= 3)`` points with their xyz mapped by ``rigid``, a ``(3, 4)`` ``[R | t]``
    (``R p + t``, in float64); a copy of the points' dtype, the other columns unchanged."""
    out = points.copy()
    out[:, :3] = points[:, :3].astype(np.float64) @ rigid[:, :3].T + rigid[:, 3]
    return out


def invert_rigid(rigid: np.ndarray) -> np.ndarray:
    """The inverse ``(3, 4)`` map of a rigid ``[R | t]`` (``R`` orthonormal): ``[R^T | -R^T t]``."""
    rotation = rigid[:, :3].T
    return np.c_[rotation, -rotation @ rigid[:, 3]]


def world_to_box(points: np.ndarray, boxes: np.ndarray) -> np.ndarray:
    """Express points ``(..., N, 3)`` in the box-local frame of boxes ``(..., 7)``.

    Extra point columns (intensity) beyond the first three are passed through unchanged.
    The output dtype follows the points (float32 in, float32 out).
    """
    points = np.asarray(points)
    boxes = np.asarray(boxes, dtype=np.float64)
    c = np.cos(boxes[..., 6])[..., None]
    s = np.sin(boxes[..., 6])[..., None]
    dx = points[..., 0] - boxes[..., 0:1]
    dy = points[..., 1] - boxes[..., 1:2]
    dz = points[..., 2] - boxes[..., 2:3]
    local = np.stack([c * dx + s * dy, -s * dx + c * dy, dz], axis=-1)
    if points.shape[-1] > 3:
        extra = np.broadcast_to(points[..., 3:], local.shape[:-1] + (points.shape[-1] - 3,))
        local = np.concatenate([local, extra], axis=-1)
    dtype = points.dtype if np.issubdtype(points.dtype, np.floating) else np.float64
    return local.astype(dtype, copy=False)


def box_to_world(points_box_frame: np.ndarray, boxes: np.ndarray) -> np.ndarray:
    """Inverse of :func:`world_to_box`: box-local points ``(..., N, 3)`` -> LiDAR frame."""
    points = np.asarray(points_box_frame)
    boxes = np.asarray(boxes, dtype=np.float64)
    c = np.cos(boxes[..., 6])[..., None]
    s = np.sin(boxes[..., 6])[..., None]
    px, py = points[..., 0], points[..., 1]
    world = np.stack(
        [
            c * px - s * py + boxes[..., 0:1],
            s * px + c * py + boxes[..., 1:2],
            points[..., 2] + boxes[..., 2:3],
        ],
        axis=-1,
    )
    if points.shape[-1] > 3:
        extra = np.broadcast_to(points[..., 3:], world.shape[:-1] + (points.shape[-1] - 3,))
        world = np.concatenate([world, extra], axis=-1)
    dtype = points.dtype if np.issubdtype(points.dtype, np.floating) else np.float64
    return world.astype(dtype, copy=False)


def points_in_box(
    points: np.ndarray, boxes: np.ndarray, scale: float = 1.0, offset_m: float = 0.0
) -> np.ndarray:
    """Mask of points ``(..., N, 3+)`` inside boxes ``(..., 7)`` -> bool ``(..., N)``.

    The box may be enlarged: half extents become ``scale * size / 2 + offset_m`` on every axis
    (the search region of docs/design.md is ``scale=1.25, offset_m=2.0``). Boundary points count
    as in.
    """
    boxes = np.asarray(boxes, dtype=np.float64)
    local = world_to_box(np.asarray(points)[..., :3], boxes)
    half = boxes[..., None, 3:6] * (0.5 * scale) + offset_m
    return np.all(np.abs(local) <= half, axis=-1)


def apply_offset(ref_boxes: np.ndarray, offsets: np.ndarray) -> np.ndarray:
    """Move reference boxes ``(..., 7)`` by offsets ``(..., 4)`` = ``(dx, dy, dz, dyaw)``.

    The translation is in the reference box's frame: new centre = centre + R(yaw) @ (dx, dy, dz),
    new yaw = wrap(yaw + dyaw); the size is unchanged (the action convention of docs/design.md).
    """
    ref = np.asarray(ref_boxes, dtype=np.float64)
    off = np.asarray(offsets, dtype=np.float64)
    lead = np.broadcast_shapes(ref.shape[:-1], off.shape[:-1])
    ref = np.broadcast_to(ref, lead + (7,))
    off = np.broadcast_to(off, lead + (4,))
    c, s = np.cos(ref[..., 6]), np.sin(ref[..., 6])
    out = ref.copy()
    out[..., 0] = ref[..., 0] + c * off[..., 0] - s * off[..., 1]
    out[..., 1] = ref[..., 1] + s * off[..., 0] + c * off[..., 1]
    out[..., 2] = ref[..., 2] + off[..., 2]
    out[..., 6] = wrap_yaw(ref[..., 6] + off[..., 3])
    return out


def offset_between(ref_boxes: np.ndarray, target_boxes: np.ndarray) -> np.ndarray:
    """The offset ``(..., 4)`` that :func:`apply_offset` needs to move ``ref`` onto ``target``."""
    ref = np.asarray(ref_boxes, dtype=np.float64)
    tgt = np.asarray(target_boxes, dtype=np.float64)
    c, s = np.cos(ref[..., 6]), np.sin(ref[..., 6])
    dx, dy = tgt[..., 0] - ref[..., 0], tgt[..., 1] - ref[..., 1]
    return np.stack(
        [
            c * dx + s * dy,
            -s * dx + c * dy,
            tgt[..., 2] - ref[..., 2],
            wrap_yaw(tgt[..., 6] - ref[..., 6]),
        ],
        axis=-1,
    )


def apply_offset_pair(ref: Sequence[float], offset: Sequence[float]) -> list[float]:
    """:func:`apply_offset` of one box (7 Python floats) by one offset (4) -> 7 floats: the lean
    path in plain Python floats for per-step callers (the env's step)."""
    x, y, z, length, width, height, yaw = ref
    dx, dy, dz, dyaw = offset
    c, s = math.cos(yaw), math.sin(yaw)
    new_yaw = (yaw + dyaw + math.pi) % (2.0 * math.pi) - math.pi
    return [x + c * dx - s * dy, y + s * dx + c * dy, z + dz, length, width, height, new_yaw]


def offset_between_pair(ref: Sequence[float], target: Sequence[float]) -> list[float]:
    """:func:`offset_between` of one pair of boxes (7 Python floats each) -> 4 floats (the lean
    path of :func:`apply_offset_pair`)."""
    x, y, z, _, _, _, yaw = ref
    tx, ty, tz, _, _, _, tyaw = target
    c, s = math.cos(yaw), math.sin(yaw)
    dx, dy = tx - x, ty - y
    dyaw = (tyaw - yaw + math.pi) % (2.0 * math.pi) - math.pi
    return [c * dx + s * dy, -s * dx + c * dy, tz - z, dyaw]


def boxes_in_frame(boxes: np.ndarray, frame_boxes: np.ndarray) -> np.ndarray:
    """Express boxes ``(..., 7)`` in the box-local frame of ``frame_boxes`` ``(..., 7)``."""
    boxes = np.asarray(boxes, dtype=np.float64)
    off = offset_between(frame_boxes, boxes)
    out = np.broadcast_to(boxes, off.shape[:-1] + (7,)).copy()
    out[..., 0:3] = off[..., 0:3]
    out[..., 6] = off[..., 3]
    return out


def center_distance(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Distance in metres between box centres, ``(..., 7)`` x ``(..., 7)`` -> ``(...)``."""
    a = np.asarray(a, dtype=np.float64)
    b = np.asarray(b, dtype=np.float64)
    return np.linalg.norm(a[..., :3] - b[..., :3], axis=-1)


# --------------------------------------------------------------------------- oriented IoU
#
# The BEV intersection area comes from Green's theorem: the area of the intersection polygon is
# the boundary integral (1/2) * sum(p0 x p1) over its edges, and that boundary is made of the
# parts of A's edges inside B plus the parts of B's edges inside A. The part of an edge
# p + t d, t in [0, 1], inside a box is one interval [t0, t1] found by clipping against the box's
# axis-aligned half-planes in that box's own frame (Liang-Barsky), and its term is
# (1/2) * (t1 - t0) * (p x d) about the clipping box's centre. Each B edge term about B's centre
# is (t1 - t0) * l_B * w_B / 4. No vertex list, no sorting: a fixed ~100 flops per pair.
#
# Degenerate cases (shared or collinear edges, identical boxes) follow one rule: an edge of A
# that lies on B's boundary counts when both run the same way round (their interiors are on the
# same side), an edge of B on A's boundary never counts. Relative yaws within 1e-8 rad of a
# multiple of pi/2 are snapped to it, so parallel edges are exactly parallel; "on the boundary"
# means within 1e-9 of the larger box dimension. The result agrees with Shapely to ~1e-13; the
# worst case, relative yaws just outside the snapping band (nearly parallel edges whose crossing
# is ill-conditioned), is ~1e-8 x size^2 in area (measured: IoU within 5e-8 of Shapely).

# Corner signs along (l, w), CCW seen from above starting front-left, and the edge vectors.
_CU = np.array([0.5, -0.5, -0.5, 0.5])
_CV = np.array([0.5, 0.5, -0.5, -0.5])
_EU = np.roll(_CU, -1) - _CU
_EV = np.roll(_CV, -1) - _CV
_SNAP = 1e-8
_TOL = 1e-9


def _bev_corners(boxes: np.ndarray) -> np.ndarray:
    """Counter-clockwise BEV corners ``(..., 4, 2)``."""
    c, s = np.cos(boxes[..., 6]), np.sin(boxes[..., 6])
    lx = boxes[..., 3, None] * _CU
    ly = boxes[..., 4, None] * _CV
    x = boxes[..., 0, None] + c[..., None] * lx - s[..., None] * ly
    y = boxes[..., 1, None] + s[..., None] * lx + c[..., None] * ly
    return np.stack([x, y], -1)


def _snap_rotation(c: np.ndarray, s: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Snap (cos, sin) within ``_SNAP`` of an axis-aligned rotation onto it exactly."""
    small_s = np.abs(s) < _SNAP
    small_c = np.abs(c) < _SNAP
    c2 = np.where(small_s, np.sign(c), np.where(small_c, 0.0, c))
    s2 = np.where(small_c, np.sign(s), np.where(small_s, 0.0, s))
    return c2, s2


def _edges_in_frame(
    length: np.ndarray,
    width: np.ndarray,
    cx: np.ndarray,
    cy: np.ndarray,
    c: np.ndarray,
    s: np.ndarray,
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Corners ``(px, py)`` and edge vectors ``(dx, dy)``, each ``(4, B)``, of BEV rectangles
    ``length x width`` ``(B,)`` in a reference box's frame, where their centres sit at
    ``(cx, cy)`` ``(B,)`` and ``c, s`` ``(B,)`` are cos, sin of ``yaw_other - yaw_ref``.

    The layout is ``(4, B)`` (edge, pair) so every numpy loop runs over the long axis.
    """
    lc = 0.5 * length * c
    ls = 0.5 * length * s
    wc = 0.5 * width * c
    ws = 0.5 * width * s
    n = len(length)
    px, py, dx, dy = np.empty((4, 4, n))
    # corners CCW from front-left: (+l, +w), (-l, +w), (-l, -w), (+l, -w) halves, turned by (c, s)
    front, back = cx + lc, cx - lc
    np.subtract(front, ws, out=px[0])
    np.subtract(back, ws, out=px[1])
    np.add(back, ws, out=px[2])
    np.add(front, ws, out=px[3])
    front, back = cy + ls, cy - ls
    np.add(front, wc, out=py[0])
    np.add(back, wc, out=py[1])
    np.subtract(back, wc, out=py[2])
    np.subtract(front, wc, out=py[3])
    # edge k runs from corner k to corner k + 1
    np.multiply(lc, -2.0, out=dx[0])
    np.multiply(ws, 2.0, out=dx[1])
    np.negative(dx[0], out=dx[2])
    np.negative(dx[1], out=dx[3])
    np.multiply(ls, -2.0, out=dy[0])
    np.multiply(wc, -2.0, out=dy[1])
    np.negative(dy[0], out=dy[2])
    np.negative(dy[1], out=dy[3])
    return px, py, dx, dy


def _clip_fraction(
    px: np.ndarray,
    py: np.ndarray,
    dx: np.ndarray,
    dy: np.ndarray,
    hx: np.ndarray,
    hy: np.ndarray,
    tol: np.ndarray,
    closed: bool,
) -> np.ndarray:
    """Fraction ``(4, B)`` of each edge ``p + t d`` (t in [0, 1]) inside ``|x| <= hx, |y| <= hy``
    (``hx, hy, tol`` ``(B,)``).

    An edge parallel to an axis (``d`` component exactly 0) lying on the box boundary (within
    ``tol``) counts when ``closed`` and it runs the box's CCW way, never when not ``closed``.
    """
    lo = np.zeros(px.shape)
    hi = np.ones(px.shape)
    # x: the +hx side runs +y (CCW); y: the +hy side runs -x.
    for p, d, h, other, sign in ((px, dx, hx, dy, 1.0), (py, dy, hy, dx, -1.0)):
        with np.errstate(divide="ignore", invalid="ignore"):
            inv = np.divide(1.0, d)
            ta = np.negative(h) - p
            ta *= inv
            tb = h - p
            tb *= inv
        tlo = np.minimum(ta, tb)
        thi = np.maximum(ta, tb, out=ta)
        par = d == 0.0
        if par.any():
            idx = np.nonzero(par)
            pp, oo = p[idx], other[idx]
            hh, tt = h[idx[1]], tol[idx[1]]
            keep = np.abs(pp) < hh - tt
            if closed:
                keep |= (np.abs(pp - hh) <= tt) & (sign * oo > 0)
                keep |= (np.abs(pp + hh) <= tt) & (sign * oo < 0)
            tlo[idx] = np.where(keep, -np.inf, np.inf)
            thi[idx] = np.where(keep, np.inf, -np.inf)
        np.maximum(lo, tlo, out=lo)
        np.minimum(hi, thi, out=hi)
    hi -= lo
    return np.maximum(hi, 0.0, out=hi)


def _intersection_area_bev(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Exact BEV intersection area of boxes ``(B, 7)`` and ``(B, 7)`` -> ``(B,)`` m^2."""
    at = np.ascontiguousarray(a.T)  # (7, B): contiguous columns
    bt = np.ascontiguousarray(b.T)
    dyaw = at[6] - bt[6]
    c, s = _snap_rotation(np.cos(dyaw), np.sin(dyaw))
    tol = _TOL * np.maximum(np.maximum(at[3], at[4]), np.maximum(bt[3], bt[4]))
    # A's centre in B's frame; B's centre in A's frame through the exact inverse of that
    # (snapped) transform, so both views see one and the same configuration.
    cb, sb = np.cos(bt[6]), np.sin(bt[6])
    ddx = at[0] - bt[0]
    ddy = at[1] - bt[1]
    cx = cb * ddx + sb * ddy
    cy = cb * ddy - sb * ddx
    px, py, dx, dy = _edges_in_frame(at[3], at[4], cx, cy, c, s)
    frac_a = _clip_fraction(px, py, dx, dy, 0.5 * bt[3], 0.5 * bt[4], tol, True)
    px *= dy
    py *= dx
    px -= py
    term_a = 0.5 * np.einsum("ij,ij->j", frac_a, px)
    qx, qy, ex, ey = _edges_in_frame(bt[3], bt[4], -c * cx - s * cy, s * cx - c * cy, c, -s)
    frac_b = _clip_fraction(qx, qy, ex, ey, 0.5 * at[3], 0.5 * at[4], tol, False)
    return term_a + 0.25 * bt[3] * bt[4] * frac_b.sum(0)


def _edges_term_1(
    ref: list[float],
    other: list[float],
    cx: float,
    cy: float,
    c: float,
    s: float,
    tol: float,
    closed: bool,
) -> tuple[float, float]:
    """Scalar twin of :func:`_edges_in_frame` + :func:`_clip_fraction` for one pair: sums over
    ``other``'s edges (centre at ``(cx, cy)`` in ``ref``'s frame, relative rotation ``c, s``) of
    the fraction inside ``ref`` and of fraction * (p x d)."""
    hx, hy = 0.5 * ref[3], 0.5 * ref[4]
    hl, hw = 0.5 * other[3], 0.5 * other[4]
    # Corners CCW from front-left and the edge vectors, in ref's frame.
    lc, ls, wc, ws = hl * c, hl * s, hw * c, hw * s
    corners = (
        (cx + lc - ws, cy + ls + wc),
        (cx - lc - ws, cy - ls + wc),
        (cx - lc + ws, cy - ls - wc),
        (cx + lc + ws, cy + ls - wc),
    )
    edges = ((-2 * lc, -2 * ls), (2 * ws, -2 * wc), (2 * lc, 2 * ls), (-2 * ws, 2 * wc))
    frac_sum = 0.0
    cross_sum = 0.0
    for (px, py), (dx, dy) in zip(corners, edges, strict=True):
        lo, hi = 0.0, 1.0
        if dx != 0.0:
            ta, tb = (-hx - px) / dx, (hx - px) / dx
            if ta > tb:
                ta, tb = tb, ta
            if ta > lo:
                lo = ta
            if tb < hi:
                hi = tb
        elif not (
            abs(px) < hx - tol
            or (closed and ((abs(px - hx) <= tol and dy > 0) or (abs(px + hx) <= tol and dy < 0)))
        ):
            continue
        if dy != 0.0:
            ta, tb = (-hy - py) / dy, (hy - py) / dy
            if ta > tb:
                ta, tb = tb, ta
            if ta > lo:
                lo = ta
            if tb < hi:
                hi = tb
        elif not (
            abs(py) < hy - tol
            or (closed and ((abs(py - hy) <= tol and dx < 0) or (abs(py + hy) <= tol and dx > 0)))
        ):
            continue
        if hi > lo:
            f = hi - lo
            frac_sum += f
            cross_sum += f * (px * dy - py * dx)
    return frac_sum, cross_sum


def iou_pair(pa: Sequence[float], pb: Sequence[float], vertical: bool = True) -> float:
    """:func:`iou_3d` (``vertical``) or :func:`iou_bev` of one pair of boxes given as 7 Python
    floats each -> a float: the lean path of two 1-D boxes (plain Python floats, no array
    temporaries), for callers that already hold the boxes as lists (the env's step)."""
    if not math.isfinite(sum(pa) + sum(pb)):
        return math.nan
    area_a = pa[3] * pa[4]
    area_b = pb[3] * pb[4]
    if vertical:
        za, ha, zb, hb = pa[2], pa[5], pb[2], pb[5]
        dz = min(za + 0.5 * ha, zb + 0.5 * hb) - max(za - 0.5 * ha, zb - 0.5 * hb)
        area_a *= ha
        area_b *= hb
    else:
        dz = 1.0
    # Bounding circles apart (or no vertical overlap): the IoU is 0.
    reach = 0.5 * (math.hypot(pa[3], pa[4]) + math.hypot(pb[3], pb[4]))
    if dz <= 0.0 or math.hypot(pa[0] - pb[0], pa[1] - pb[1]) > reach:
        return 0.0
    dyaw = pa[6] - pb[6]
    c, s = math.cos(dyaw), math.sin(dyaw)
    if abs(s) < _SNAP:
        c, s = math.copysign(1.0, c), 0.0
    elif abs(c) < _SNAP:
        c, s = 0.0, math.copysign(1.0, s)
    tol = _TOL * max(pa[3], pa[4], pb[3], pb[4])
    cb, sb = math.cos(pb[6]), math.sin(pb[6])
    ddx, ddy = pa[0] - pb[0], pa[1] - pb[1]
    cx, cy = cb * ddx + sb * ddy, cb * ddy - sb * ddx
    _, cross_a = _edges_term_1(pb, pa, cx, cy, c, s, tol, True)
    frac_b, _ = _edges_term_1(pa, pb, -c * cx - s * cy, s * cx - c * cy, c, -s, tol, False)
    inter = (0.5 * cross_a + 0.25 * pb[3] * pb[4] * frac_b) * dz
    union = area_a + area_b - inter
    if union != union:
        return math.nan
    return min(max(inter / union, 0.0), 1.0) if union > 0 else 0.0


_CHUNK = 1 << 13  # (4, 8192) float64 temporaries stay in L2: ~2x faster than 1 << 14


def _iou(a: np.ndarray, b: np.ndarray, vertical: bool) -> np.ndarray:
    a = np.asarray(a, dtype=np.float64)
    b = np.asarray(b, dtype=np.float64)
    if a.shape[-1] != 7 or b.shape[-1] != 7:
        raise ValueError(f"boxes must have shape (..., 7); got {a.shape} and {b.shape}")
    if a.ndim == 1 and b.ndim == 1:
        return np.float64(iou_pair(a.tolist(), b.tolist(), vertical))
    a, b = np.broadcast_arrays(a, b)
    shape = a.shape[:-1]
    a = a.reshape(-1, 7)
    b = b.reshape(-1, 7)
    out = np.empty(len(a))
    for start in range(0, len(a), _CHUNK):
        sa, sb = a[start : start + _CHUNK], b[start : start + _CHUNK]
        inter = _intersection_area_bev(sa, sb)
        area_a = sa[:, 3] * sa[:, 4]
        area_b = sb[:, 3] * sb[:, 4]
        if vertical:
            top = np.minimum(sa[:, 2] + 0.5 * sa[:, 5], sb[:, 2] + 0.5 * sb[:, 5])
            bottom = np.maximum(sa[:, 2] - 0.5 * sa[:, 5], sb[:, 2] - 0.5 * sb[:, 5])
            inter = inter * np.maximum(top - bottom, 0.0)
            area_a = area_a * sa[:, 5]
            area_b = area_b * sb[:, 5]
        union = area_a + area_b - inter
        with np.errstate(divide="ignore", invalid="ignore"):
            iou = inter / union
        out[start : start + _CHUNK] = np.where(
            union > 0, iou, np.where(np.isnan(union), np.nan, 0.0)
        )
    return np.clip(out, 0.0, 1.0).reshape(shape)


def iou_3d(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Exact oriented 3D IoU of boxes ``(..., 7)`` and ``(..., 7)`` (broadcast) -> ``(...)``.

    BEV intersection of the rotated rectangles times the overlap of ``[z - h/2, z + h/2]``.
    Exact up to rounding (agrees with Shapely to ~1e-13); boxes that only touch give 0, identical
    boxes 1; a NaN in a box gives NaN. Two 1-D boxes take a lean pure-Python path (~20 us);
    batches run vectorised (~1M pairs/s on 2 cores).
    """
    return _iou(a, b, vertical=True)


def iou_bev(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Exact bird's-eye-view IoU of the rotated rectangles of boxes ``(..., 7)`` -> ``(...)``."""
    return _iou(a, b, vertical=False)


# --------------------------------------------------------------------------- torch twins


def world_to_box_torch(points: torch.Tensor, boxes: torch.Tensor) -> torch.Tensor:
    """Torch twin of :func:`world_to_box` for xyz: points ``(..., N, 3)``, boxes ``(..., 7)``."""
    c = torch.cos(boxes[..., 6])[..., None]
    s = torch.sin(boxes[..., 6])[..., None]
    dx = points[..., 0] - boxes[..., 0:1]
    dy = points[..., 1] - boxes[..., 1:2]
    dz = points[..., 2] - boxes[..., 2:3]
    return torch.stack([c * dx + s * dy, -s * dx + c * dy, dz], dim=-1)


def box_to_world_torch(points_box_frame: torch.Tensor, boxes: torch.Tensor) -> torch.Tensor:
    """Torch twin of :func:`box_to_world` for xyz."""
    c = torch.cos(boxes[..., 6])[..., None]
    s = torch.sin(boxes[..., 6])[..., None]
    px, py = points_box_frame[..., 0], points_box_frame[..., 1]
    return torch.stack(
        [
            c * px - s * py + boxes[..., 0:1],
            s * px + c * py + boxes[..., 1:2],
            points_box_frame[..., 2] + boxes[..., 2:3],
        ],
        dim=-1,
    )


def box_corners_torch(boxes: torch.Tensor) -> torch.Tensor:
    """Torch twin of :func:`box_corners`: ``(..., 7)`` -> ``(..., 8, 3)``."""
    signs = torch.as_tensor(_CORNER_SIGNS, dtype=boxes.dtype, device=boxes.device)
    return box_to_world_torch(boxes[..., None, 3:6] * signs, boxes)
