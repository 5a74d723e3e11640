"""Bird's-eye rendering of a search region: pure numpy rasterisation (no matplotlib).

Used by ``TrackingEnv.render()`` (``render_mode="rgb_array"``).
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np

from envs.geometry import box_corners, world_to_box

__all__ = ["render_birds_eye", "render_search_region"]

BACKGROUND = (18, 18, 24)
POINT_COLOR = (200, 200, 200)
REFERENCE_COLOR, GT_COLOR, PREDICTION_COLOR = (70, 110, 255), (40, 200, 40), (230, 40, 40)


def _draw_line(img: np.ndarray, p0: np.ndarray, p1: np.ndarray, color, width: int = 1) -> None:
    """Draw the pixel segment ``p0 -> p1`` (pixel coordinates, float) on ``img`` in place."""
    n = int(max(abs(p1[0] - p0[0]), abs(p1[1] - p0[1]))) + 2
    ts = np.linspace(0.0, 1.0, n)
    xs = np.rint(p0[0] + ts * (p1[0] - p0[0])).astype(np.int64)
    ys = np.rint(p0[1] + ts * (p1[1] - p0[1])).astype(np.int64)
    h, w = img.shape[:2]
    for dx in range(-(width // 2), width - width // 2):
        for dy in range(-(width // 2), width - width // 2):
            x, y = xs + dx, ys + dy
            ok = (x >= 0) & (x < w) & (y >= 0) & (y < h)
            img[y[ok], x[ok]] = color


def render_birds_eye(
    points: np.ndarray,
    boxes: Sequence[tuple[np.ndarray, tuple[int, int, int]]],
    *,
    frame_box: np.ndarray | None,
    extent_m: float,
    size_px: int = 256,
) -> np.ndarray:
    """Render a top view ``(size_px, size_px, 3)`` uint8.

    Args:
        points: ``(N, 3+)`` points already in the frame of ``frame_box`` (the search region), m.
        boxes: ``(box (7,), rgb)`` pairs in the LiDAR frame; drawn in ``frame_box``'s frame
            (outline plus a heading tick).
        frame_box: ``(7,)`` the box whose frame the image is drawn in (``None``: LiDAR frame).
        extent_m: half width of the square view, metres.
        size_px: image side, pixels.

    The box frame's +x points up in the image, +y left (a driver's view from above).
    """
    img = np.empty((size_px, size_px, 3), dtype=np.uint8)
    img[:] = BACKGROUND
    scale = size_px / (2.0 * max(float(extent_m), 1e-3))

    def to_px(xy: np.ndarray) -> np.ndarray:
        # x forward -> up (row decreases), y left -> left (column decreases)
        col = size_px / 2.0 - xy[..., 1] * scale
        row = size_px / 2.0 - xy[..., 0] * scale
        return np.stack([col, row], axis=-1)

    pts = np.asarray(points, dtype=np.float64)
    if len(pts):
        px = np.rint(to_px(pts[:, :2])).astype(np.int64)
        ok = (px[:, 0] >= 0) & (px[:, 0] < size_px) & (px[:, 1] >= 0) & (px[:, 1] < size_px)
        img[px[ok, 1], px[ok, 0]] = POINT_COLOR
    for box, color in boxes:
        box = np.asarray(box, dtype=np.float64)
        corners = box_corners(box)[:4]  # bottom face, (4, 3)
        heading = np.array([[box[0], box[1], box[2]], [0.0, 0.0, 0.0]])
        c, s = np.cos(box[6]), np.sin(box[6])
        heading[1] = heading[0] + np.array([c, s, 0.0]) * box[3] * 0.5
        if frame_box is not None:
            corners = world_to_box(corners, frame_box)
            heading = world_to_box(heading, frame_box)
        cp = to_px(corners[:, :2])
        for i in range(4):
            _draw_line(img, cp[i], cp[(i + 1) % 4], color, width=2)
        hp = to_px(heading[:, :2])
        _draw_line(img, hp[0], hp[1], color, width=1)
    return img


def render_search_region(
    points: np.ndarray,
    ref: np.ndarray,
    gt: np.ndarray,
    pred: np.ndarray | None,
    search_enlargement: tuple[float, float],
) -> np.ndarray:
    """The env's view ``(256, 256, 3)`` uint8: the search region's points ``(N, 3)`` (in the
    frame of ``ref``, m), the reference box ``ref`` (blue), the ground truth ``gt`` (green) and
    the prediction ``pred`` (red; ``None``: none yet), boxes ``(7,)`` in the LiDAR frame, over
    the extent of the search crop ``(scale, offset_m)``."""
    boxes = [(ref, REFERENCE_COLOR), (gt, GT_COLOR)]
    if pred is not None:
        boxes.append((pred, PREDICTION_COLOR))
    scale, offset_m = search_enlargement
    half = 0.5 * scale * float(max(ref[3], ref[4])) + offset_m
    return render_birds_eye(points, boxes, frame_box=ref, extent_m=half)
