"""Target motion statistics of KITTI-layout label files (real or synthetic).

Everything is ego-relative: KITTI tracking labels give boxes in each frame's camera frame and no
ego motion, so a parked car passed by the ego car moves here, and a car driving alongside stands
still. That is what a tracker sees, and what the synthetic world has to match.

Per category, over all pairs of consecutive labelled frames of a track (frame gap 1, 10 Hz):

- ``displacement_m``: the bottom centre's horizontal displacement (camera x / z), metres a frame;
- ``acceleration_mps2``: the norm of the second difference of the horizontal centre over three
  consecutive frames, divided by ``dt**2`` (m/s^2);
- ``yaw_rate_radps``: the wrapped difference of ``rotation_y``, divided by ``dt`` (rad/s);
- the share of still pairs: displacement below ``still_m``.
"""

from __future__ import annotations

from collections.abc import Iterable, Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from envs.data.kitti import read_labels

FRAME_DT_S = 0.1  # KITTI's 10 Hz
STILL_M = 0.05  # below this a frame-to-frame displacement counts as still
CATEGORIES = ("Car", "Van", "Pedestrian", "Cyclist")
MEASURES = ("displacement_m", "acceleration_mps2", "yaw_rate_radps")


@dataclass(frozen=True)
class CategoryMotion:
    """The pooled per-pair samples of one category (each array 1-D, any length)."""

    category: str
    displacement_m: np.ndarray
    acceleration_mps2: np.ndarray
    yaw_rate_radps: np.ndarray
    tracks: int

    def still_share(self, still_m: float = STILL_M) -> float:
        """Fraction of frame pairs whose displacement is below ``still_m`` (nan if none)."""
        d = self.displacement_m
        return float(np.mean(d < still_m)) if d.size else float("nan")

    def summary(self) -> dict[str, float]:
        """Median and 90th percentile of each measure, the still share and the counts."""
        out: dict[str, float] = {
            "tracks": float(self.tracks),
            "pairs": float(self.displacement_m.size),
        }
        for name in MEASURES:
            values = np.abs(getattr(self, name))
            out[f"{name}_median"] = float(np.median(values)) if values.size else float("nan")
            out[f"{name}_p90"] = float(np.percentile(values, 90)) if values.size else float("nan")
        out["still_share"] = self.still_share()
        return out


def _wrap(angle: np.ndarray) -> np.ndarray:
    return (angle + np.pi) % (2 * np.pi) - np.pi


def track_samples(frames: np.ndarray, xz: np.ndarray, yaw: np.ndarray) -> tuple[np.ndarray, ...]:
    """Samples of one track: ``frames (T,)`` int, ``xz (T, 2)`` m, ``yaw (T,)`` rad, in frame
    order. Returns ``(displacement (P,), acceleration (Q,), yaw_rate (P,))`` over pairs (triples)
    of consecutive frames only."""
    step = np.diff(frames) == 1  # (T-1,)
    delta = np.diff(xz, axis=0)  # (T-1, 2)
    displacement = np.linalg.norm(delta, axis=1)[step]
    yaw_rate = _wrap(np.diff(yaw))[step] / FRAME_DT_S
    both = step[:-1] & step[1:]  # triples t, t+1, t+2 all consecutive
    accel = np.linalg.norm(np.diff(delta, axis=0), axis=1)[both] / FRAME_DT_S**2
    return displacement, accel, yaw_rate


def label_motion(
    label_files: Iterable[str | Path], categories: Sequence[str] = CATEGORIES
) -> dict[str, CategoryMotion]:
    """Per-category motion samples pooled over ``label_files`` (KITTI tracking label files;
    DontCare rows are ignored)."""
    pooled: dict[str, list[list[np.ndarray]]] = {c: [[], [], []] for c in categories}
    tracks = dict.fromkeys(categories, 0)
    for path in label_files:
        by_track: dict[tuple[str, int], list] = {}
        for row in read_labels(path):
            if row.type in pooled and row.track_id >= 0:
                by_track.setdefault((row.type, row.track_id), []).append(row)
        for (category, _), rows in sorted(by_track.items()):
            rows.sort(key=lambda r: r.frame)
            frames = np.array([r.frame for r in rows])
            xz = np.array([[r.x, r.z] for r in rows], dtype=np.float64)
            yaw = np.array([r.rotation_y for r in rows], dtype=np.float64)
            for bucket, samples in zip(
                pooled[category], track_samples(frames, xz, yaw), strict=True
            ):
                bucket.append(samples)
            tracks[category] += 1
    return {
        c: CategoryMotion(
            c,
            *(np.concatenate(b) if b else np.zeros(0) for b in pooled[c]),
            tracks=tracks[c],
        )
        for c in categories
    }


def wasserstein_1(a: np.ndarray, b: np.ndarray, quantiles: int = 201) -> float:
    """The 1-Wasserstein distance between two samples' distributions, by their quantile
    functions on an even grid (same units as the samples; nan if either is empty)."""
    if a.size == 0 or b.size == 0:
        return float("nan")
    q = np.linspace(0.0, 1.0, quantiles)
    return float(np.mean(np.abs(np.quantile(a, q) - np.quantile(b, q))))


def compare(
    real: dict[str, CategoryMotion], generated: dict[str, CategoryMotion]
) -> list[dict[str, float | str]]:
    """One row per category and measure: real and generated median / p90, their relative
    differences (generated / real - 1) and the 1-Wasserstein distance."""
    rows: list[dict[str, float | str]] = []
    for category in real:
        if category not in generated:
            continue
        for name in MEASURES:
            r = np.abs(getattr(real[category], name))
            g = np.abs(getattr(generated[category], name))
            row: dict[str, float | str] = {"category": category, "measure": name}
            for stat, fn in (("median", np.median), ("p90", lambda x: np.percentile(x, 90))):
                rv = float(fn(r)) if r.size else float("nan")
                gv = float(fn(g)) if g.size else float("nan")
                row[f"real_{stat}"], row[f"gen_{stat}"] = rv, gv
                row[f"rel_{stat}"] = gv / rv - 1.0 if rv > 1e-9 else float("nan")
            row["w1"] = wasserstein_1(r, g)
            rows.append(row)
        rows.append(
            {
                "category": category,
                "measure": "still_share",
                "real_median": real[category].still_share(),
                "gen_median": generated[category].still_share(),
            }
        )
    return rows
