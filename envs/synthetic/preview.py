"""Pictures of a generated world: a bird's-eye and a 3D view of one frame with its boxes."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from envs.data import KittiTracking
from envs.data.kitti import read_scan, scan_path
from envs.geometry import box_corners
from envs.plotting import pyplot, save_figure

__all__ = ["frame_boxes", "save_preview"]

_COLORS = {
    "Car": "red",
    "Van": "orange",
    "Truck": "sandybrown",
    "Bus": "violet",
    "Pedestrian": "deepskyblue",
    "Cyclist": "lime",
    "Bicycle": "yellow",
    "Motorcycle": "hotpink",
}


def frame_boxes(root: str | Path, scene: str, frame: int) -> list[tuple[str, np.ndarray]]:
    """``(category, box (7,))`` of every labelled object of ``scene`` at ``frame``, read back
    through :class:`envs.data.KittiTracking` (so the picture shows what a loader sees)."""
    out = []
    for tr in KittiTracking(root, "all").tracklets:
        if tr.scene != scene:
            continue
        hit = np.flatnonzero(tr.frames == frame)
        if len(hit):
            out.append((tr.category, tr.boxes[hit[0]]))
    return out


def save_preview(
    root: str | Path,
    out_png: str | Path,
    scene: str | None = None,
    frame: int | None = None,
    *,
    bev_range: float = 25.0,
    dpi: int = 80,
) -> Path:
    """Write a PNG with a bird's-eye view (left) and a 3D view (right) of one frame.

    Args:
        root: a world directory (KITTI layout).
        out_png: output file.
        scene: scene name such as ``"0000"`` (default: the first).
        frame: frame index (default: the middle frame of the scene).
        bev_range: half-width in metres of the bird's-eye window (x from -5 to ``2 * range``).
        dpi: resolution.
    """
    plt = pyplot()

    root = Path(root)
    if scene is None:
        scene = sorted(p.name for p in (root / "velodyne").iterdir())[0]
    frames = sorted((root / "velodyne" / scene).glob("*.bin"))
    if frame is None:
        frame = len(frames) // 2
    pts = read_scan(scan_path(root, scene, frame))
    boxes = frame_boxes(root, scene, frame)

    fig = plt.figure(figsize=(13, 5.5), dpi=dpi)
    ax = fig.add_subplot(1, 2, 1)
    near = (np.abs(pts[:, 1]) < bev_range) & (pts[:, 0] > -5) & (pts[:, 0] < 2 * bev_range)
    p = pts[near]
    ax.set_facecolor("black")
    # Ground returns small and grey, everything standing on it larger and coloured by height,
    # so objects stand out at this scale.
    low = p[:, 2] < np.percentile(pts[:, 2], 40) + 0.25
    ax.scatter(p[low, 1], p[low, 0], s=0.3, c="0.45", rasterized=True, linewidths=0)
    ax.scatter(
        p[~low, 1],
        p[~low, 0],
        s=2.5,
        c=p[~low, 2],
        cmap="cool",
        vmin=-1.8,
        vmax=1.0,
        rasterized=True,
        linewidths=0,
    )
    for cat, box in boxes:
        c = box_corners(box)[:4, :2]
        loop = np.vstack([c, c[:1]])
        ax.plot(loop[:, 1], loop[:, 0], color=_COLORS.get(cat, "w"), lw=1.4)
    ax.set_xlim(bev_range, -bev_range)  # y to the left, as seen from above looking forward
    ax.set_ylim(-5, 2 * bev_range)
    ax.set_aspect("equal")
    ax.set_xlabel("y (m, left)")
    ax.set_ylabel("x (m, forward)")
    ax.set_title(
        f"scene {scene} frame {frame}: bird's-eye view ({len(pts)} points; colour: height)"
    )
    handles = [
        plt.Line2D([], [], color=col, label=cat)
        for cat, col in _COLORS.items()
        if any(b[0] == cat for b in boxes)
    ]
    ax.legend(handles=handles, loc="lower left", fontsize=7)

    ax3 = fig.add_subplot(1, 2, 2, projection="3d")
    ax3.set_facecolor("black")
    for axis in (ax3.xaxis, ax3.yaxis, ax3.zaxis):
        axis.set_pane_color((0.0, 0.0, 0.0, 1.0))
    sel = near & (pts[:, 0] > 0) & (pts[:, 0] < 35) & (np.abs(pts[:, 1]) < 15)
    q = pts[sel]
    ax3.scatter(
        q[:, 0],
        q[:, 1],
        q[:, 2],
        s=0.5,
        c=q[:, 3],
        cmap="turbo",
        vmin=-0.25,  # keep the darkest returns visible on the black background
        vmax=0.7,
        rasterized=True,
        linewidths=0,
    )
    edges = [
        (0, 1),
        (1, 2),
        (2, 3),
        (3, 0),
        (4, 5),
        (5, 6),
        (6, 7),
        (7, 4),
        (0, 4),
        (1, 5),
        (2, 6),
        (3, 7),
    ]
    for cat, box in boxes:
        if not (0 < box[0] < 35 and abs(box[1]) < 15):
            continue
        c = box_corners(box)
        for a, b in edges:
            ax3.plot(*zip(c[a], c[b], strict=True), color=_COLORS.get(cat, "w"), lw=0.9)
    ax3.set_xlim(0, 35)
    ax3.set_ylim(-15, 15)
    ax3.set_zlim(-2.5, 3)
    ax3.set_box_aspect((35, 30, 5.5))
    ax3.view_init(elev=30, azim=200)
    ax3.set_title("3D view (colour: intensity)")
    fig.tight_layout()
    return save_figure(fig, out_png, dpi)
