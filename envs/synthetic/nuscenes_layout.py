"""The synthetic world written in the nuScenes v1.0 layout (devkit-compatible tables).

``pointtrack generate --layout nuscenes`` writes ``DIR/<version>/*.json`` (the 13 tables the
nuScenes devkit loads), ``DIR/samples/LIDAR_TOP/*.pcd.bin`` (5 float32 per point: x, y, z,
intensity 0-255, ring index), one small map mask per log under ``DIR/maps/`` (the devkit checks
that it exists) and ``DIR/manifest.json``. Read it with ``envs.data.NuScenesTracking``.

What is simulated. The scenes of the KITTI-layout world (same :func:`build_scene`, same seeds,
same motion version, same scans at the same frames) run at 10 Hz; every 5th frame is a key frame
(2 Hz, as nuScenes annotates), and only key frames are rendered and written (no sweeps). A key
frame annotates every agent within :data:`~envs.synthetic.scene.LABEL_RANGE` all around the
sensor (nuScenes annotates 360 degrees) that returns at least ``MIN_LABEL_POINTS`` points of its
own; ``num_lidar_pts`` holds that count. An agent keeps one instance over the scene, so a hidden
stretch is a gap in its annotation chain. Visibility is not simulated (``visibility_token`` is
empty).

Frames. The simulated sensor frame ``S`` (x forward, y left, z up, level) is re-expressed as a
nuScenes ``LIDAR_TOP`` frame ``L = S`` turned by -90 degrees about z (x right, y forward, as
in nuScenes); points are written in ``L``. The calibration ``LIDAR_TOP -> ego body`` is
:data:`LIDAR_CALIBRATION` (the real rig's rotation, with its small tilt, and lever arm), so the
ego body frame of each key frame is tilted by the inverse of that tilt, and its pose is moved
into a global frame rotated and shifted per scene. Boxes are written in the global frame with
nuScenes conventions (size ``(w, l, h)``, quaternion ``(w, x, y, z)``).

Scene names come from the official split lists, by KITTI role of the preset's scene number:
0-16 (train) -> ``train_track``, 17-18 (val) -> ``train_detect``, 19-20 (test) -> ``val`` (the
SOT test split), so the roles of :data:`envs.data.nuscenes.SOT_SPLITS` name them.
"""

from __future__ import annotations

import hashlib
import json
import math
import os
import struct
import uuid
import zlib
from pathlib import Path

import numpy as np

from envs.data.nuscenes import LIDAR_CHANNEL, split_scenes
from envs.synthetic.objects import CATEGORIES
from envs.synthetic.presets import get_preset
from envs.synthetic.scene import (
    agent_boxes_world,
    render_frame,
    sensor_pose,
    world_to_sensor_boxes,
)
from envs.synthetic.scene_types import LABEL_RANGE, Scene
from envs.synthetic.sensor import SensorModel, get_sensor
from envs.synthetic.world import (
    MANIFEST,
    MIN_LABEL_POINTS,
    clean_stale_temps,
    default_cache_dir,
    generated_scenes,
    manifest_matches,
    progress_bar,
    remove_tree,
    scene_frames,
    world_identity,
)

__all__ = [
    "DEFAULT_VERSION",
    "KEYFRAME_EVERY",
    "LIDAR_CALIBRATION",
    "NUSCENES_NAMES",
    "ensure_nuscenes_world",
    "expected_lidar_boxes",
    "generate_nuscenes_world",
    "lidar_from_sensor",
    "scene_name",
]

DEFAULT_VERSION = "v1.0-mini"
KEYFRAME_EVERY = 5  # 10 Hz simulation -> 2 Hz key frames
_BASE_TIMESTAMP_US = 1_533_151_603_547_590  # an ordinary nuScenes-era timestamp, microseconds

# LIDAR_TOP -> ego body: translation (metres) and rotation (w, x, y, z) of the nuScenes rig
# (LIDAR_TOP about 0.94 m ahead of the rear axle, 1.84 m up, x right / y forward, slightly
# tilted). Non-identity on purpose, so readers must apply it.
LIDAR_CALIBRATION = {
    "translation": [0.943713, 0.0, 1.84023],
    "rotation": [
        0.7077955119163518,
        -0.006492242056004365,
        0.010646214713995808,
        -0.7063073142877817,
    ],
}

# Synthetic category -> (nuScenes category, attribute or None). nuScenes has no van class (vans
# are vehicle.car) and annotates a ridden bicycle as vehicle.bicycle with cycle.with_rider.
NUSCENES_NAMES: dict[str, tuple[str, str | None]] = {
    "Car": ("vehicle.car", None),
    "Van": ("vehicle.car", None),
    "Truck": ("vehicle.truck", None),
    "Bus": ("vehicle.bus.rigid", None),
    "Pedestrian": ("human.pedestrian.adult", None),
    "Cyclist": ("vehicle.bicycle", "cycle.with_rider"),
    "Bicycle": ("vehicle.bicycle", "cycle.without_rider"),
    "Motorcycle": ("vehicle.motorcycle", None),
}
_ATTRIBUTES = ("cycle.with_rider", "cycle.without_rider")
_R_SL = np.array([[0.0, 1.0, 0.0], [-1.0, 0.0, 0.0], [0.0, 0.0, 1.0]])  # Rz(-90 deg): L in S


def _writer_digest() -> str:
    return hashlib.sha256(Path(__file__).read_bytes()).hexdigest()[:16]


def _token(*parts: object) -> str:
    """A deterministic 32-hex token (nuScenes tokens are 32 hex digits)."""
    return hashlib.md5("/".join(map(str, parts)).encode()).hexdigest()


def scene_name(scene_id: int) -> str:
    """Official scene name for a preset scene number (see the module docstring)."""
    if 0 <= scene_id <= 16:
        return split_scenes("train_track")[scene_id]
    if 17 <= scene_id <= 18:
        return split_scenes("train_detect")[scene_id - 17]
    if 19 <= scene_id <= 20:
        return split_scenes("val")[scene_id - 19]
    raise ValueError(f"scene number {scene_id} has no nuScenes name (0..20)")


# --------------------------------------------------------------------------- rotations


def _quat_to_matrix(q: np.ndarray) -> np.ndarray:
    w, x, y, z = np.asarray(q, np.float64) / np.linalg.norm(q)
    return np.array(
        [
            [1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
            [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
            [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)],
        ]
    )


def _matrix_to_quat(r: np.ndarray) -> list[float]:
    """Unit quaternion ``(w, x, y, z)`` with ``w >= 0`` of a rotation matrix ``(3, 3)``."""
    tr = np.trace(r)
    if tr > 0:
        s = 2.0 * math.sqrt(tr + 1.0)
        q = [0.25 * s, (r[2, 1] - r[1, 2]) / s, (r[0, 2] - r[2, 0]) / s, (r[1, 0] - r[0, 1]) / s]
    else:
        i = int(np.argmax(np.diag(r)))
        j, k = (i + 1) % 3, (i + 2) % 3
        s = 2.0 * math.sqrt(1.0 + r[i, i] - r[j, j] - r[k, k])
        q = [0.0, 0.0, 0.0, 0.0]
        q[0] = (r[k, j] - r[j, k]) / s
        q[1 + i] = 0.25 * s
        q[1 + j] = (r[j, i] + r[i, j]) / s
        q[1 + k] = (r[k, i] + r[i, k]) / s
    q = np.asarray(q) / np.linalg.norm(q)
    return [float(v) for v in (q if q[0] >= 0 else -q)]


def _rz(angle: float) -> np.ndarray:
    c, s = math.cos(angle), math.sin(angle)
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])


def lidar_from_sensor(boxes: np.ndarray) -> np.ndarray:
    """Boxes ``(..., 7)`` in the simulated sensor frame ``S`` -> the written ``LIDAR_TOP`` frame
    (``L`` = ``S`` turned by -90 degrees about z: ``x_L = -y_S``, ``y_L = x_S``, yaw + pi/2)."""
    b = np.asarray(boxes, np.float64)
    out = b.copy()
    out[..., 0] = -b[..., 1]
    out[..., 1] = b[..., 0]
    out[..., 6] = (b[..., 6] + 0.5 * np.pi + np.pi) % (2 * np.pi) - np.pi
    return out


# --------------------------------------------------------------------------- files


def _tiny_png(path: Path) -> None:
    """A 1x1 grayscale PNG (the devkit's ``MapMask`` only checks the file exists at load)."""

    def chunk(kind: bytes, data: bytes) -> bytes:
        body = kind + data
        return struct.pack(">I", len(data)) + body + struct.pack(">I", zlib.crc32(body))

    png = b"\x89PNG\r\n\x1a\n" + chunk(b"IHDR", struct.pack(">IIBBBBB", 1, 1, 8, 0, 0, 0, 0))
    png += chunk(b"IDAT", zlib.compress(b"\x00\x00")) + chunk(b"IEND", b"")
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_bytes(png)


def _ring_index(points: np.ndarray, sensor: SensorModel) -> np.ndarray:
    """``(N,)`` beam index of each sensor-frame point (nearest beam elevation; range noise acts
    along the ray, so the elevation is exact up to float32)."""
    el = np.degrees(np.arctan2(points[:, 2], np.hypot(points[:, 0], points[:, 1])))
    beams = np.asarray(sensor.elevations_deg)  # descending
    idx = np.searchsorted(-beams, -el).clip(1, len(beams) - 1)
    nearer_prev = np.abs(beams[idx - 1] - el) <= np.abs(beams[idx] - el)
    return np.where(nearer_prev, idx - 1, idx).astype(np.float32)


def _write_pcd_bin(path: Path, points_s: np.ndarray, sensor: SensorModel) -> None:
    """Sensor-frame points ``(N, 4)`` (intensity in [0, 1]) -> ``L`` frame, 5 float32 each."""
    out = np.empty((len(points_s), 5), dtype="<f4")
    out[:, 0] = -points_s[:, 1]
    out[:, 1] = points_s[:, 0]
    out[:, 2] = points_s[:, 2]
    out[:, 3] = points_s[:, 3] * np.float32(255.0)
    out[:, 4] = _ring_index(points_s, sensor)
    path.parent.mkdir(parents=True, exist_ok=True)
    out.tofile(path)


def _chain(records: list[dict]) -> None:
    """Set ``prev`` / ``next`` of consecutive records (in place)."""
    for i, r in enumerate(records):
        r["prev"] = records[i - 1]["token"] if i else ""
        r["next"] = records[i + 1]["token"] if i + 1 < len(records) else ""


class _Tables:
    """The 13 tables, filled scene by scene."""

    def __init__(self, seed: int) -> None:
        self.seed = seed
        names = sorted({v[0] for v in NUSCENES_NAMES.values()})
        self.category = [
            {"token": _token("category", n), "name": n, "description": f"synthetic {n}"}
            for n in names
        ]
        self.attribute = [
            {"token": _token("attribute", n), "name": n, "description": n} for n in _ATTRIBUTES
        ]
        self.visibility = [
            {"token": str(i), "level": lvl, "description": f"visibility of whole object {lvl}"}
            for i, lvl in enumerate(("v0-40", "v40-60", "v60-80", "v80-100"), 1)
        ]
        self.sensor = [
            {
                "token": _token("sensor", LIDAR_CHANNEL),
                "channel": LIDAR_CHANNEL,
                "modality": "lidar",
            }
        ]
        self.instance: list[dict] = []
        self.calibrated_sensor: list[dict] = []
        self.ego_pose: list[dict] = []
        self.log: list[dict] = []
        self.scene: list[dict] = []
        self.sample: list[dict] = []
        self.sample_data: list[dict] = []
        self.sample_annotation: list[dict] = []
        self.map: list[dict] = []

    def write(self, table_dir: Path) -> None:
        table_dir.mkdir(parents=True, exist_ok=True)
        for name in (
            "category",
            "attribute",
            "visibility",
            "instance",
            "sensor",
            "calibrated_sensor",
            "ego_pose",
            "log",
            "scene",
            "sample",
            "sample_data",
            "sample_annotation",
            "map",
        ):
            (table_dir / f"{name}.json").write_text(json.dumps(getattr(self, name), indent=0))


def _write_scene(
    root: Path, tables: _Tables, scene: Scene, sensor: SensorModel, seed: int, bar
) -> dict:
    """Render the key frames of one scene, write their scans and fill the tables."""
    sid = scene.scene_id
    name = scene_name(sid)
    cat_token = {c["name"]: c["token"] for c in tables.category}
    attr_token = {a["name"]: a["token"] for a in tables.attribute}
    log_token, scene_token = _token(seed, sid, "log"), _token(seed, sid, "scene")
    cs_token = _token(seed, sid, "calibrated_sensor")
    tables.log.append(
        {
            "token": log_token,
            "logfile": f"synthetic-s{seed}-{sid:04d}",
            "vehicle": "synthetic",
            "date_captured": "2018-08-01",
            "location": "synthetic",
        }
    )
    map_token = _token(seed, sid, "map")
    tables.map.append(
        {
            "token": map_token,
            "log_tokens": [log_token],
            "category": "semantic_prior",
            "filename": f"maps/{map_token}.png",
        }
    )
    _tiny_png(root / "maps" / f"{map_token}.png")
    tables.calibrated_sensor.append(
        {
            "token": cs_token,
            "sensor_token": tables.sensor[0]["token"],
            **LIDAR_CALIBRATION,
            "camera_intrinsic": [],
        }
    )
    # Global frame: the world rotated and shifted per scene.
    rng = np.random.default_rng([seed, sid, 29])
    r_gw = _rz(float(rng.uniform(-np.pi, np.pi)))
    t_gw = np.array([rng.uniform(300.0, 2000.0), rng.uniform(300.0, 2000.0), 0.0])
    r_el = _quat_to_matrix(np.array(LIDAR_CALIBRATION["rotation"]))
    t_el = np.array(LIDAR_CALIBRATION["translation"])

    keyframes = range(0, scene.n_frames, KEYFRAME_EVERY)
    samples: list[dict] = []
    sds: list[dict] = []
    by_agent: dict[int, list[dict]] = {}
    n_points = 0
    for k, t in enumerate(keyframes):
        frame = render_frame(scene, t, sensor, np.random.default_rng([seed, sid, 11, t]))
        ts = _BASE_TIMESTAMP_US + sid * 10**9 + t * 100_000
        sample_token, sd_token = _token(seed, sid, "sample", k), _token(seed, sid, "sd", k)
        filename = f"samples/{LIDAR_CHANNEL}/{name}__{LIDAR_CHANNEL}__{ts}.pcd.bin"
        _write_pcd_bin(root / filename, frame.points, sensor)
        n_points += len(frame.points)
        origin, yaw = sensor_pose(scene, t, sensor)
        r_ws = _rz(yaw)
        r_we = r_ws @ _R_SL @ r_el.T  # ego body in world: L = S Rz(-90), L in body = R_el
        t_we = origin - r_we @ t_el
        tables.ego_pose.append(
            {
                "token": sd_token,
                "timestamp": ts,
                "rotation": _matrix_to_quat(r_gw @ r_we),
                "translation": [float(v) for v in r_gw @ t_we + t_gw],
            }
        )
        samples.append({"token": sample_token, "timestamp": ts, "scene_token": scene_token})
        sds.append(
            {
                "token": sd_token,
                "sample_token": sample_token,
                "ego_pose_token": sd_token,
                "calibrated_sensor_token": cs_token,
                "timestamp": ts,
                "fileformat": "pcd",
                "is_key_frame": True,
                "height": 0,
                "width": 0,
                "filename": filename,
            }
        )
        dist = np.hypot(frame.boxes[:, 0], frame.boxes[:, 1])
        sel = np.flatnonzero((dist <= LABEL_RANGE) & (frame.n_points >= MIN_LABEL_POINTS))
        world = agent_boxes_world(scene, t)
        for i in sel:
            a = int(frame.agent_index[i])
            agent = scene.agents[a]
            box = world[a]
            centre = r_gw @ box[:3] + t_gw
            rot = r_gw @ _rz(float(box[6]))
            _, attr = NUSCENES_NAMES[agent.category]
            by_agent.setdefault(a, []).append(
                {
                    "token": _token(seed, sid, "ann", a, k),
                    "sample_token": sample_token,
                    "instance_token": _token(seed, sid, "instance", a),
                    "visibility_token": "",
                    "attribute_tokens": [] if attr is None else [attr_token[attr]],
                    "translation": [float(v) for v in centre],
                    "size": [float(box[4]), float(box[3]), float(box[5])],  # (w, l, h)
                    "rotation": _matrix_to_quat(rot),
                    "num_lidar_pts": int(frame.n_points[i]),
                    "num_radar_pts": 0,
                }
            )
        bar.update(KEYFRAME_EVERY if t + KEYFRAME_EVERY <= scene.n_frames else scene.n_frames - t)
    _chain(samples)
    _chain(sds)
    tables.sample.extend(samples)
    tables.sample_data.extend(sds)
    n_ann = 0
    for a in sorted(by_agent):
        anns = by_agent[a]
        _chain(anns)
        tables.sample_annotation.extend(anns)
        n_ann += len(anns)
        tables.instance.append(
            {
                "token": anns[0]["instance_token"],
                "category_token": cat_token[NUSCENES_NAMES[scene.agents[a].category][0]],
                "nbr_annotations": len(anns),
                "first_annotation_token": anns[0]["token"],
                "last_annotation_token": anns[-1]["token"],
            }
        )
    tables.scene.append(
        {
            "token": scene_token,
            "log_token": log_token,
            "nbr_samples": len(samples),
            "first_sample_token": samples[0]["token"],
            "last_sample_token": samples[-1]["token"],
            "name": name,
            "description": f"synthetic scene {sid} (seed {seed})",
        }
    )
    return {
        "name": name,
        "frames": scene.n_frames,
        "key_frames": len(samples),
        "instances": len(by_agent),
        "annotations": n_ann,
        "mean_points": round(n_points / max(len(samples), 1), 1),
    }


def expected_lidar_boxes(scene: Scene, sensor: SensorModel, t: int) -> np.ndarray:
    """``(A, 7)`` boxes of every agent at frame ``t`` in the written ``LIDAR_TOP`` frame,
    straight from the simulation (world boxes -> sensor frame -> ``L``), for checks."""
    origin, yaw = sensor_pose(scene, t, sensor)
    return lidar_from_sensor(world_to_sensor_boxes(agent_boxes_world(scene, t), origin, yaw))


def nuscenes_identity(preset: str, sensor: str, seed: int, version: str) -> dict:
    """The manifest fields that decide whether a nuScenes-layout world can be reused."""
    ident = world_identity(preset, sensor, seed)
    ident["layout"] = {
        "name": "nuscenes",
        "version": version,
        "writer": _writer_digest(),
        "keyframe_every": KEYFRAME_EVERY,
    }
    return ident


def _check_version(version: str) -> str:
    if not isinstance(version, str) or not version or "/" in version or version.startswith("."):
        raise ValueError(f"version must be a folder name such as 'v1.0-mini', got {version!r}")
    return version


def generate_nuscenes_world(
    out_dir: str | Path,
    preset: str = "small",
    sensor: str = "hdl32",
    seed: int = 0,
    version: str = DEFAULT_VERSION,
    *,
    progress: bool | None = None,
    overwrite: bool = False,
) -> Path:
    """Generate a synthetic world in the nuScenes layout into ``out_dir`` (atomically: a temp
    sibling renamed into place) and return ``out_dir``; an existing identical world is reused,
    another non-empty directory raises ``FileExistsError`` unless ``overwrite``.

    Args:
        preset: ``tiny``, ``small`` or ``default`` (scene numbers and lengths of the KITTI-layout
            world; key frames are every 5th frame), or ``tiny-km`` / ``small-km`` /
            ``default-km``: the motion fitted to KITTI, the same per second as in the KITTI
            layout, sampled at the 2 Hz key frames.
        sensor: ``hdl32`` (nuScenes-like, the default) or ``hdl64``.
        seed: non-negative integer; the same seed gives byte-identical files.
        version: the table folder name (``v1.0-mini`` by default).
    """
    p = get_preset(preset)
    sensor_model = get_sensor(sensor)
    if p.column_factor > 1:
        sensor_model = sensor_model.subsampled(p.column_factor)
    version = _check_version(version)
    ident = nuscenes_identity(preset, sensor, seed, version)
    seed = int(ident["seed"])
    out = Path(out_dir)
    if out.exists():
        if manifest_matches(out, ident):
            return out
        if any(out.iterdir()) and not overwrite:
            raise FileExistsError(
                f"{out} exists and is not this nuScenes-layout world (preset={preset}, "
                f"sensor={sensor}, seed={seed}, version={version}); choose another --out or "
                "overwrite"
            )
        remove_tree(out)
    out.parent.mkdir(parents=True, exist_ok=True)
    clean_stale_temps(out.parent, out.name)  # what killed writers of this world left
    tmp = out.parent / f".{out.name}.tmp-{os.getpid()}-{uuid.uuid4().hex[:8]}"
    tmp.mkdir()
    try:
        tables = _Tables(seed)
        entries = {}
        total = sum(scene_frames(p, seed, s) for s in p.scenes)
        with progress_bar(
            total, f"synthetic nuScenes {p.name}/{sensor_model.name}", progress
        ) as bar:
            for scene_id, scene in generated_scenes(p, seed, sensor_model):
                entries[f"{scene_id:04d}"] = _write_scene(
                    tmp, tables, scene, sensor_model, seed, bar
                )
        tables.write(tmp / version)
        manifest = dict(ident)
        manifest["scene_stats"] = entries
        manifest["categories"] = list(CATEGORIES)
        (tmp / MANIFEST).write_text(json.dumps(manifest, indent=2, sort_keys=True) + "\n")
        try:
            os.rename(tmp, out)
        except OSError:
            if manifest_matches(out, ident):
                remove_tree(tmp)
                return out
            raise
    except BaseException:
        remove_tree(tmp)
        raise
    return out


def ensure_nuscenes_world(
    preset: str = "small",
    sensor: str = "hdl32",
    seed: int = 0,
    version: str = DEFAULT_VERSION,
    cache_dir: str | Path | None = None,
    *,
    progress: bool | None = None,
) -> Path:
    """The root of the nuScenes-layout world ``(preset, sensor, seed, version)``, generated
    into the cache (``<cache>/worlds/nuscenes-<preset>-<sensor>-s<seed>-<hash>``) on first use."""
    ident = nuscenes_identity(preset, sensor, seed, _check_version(version))
    digest = hashlib.sha256(json.dumps(ident, sort_keys=True).encode()).hexdigest()[:12]
    base = Path(cache_dir) if cache_dir is not None else default_cache_dir()
    out = base / "worlds" / f"nuscenes-{preset}-{sensor}-s{int(seed)}-{digest}"
    if manifest_matches(out, ident):
        return out
    return generate_nuscenes_world(
        out, preset, sensor, seed, version, progress=progress, overwrite=True
    )
