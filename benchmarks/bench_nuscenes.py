"""Benchmark the nuScenes layout: writing the synthetic world in nuScenes layout, and building
tracklets with ``envs.data.NuScenesTracking`` (tables only; scans are read lazily).

Usage::

    python benchmarks/bench_nuscenes.py [--preset default] [--out DIR] [--scaled F]

1. Generates the ``--preset`` world (sensor hdl32, seed 0) into ``--out`` (a fresh temporary
   folder by default; an existing identical world is reused and its generation not timed) and
   prints the simulated frames (10 Hz) and key frames per second and the size on disk.
2. Times ``NuScenesTracking(root, version, "all")`` (every mapped category, best of 3) and
   extrapolates per annotation to v1.0-trainval's 1,166,187 annotations.
3. With ``--scaled F``: writes tables with F times the record counts of v1.0-trainval (850
   scenes, 34,149 samples, 2,631,083 sample_data, 1,166,187 annotations, 64,386 instances; no
   scans) and times the reader on them, since real sample_data / ego_pose tables are much larger
   per annotation than the synthetic world's (they list every camera, radar and sweep).
"""

from __future__ import annotations

import argparse
import json
import tempfile
import time
from pathlib import Path

import numpy as np

from envs.data.nuscenes import NuScenesTracking

TRAINVAL = {
    "scenes": 850,
    "samples": 34_149,
    "sample_data": 2_631_083,
    "annotations": 1_166_187,
    "instances": 64_386,
}


def best_of(fn, repeats: int = 3, clock=time.perf_counter) -> float:
    """Best of ``repeats`` runs of ``fn`` on ``clock`` (wall by default; ``time.process_time``
    gives this process's CPU seconds, which a machine shared with other jobs inflates less)."""
    times = []
    for _ in range(repeats):
        start = clock()
        fn()
        times.append(clock() - start)
    return min(times)


def bench_world(preset: str, out: Path | None) -> None:
    from envs.synthetic.nuscenes_layout import DEFAULT_VERSION, generate_nuscenes_world

    tmp = None
    if out is None:
        tmp = tempfile.TemporaryDirectory(prefix="bench-nuscenes-")
        out = Path(tmp.name) / "world"
    fresh = not (out / "manifest.json").is_file()
    start = time.perf_counter()
    root = generate_nuscenes_world(out, preset, "hdl32", 0, progress=False)
    elapsed = time.perf_counter() - start
    manifest = json.loads((root / "manifest.json").read_text())
    stats = manifest["scene_stats"].values()
    frames = sum(s["frames"] for s in stats)
    keys = sum(s["key_frames"] for s in stats)
    n_ann = sum(s["annotations"] for s in stats)
    size = sum(p.stat().st_size for p in root.rglob("*") if p.is_file())
    print(
        f"world {preset}/hdl32: {len(manifest['scene_stats'])} scenes, {frames} frames at 10 Hz, "
        f"{keys} key frames, {n_ann} annotations, {size / 1e6:.1f} MB on disk"
    )
    if fresh:
        print(
            f"generation: {elapsed:.1f} s = {frames / elapsed:.1f} simulated frames/s "
            f"({keys / elapsed:.1f} key frames rendered and written per s)"
        )
    load = best_of(lambda: NuScenesTracking(root, DEFAULT_VERSION, "all"))
    cpu = best_of(lambda: NuScenesTracking(root, DEFAULT_VERSION, "all"), clock=time.process_time)
    data = NuScenesTracking(root, DEFAULT_VERSION, "all")
    per, per_cpu = load / n_ann, cpu / n_ann
    print(
        f"NuScenesTracking(all): {len(data)} tracklets in {load * 1e3:.0f} ms wall, "
        f"{cpu * 1e3:.0f} ms CPU = {per * 1e6:.1f} / {per_cpu * 1e6:.1f} us per annotation -> "
        f"{per * TRAINVAL['annotations']:.0f} s wall / {per_cpu * TRAINVAL['annotations']:.0f} s"
        f" CPU for v1.0-trainval's {TRAINVAL['annotations']:,} annotations (per-annotation "
        "extrapolation)"
    )
    scan = best_of(lambda: [data.tracklets[0].scans.loader(i) for i in range(5)])
    print(f"reading a key-frame scan: {scan / 5 * 1e3:.1f} ms")
    if tmp is not None:
        tmp.cleanup()


def write_scaled_tables(root: Path, factor: float, seed: int = 0) -> int:
    """Tables with ``factor`` times the v1.0-trainval record counts (random poses and boxes,
    one LIDAR_TOP key frame per sample, the other sample_data non-key frames); returns the
    number of annotations."""
    rng = np.random.default_rng(seed)
    n = {k: max(1, int(round(v * factor))) for k, v in TRAINVAL.items()}
    tok = (f"{i:032x}" for i in range(1, 10**9))
    d = root / "v1.0-trainval"
    d.mkdir(parents=True)
    cats = [
        {"token": next(tok), "name": name, "description": ""}
        for name in (
            "vehicle.car",
            "human.pedestrian.adult",
            "vehicle.truck",
            "vehicle.bicycle",
            "movable_object.barrier",
        )
    ]
    lidar = {"token": next(tok), "channel": "LIDAR_TOP", "modality": "lidar"}
    cam = {"token": next(tok), "channel": "CAM_FRONT", "modality": "camera"}
    cs = [
        {
            "token": next(tok),
            "sensor_token": s["token"],
            "translation": [0.9, 0.0, 1.8],
            "rotation": [0.7071, 0.0, 0.0, -0.7071],
            "camera_intrinsic": [],
        }
        for s in (lidar, cam)
    ]
    log = {"token": next(tok), "logfile": "", "vehicle": "", "date_captured": "", "location": ""}
    scene_of_sample = np.sort(rng.integers(0, n["scenes"], n["samples"]))
    samples = [
        {"token": next(tok), "timestamp": int(i), "scene_token": ""} for i in range(n["samples"])
    ]
    scenes = []
    for s in range(n["scenes"]):
        idx = np.flatnonzero(scene_of_sample == s)
        rec = {
            "token": next(tok),
            "log_token": log["token"],
            "name": f"scene-{s + 1:04d}",
            "description": "",
            "nbr_samples": len(idx),
            "first_sample_token": samples[idx[0]]["token"] if len(idx) else "",
            "last_sample_token": samples[idx[-1]]["token"] if len(idx) else "",
        }
        for j, i in enumerate(idx):
            samples[i]["scene_token"] = rec["token"]
            samples[i]["prev"] = samples[idx[j - 1]]["token"] if j else ""
            samples[i]["next"] = samples[idx[j + 1]]["token"] if j + 1 < len(idx) else ""
        scenes.append(rec)
    sds, poses = [], []
    for i in range(n["sample_data"]):
        k = i % n["samples"]
        key = i < n["samples"]
        pose = {
            "token": next(tok),
            "timestamp": i,
            "translation": rng.normal(size=3).tolist(),
            "rotation": (rng.normal(size=4)).tolist(),
        }
        poses.append(pose)
        sds.append(
            {
                "token": pose["token"],
                "sample_token": samples[k]["token"],
                "ego_pose_token": pose["token"],
                "calibrated_sensor_token": cs[0 if key else 1]["token"],
                "is_key_frame": key,
                "filename": f"samples/LIDAR_TOP/{i}.pcd.bin",
                "fileformat": "pcd",
                "timestamp": i,
                "prev": "",
                "next": "",
            }
        )
    inst = [
        {"token": next(tok), "category_token": cats[i % len(cats)]["token"]}
        for i in range(n["instances"])
    ]
    anns = []
    for i in range(n["annotations"]):
        anns.append(
            {
                "token": next(tok),
                "sample_token": samples[i % n["samples"]]["token"],
                "instance_token": inst[(i // n["samples"] + i) % n["instances"]]["token"],
                "translation": rng.normal(size=3).tolist(),
                "size": [1.8, 4.5, 1.6],
                "rotation": rng.normal(size=4).tolist(),
                "prev": "",
                "next": "",
                "num_lidar_pts": 1,
                "num_radar_pts": 0,
                "attribute_tokens": [],
                "visibility_token": "4",
            }
        )
    tables = {
        "category": cats,
        "sensor": [lidar, cam],
        "calibrated_sensor": cs,
        "log": [log],
        "scene": scenes,
        "sample": samples,
        "sample_data": sds,
        "ego_pose": poses,
        "instance": inst,
        "sample_annotation": anns,
    }
    for name, records in tables.items():
        (d / f"{name}.json").write_text(json.dumps(records))
    return n["annotations"]


def bench_scaled(factor: float) -> None:
    with tempfile.TemporaryDirectory(prefix="bench-nuscenes-scaled-") as tmp:
        n_ann = write_scaled_tables(Path(tmp), factor)
        size = sum(p.stat().st_size for p in Path(tmp).rglob("*.json"))
        # Random instance/sample pairs may repeat an instance in a sample: keep it a timing run.
        try:
            load = best_of(lambda: NuScenesTracking(tmp, "v1.0-trainval", "all"), repeats=2)
        except ValueError as exc:
            raise SystemExit(f"scaled tables invalid: {exc}") from exc
        cpu = best_of(
            lambda: NuScenesTracking(tmp, "v1.0-trainval", "all"),
            repeats=2,
            clock=time.process_time,
        )
        start = time.process_time()
        for path in Path(tmp, "v1.0-trainval").glob("*.json"):
            json.loads(path.read_text())
        parse = time.process_time() - start
        print(
            f"scaled tables ({factor:g} x v1.0-trainval counts, {size / 1e6:.0f} MB of JSON, "
            f"{n_ann:,} annotations): {load:.2f} s wall, {cpu:.2f} s CPU of which "
            f"{parse:.2f} s is json.loads alone -> {load / factor:.0f} s wall / "
            f"{cpu / factor:.0f} s CPU at full size (linear)"
        )


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--preset", default="default")
    parser.add_argument("--out", type=Path, default=None)
    parser.add_argument("--scaled", type=float, default=None, metavar="F")
    args = parser.parse_args()
    bench_world(args.preset, args.out)
    if args.scaled:
        bench_scaled(args.scaled)


if __name__ == "__main__":
    main()
