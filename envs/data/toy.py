"""A tiny in-memory dataset for tests and examples: one scene, one box-shaped target per
category moving along a line, plus uniform clutter and a ground grid.

:func:`make_toy_dataset` builds it (deterministic in its seed, picklable); :class:`ToyDataset`
can write itself in the KITTI tracking layout.
"""

from __future__ import annotations

import math
import os
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from envs.data.kitti import (
    Calibration,
    LabelRow,
    declare_scenes,
    lidar_to_camera_boxes,
    write_calibration,
    write_labels,
    write_scan,
)
from envs.data.tracklet import Tracklet

__all__ = ["ToyDataset", "make_toy_dataset"]


class _ToyScans:
    """Picklable scan loader of :func:`make_toy_dataset`: frame -> ``(N, 4)`` float32.

    Each frame: ``num_clutter`` uniform clutter points in a 60 m square around the origin, a flat
    ground grid, and for every target its box surface sampled with ``target_points`` points.
    Deterministic in ``(seed, frame)``.
    """

    def __init__(
        self,
        seed: int,
        boxes_per_frame: dict[int, list[np.ndarray]],
        target_points: int,
        num_clutter: int,
    ) -> None:
        self.seed = seed
        self.boxes_per_frame = boxes_per_frame
        self.target_points = target_points
        self.num_clutter = num_clutter

    def __call__(self, frame: int) -> np.ndarray:
        rng = np.random.default_rng([self.seed, frame])
        clutter = np.column_stack(
            [rng.uniform(-30, 30, (self.num_clutter, 2)), rng.uniform(-1.5, 2.5, self.num_clutter)]
        )
        parts = [clutter]
        for box in self.boxes_per_frame.get(frame, []):
            local = rng.uniform(-0.5, 0.5, (self.target_points, 3)) * box[3:6]
            face = rng.integers(0, 3, self.target_points)
            sign = np.where(rng.random(self.target_points) < 0.5, -0.5, 0.5)
            local[np.arange(self.target_points), face] = sign * box[3:6][face]
            c, s = math.cos(box[6]), math.sin(box[6])
            world = np.column_stack(
                [
                    box[0] + c * local[:, 0] - s * local[:, 1],
                    box[1] + s * local[:, 0] + c * local[:, 1],
                    box[2] + local[:, 2],
                ]
            )
            parts.append(world)
        xyz = np.concatenate(parts)
        intensity = rng.random((len(xyz), 1))
        return np.hstack([xyz, intensity]).astype(np.float32)


@dataclass
class ToyDataset:
    """What :func:`make_toy_dataset` returns: ``.tracklets``, ``.split``, ``.categories``."""

    tracklets: list[Tracklet]
    split: str = "test"
    categories: tuple[str, ...] | None = None

    def write_kitti(self, root: str | os.PathLike, scene: str = "0019") -> str:
        """Write the dataset in the KITTI tracking layout under ``root`` as scene ``scene``
        (``0019``: the test split) with a KITTI-like calibration; returns ``root``."""
        root = Path(root)
        velo_to_cam = np.array(
            [[0.0, -1.0, 0.0, 0.0], [0.0, 0.0, -1.0, -0.08], [1.0, 0.0, 0.0, -0.27]]
        )
        calib = Calibration(tr_velo_to_cam=velo_to_cam)
        write_calibration(root / "calib" / f"{scene}.txt", calib)
        rows, frames = [], set()
        for tr in self.tracklets:
            cam = lidar_to_camera_boxes(tr.boxes, calib)
            for f, box in zip(tr.frames, cam, strict=True):
                rows.append(LabelRow.from_box(int(f), tr.track_id, tr.category, box))
                frames.add(int(f))
        rows.sort(key=lambda r: (r.frame, r.track_id))
        write_labels(root / "label_02" / f"{scene}.txt", rows)
        loader = self.tracklets[0].scans
        for f in range(max(frames) + 1):
            write_scan(root / "velodyne" / scene / f"{f:06d}.bin", loader(f))
        declare_scenes(root, [scene])  # a one-scene root: its split needs only this scene
        return str(root)


_TOY_SIZES = {
    "Car": (4.0, 1.8, 1.5),
    "Van": (5.0, 2.0, 2.2),
    "Pedestrian": (0.8, 0.6, 1.75),
    "Cyclist": (1.8, 0.6, 1.7),
}


def make_toy_dataset(
    categories: Sequence[str] = ("Car", "Pedestrian", "Van", "Cyclist"),
    num_frames: int | Sequence[int] = 8,
    seed: int = 0,
    target_points: int = 300,
    num_clutter: int = 4000,
    speed_mps: float = 8.0,
) -> ToyDataset:
    """A tiny in-memory dataset: one scene, one target per category moving along a straight line
    (10 Hz; heading turning slowly), plus clutter; ``num_frames`` per tracklet (an int or one per
    category). Deterministic in ``seed``; picklable. For tests and examples."""
    rng = np.random.default_rng(seed)
    if isinstance(num_frames, int):
        num_frames = [num_frames] * len(categories)
    boxes_per_frame: dict[int, list[np.ndarray]] = {}
    specs = []
    for k, (cat, n) in enumerate(zip(categories, num_frames, strict=True)):
        l, w, h = _TOY_SIZES.get(cat, (2.0, 1.0, 1.5))
        start = np.array([rng.uniform(-15, 15), rng.uniform(-15, 15)])
        yaw0 = rng.uniform(-math.pi, math.pi)
        speed = speed_mps * (0.25 if cat == "Pedestrian" else 1.0)
        t = np.arange(n)
        yaw = yaw0 + 0.02 * t
        xy = (
            start
            + np.cumsum(np.column_stack([np.cos(yaw), np.sin(yaw)]) * speed * 0.1, axis=0)
            - np.array([math.cos(yaw0), math.sin(yaw0)]) * speed * 0.1
        )
        boxes = np.column_stack(
            [
                xy,
                np.full(n, -1.0 + h / 2),
                np.full((n, 3), (l, w, h)),
                (yaw + math.pi) % (2 * math.pi) - math.pi,
            ]
        )
        frames = np.arange(n) + k  # staggered starts
        for f, b in zip(frames, boxes, strict=True):
            boxes_per_frame.setdefault(int(f), []).append(b)
        specs.append((k, cat, frames, boxes))
    loader = _ToyScans(seed, boxes_per_frame, target_points, num_clutter)
    tracklets = [
        Tracklet(f"0000/{k}", "0000", k, cat, frames, boxes, loader)
        for k, cat, frames, boxes in specs
    ]
    return ToyDataset(tracklets, "test", tuple(categories))
