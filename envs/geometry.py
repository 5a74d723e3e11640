"""Box geometry in the LiDAR frame, vectorised over any leading dimensions.

Box convention (DESIGN.md): ``(x, y, z, l, w, h, yaw)`` with ``(x, y, z)`` the geometric centre,
``l`` along the heading, ``w`` across it, ``h`` up, ``yaw`` about +z counter-clockwise from +x,
wrapped to ``[-pi, pi)``. The box-local (canonical) frame of a box is reached by translating by
``-centre`` and rotating by ``-yaw``.

All functions take numpy arrays and broadcast their leading dimensions. A few torch twins used by
the trackers live at the end of the module (suffix ``_torch``).
"""

from __future__ import annotations

import math

import numpy as np
import torch

__all__ = [
    "apply_offset",
    "apply_offset_torch",
    "box_corners",
    "box_corners_torch",
    "box_to_world",
    "box_to_world_torch",
    "boxes_in_frame",
    "center_distance",
    "iou_3d",
    "iou_bev",
    "offset_between",
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
        [np.stack([c, -s, zeros], -1), np.stack([s, c, zeros], -1), np.stack([zeros, zeros, ones], -1)],
        -2,
    )


def box_corners(boxes: np.ndarray) -> np.ndarray:
    """Corners of boxes ``(..., 7)`` -> ``(..., 8, 3)``; order as ``_CORNER_SIGNS``."""
    boxes = np.asarray(boxes, dtype=np.float64)
    local = boxes[..., None, 3:6] * _CORNER_SIGNS
    return box_to_world(local, boxes)


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
        [c * px - s * py + boxes[..., 0:1], s * px + c * py + boxes[..., 1:2], points[..., 2] + boxes[..., 2:3]],
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
    (the search region of DESIGN.md is ``scale=1.25, offset_m=2.0``). Boundary points count as in.
    """
    boxes = np.asarray(boxes, dtype=np.float64)
    local = world_to_box(np.asarray(points)[..., :3], boxes)
    half = boxes[..., None, 3:6] * (0.5 * scale) + offset_m
    return np.all(np.abs(local) <= half, axis=-1)


def apply_offset(ref_boxes: np.ndarray, offsets: np.ndarray) -> np.ndarray:
    """Move reference boxes ``(..., 7)`` by offsets ``(..., 4)`` = ``(dx, dy, dz, dyaw)``.

    The translation is in the reference box's frame: new centre = centre + R(yaw) @ (dx, dy, dz),
    new yaw = wrap(yaw + dyaw); the size is unchanged (the action convention of DESIGN.md).
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
        [c * dx + s * dy, -s * dx + c * dy, tgt[..., 2] - ref[..., 2], wrap_yaw(tgt[..., 6] - ref[..., 6])],
        axis=-1,
    )


def boxes_in_frame(boxes: np.ndarray, frame_boxes: np.ndarray) -> np.ndarray:
    """Express boxes ``(..., 7)`` in the box-local frame of ``frame_boxes`` ``(..., 7)``."""
    boxes = np.asarray(boxes, dtype=np.float64)
    off = offset_between(frame_boxes, boxes)
    out = np.broadcast_to(boxes, off.shape[:-1] + (7,)).copy()
    out[..., 0:3] = off[..., 0:3]
    out[..., 6] = off[..., 3]
    return out


def center_distance(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Euclidean distance in metres between box centres, ``(..., 7)`` x ``(..., 7)`` -> ``(...)``."""
    a = np.asarray(a, dtype=np.float64)
    b = np.asarray(b, dtype=np.float64)
    return np.linalg.norm(a[..., :3] - b[..., :3], axis=-1)


# --------------------------------------------------------------------------- oriented IoU


def _bev_corners(boxes: np.ndarray) -> np.ndarray:
    """Counter-clockwise BEV corners ``(..., 4, 2)``."""
    c, s = np.cos(boxes[..., 6]), np.sin(boxes[..., 6])
    hl, hw = boxes[..., 3] * 0.5, boxes[..., 4] * 0.5
    lx = np.stack([hl, -hl, -hl, hl], -1)
    ly = np.stack([hw, hw, -hw, -hw], -1)
    x = boxes[..., 0, None] + c[..., None] * lx - s[..., None] * ly
    y = boxes[..., 1, None] + s[..., None] * lx + c[..., None] * ly
    return np.stack([x, y], -1)


def _inside(poly: np.ndarray, pts: np.ndarray, tol: np.ndarray) -> np.ndarray:
    """Points ``(B, P, 2)`` inside CCW convex quads ``(B, 4, 2)`` (boundary included) -> ``(B, P)``."""
    edge = np.roll(poly, -1, axis=1) - poly  # (B, 4, 2)
    rel = pts[:, None, :, :] - poly[:, :, None, :]  # (B, 4, P, 2)
    cross = edge[:, :, None, 0] * rel[..., 1] - edge[:, :, None, 1] * rel[..., 0]
    return np.all(cross >= -tol[:, None, None], axis=1)


def _intersection_area_bev(ca: np.ndarray, cb: np.ndarray, scale: np.ndarray) -> np.ndarray:
    """Exact area of the intersection of CCW convex quads ``(B, 4, 2)`` and ``(B, 4, 2)``.

    The intersection polygon's vertices are the corners of each quad inside the other plus the
    edge-edge crossings; they are ordered by angle about their mean and summed by the shoelace
    formula. ``scale`` ``(B,)`` sets the tolerances.
    """
    tol = 1e-9 * scale * scale
    in_a = _inside(ca, cb, tol)  # corners of b inside a
    in_b = _inside(cb, ca, tol)
    p = ca[:, :, None, :]
    r = (np.roll(ca, -1, axis=1) - ca)[:, :, None, :]
    q = cb[:, None, :, :]
    s = (np.roll(cb, -1, axis=1) - cb)[:, None, :, :]
    rxs = r[..., 0] * s[..., 1] - r[..., 1] * s[..., 0]  # (B, 4, 4)
    qp = q - p
    qpxs = qp[..., 0] * s[..., 1] - qp[..., 1] * s[..., 0]
    qpxr = qp[..., 0] * r[..., 1] - qp[..., 1] * r[..., 0]
    parallel = np.abs(rxs) <= 1e-12 * scale[:, None, None] ** 2
    denom = np.where(parallel, 1.0, rxs)
    t = qpxs / denom
    u = qpxr / denom
    ok = ~parallel & (t >= -1e-12) & (t <= 1 + 1e-12) & (u >= -1e-12) & (u <= 1 + 1e-12)
    cross_pts = (p + t[..., None] * r).reshape(len(ca), 16, 2)
    pts = np.concatenate([ca, cb, cross_pts], axis=1)  # (B, 24, 2)
    valid = np.concatenate([in_b, in_a, ok.reshape(len(ca), 16)], axis=1)
    count = valid.sum(axis=1)
    centre = (pts * valid[..., None]).sum(axis=1) / np.maximum(count, 1)[:, None]
    rel = pts - centre[:, None, :]
    ang = np.arctan2(rel[..., 1], rel[..., 0])
    ang = np.where(valid, ang, np.inf)
    order = np.argsort(ang, axis=1)
    rel = np.take_along_axis(rel, order[..., None], axis=1)
    valid_sorted = np.take_along_axis(valid, order, axis=1)
    # Invalid slots repeat the first vertex: they add zero-area edges and close the polygon.
    rel = np.where(valid_sorted[..., None], rel, rel[:, :1, :])
    nxt = np.roll(rel, -1, axis=1)
    area = 0.5 * np.abs((rel[..., 0] * nxt[..., 1] - rel[..., 1] * nxt[..., 0]).sum(axis=1))
    return np.where(count >= 3, area, 0.0)


def _clip_convex(subject: list[tuple[float, float]], clip: list[tuple[float, float]]) -> list:
    """Sutherland-Hodgman clipping of a convex polygon by a CCW convex polygon (scalar path)."""
    out = subject
    for i in range(len(clip)):
        if not out:
            break
        (x1, y1), (x2, y2) = clip[i], clip[(i + 1) % len(clip)]
        ex, ey = x2 - x1, y2 - y1
        inp, out = out, []
        prev = inp[-1]
        prev_side = ex * (prev[1] - y1) - ey * (prev[0] - x1)
        for cur in inp:
            cur_side = ex * (cur[1] - y1) - ey * (cur[0] - x1)
            if cur_side >= 0:
                if prev_side < 0:
                    t = prev_side / (prev_side - cur_side)
                    out.append((prev[0] + t * (cur[0] - prev[0]), prev[1] + t * (cur[1] - prev[1])))
                out.append(cur)
            elif prev_side >= 0:
                t = prev_side / (prev_side - cur_side)
                out.append((prev[0] + t * (cur[0] - prev[0]), prev[1] + t * (cur[1] - prev[1])))
            prev, prev_side = cur, cur_side
    return out


def _quad(box: np.ndarray) -> list[tuple[float, float]]:
    x, y, _, l, w, _, yaw = (float(v) for v in box)
    c, s = math.cos(yaw), math.sin(yaw)
    hl, hw = 0.5 * l, 0.5 * w
    return [(x + c * a - s * b, y + s * a + c * b) for a, b in ((hl, hw), (-hl, hw), (-hl, -hw), (hl, -hw))]


def _iou_single(a: np.ndarray, b: np.ndarray, vertical: bool) -> float:
    """Lean path for one pair: plain Python floats, no array temporaries."""
    poly = _clip_convex(_quad(a), _quad(b))
    inter = 0.0
    for i in range(len(poly)):
        x1, y1 = poly[i]
        x2, y2 = poly[(i + 1) % len(poly)]
        inter += x1 * y2 - x2 * y1
    inter = abs(inter) * 0.5
    area_a = float(a[3]) * float(a[4])
    area_b = float(b[3]) * float(b[4])
    if vertical:
        za, ha, zb, hb = float(a[2]), float(a[5]), float(b[2]), float(b[5])
        dz = min(za + 0.5 * ha, zb + 0.5 * hb) - max(za - 0.5 * ha, zb - 0.5 * hb)
        inter *= max(dz, 0.0)
        area_a *= ha
        area_b *= hb
    union = area_a + area_b - inter
    return min(max(inter / union, 0.0), 1.0) if union > 0 else 0.0


_CHUNK = 1 << 16


def _iou(a: np.ndarray, b: np.ndarray, vertical: bool) -> np.ndarray:
    a = np.asarray(a, dtype=np.float64)
    b = np.asarray(b, dtype=np.float64)
    if a.shape[-1] != 7 or b.shape[-1] != 7:
        raise ValueError(f"boxes must have shape (..., 7); got {a.shape} and {b.shape}")
    if a.ndim == 1 and b.ndim == 1:
        return np.float64(_iou_single(a, b, vertical))
    a, b = np.broadcast_arrays(a, b)
    shape = a.shape[:-1]
    a = a.reshape(-1, 7)
    b = b.reshape(-1, 7)
    out = np.empty(len(a))
    for start in range(0, len(a), _CHUNK):
        sa, sb = a[start : start + _CHUNK], b[start : start + _CHUNK]
        scale = np.maximum(np.abs(sa[:, 3:5]).max(1), np.abs(sb[:, 3:5]).max(1)) + 1e-12
        inter = _intersection_area_bev(_bev_corners(sa), _bev_corners(sb), scale)
        area_a = sa[:, 3] * sa[:, 4]
        area_b = sb[:, 3] * sb[:, 4]
        if vertical:
            top = np.minimum(sa[:, 2] + 0.5 * sa[:, 5], sb[:, 2] + 0.5 * sb[:, 5])
            bottom = np.maximum(sa[:, 2] - 0.5 * sa[:, 5], sb[:, 2] - 0.5 * sb[:, 5])
            inter = inter * np.clip(top - bottom, 0.0, None)
            area_a = area_a * sa[:, 5]
            area_b = area_b * sb[:, 5]
        union = area_a + area_b - inter
        out[start : start + _CHUNK] = np.where(union > 0, inter / np.where(union > 0, union, 1.0), 0.0)
    return np.clip(out, 0.0, 1.0).reshape(shape)


def iou_3d(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Exact oriented 3D IoU of boxes ``(..., 7)`` and ``(..., 7)`` (broadcast) -> ``(...)``.

    BEV intersection of the rotated rectangles times the overlap of ``[z - h/2, z + h/2]``.
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
        [c * px - s * py + boxes[..., 0:1], s * px + c * py + boxes[..., 1:2], points_box_frame[..., 2] + boxes[..., 2:3]],
        dim=-1,
    )


def box_corners_torch(boxes: torch.Tensor) -> torch.Tensor:
    """Torch twin of :func:`box_corners`: ``(..., 7)`` -> ``(..., 8, 3)``."""
    signs = torch.as_tensor(_CORNER_SIGNS, dtype=boxes.dtype, device=boxes.device)
    return box_to_world_torch(boxes[..., None, 3:6] * signs, boxes)


def apply_offset_torch(ref_boxes: torch.Tensor, offsets: torch.Tensor) -> torch.Tensor:
    """Torch twin of :func:`apply_offset`: ``(..., 7)``, ``(..., 4)`` -> ``(..., 7)``."""
    c, s = torch.cos(ref_boxes[..., 6]), torch.sin(ref_boxes[..., 6])
    x = ref_boxes[..., 0] + c * offsets[..., 0] - s * offsets[..., 1]
    y = ref_boxes[..., 1] + s * offsets[..., 0] + c * offsets[..., 1]
    z = ref_boxes[..., 2] + offsets[..., 2]
    yaw = torch.remainder(ref_boxes[..., 6] + offsets[..., 3] + math.pi, 2 * math.pi) - math.pi
    return torch.cat([torch.stack([x, y, z], -1), ref_boxes[..., 3:6], yaw[..., None]], -1)
