"""Speed of the synthetic LiDAR world.

    python benchmarks/bench_synthetic.py [--quick] [--full]

Prints: ms per frame for ``hdl64`` and ``hdl32`` on a street scene with 40 agents (plus its
buildings, sidewalks, trees and poles), the ``tiny`` preset end to end, and with ``--full`` the
``default`` preset's time and size. Wall-clock and process CPU time are both shown: on a shared
machine the CPU time is the steadier number.
"""

from __future__ import annotations

import argparse
import statistics
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from envs.synthetic import generate_world, get_sensor  # noqa: E402
from envs.synthetic.scene import SceneConfig, agent_boxes_world, build_scene, render_frame  # noqa: E402


def scene_with(n_agents: int, n_frames: int):
    """Scene 0 (seed 0) keeping the ``n_agents`` agents nearest to the ego at mid-scene."""
    scene = build_scene(0, 0, SceneConfig(n_frames=n_frames, density=1.5))
    mid = n_frames // 2
    boxes = agent_boxes_world(scene, mid)
    d = np.hypot(boxes[:, 0] - scene.ego[mid, 0], boxes[:, 1] - scene.ego[mid, 1])
    keep = np.argsort(d)[:n_agents]
    scene.agents = [scene.agents[i] for i in sorted(keep)]
    return scene


def bench_frames(sensor_name: str, n_frames: int, n_agents: int = 40) -> dict:
    sensor = get_sensor(sensor_name)
    sensor.ray_directions()
    scene = scene_with(n_agents, n_frames)
    render_frame(scene, 0, sensor, np.random.default_rng(0))  # warm-up
    wall, cpu, points = [], [], []
    for t in range(n_frames):
        w0, c0 = time.perf_counter(), time.process_time()
        fr = render_frame(scene, t, sensor, np.random.default_rng(t))
        wall.append(time.perf_counter() - w0)
        cpu.append(time.process_time() - c0)
        points.append(len(fr.points))
    return {
        "sensor": sensor_name,
        "rays": sensor.n_rays,
        "agents": len(scene.agents),
        "static": len(scene.static_bounds),
        "wall_ms": 1000 * statistics.median(wall),
        "cpu_ms": 1000 * statistics.median(cpu),
        "points": int(statistics.median(points)),
    }


def bench_preset(preset: str) -> dict:
    with tempfile.TemporaryDirectory() as tmp:
        w0, c0 = time.perf_counter(), time.process_time()
        root = generate_world(Path(tmp) / "w", preset, "hdl64", 0, progress=False)
        wall, cpu = time.perf_counter() - w0, time.process_time() - c0
        files = [p for p in root.rglob("*") if p.is_file()]
        size = sum(p.stat().st_size for p in files)
        frames = len([p for p in files if p.suffix == ".bin"])
    return {"preset": preset, "wall_s": wall, "cpu_s": cpu, "frames": frames, "bytes": size}


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--quick", action="store_true", help="fewer frames")
    parser.add_argument("--full", action="store_true", help="also time the default preset")
    args = parser.parse_args(argv)
    n = 5 if args.quick else 20
    for name in ("hdl64", "hdl32"):
        r = bench_frames(name, n)
        print(
            f"synthetic frame {r['sensor']}: {r['wall_ms']:.1f} ms wall, {r['cpu_ms']:.1f} ms cpu "
            f"({r['rays']} rays, {r['agents']} agents + {r['static']} static objects, "
            f"{r['points']} points; median of {n} frames)"
        )
    presets = ["tiny"] + (["default"] if args.full else [])
    for preset in presets:
        r = bench_preset(preset)
        print(
            f"synthetic preset {r['preset']}: {r['wall_s']:.1f} s wall, {r['cpu_s']:.1f} s cpu, "
            f"{r['frames']} frames, {r['bytes'] / 1e6:.0f} MB"
        )
    return 0


if __name__ == "__main__":
    sys.exit(main())
