"""Label-driven replay: real KITTI objects (categories, sizes, trajectories) in a generated street.

Given a KITTI tracking ``label_02/`` + ``calib/`` folder, every labelled track becomes an agent
with the shape family of its category, built to its labelled size, placed exactly on its
labelled box in every labelled frame (and absent in the others). The labels written for the
replayed world are the source rows byte for byte, so frame and tracklet counts per split are the
published ones.

Limitation: the labels do not carry the ego motion, so the replayed street is static in the
sensor frame (the ego is treated as standing); buildings, trees and poles are placed clear of
every labelled footprint of the scene so they never intersect an object.
"""

from __future__ import annotations

import dataclasses
import math
from pathlib import Path

import numpy as np

from envs.data.kitti import Calibration, camera_to_lidar_boxes, read_calibration, read_labels
from envs.synthetic.calibration import KITTI_LIKE_CALIBRATION
from envs.synthetic.objects import make_object
from envs.synthetic.raycast import Parts
from envs.synthetic.scene_types import Agent, Ground, Scene
from envs.synthetic.sensor import SensorModel
from envs.synthetic.street import StaticObject, make_pole, make_tree

__all__ = ["SHAPE_OF", "build_replay_scene", "replay_scene_ids"]

# KITTI label type -> the shape family that renders it.
SHAPE_OF: dict[str, str] = {
    "Car": "Car",
    "Van": "Van",
    "Truck": "Truck",
    "Pedestrian": "Pedestrian",
    "Person_sitting": "Pedestrian",
    "Cyclist": "Cyclist",
    "Tram": "Bus",
    "Misc": "Van",
    "Bus": "Bus",
    "Bicycle": "Bicycle",
    "Motorcycle": "Motorcycle",
    "Trailer": "Truck",
}


def replay_scene_ids(labels_dir: str | Path) -> tuple[int, ...]:
    """Scene numbers with a label file in ``labels_dir/label_02``."""
    files = sorted((Path(labels_dir) / "label_02").glob("*.txt"))
    return tuple(int(p.stem) for p in files if p.stem.isdigit())


def build_replay_scene(
    labels_dir: str | Path, scene_id: int, seed: int, sensor: SensorModel
) -> tuple[Scene, list[str], Calibration, SensorModel]:
    """The replay of one labelled scene.

    Returns:
        ``(scene, rows, calib, sensor)``: the scene (world frame = LiDAR frame lifted so the
        ground is at z = 0), the source label lines (with newlines) to write unchanged, the
        scene's calibration, and the sensor with its mounting height set from the labels.
    """
    root = Path(labels_dir)
    name = f"{int(scene_id):04d}"
    label_file = root / "label_02" / f"{name}.txt"
    if not label_file.is_file():
        raise ValueError(f"no label file for scene {name} in {root / 'label_02'}")
    lines = [
        ln if ln.endswith("\n") else ln + "\n"
        for ln in label_file.read_text().splitlines()
        if ln.strip()
    ]
    rows = read_labels(label_file)
    calib_file = root / "calib" / f"{name}.txt"
    if calib_file.is_file():
        calib = read_calibration(calib_file)
    else:
        calib = KITTI_LIKE_CALIBRATION
    rng = np.random.default_rng([int(seed), int(scene_id), 5])
    objs = [r for r in rows if r.type != "DontCare" and r.track_id >= 0]
    n_frames = max((r.frame for r in rows), default=0) + 1
    n_frames = max(n_frames, 2)
    boxes = (
        camera_to_lidar_boxes(np.array([r.hwl_xyz_ry for r in objs]), calib)
        if objs
        else np.zeros((0, 7))
    )
    # Ground height (LiDAR frame) from the labelled bottoms; the sensor sits that high above it.
    bottoms = boxes[:, 2] - boxes[:, 5] / 2 if len(boxes) else np.array([-1.73])
    ground_z = float(np.median(bottoms)) if len(bottoms) else -1.73
    height = -ground_z if 0.5 < -ground_z < 3.0 else 1.73
    rsensor = dataclasses.replace(sensor, height=height, _dirs=None)

    agents: list[Agent] = []
    frames = np.array([r.frame for r in objs], dtype=np.int64)
    tids = np.array([r.track_id for r in objs], dtype=np.int64)
    for tid in np.unique(tids):
        idx = np.flatnonzero(tids == tid)
        cat = objs[idx[0]].type
        shape = SHAPE_OF.get(cat, "Van")
        size = np.median(boxes[idx, 3:6], axis=0)
        ridden = not (cat == "Bicycle")
        model = make_object(shape, size, rng, ridden=ridden)
        pose = np.zeros((n_frames, 3))
        z = np.zeros(n_frames)
        present = np.zeros(n_frames, dtype=bool)
        f = frames[idx]
        pose[f, 0:2] = boxes[idx, 0:2]
        pose[f, 2] = boxes[idx, 6]
        z[f] = boxes[idx, 2] + height
        present[f] = True
        # Gait / pedal phase from the distance travelled along the track.
        step = np.r_[0.0, np.hypot(*np.diff(boxes[idx, :2], axis=0).T)]
        dist = np.zeros(n_frames)
        dist[f] = np.cumsum(step)
        speed = np.zeros(n_frames)
        speed[f[1:]] = step[1:] / np.maximum(np.diff(f), 1) / 0.1
        stride = 1.45 * size[2] / 1.75 if shape == "Pedestrian" else 5.25
        phase = dist / stride * 2 * np.pi + rng.uniform(0, 2 * np.pi)
        amplitude = np.clip(speed / 1.1, 0.0, 1.0) if shape == "Pedestrian" else (speed > 0.2)
        agents.append(Agent(int(tid), cat, model, pose, phase, amplitude.astype(float), present, z))

    st = _street_around(boxes, rng)
    k_mag = 2 * np.pi / rng.uniform(2.0, 15.0, 3)
    k_dir = rng.uniform(0, 2 * np.pi, 3)
    ground = Ground(
        slope_x=0.0,
        slope_y=0.0,
        rough_amp=rng.uniform(0.005, 0.015, 3),
        rough_k=np.stack([k_mag * np.cos(k_dir), k_mag * np.sin(k_dir)], 1),
        rough_phase=rng.uniform(0, 2 * np.pi, 3),
        road_y=(-5.0, 5.0),
        markings_y=np.array([0.0]),
        cross_x=math.nan,
        cross_half=0.0,
    )
    scene = Scene(
        scene_id=int(scene_id),
        n_frames=n_frames,
        ground=ground,
        ego=np.zeros((n_frames, 3)),
        static_bounds=np.array(st.bounds).reshape(-1, 7),
        static_solid=np.array(st.solid, dtype=bool),
        static_refl=np.array(st.refl, dtype=np.float32),
        static_parts=Parts.concat(st.parts),
        agents=agents,
    )
    return scene, lines, calib, rsensor


class _Occupancy:
    """A bird's-eye grid of every labelled footprint of a scene (all frames), dilated, used to
    place scenery where no labelled object ever is."""

    def __init__(self, boxes: np.ndarray, cell: float = 0.5, margin: float = 1.0) -> None:
        self.cell = cell
        self.x0, self.y0 = -80.0, -60.0
        self.grid = np.zeros((int(200 / cell), int(120 / cell)), dtype=bool)
        if not len(boxes):
            return
        # Moving objects sweep the same cells frame after frame: rasterise unique poses only.
        key = np.round(boxes[:, [0, 1, 3, 4, 6]] / np.array([0.5, 0.5, 0.5, 0.5, 0.2]))
        _, first = np.unique(key, axis=0, return_index=True)
        for b in boxes[np.sort(first)]:
            half = np.hypot(b[3], b[4]) / 2 + margin
            i0, i1 = self._index(b[0] - half, b[0] + half, axis=0)
            j0, j1 = self._index(b[1] - half, b[1] + half, axis=1)
            if i1 <= i0 or j1 <= j0:
                continue
            xs = self.x0 + (np.arange(i0, i1) + 0.5) * cell
            ys = self.y0 + (np.arange(j0, j1) + 0.5) * cell
            dx = xs[:, None] - b[0]
            dy = ys[None, :] - b[1]
            c, s_ = math.cos(b[6]), math.sin(b[6])
            lx = np.abs(c * dx + s_ * dy)
            ly = np.abs(-s_ * dx + c * dy)
            self.grid[i0:i1, j0:j1] |= (lx <= b[3] / 2 + margin) & (ly <= b[4] / 2 + margin)

    def _index(self, lo: float, hi: float, axis: int) -> tuple[int, int]:
        origin = self.x0 if axis == 0 else self.y0
        n = self.grid.shape[axis]
        return (
            int(np.clip(math.floor((lo - origin) / self.cell), 0, n)),
            int(np.clip(math.ceil((hi - origin) / self.cell), 0, n)),
        )

    def free(self, x0: float, x1: float, y0: float, y1: float) -> bool:
        """No labelled footprint in the axis-aligned rectangle."""
        i0, i1 = self._index(x0, x1, 0)
        j0, j1 = self._index(min(y0, y1), max(y0, y1), 1)
        return not self.grid[i0:i1, j0:j1].any()


def _street_around(boxes: np.ndarray, rng: np.random.Generator) -> StaticObject:
    """Buildings, trees and poles clear of every labelled footprint ``boxes (N, 7)`` (LiDAR
    frame, all frames of the scene): short building blocks at the nearest free distance on each
    side of the x axis, and trees and poles wherever no labelled object ever goes."""
    st = StaticObject()
    flat = Ground(
        0.0,
        0.0,
        np.zeros(0),
        np.zeros((0, 2)),
        np.zeros(0),
        (-5.0, 5.0),
        np.zeros(0),
        math.nan,
        0.0,
    )
    occ = _Occupancy(boxes)
    fronts = np.arange(6.0, 35.0, 0.5)
    for side in (-1.0, 1.0):
        x = -60.0 + rng.uniform(-5, 5)
        while x < 90.0:
            length = rng.uniform(6.0, 16.0)
            for front in fronts + rng.uniform(0.0, 2.0):
                if occ.free(x, x + length, side * front, side * (front + 3.0)):
                    # As deep as the free space allows (3 to 14 m).
                    depth = 3.0
                    while depth < 14.0 and occ.free(
                        x, x + length, side * front, side * (front + depth + 1.0)
                    ):
                        depth += 1.0
                    hgt = rng.uniform(4.0, 16.0)
                    st.solid_box(
                        x + length / 2,
                        side * (front + depth / 2),
                        -0.5,
                        length,
                        depth,
                        hgt + 0.5,
                        0.0,
                        float(rng.uniform(0.2, 0.6)),
                    )
                    break
            x += length + (rng.uniform(0.5, 6.0) if rng.random() < 0.5 else 0.3)
    # Trees and poles: random free spots near the road.
    for _ in range(60):
        xt = rng.uniform(-30.0, 70.0)
        yt = rng.choice([-1.0, 1.0]) * rng.uniform(3.5, 20.0)
        if rng.random() < 0.5:
            r = 2.6  # crown radius upper bound
            if occ.free(xt - r, xt + r, yt - r, yt + r):
                make_tree(st, flat, float(xt), float(yt), rng)
        elif occ.free(xt - 1.2, xt + 1.2, yt - 2.2, yt + 2.2):
            make_pole(st, flat, float(xt), float(yt), rng, 1.0 if yt > 0 else -1.0)
    return st
