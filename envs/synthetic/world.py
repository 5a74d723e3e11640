"""The KITTI-layout writer and the generate-once cache of synthetic worlds (their sizes:
:mod:`envs.synthetic.presets`).

A world directory holds ``velodyne/SSSS/FFFFFF.bin``, ``label_02/SSSS.txt``, ``calib/SSSS.txt``
(the KITTI tracking layout, so :class:`envs.data.KittiTracking` reads it unchanged) and
``manifest.json`` (generator version, preset, sensor, seed, the full config). A directory is only
ever taken as complete when its manifest matches: generation writes into a temporary sibling
directory and renames it into place at the end (atomic on one file system), so a killed run
never leaves a half-written world under the final name, and two processes generating the same
world end with one complete copy (the second rename fails and that process uses the first copy).

Integrity. The manifest records every file's size and SHA-256. :func:`ensure_world` checks the
sizes (a ``stat`` per file) on every use and regenerates a world that fails; the digests are
checked by :func:`verify_world` (``pointtrack generate --verify DIR``). Temp directories of
killed runs are told from live ones by a ``flock`` their writer holds, and are removed on the
next use of the cache (:func:`clean_stale_temps`).
"""

from __future__ import annotations

import fcntl
import hashlib
import json
import os
import shutil
import uuid
import warnings
from collections.abc import Iterator
from dataclasses import asdict
from pathlib import Path

import numpy as np

from envs.data.kitti import (
    Calibration,
    LabelRow,
    lidar_to_camera_boxes,
    write_calibration,
    write_labels,
    write_scan,
)
from envs.synthetic.calibration import KITTI_LIKE_CALIBRATION
from envs.synthetic.kitti_motion import KittiMotion
from envs.synthetic.objects import CATEGORIES
from envs.synthetic.presets import Preset, get_preset
from envs.synthetic.replay import build_replay_scene, replay_scene_ids
from envs.synthetic.scene import render_frame
from envs.synthetic.scene_types import DT, FrameResult, Scene, SceneConfig
from envs.synthetic.sensor import SensorModel, get_sensor
from envs.synthetic.street import build_scene

__all__ = [
    "GENERATOR_VERSION",
    "default_cache_dir",
    "ensure_world",
    "generate_world",
    "MAX_LABEL_GAP",
    "MIN_LABEL_POINTS",
    "MIN_TRACK_FRAMES",
    "label_rows",
    "split_tracks",
    "clean_stale_temps",
    "verify_world",
    "world_identity",
]

GENERATOR_VERSION = "1.0"


def _source_digest() -> str:
    """SHA-256 of the generator's own source files: any change to the code that makes worlds
    invalidates cached worlds, even when nobody remembered to bump the version."""
    h = hashlib.sha256()
    for path in sorted(Path(__file__).resolve().parent.glob("*.py")):
        if path.name in ("preview.py", "__init__.py", "nuscenes_layout.py"):
            continue  # pictures, re-exports and the nuScenes writer do not change these worlds
        h.update(path.name.encode())
        h.update(path.read_bytes())
    return h.hexdigest()[:16]


SOURCE_DIGEST = _source_digest()
MANIFEST = "manifest.json"
IMAGE_SIZE = (1242, 375)  # KITTI camera 2 image, pixels (width, height)


def _check_seed(seed: int) -> int:
    if isinstance(seed, bool) or not isinstance(seed, int | np.integer) or seed < 0:
        raise ValueError(f"seed must be a non-negative integer, got {seed!r}")
    return int(seed)


def default_cache_dir() -> Path:
    """``$POINTTRACK_CACHE`` if set, else the user cache dir of ``pointtrack``."""
    env = os.environ.get("POINTTRACK_CACHE")
    if env:
        return Path(env).expanduser()
    import platformdirs

    return Path(platformdirs.user_cache_dir("pointtrack"))


def _labels_digest(labels_dir: Path) -> str:
    """SHA-256 over the label and calibration files (names and bytes)."""
    h = hashlib.sha256()
    for sub in ("label_02", "calib"):
        for path in sorted((labels_dir / sub).glob("*.txt")):
            h.update(f"{sub}/{path.name}\n".encode())
            h.update(path.read_bytes())
    return h.hexdigest()


def world_identity(
    preset: str,
    sensor: str,
    seed: int,
    labels_dir: str | Path | None = None,
    scan_frames: int | None = None,
    scenes: tuple[int, ...] | None = None,
) -> dict:
    """The manifest fields that decide whether a world directory can be reused."""
    p = get_preset(preset)
    s = get_sensor(sensor)
    seed = _check_seed(seed)
    preset_config = asdict(p)
    if p.motion == "v1":
        del preset_config["motion"]  # the worlds made before motion versions: same manifest
    ident: dict = {
        "generator": "pointtrack.envs.synthetic",
        "generator_version": GENERATOR_VERSION,
        "source_digest": SOURCE_DIGEST,
        "preset": p.name,
        "sensor": s.name,
        "seed": seed,
        "config": {
            "preset": preset_config,
            "sensor": {k: v for k, v in asdict(s).items() if not k.startswith("_")},
            "frame_rate_hz": 1.0 / DT,
        },
        "labels": None,
        "scan_frames": None if scan_frames is None else int(scan_frames),
        "scenes": None if scenes is None else [int(v) for v in scenes],
    }
    if labels_dir is not None:
        root = Path(labels_dir)
        if not (root / "label_02").is_dir():
            raise ValueError(f"labels directory {root} has no label_02/ folder")
        ident["labels"] = {"path": str(root.resolve()), "sha256": _labels_digest(root)}
    if scan_frames is not None and scan_frames < 0:
        raise ValueError(f"scan_frames must be >= 0, got {scan_frames}")
    return ident


def _read_manifest(root: Path) -> dict | None:
    try:
        return json.loads((root / MANIFEST).read_text())
    except (OSError, ValueError):
        return None


def manifest_matches(root: Path, ident: dict) -> bool:
    manifest = _read_manifest(root)
    if manifest is None:
        return False
    ident_json = json.loads(json.dumps(ident))
    return all(manifest.get(k) == v for k, v in ident_json.items())


# --------------------------------------------------------------------------- labels


def _image_boxes(cam: np.ndarray, calib: Calibration) -> tuple[np.ndarray, np.ndarray]:
    """2D boxes ``(N, 4)`` (left, top, right, bottom, clipped to the image) and truncation
    ``(N,)`` in [0, 1] of camera boxes ``(N, 7)`` ``[h, w, l, x, y, z, ry]`` through ``P2``."""
    n = len(cam)
    if n == 0:
        return np.zeros((0, 4)), np.zeros(0)
    h, w, l, x, y, z, ry = (cam[:, i] for i in range(7))
    sx = np.array([1, 1, -1, -1, 1, 1, -1, -1]) * 0.5
    sz = np.array([1, -1, -1, 1, 1, -1, -1, 1]) * 0.5
    sy = np.array([0, 0, 0, 0, -1, -1, -1, -1])
    c, s = np.cos(ry)[:, None], np.sin(ry)[:, None]
    lx, lz = l[:, None] * sx, w[:, None] * sz
    px = c * lx + s * lz + x[:, None]
    pz = -s * lx + c * lz + z[:, None]
    py = h[:, None] * sy + y[:, None]
    pts = np.stack([px, py, pz, np.ones_like(px)], -1) @ calib.p2.T
    depth = np.maximum(pts[..., 2], 0.1)
    u, v = pts[..., 0] / depth, pts[..., 1] / depth
    box = np.stack([u.min(1), v.min(1), u.max(1), v.max(1)], 1)
    clipped = box.copy()
    clipped[:, [0, 2]] = np.clip(box[:, [0, 2]], 0, IMAGE_SIZE[0] - 1)
    clipped[:, [1, 3]] = np.clip(box[:, [1, 3]], 0, IMAGE_SIZE[1] - 1)
    area = np.maximum(box[:, 2] - box[:, 0], 1e-6) * np.maximum(box[:, 3] - box[:, 1], 1e-6)
    area_c = np.maximum(clipped[:, 2] - clipped[:, 0], 0) * np.maximum(
        clipped[:, 3] - clipped[:, 1], 0
    )
    trunc = np.clip(1.0 - area_c / area, 0.0, 1.0)
    trunc[(pts[..., 2] <= 0.1).any(1)] = np.maximum(trunc[(pts[..., 2] <= 0.1).any(1)], 0.5)
    return clipped, trunc


def _occlusion_level(bbox_rays: np.ndarray, clear_rays: np.ndarray) -> np.ndarray:
    """KITTI occlusion state from the unoccluded share of the rays entering the box: 0 fully
    visible (>= 75 %), 1 partly (>= 30 %), 2 largely occluded, 3 unknown (no ray reaches it)."""
    frac = clear_rays / np.maximum(bbox_rays, 1)
    level = np.where(frac >= 0.75, 0, np.where(frac >= 0.3, 1, 2))
    return np.where(bbox_rays == 0, 3, level)


# Labelling rule (KITTI-like: annotators label what they see). An agent is labelled in a frame
# only when it is in the labelled field of view AND receives at least MIN_LABEL_POINTS LiDAR
# returns of its own (after dropout; ground or other objects' points inside its box do not
# count). A target hidden for more than MAX_LABEL_GAP consecutive frames (0.5 s) gets a new
# track id when it reappears; shorter gaps stay inside one track (the loader keeps the labelled
# frames in order, like KITTI's gapped tracks). Stretches with fewer than MIN_TRACK_FRAMES
# labelled frames (a glimpse) are not labelled. Label-driven replay writes its source labels
# unchanged and does not apply this rule.
MIN_LABEL_POINTS = 3
MAX_LABEL_GAP = 5
MIN_TRACK_FRAMES = 2


def label_rows(
    scene: Scene, t: int, frame: FrameResult, calib: Calibration, min_points: int = 0
) -> list[LabelRow]:
    """KITTI tracking label rows of the agents in the labelled field of view of frame ``t``
    that return at least ``min_points`` points of their own (track id = agent track id)."""
    sel = np.flatnonzero(frame.in_fov & (frame.n_points >= min_points))
    if not len(sel):
        return []
    boxes = frame.boxes[sel]
    cam = lidar_to_camera_boxes(boxes, calib)
    bbox, trunc = _image_boxes(cam, calib)
    occ = _occlusion_level(frame.bbox_rays[sel], frame.clear_rays[sel])
    rows = []
    for k, i in enumerate(sel):
        agent = scene.agents[frame.agent_index[i]]
        rows.append(
            LabelRow.from_box(
                t,
                agent.track_id,
                agent.category,
                np.round(cam[k], 6),
                truncated=round(float(trunc[k]), 2),
                occluded=int(occ[k]),
                bbox=np.round(bbox[k], 2),
            )
        )
    rows.sort(key=lambda r: r.track_id)
    return rows


def split_tracks(
    rows: list[LabelRow],
    max_gap: int = MAX_LABEL_GAP,
    min_frames: int = MIN_TRACK_FRAMES,
) -> list[LabelRow]:
    """Apply the gap rule to visible rows of one scene: each agent's labelled frames are cut
    where more than ``max_gap`` frames in a row are missing, stretches with fewer than
    ``min_frames`` frames are dropped, and the stretches get dense new track ids (ordered by
    agent, then time). Returns the rows sorted by frame, then track id."""
    by_track: dict[int, list[LabelRow]] = {}
    for r in rows:
        by_track.setdefault(r.track_id, []).append(r)
    out: list[LabelRow] = []
    next_id = 0
    for tid in sorted(by_track):
        track = sorted(by_track[tid], key=lambda r: r.frame)
        segments: list[list[LabelRow]] = [[track[0]]]
        for prev, cur in zip(track[:-1], track[1:], strict=True):
            if cur.frame - prev.frame - 1 > max_gap:
                segments.append([])
            segments[-1].append(cur)
        for seg in segments:
            if len(seg) < min_frames:
                continue
            out.extend(r._replace(track_id=next_id) for r in seg)
            next_id += 1
    out.sort(key=lambda r: (r.frame, r.track_id))
    return out


# --------------------------------------------------------------------------- generation


def progress_bar(total: int, desc: str, progress: bool | None):
    from tqdm.auto import tqdm

    # progress=None: tqdm decides (shown on a terminal, silent in logs and tests).
    return tqdm(
        total=total,
        desc=desc,
        unit="frame",
        disable=None if progress is None else not progress,
        leave=False,
    )


def scene_frames(preset: Preset, seed: int, scene_id: int) -> int:
    lo, hi = preset.frames
    rng = np.random.default_rng([seed, scene_id, 3])
    return int(rng.integers(lo, hi + 1))


def generated_scenes(
    preset: Preset, seed: int, sensor: SensorModel, motion_params: KittiMotion | None = None
) -> Iterator[tuple]:
    """``(scene_id, Scene)`` of every scene of the preset (``motion_params``: see
    :func:`build_scene`)."""
    for scene_id in preset.scenes:
        cfg = SceneConfig(
            n_frames=scene_frames(preset, seed, scene_id),
            density=preset.density,
            static_density=preset.static_density,
            required=CATEGORIES,
            motion=preset.motion,
        )
        yield scene_id, build_scene(scene_id, seed, cfg, motion_params)


def _write_scene(
    root: Path,
    scene: Scene,
    sensor: SensorModel,
    seed: int,
    calib: Calibration,
    bar,
    rows_override: list[str] | None = None,
    scan_frames: int | None = None,
) -> dict:
    """Render and write one scene; returns its manifest entry."""
    name = f"{scene.scene_id:04d}"
    write_calibration(root / "calib" / f"{name}.txt", calib)
    rows: list[LabelRow] = []
    n_scans = scene.n_frames if scan_frames is None else min(scene.n_frames, scan_frames)
    n_points = 0
    for t in range(n_scans):
        rng = np.random.default_rng([seed, scene.scene_id, 11, t])
        frame = render_frame(scene, t, sensor, rng)
        write_scan(root / "velodyne" / name / f"{t:06d}.bin", frame.points)
        n_points += len(frame.points)
        if rows_override is None:
            rows.extend(label_rows(scene, t, frame, calib, min_points=MIN_LABEL_POINTS))
        bar.update(1)
    label_file = root / "label_02" / f"{name}.txt"
    if rows_override is None:
        rows = split_tracks(rows)
        write_labels(label_file, rows)
        tracks = len({r.track_id for r in rows})
        n_rows = len(rows)
    else:  # label-driven replay: the source rows, byte for byte
        label_file.parent.mkdir(parents=True, exist_ok=True)
        label_file.write_text("".join(rows_override))
        n_rows = sum(1 for r in rows_override if r.split()[2] != "DontCare")
        tracks = len({r.split()[1] for r in rows_override if r.split()[2] != "DontCare"})
    return {
        "frames": scene.n_frames,
        "scans": n_scans,
        "label_rows": n_rows,
        "tracks": tracks,
        "mean_points": round(n_points / max(n_scans, 1), 1),
    }


def _generate_into(
    tmp: Path,
    ident: dict,
    preset: Preset,
    sensor: SensorModel,
    seed: int,
    labels_dir: Path | None,
    progress: bool | None,
    scan_frames: int | None,
    scenes: tuple[int, ...] | None,
) -> None:
    calib = KITTI_LIKE_CALIBRATION
    entries: dict[str, dict] = {}
    if labels_dir is None:
        if scan_frames is not None or scenes is not None:
            raise ValueError("scan_frames and scenes apply to label-driven replay only")
        total = sum(scene_frames(preset, seed, s) for s in preset.scenes)
        with progress_bar(total, f"synthetic {preset.name}/{sensor.name}", progress) as bar:
            for scene_id, scene in generated_scenes(preset, seed, sensor):
                entries[f"{scene_id:04d}"] = _write_scene(tmp, scene, sensor, seed, calib, bar)
    else:
        ids = replay_scene_ids(labels_dir) if scenes is None else tuple(scenes)
        built = []
        total = 0
        for scene_id in ids:
            scene, rows, scene_calib, rsensor = build_replay_scene(
                labels_dir, scene_id, seed, sensor
            )
            built.append((scene_id, scene, rows, scene_calib, rsensor))
            n = scene.n_frames if scan_frames is None else min(scene.n_frames, scan_frames)
            total += n
        with progress_bar(total, f"replay {labels_dir.name}/{sensor.name}", progress) as bar:
            for scene_id, scene, rows, scene_calib, rsensor in built:
                entries[f"{scene_id:04d}"] = _write_scene(
                    tmp, scene, rsensor, seed, scene_calib, bar, rows, scan_frames
                )
    manifest = dict(ident)
    manifest["scene_stats"] = entries
    manifest["categories"] = list(CATEGORIES)
    manifest["files"] = _file_table(tmp)
    # Written last: a directory with a manifest is complete.
    (tmp / MANIFEST).write_text(json.dumps(manifest, indent=2, sort_keys=True) + "\n")


def generate_world(
    out_dir: str | Path,
    preset: str = "small",
    sensor: str = "hdl64",
    seed: int = 0,
    labels_dir: str | Path | None = None,
    *,
    progress: bool | None = None,
    overwrite: bool = False,
    scan_frames: int | None = None,
    scenes: tuple[int, ...] | None = None,
) -> Path:
    """Generate a world into ``out_dir`` (atomically) and return ``out_dir``.

    Args:
        out_dir: final directory. When it already holds a world with the same manifest identity
            it is reused as is; another non-empty directory raises ``FileExistsError`` unless
            ``overwrite``.
        preset: ``"tiny"``, ``"small"``, ``"default"`` or their KITTI-motion versions
            ``"tiny-km"``, ``"small-km"``, ``"default-km"`` (see :mod:`envs.synthetic.presets`).
        sensor: ``"hdl64"`` (KITTI-like) or ``"hdl32"`` (nuScenes-like).
        seed: non-negative integer; the same seed gives byte-identical files.
        labels_dir: a KITTI ``label_02`` + ``calib`` folder: replay its labelled objects (real
            categories, sizes, trajectories) in a generated street and write exactly its labels.
            ``preset`` then only picks the sensor resolution (``tiny`` halves it).
        progress: show a tqdm bar (``None``: only on a terminal).
        overwrite: replace a non-matching existing directory.
        scan_frames: replay only: simulate scans for the first ``scan_frames`` frames of each
            scene (labels stay complete) — for quick checks.
        scenes: replay only: the scene numbers to replay (default: every label file).

    Raises:
        ValueError: an invalid preset, sensor, seed or option (the message lists valid values).
    """
    p = get_preset(preset)
    sensor_model = get_sensor(sensor)
    if p.column_factor > 1:
        sensor_model = sensor_model.subsampled(p.column_factor)
    seed = _check_seed(seed)
    labels_path = None if labels_dir is None else Path(labels_dir)
    ident = world_identity(preset, sensor, seed, labels_path, scan_frames, scenes)
    out = Path(out_dir)
    if out.exists():
        if manifest_matches(out, ident) and not verify_world(out, digests=False):
            return out
        if any(out.iterdir()) and not manifest_matches(out, ident) and not overwrite:
            raise FileExistsError(
                f"{out} exists and is not this world (preset={preset}, sensor={sensor}, "
                f"seed={seed}); choose another --out or overwrite"
            )
        remove_tree(out)  # another world (overwrite) or this one, damaged: regenerate
    try:
        out.parent.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise OSError(f"cannot create {out.parent} for the world: {exc.strerror or exc}") from None
    clean_stale_temps(out.parent, out.name)  # only this world's: the folder may be anyone's
    tmp = out.parent / f".{out.name}.tmp-{os.getpid()}-{uuid.uuid4().hex[:8]}"
    lock = _hold_lock(tmp)  # before the directory exists: a cleaner never sees it unlocked
    try:
        tmp.mkdir()
        _generate_into(
            tmp, ident, p, sensor_model, seed, labels_path, progress, scan_frames, scenes
        )
        try:
            os.rename(tmp, out)
        except OSError:
            # Someone else finished a world under this name first: keep it if it is this one.
            if manifest_matches(out, ident):
                remove_tree(tmp)
                return out
            raise FileExistsError(
                f"{out} was written by another process meanwhile and is not this world "
                f"(preset={preset}, sensor={sensor}, seed={seed}); choose another --out"
            ) from None
    except BaseException:
        remove_tree(tmp)
        raise
    finally:
        _release_lock(tmp, lock)
    return out


def _lock_path(tmp: Path) -> Path:
    return tmp.with_name(tmp.name + ".lock")


def _hold_lock(tmp: Path) -> int:
    """Create and lock (``flock``) the lock file of a temp directory; the kernel releases the
    lock when the process dies, however it dies, which is how a cleaner tells a stale temp
    directory from one being written (in any process namespace)."""
    fd = os.open(_lock_path(tmp), os.O_RDWR | os.O_CREAT, 0o644)
    fcntl.flock(fd, fcntl.LOCK_EX)
    return fd


def _release_lock(tmp: Path, fd: int) -> None:
    _lock_path(tmp).unlink(missing_ok=True)
    os.close(fd)


def _owner_alive(tmp: Path) -> bool:
    """Whether the process that made temp directory ``tmp`` is still writing it."""
    try:
        fd = os.open(_lock_path(tmp), os.O_RDWR)
    except FileNotFoundError:  # no lock file (its owner finished or failed): ask the pid
        try:
            pid = int(tmp.name.split(".tmp-", 1)[1].split("-")[0])
            os.kill(pid, 0)
        except (ValueError, IndexError, ProcessLookupError):
            return False
        except PermissionError:
            return True
        return True
    try:
        fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
    except BlockingIOError:
        return True
    finally:
        os.close(fd)
    return False


def clean_stale_temps(directory: str | Path, name: str = "*") -> list[Path]:
    """Remove what killed runs left in ``directory`` (``SIGKILL`` skips every cleanup): temp
    directories ``.NAME.tmp-*`` whose writer is gone (:func:`_owner_alive`), their lock files,
    and half-deleted ``.NAME.trash-*`` trees, of the world ``name`` (default: every world: the
    cache's own directory). Cheap (one ``glob``); run on every use of the cache. Returns the
    removed paths."""
    directory = Path(directory)
    removed: list[Path] = []
    if not directory.is_dir():
        return removed
    for path in directory.glob(f".{name}.tmp-*"):
        if path.name.endswith(".lock"):
            if not path.with_name(path.name.removesuffix(".lock")).exists():
                tmp = path.with_name(path.name.removesuffix(".lock"))
                if not _owner_alive(tmp):
                    path.unlink(missing_ok=True)
                    removed.append(path)
            continue
        if _owner_alive(path):
            continue
        if path.is_dir():
            remove_tree(path)
            _lock_path(path).unlink(missing_ok=True)
        else:  # a write probe of a killed process
            path.unlink(missing_ok=True)
        removed.append(path)
    for path in directory.glob(f".{name}.trash-*"):
        shutil.rmtree(path, ignore_errors=True)
        removed.append(path)
    return removed


def _file_table(root: Path) -> dict[str, dict]:
    """``{relative path: {"bytes", "sha256"}}`` of every file under ``root`` (the manifest's
    record of what a complete world holds)."""
    table = {}
    for path in sorted(p for p in root.rglob("*") if p.is_file()):
        rel = path.relative_to(root).as_posix()
        if rel in (MANIFEST, "preview.png"):
            continue
        table[rel] = {"bytes": path.stat().st_size, "sha256": _sha256(path)}
    return table


def _sha256(path: Path) -> str:
    h = hashlib.sha256()
    with open(path, "rb") as f:
        for block in iter(lambda: f.read(1 << 20), b""):
            h.update(block)
    return h.hexdigest()


def verify_world(root: str | Path, *, digests: bool = True) -> list[str]:
    """Check a world directory against its manifest; returns the problems (empty: intact).

    Every file the manifest lists must exist with its size; with ``digests`` also with its
    SHA-256 (reads every byte: about a second per GB). The size check alone is a ``stat`` per
    file (milliseconds for the ``default`` world), so :func:`ensure_world` runs it on every use
    and regenerates a world that fails it; ``pointtrack generate --verify DIR`` runs both."""
    root = Path(root)
    manifest = _read_manifest(root)
    if manifest is None:
        return [f"{root}: no readable {MANIFEST} (not a generated world, or an incomplete one)"]
    files = manifest.get("files")
    if not isinstance(files, dict):
        return [
            f"{root / MANIFEST}: no file list (written by a generator older than the "
            "integrity check); regenerate the world"
        ]
    problems = []
    for rel, entry in files.items():
        path = root / rel
        try:
            size = path.stat().st_size
        except OSError:
            problems.append(f"{path}: missing")
            continue
        if size != entry["bytes"]:
            problems.append(f"{path}: {size} bytes, the manifest says {entry['bytes']}")
        elif digests and _sha256(path) != entry["sha256"]:
            problems.append(f"{path}: SHA-256 differs from the manifest's")
    return problems


def remove_tree(path: Path) -> None:
    if path.exists():
        # Rename first so a half-deleted tree never sits under a name someone may read.
        trash = path.parent / f".{path.name}.trash-{uuid.uuid4().hex[:8]}"
        try:
            os.rename(path, trash)
        except OSError:
            trash = path
        shutil.rmtree(trash, ignore_errors=True)


def ensure_world(
    preset: str = "small",
    sensor: str = "hdl64",
    seed: int = 0,
    labels_dir: str | Path | None = None,
    cache_dir: str | Path | None = None,
    *,
    progress: bool | None = None,
) -> Path:
    """The root of the world ``(preset, sensor, seed[, labels_dir])``, generated into the cache
    on first use and reused afterwards.

    The cache directory is ``cache_dir``, else ``$POINTTRACK_CACHE``, else the user cache dir of
    ``pointtrack`` (``platformdirs``). Each world lives in ``<cache>/worlds/<preset>-<sensor>-
    s<seed>-<hash>``; the hash covers the manifest identity (generator version, config, label
    digest), so a changed generator or config never reuses an old directory.
    """
    ident = world_identity(preset, sensor, seed, labels_dir)
    digest = hashlib.sha256(json.dumps(ident, sort_keys=True).encode()).hexdigest()[:12]
    base = Path(cache_dir) if cache_dir is not None else default_cache_dir()
    tag = "" if labels_dir is None else "replay-"
    out = base / "worlds" / f"{tag}{preset}-{sensor}-s{int(seed)}-{digest}"
    clean_stale_temps(out.parent)
    if manifest_matches(out, ident):
        problems = verify_world(out, digests=False)
        if not problems:
            return out
        warnings.warn(
            f"cached world {out} is damaged ({problems[0]}"
            + (f" and {len(problems) - 1} more" if len(problems) > 1 else "")
            + "); regenerating it",
            stacklevel=2,
        )
    _check_cache_writable(base)
    return generate_world(out, preset, sensor, seed, labels_dir, progress=progress, overwrite=True)


def _check_cache_writable(base: Path) -> None:
    """A one-line ``OSError`` naming the cache and ``$POINTTRACK_CACHE`` when worlds cannot be
    written there."""
    worlds = base / "worlds"
    try:
        worlds.mkdir(parents=True, exist_ok=True)
        probe = worlds / f".write-test.tmp-{os.getpid()}"
        probe.write_bytes(b"")
        probe.unlink()
    except OSError as exc:
        raise OSError(
            f"cannot write synthetic worlds to the cache {worlds} ({exc.strerror or exc}); set "
            "POINTTRACK_CACHE to a writable directory"
        ) from None
