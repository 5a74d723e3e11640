"""The README picture: one frame clean and under fog, rain and snow at levels 1, 3 and 5.

    python -m envs.weather.figure [docs/weather_levels.png] [--seed 0]

Uses a frame of the synthetic ``tiny`` world when :func:`envs.synthetic.ensure_world` is
available, else a small ray-cast street (ground, walls, parked cars) of our own.
"""

from __future__ import annotations

import argparse
import math
from pathlib import Path

import numpy as np

from envs.data import KittiTracking
from envs.plotting import pyplot, save_figure
from envs.synthetic import ensure_world
from envs.weather.fog import fog_alpha
from envs.weather.levels import KINDS, describe, parameter
from envs.weather.precipitation import precipitation_rate
from envs.weather.wrapper import WeatherTransform


def street_scan(seed: int = 0, beams: int = 64, columns: int = 1800) -> tuple[np.ndarray, list]:
    """A ray-cast street: ground at -1.73 m, building walls at |y| = 12 m, parked cars. Returns
    ``(scan (N, 4) float32, car boxes [(7,)])``."""
    rng = np.random.default_rng(seed)
    el = np.radians(np.linspace(-24.9, 2.0, beams))
    az = np.linspace(-math.pi, math.pi, columns, endpoint=False)
    e, a = np.meshgrid(el, az, indexing="ij")
    d = np.stack([np.cos(e) * np.cos(a), np.cos(e) * np.sin(a), np.sin(e)], -1).reshape(-1, 3)
    n = len(d)
    t = np.full(n, np.inf)
    refl = np.zeros(n)
    with np.errstate(divide="ignore", invalid="ignore"):
        tg = np.where(d[:, 2] < 0, -1.73 / d[:, 2], np.inf)
        t, refl = np.where(tg < t, tg, t), np.where(tg < t, 0.25, refl)
        for side in (-12.0, 12.0):
            tw = np.where(d[:, 1] * side > 0, side / d[:, 1], np.inf)
            z = tw * d[:, 2]
            tw = np.where(z < 8.0, tw, np.inf)
            t, refl = np.where(tw < t, tw, t), np.where(tw < t, 0.45, refl)
    boxes = []
    for x in (-30, -16, 9, 22, 38, 55, 70):
        for y in (-6.5, 6.5):
            if rng.random() < 0.6:
                boxes.append(np.array([x + rng.uniform(-2, 2), y, -0.95, 4.2, 1.8, 1.55, 0.0]))
    boxes.append(np.array([14.0, -2.0, -0.95, 4.4, 1.9, 1.6, 0.05]))  # the target, on the road
    for b in boxes:
        lo, hi = b[:3] - b[3:6] / 2, b[:3] + b[3:6] / 2
        with np.errstate(divide="ignore", invalid="ignore"):
            t0, t1 = lo / d, hi / d
        tmin = np.nanmax(np.minimum(t0, t1), axis=1)
        tmax = np.nanmin(np.maximum(t0, t1), axis=1)
        hit = (tmax >= tmin) & (tmin > 0)
        tb = np.where(hit, tmin, np.inf)
        r = rng.uniform(0.1, 0.7)
        t, refl = np.where(tb < t, tb, t), np.where(tb < t, r, refl)
    ok = t <= 120.0
    t = t[ok] + rng.normal(0, 0.01, ok.sum())
    pts = d[ok] * t[:, None]
    inten = np.clip(refl[ok] * (1 - 0.3 * t / 120) + rng.normal(0, 0.02, ok.sum()), 0, 1)
    return np.column_stack([pts, inten]).astype(np.float32), boxes[-1:]


def synthetic_frame(seed: int = 0):
    """A frame of the synthetic ``tiny`` world with a target box, or ``None`` if unavailable."""
    try:
        root = ensure_world("tiny", seed=seed)
        ds = KittiTracking(root, "all", ("Car",))
        tr = max(ds.tracklets, key=len)
        t = len(tr) // 2
        return np.asarray(tr.points_with_intensity(t), np.float32), [tr.boxes[t]], tr, t
    except Exception:  # noqa: BLE001 - any failure means "use the fallback street"
        return None


def _corrupt_with_source(kind, level, scan, rng):
    p = parameter(kind, level)
    if kind == "fog":
        return fog_alpha(scan[:, :3], scan[:, 3], rng, p, return_source=True)
    return precipitation_rate(scan[:, :3], scan[:, 3], rng, kind, p, return_source=True)


def levels_figure(
    scan: np.ndarray,
    path: str | Path,
    boxes=(),
    scene: str = "0000",
    frame: int = 0,
    seed: int = 0,
    extent_m: float = 50.0,
) -> Path:
    """Draw ``scan`` clean and under each kind at levels 1, 3, 5 (bird's eye) into one PNG:
    surviving returns grey, returns moved toward the sensor (fog / particle scatter) red, lost
    returns (at their clean position) orange. The generator is the one
    :class:`WeatherTransform` uses for this scene and frame, so the panels show exactly what the
    env serves."""
    plt = pyplot()

    levels = (1, 3, 5)
    r_in = np.linalg.norm(scan[:, :3], axis=1)
    fig, axes = plt.subplots(len(KINDS), 1 + len(levels), figsize=(13, 9.8))

    def draw(ax, pts, color, size):
        sel = (np.abs(pts[:, 0]) < extent_m) & (np.abs(pts[:, 1]) < extent_m)
        ax.scatter(pts[sel, 0], pts[sel, 1], c=color, s=size, linewidths=0, rasterized=True)

    for i, kind in enumerate(KINDS):
        for j, level in enumerate((0,) + levels):
            ax = axes[i][j]
            if level == 0:
                draw(ax, scan, "0.35", 0.05)
                title = f"clean ({len(scan):,} points)"
            else:
                rng = WeatherTransform(kind, level, seed=seed).rng(scene, frame)
                out, _, src = _corrupt_with_source(kind, level, scan, rng)
                moved = np.linalg.norm(out, axis=1) < r_in[src] - 0.3
                lost = np.ones(len(scan), dtype=bool)
                lost[src] = False
                draw(ax, out[~moved], "0.35", 0.05)
                draw(ax, scan[lost, :3], "tab:orange", 0.6)
                draw(ax, out[moved], "red", 1.5)
                title = (
                    f"{describe(kind, level)}\nlost {lost.sum():,}, moved closer {moved.sum():,}"
                )
            for b in boxes:
                c, s = math.cos(b[6]), math.sin(b[6])
                hl, hw = b[3] / 2, b[4] / 2
                corners = np.array([[hl, hw], [hl, -hw], [-hl, -hw], [-hl, hw], [hl, hw]])
                xy = corners @ np.array([[c, s], [-s, c]]) + b[:2]
                ax.plot(xy[:, 0], xy[:, 1], "b-", lw=0.8)
            ax.plot(0, 0, "k^", ms=3)
            ax.set_xlim(-extent_m, extent_m)
            ax.set_ylim(-extent_m, extent_m)
            ax.set_aspect("equal")
            ax.set_xticks([])
            ax.set_yticks([])
            ax.set_title(title, fontsize=8)
    fig.suptitle(
        f"one frame, bird's eye (±{extent_m:g} m): grey = returns kept, red = moved "
        "toward the sensor (fog / rain / snow scatter), orange = lost; blue = target box",
        fontsize=9,
    )
    fig.tight_layout()
    return save_figure(fig, path, 80)


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("out", nargs="?", default="docs/weather_levels.png")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--street", action="store_true", help="use the built-in street scene")
    args = parser.parse_args(argv)
    found = None if args.street else synthetic_frame(args.seed)
    if found is not None:
        scan, boxes, tr, t = found
        path = levels_figure(scan, args.out, boxes, tr.scene, int(tr.frames[t]), args.seed)
        print(f"{path}: synthetic tiny world, tracklet {tr.tracklet_id}, frame {int(tr.frames[t])}")
    else:
        scan, boxes = street_scan(args.seed)
        path = levels_figure(scan, args.out, boxes, seed=args.seed)
        print(f"{path}: built-in street scene ({len(scan):,} points)")
    print(f"{path.stat().st_size / 1024:.0f} KB")


if __name__ == "__main__":
    main()
