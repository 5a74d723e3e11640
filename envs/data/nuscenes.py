"""The nuScenes v1.0 layout: a native reader of the JSON tables (no devkit), the category
mapping, the official split lists, and the LIDAR_TOP scan loader.

Layout under ``root`` (the nuScenes ``dataroot``, or a synthetic world written by
:mod:`envs.synthetic.nuscenes_layout`)::

    <version>/scene.json, sample.json, sample_data.json, sample_annotation.json, instance.json,
              category.json, ego_pose.json, calibrated_sensor.json, sensor.json, log.json
    samples/LIDAR_TOP/*.pcd.bin   float32 (x, y, z, intensity 0-255, ring index) per point

Frames. An annotation's box is given in the global frame: ``translation`` (box centre, metres),
``size`` = ``(w, l, h)`` (nuScenes order: width first), ``rotation`` a unit quaternion
``(w, x, y, z)``. The key frame's ``LIDAR_TOP`` sample_data names an ``ego_pose`` (vehicle body
-> global) and a ``calibrated_sensor`` (sensor -> vehicle body). A global point ``p`` maps to the
LiDAR frame by ``R_cs^T (R_ego^T (p - t_ego) - t_cs)`` — the transform of the devkit's
``get_sample_data``. A box's orientation maps the same way (``R = R_cs^T R_ego^T R_box``); its
``yaw`` is the angle of the box heading ``R[:, 0]`` about LiDAR +z, ``atan2(R[1, 0], R[0, 0])``
(= pyquaternion's ``yaw_pitch_roll[0]``), wrapped to ``[-pi, pi)``. Boxes come out as
``(x, y, z, l, w, h, yaw)`` like the KITTI loader's. Real nuScenes LiDAR frames have x to the
right and y forward (the KITTI one: x forward); nothing downstream depends on the axis names.

Which LiDAR frame (``frame``, :data:`NUSCENES_FRAMES`): ``"lidar"`` (the default) serves each key
frame's scan and boxes in that key frame's own LiDAR frame, as the devkit does, so the ego's
motion between the 2 Hz key frames moves every target; ``"scene"`` serves all key frames of a
scene in the LiDAR frame of its first key frame (ego motion removed, the sensor of frame 0 at
the origin): up to one rigid map per scene, the global frame Open3DSOT's nuScenes loader tracks
in. Range-dependent scan transforms (the weather) assume the sensor at the origin and are
refused on ``"scene"`` data (``TrackingEnv``).

Tracklets. One per annotated instance of a wanted category in the scenes of the split, over the
instance's key frames in time order; ``frames`` are the key-frame (sample) indices in the scene,
so an instance missing from some samples keeps one tracklet with a gap, as in the KITTI loader.
"""

from __future__ import annotations

import gc
import json
from collections.abc import Iterator, Sequence
from contextlib import contextmanager
from functools import cache, cached_property
from pathlib import Path

import numpy as np

from envs.data.kitti import finite_rows
from envs.data.nuscenes_poses import (
    global_to_lidar_boxes,
    lidar_to_reference,
    quaternion_to_matrix,
)
from envs.data.tracklet import ScanCache, Tracklet, check_categories
from envs.geometry import map_points

__all__ = [
    "CATEGORY_MAP",
    "LIDAR_CHANNEL",
    "NUSCENES_CATEGORIES",
    "NUSCENES_FRAMES",
    "check_frame",
    "POINT_FIELDS",
    "TABLES",
    "SOT_SPLITS",
    "NuScenesScans",
    "NuScenesTracking",
    "quaternion_to_matrix",
    "read_pcd_bin",
    "split_scenes",
]

# The tables the reader needs, in the order it loads them.
TABLES: tuple[str, ...] = (
    "category",
    "instance",
    "sensor",
    "calibrated_sensor",
    "ego_pose",
    "log",
    "scene",
    "sample",
    "sample_data",
    "sample_annotation",
)

LIDAR_CHANNEL = "LIDAR_TOP"
NUSCENES_FRAMES: tuple[str, ...] = ("lidar", "scene")
"""The frames :class:`NuScenesTracking` serves scans and boxes in (module docstring)."""


def check_frame(frame: str, dataset: str = "nuscenes") -> None:
    """Refuse a ``frame`` not in :data:`NUSCENES_FRAMES`, or one other than ``"lidar"`` for a
    ``dataset`` that is not nuScenes (only nuScenes data has a scene frame)."""
    if frame not in NUSCENES_FRAMES:
        raise ValueError(f"nuScenes frame {frame!r} is not one of {list(NUSCENES_FRAMES)}")
    if frame != "lidar" and dataset != "nuscenes":
        raise ValueError(
            f"nuscenes_frame={frame!r} applies to dataset nuscenes only, not {dataset!r}"
        )


POINT_FIELDS = 5  # x, y, z, intensity, ring index (float32 each)

# nuScenes category -> the project's category names (those of envs.data.settings). This is the
# nuScenes tracking-challenge mapping (``category_to_tracking_name`` of the nuScenes devkit,
# nuscenes/eval/tracking/utils.py), spelt like the KITTI names; every other category (animals,
# strollers, wheelchairs, personal mobility, emergency and construction vehicles, movable and
# static objects) is not a tracking class and is never loaded.
CATEGORY_MAP: dict[str, str] = {
    "vehicle.bicycle": "Bicycle",
    "vehicle.bus.bendy": "Bus",
    "vehicle.bus.rigid": "Bus",
    "vehicle.car": "Car",
    "vehicle.motorcycle": "Motorcycle",
    "human.pedestrian.adult": "Pedestrian",
    "human.pedestrian.child": "Pedestrian",
    "human.pedestrian.construction_worker": "Pedestrian",
    "human.pedestrian.police_officer": "Pedestrian",
    "vehicle.trailer": "Trailer",
    "vehicle.truck": "Truck",
}
NUSCENES_CATEGORIES: tuple[str, ...] = tuple(sorted(set(CATEGORY_MAP.values())))

# The project's split roles (train / val / test, as for KITTI: what the CLI's ``--split`` and
# the training code name) -> official nuScenes splits. Open3DSOT trains on ``train_track`` and
# tests on the labelled ``val``; model selection uses the other half of the official train
# scenes, ``train_detect``, so that the test split is never used to choose a model.
SOT_SPLITS: dict[str, str] = {
    "train": "train_track",
    "val": "train_detect",
    "test": "val",
    "all": "all",
}

_SPLITS_FILE = Path(__file__).with_name("nuscenes_splits.json")


@cache
def _official_splits() -> dict[str, tuple[str, ...]]:
    data = json.loads(_SPLITS_FILE.read_text())
    return {k: tuple(v) for k, v in data.items() if not k.startswith("_")}


def split_scenes(split: str) -> tuple[str, ...] | None:
    """Scene names of an official nuScenes split (``None`` for ``"all"``).

    Splits: ``train`` (700 scenes), ``val`` (150, the labelled split SOT papers test on),
    ``test`` (150, unlabelled), ``mini_train``, ``mini_val``, ``train_detect``, ``train_track``
    — transcribed from the nuScenes devkit's ``splits.py`` into ``nuscenes_splits.json``.
    Raises ``ValueError`` listing the valid names for an unknown one.
    """
    splits = _official_splits()
    if split == "all":
        return None
    if split not in splits:
        raise ValueError(
            f"unknown nuScenes split {split!r}; valid splits: {', '.join(splits)}, all"
        )
    return splits[split]


# --------------------------------------------------------------------------- scans


def read_pcd_bin(path: str | Path) -> np.ndarray:
    """Read a nuScenes ``.pcd.bin`` -> ``(N, 4)`` float32 (x, y, z metres, intensity in [0, 1]).

    The file holds 5 little-endian float32 per point (x, y, z, intensity 0-255, ring index);
    intensity is divided by 255 so it matches the KITTI scans' [0, 1]. Non-finite points are
    dropped with a :class:`~envs.data.kitti.NonFinitePointsWarning` naming the file and count.
    A missing file raises ``FileNotFoundError``, a size that is not a multiple of 20 bytes (a
    truncated file) ``ValueError``, both naming the file.
    """
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"nuScenes scan file {path} not found")
    size = path.stat().st_size
    if size % (4 * POINT_FIELDS):
        raise ValueError(
            f"nuScenes scan file {path}: size {size} bytes is not a multiple of "
            f"{4 * POINT_FIELDS} (5 float32 per point: x, y, z, intensity, ring); truncated?"
        )
    raw = np.fromfile(path, dtype="<f4").reshape(-1, POINT_FIELDS)
    points = raw[:, :4].astype(np.float32)
    points[:, 3] *= np.float32(1.0 / 255.0)
    return finite_rows(points, f"nuScenes scan file {path}")[0]


class NuScenesScans:
    """Picklable scan loader of one scene: key-frame index -> ``(N, 4)`` float32 scan.

    Args:
        root: the dataroot.
        scene: scene name (quoted in errors).
        filenames: the ``LIDAR_TOP`` sample_data filename of each key frame, relative to root.
        to_reference: ``None`` (each scan in its own LiDAR frame) or ``(T, 3, 4)`` maps
            ``[R | t]`` of the key frames into one reference frame
            (:func:`~envs.data.nuscenes_poses.lidar_to_reference`), applied in float64.
    """

    def __init__(
        self,
        root: str | Path,
        scene: str,
        filenames: Sequence[str],
        to_reference: np.ndarray | None = None,
    ) -> None:
        self.root = Path(root)
        self.scene = scene
        self.filenames = tuple(filenames)
        if to_reference is not None and np.shape(to_reference) != (len(self.filenames), 3, 4):
            raise ValueError(
                f"nuScenes scene {scene}: to_reference has shape {np.shape(to_reference)}, "
                f"expected ({len(self.filenames)}, 3, 4)"
            )
        self.to_reference = to_reference

    def __call__(self, frame: int) -> np.ndarray:
        if not 0 <= int(frame) < len(self.filenames):
            raise IndexError(
                f"nuScenes scene {self.scene}: key frame {int(frame)} out of range "
                f"(0..{len(self.filenames) - 1})"
            )
        path = self.root / self.filenames[int(frame)]
        try:
            points = read_pcd_bin(path)
        except (FileNotFoundError, ValueError) as exc:
            raise type(exc)(f"nuScenes scene {self.scene} key frame {int(frame)}: {exc}") from None
        if self.to_reference is not None:
            points = map_points(points, self.to_reference[int(frame)])
        return points

    def __repr__(self) -> str:
        return f"NuScenesScans({str(self.root)!r}, {self.scene!r}, {len(self.filenames)} frames)"


# --------------------------------------------------------------------------- tables


@contextmanager
def _gc_paused() -> Iterator[None]:
    """Pause the cyclic garbage collector: parsing millions of JSON records (which form no
    cycles) would otherwise trigger repeated full collections over all of them."""
    enabled = gc.isenabled()
    gc.disable()
    try:
        yield
    finally:
        if enabled:
            gc.enable()


def _load_table(table_dir: Path, name: str) -> list[dict]:
    path = table_dir / f"{name}.json"
    if not path.is_file():
        raise FileNotFoundError(f"nuScenes table {path} is missing")
    try:
        data = json.loads(path.read_text())
    except (OSError, ValueError) as exc:
        raise ValueError(f"nuScenes table {path} cannot be read as JSON: {exc}") from exc
    if not isinstance(data, list):
        raise ValueError(f"nuScenes table {path}: expected a JSON list of records")
    return data


class _Table:
    """A loaded table with its token index (built once, on first use: the reader never looks
    up sample_data or sample_annotation records by token, the two largest tables)."""

    def __init__(self, table_dir: Path, name: str) -> None:
        self.name = name
        self.path = table_dir / f"{name}.json"
        self.records = _load_table(table_dir, name)

    @cached_property
    def index(self) -> dict[str, int]:
        try:
            return {r["token"]: i for i, r in enumerate(self.records)}
        except (KeyError, TypeError):
            raise ValueError(f"nuScenes table {self.path}: a record has no 'token'") from None

    def find(self, token: str, referrer: str) -> int:
        """Index of ``token``; a dangling token raises ``KeyError`` naming both records."""
        i = self.index.get(token)
        if i is None:
            raise KeyError(
                f"nuScenes: {referrer} refers to {self.name} token {token!r}, "
                f"which is not in {self.path}"
            )
        return i

    def column(self, key: str, rows: Sequence[int] | None = None) -> list:
        records = self.records if rows is None else [self.records[i] for i in rows]
        try:
            return [r[key] for r in records]
        except KeyError:
            raise ValueError(f"nuScenes table {self.path}: a record lacks field {key!r}") from None


def _check_quaternions(q: np.ndarray, table: _Table, rows: np.ndarray) -> None:
    norm = np.linalg.norm(q, axis=-1)
    bad = ~(np.isfinite(norm) & (norm > 1e-9))
    if bad.any():
        token = table.records[int(rows[np.flatnonzero(bad)[0]])]["token"]
        raise ValueError(
            f"nuScenes table {table.path}: record {token!r} has a zero or "
            "non-finite rotation quaternion"
        )


def _floats(table: _Table, key: str, idx: np.ndarray, width: int) -> np.ndarray:
    """``(len(idx), width)`` float64 of field ``key`` of records ``idx``; a record whose field is
    not ``width`` finite numbers raises naming it."""
    values = table.column(key, idx)
    try:
        arr = np.array(values, dtype=np.float64)
    except (TypeError, ValueError):
        arr = None
    if arr is not None and arr.shape == (len(idx), width) and np.isfinite(arr).all():
        return arr
    for i, v in zip(idx, values, strict=True):  # slow path: name the bad record
        try:
            ok = np.shape(v) == (width,) and bool(np.isfinite(np.array(v, float)).all())
        except (TypeError, ValueError):
            ok = False
        if not ok:
            raise ValueError(
                f"nuScenes table {table.path}: record {table.records[int(i)]['token']!r} "
                f"field {key!r} must be {width} finite numbers, got {v!r}"
            )
    raise AssertionError("unreachable")  # pragma: no cover


def _poses(
    t: dict[str, _Table], sd_rows: np.ndarray
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """The ego pose ``(t, q)`` and sensor calibration ``(t, q)`` of each sample_data row, each
    pose record converted once: ``(N, 3)``, ``(N, 4)``, ``(N, 3)``, ``(N, 4)``."""
    sd = t["sample_data"]

    def record_rows(table: str, key: str) -> np.ndarray:
        return np.array(
            [
                t[table].find(
                    sd.records[int(j)][key], f"sample_data {sd.records[int(j)]['token']!r}"
                )
                for j in sd_rows
            ],
            np.int64,
        )

    ego_u, ego_inv = np.unique(record_rows("ego_pose", "ego_pose_token"), return_inverse=True)
    cs_u, cs_inv = np.unique(
        record_rows("calibrated_sensor", "calibrated_sensor_token"), return_inverse=True
    )
    ego_t = _floats(t["ego_pose"], "translation", ego_u, 3)
    ego_q = _floats(t["ego_pose"], "rotation", ego_u, 4)
    cs_t = _floats(t["calibrated_sensor"], "translation", cs_u, 3)
    cs_q = _floats(t["calibrated_sensor"], "rotation", cs_u, 4)
    _check_quaternions(ego_q, t["ego_pose"], ego_u)
    _check_quaternions(cs_q, t["calibrated_sensor"], cs_u)
    return ego_t[ego_inv], ego_q[ego_inv], cs_t[cs_inv], cs_q[cs_inv]


class NuScenesTracking:
    """Tracklets of the nuScenes v1.0 layout (real or synthetic), read without the devkit.

    Construction reads the tables only (each indexed by token once; the pose maths of all
    annotations is one vectorised pass); scans are read lazily through one shared
    :class:`~envs.data.tracklet.ScanCache` per scene.

    Args:
        root: the dataroot (holding ``<version>/`` and ``samples/``).
        version: the table folder, e.g. ``"v1.0-trainval"`` or ``"v1.0-mini"``.
        split: an official split (see :func:`split_scenes`) or ``"all"``. ``"val"`` is the
            labelled split the SOT literature tests on (as Open3DSOT does).
        categories: project category names (see :data:`CATEGORY_MAP`), one name, or ``None`` for
            every mapped category.
        cache_size: scans kept per scene.
        frame: ``"lidar"`` (each key frame's own LiDAR frame) or ``"scene"`` (the LiDAR frame of
            the scene's first key frame: ego motion removed); see the module docstring.

    Attributes:
        tracklets: ordered by scene (split order), then instance (by first key frame, then
            instance table order); ``track_id`` numbers them within the scene.
        instance_tokens: the nuScenes instance token of each tracklet.
        annotation_tokens: per tracklet, the sample_annotation token of each frame.
        scenes: scene names read; root, version, split, categories, frame.

    Raises:
        FileNotFoundError: a missing version folder (the message lists those found) or table.
        KeyError: a dangling token (names the referring record and the table).
        ValueError: an unknown split, category or frame (lists the valid ones), or a split naming
            none of the version's scenes.
    """

    def __init__(
        self,
        root: str | Path,
        version: str = "v1.0-trainval",
        split: str = "val",
        categories: str | Sequence[str] | None = None,
        *,
        cache_size: int = 8,
        frame: str = "lidar",
    ) -> None:
        check_frame(frame)
        self.root = Path(root)
        self.version = version
        self.split = split
        self.frame = frame
        self.categories = check_categories(categories, NUSCENES_CATEGORIES, "nuScenes")
        wanted_scenes = split_scenes(split)
        table_dir = self.root / version
        if not table_dir.is_dir():
            found = sorted(p.name for p in self.root.glob("v1.0-*") if p.is_dir())
            raise FileNotFoundError(
                f"nuScenes root {self.root}: no version folder {table_dir}; "
                f"found: {', '.join(found) if found else 'none'}"
            )
        with _gc_paused():
            t = {name: _Table(table_dir, name) for name in TABLES}
        self.tracklets: list[Tracklet] = []
        self.instance_tokens: list[str] = []
        self.annotation_tokens: list[tuple[str, ...]] = []

        scene_names = t["scene"].column("name")
        if wanted_scenes is None:
            scene_rows = list(range(len(scene_names)))
        else:
            by_name = {n: i for i, n in enumerate(scene_names)}
            scene_rows = [by_name[n] for n in wanted_scenes if n in by_name]
            if not scene_rows:
                raise ValueError(
                    f"nuScenes split {split!r} names none of the {len(scene_names)} scenes in "
                    f"{t['scene'].path}"
                )
        self.scenes: list[str] = [scene_names[i] for i in scene_rows]

        # Key frames of each scene, in time order along the sample chain.
        sample_frame = np.full(len(t["sample"].records), -1, np.int64)
        sample_scene = np.full(len(t["sample"].records), -1, np.int64)
        scene_samples: list[list[int]] = []
        for k, row in enumerate(scene_rows):
            rec = t["scene"].records[row]
            chain: list[int] = []
            token = rec.get("first_sample_token", "")
            referrer = f"scene {rec['name']!r} (first_sample_token)"
            while token:
                i = t["sample"].find(token, referrer)
                if sample_scene[i] >= 0:
                    raise ValueError(
                        f"nuScenes: sample {token!r} is reached twice "
                        f"(scene {rec['name']!r}); the sample chain loops"
                    )
                sample_frame[i], sample_scene[i] = len(chain), k
                chain.append(i)
                referrer = f"sample {token!r} (next)"
                token = t["sample"].records[i].get("next", "")
            scene_samples.append(chain)
            t["log"].find(rec.get("log_token", ""), f"scene {rec['name']!r}")

        lidar_sd = self._lidar_key_frames(t, sample_scene >= 0)

        # Annotations of the selected scenes and wanted categories, all at once.
        cat_names = t["category"].column("name")
        inst_cat = np.array(
            [
                t["category"].find(tok, f"instance {inst['token']!r}")
                for inst, tok in zip(
                    t["instance"].records, t["instance"].column("category_token"), strict=True
                )
            ],
            np.int64,
        )
        mapped = [CATEGORY_MAP.get(n) for n in cat_names]
        wanted = set(self.categories) if self.categories is not None else set(NUSCENES_CATEGORIES)
        cat_keep = np.array([m is not None and m in wanted for m in mapped], bool)
        anns = t["sample_annotation"]
        ann_sample = np.array(
            [t["sample"].index.get(s, -1) for s in anns.column("sample_token")], np.int64
        )
        if (ann_sample < 0).any():
            k = int(np.flatnonzero(ann_sample < 0)[0])
            t["sample"].find(
                anns.records[k]["sample_token"], f"sample_annotation {anns.records[k]['token']!r}"
            )
        ann_inst = np.array(
            [t["instance"].index.get(s, -1) for s in anns.column("instance_token")], np.int64
        )
        if (ann_inst < 0).any():
            k = int(np.flatnonzero(ann_inst < 0)[0])
            t["instance"].find(
                anns.records[k]["instance_token"], f"sample_annotation {anns.records[k]['token']!r}"
            )
        keep = (sample_scene[ann_sample] >= 0) & cat_keep[inst_cat[ann_inst]]
        rows = np.flatnonzero(keep)
        if len(rows) == 0:
            return
        scene_of = sample_scene[ann_sample[rows]]
        frame_of = sample_frame[ann_sample[rows]]
        inst_of = ann_inst[rows]
        # Order: scene, then instance by its first key frame (then instance row), then time.
        first = np.full(len(t["instance"].records), np.iinfo(np.int64).max)
        np.minimum.at(first, inst_of, frame_of)
        order = np.lexsort((frame_of, inst_of, first[inst_of], scene_of))
        rows, scene_of = rows[order], scene_of[order]
        frame_of, inst_of = frame_of[order], inst_of[order]
        same = inst_of[1:] == inst_of[:-1]
        dup = same & (frame_of[1:] == frame_of[:-1])
        if dup.any():
            k = int(np.flatnonzero(dup)[0])
            raise ValueError(
                f"nuScenes: instance {t['instance'].records[int(inst_of[k])]['token']!r} is "
                f"annotated twice in sample "
                f"{anns.records[int(rows[k + 1])]['sample_token']!r} ({anns.path})"
            )

        first_sample = np.array([chain[0] if chain else -1 for chain in scene_samples], np.int64)
        pose_samples = ann_sample[rows] if frame == "lidar" else first_sample[scene_of]
        boxes = self._boxes(t, rows, lidar_sd[pose_samples])
        starts = np.concatenate([[0], np.flatnonzero(~same) + 1, [len(rows)]])
        caches: dict[int, ScanCache] = {}
        scene_maps: dict[int, np.ndarray | None] = {}  # scene -> its key frames' maps
        sd = t["sample_data"].records
        track_in_scene: dict[int, int] = {}
        for a, b in zip(starts[:-1], starts[1:], strict=True):
            k = int(scene_of[a])
            name = self.scenes[k]
            if k not in caches:
                sd_rows = lidar_sd[scene_samples[k]]
                files = [sd[int(j)]["filename"] for j in sd_rows]
                maps = None if frame == "lidar" else lidar_to_reference(*_poses(t, sd_rows))
                scene_maps[k] = maps
                caches[k] = ScanCache(NuScenesScans(self.root, name, files, maps), cache_size)
            track_id = track_in_scene.get(k, 0)
            track_in_scene[k] = track_id + 1
            inst = int(inst_of[a])
            self.tracklets.append(
                Tracklet(
                    tracklet_id=f"{name}/{track_id}",
                    scene=name,
                    track_id=track_id,
                    category=str(mapped[int(inst_cat[inst])]),
                    frames=frame_of[a:b].copy(),
                    boxes=boxes[a:b].copy(),
                    scans=caches[k],
                    sensor_poses=None if scene_maps[k] is None else scene_maps[k][frame_of[a:b]],
                )
            )
            self.instance_tokens.append(t["instance"].records[inst]["token"])
            self.annotation_tokens.append(tuple(anns.records[int(r)]["token"] for r in rows[a:b]))

    @staticmethod
    def _lidar_key_frames(t: dict[str, _Table], selected: np.ndarray) -> np.ndarray:
        """``(S,)`` row of the ``LIDAR_TOP`` key-frame sample_data of each sample (``-1`` for
        samples outside the split); a selected sample without one raises naming it."""
        lidar_sensors = {
            r["token"] for r in t["sensor"].records if r.get("channel") == LIDAR_CHANNEL
        }
        cs = t["calibrated_sensor"]
        lidar_cs = {r["token"] for r in cs.records if r.get("sensor_token") in lidar_sensors}
        out = np.full(len(t["sample"].records), -1, np.int64)
        sd = t["sample_data"]
        for j, r in enumerate(sd.records):
            if r.get("is_key_frame") and r.get("calibrated_sensor_token") in lidar_cs:
                i = t["sample"].index.get(r.get("sample_token"))
                if i is None:
                    t["sample"].find(r.get("sample_token"), f"sample_data {r['token']!r}")
                out[i] = j
        missing = np.flatnonzero(selected & (out < 0))
        if len(missing):
            token = t["sample"].records[int(missing[0])]["token"]
            raise ValueError(
                f"nuScenes: sample {token!r} has no {LIDAR_CHANNEL} key-frame sample_data in "
                f"{sd.path}"
            )
        return out

    @staticmethod
    def _boxes(t: dict[str, _Table], rows: np.ndarray, sd_rows: np.ndarray) -> np.ndarray:
        """``(N, 7)`` boxes of annotation ``rows`` in the LiDAR frames of the key-frame
        sample_data ``sd_rows`` (one per annotation; one vectorised pass)."""
        anns = t["sample_annotation"]
        trans = _floats(anns, "translation", rows, 3)
        size = _floats(anns, "size", rows, 3)
        rot = _floats(anns, "rotation", rows, 4)
        _check_quaternions(rot, anns, rows)
        return global_to_lidar_boxes(trans, size, rot, *_poses(t, sd_rows))

    def __len__(self) -> int:
        return len(self.tracklets)

    def __repr__(self) -> str:
        return (
            f"NuScenesTracking({str(self.root)!r}, version={self.version!r}, "
            f"split={self.split!r}, categories={self.categories!r}, frame={self.frame!r}, "
            f"tracklets={len(self.tracklets)})"
        )
