"""Agent motion for the synthetic scenes: speed profiles, lane paths (with turns into the cross
street), lateral drift and pedestrian walks, as per-frame poses ``(T, 3)`` (x, y, yaw; metres,
radians) at :data:`envs.synthetic.scene_types.DT` seconds per frame.
"""

from __future__ import annotations

import math

import numpy as np

from envs.synthetic.scene_types import DT

__all__ = ["cumdist", "drift", "lane_path", "polyline_walk", "speed_profile", "walk"]


def speed_profile(
    rng: np.random.Generator, n: int, v_mean: float, stop_prob: float, accel: float = 2.0
) -> np.ndarray:
    """``(n,)`` speeds (m/s) at 10 Hz: piecewise targets every 2–6 s (sometimes a stop), tracked
    with a bounded acceleration so speed changes look like driving."""
    v = np.empty(n)
    cur = v_mean * rng.uniform(0.7, 1.15)
    target = cur
    next_change = int(rng.integers(20, 60))
    for t in range(n):
        if t == next_change:
            target = 0.0 if rng.random() < stop_prob else v_mean * rng.uniform(0.5, 1.2)
            next_change += int(rng.integers(20, 60))
        cur += float(np.clip(target - cur, -accel * DT, accel * DT))
        v[t] = max(cur, 0.0)
    return v


def cumdist(v: np.ndarray) -> np.ndarray:
    """Distance travelled at each frame (0 at frame 0) from speeds ``(T,)``."""
    return np.concatenate([[0.0], np.cumsum(v[:-1] * DT)])


def lane_path(
    s: np.ndarray, x0: float, y0: float, direction: float, turn: tuple[float, float] | None
) -> np.ndarray:
    """``(T, 3)`` poses along a lane at arc lengths ``s`` from ``(x0, y0)``; ``direction`` is +1
    (towards +x) or -1. ``turn = (x_t, r)``: a right turn of radius ``r`` that ends heading along
    the cross street in the lane at ``x = x_t`` (given for direction +1 in the +x frame)."""
    # Work in the frame where the lane runs towards +x, then map back.
    xs = x0 * direction
    ys = y0 * direction
    pos = np.empty((len(s), 3))
    if turn is None:
        pos[:, 0] = xs + s
        pos[:, 1] = ys
        pos[:, 2] = 0.0
    else:
        x_t, r = turn
        s1 = (x_t - r) - xs  # arc starts here
        s2 = s1 + 0.5 * math.pi * r
        straight = s <= s1
        arc = (s > s1) & (s <= s2)
        after = s > s2
        pos[straight, 0] = xs + s[straight]
        pos[straight, 1] = ys
        pos[straight, 2] = 0.0
        phi = (s[arc] - s1) / r
        pos[arc, 0] = x_t - r + r * np.sin(phi)
        pos[arc, 1] = ys - r + r * np.cos(phi)
        pos[arc, 2] = -phi
        pos[after, 0] = x_t
        pos[after, 1] = ys - r - (s[after] - s2)
        pos[after, 2] = -0.5 * math.pi
    if direction < 0:
        pos[:, 0] = -pos[:, 0]
        pos[:, 1] = -pos[:, 1]
        pos[:, 2] = pos[:, 2] + math.pi
    pos[:, 2] = (pos[:, 2] + math.pi) % (2 * math.pi) - math.pi
    return pos


def drift(rng: np.random.Generator, n: int) -> np.ndarray:
    """``(n,)`` a slow sinusoidal speed offset (m/s): +-1 to 2.5 m/s over 8–20 s, i.e. a few
    metres of relative back-and-forth motion."""
    period = rng.uniform(8.0, 20.0) / DT
    amp = rng.uniform(1.0, 2.5)
    return amp * np.sin(2 * np.pi * np.arange(n) / period + rng.uniform(0, 2 * np.pi))


def polyline_walk(
    rng: np.random.Generator, n: int, points: np.ndarray, speed: float, pause_at: int
) -> tuple[np.ndarray, np.ndarray]:
    """Walk along the waypoints ``points (K, 2)`` at ``speed`` m/s, pausing 1–3 s on reaching
    waypoint ``pause_at`` (waiting at the kerb), standing still at the end. Returns poses
    ``(n, 3)`` (heading along the current segment) and speeds ``(n,)``."""
    seg = np.diff(points, axis=0)
    cum = np.concatenate([[0.0], np.cumsum(np.hypot(seg[:, 0], seg[:, 1]))])
    s_pause = cum[pause_at]
    pause = int(rng.integers(10, 30))
    s = np.empty(n)
    v = np.empty(n)
    cur, waited = 0.0, 0
    for t in range(n):
        s[t] = cur
        if cur >= s_pause and waited < pause:
            waited += 1
            v[t] = 0.0
        else:
            v[t] = speed if cur < cum[-1] else 0.0
        cur = min(cur + v[t] * DT, cum[-1])
        if cur > s_pause and waited == 0 and s[t] < s_pause:
            cur = s_pause  # stop exactly at the kerb
    k = np.clip(np.searchsorted(cum, s, side="right") - 1, 0, len(seg) - 1)
    pose = np.empty((n, 3))
    pose[:, 0] = np.interp(s, cum, points[:, 0])
    pose[:, 1] = np.interp(s, cum, points[:, 1])
    pose[:, 2] = np.arctan2(seg[k, 1], seg[k, 0])
    return pose, v


def walk(
    rng: np.random.Generator,
    n: int,
    x0: float,
    y0: float,
    heading: float,
    y_lo: float,
    y_hi: float,
    speed: float,
    heading_noise: float = 0.02,
) -> tuple[np.ndarray, np.ndarray]:
    """A pedestrian walking in the strip ``y_lo <= y <= y_hi``: smooth heading wander (noise
    ``heading_noise`` rad a frame), pauses and occasional turn-arounds. Returns poses ``(n, 3)``
    and speeds ``(n,)``."""
    pose = np.empty((n, 3))
    v = np.empty(n)
    x, y, th = x0, y0, heading
    base = heading
    cur_v = speed
    paused = 0
    dth = 0.0
    for t in range(n):
        if paused > 0:
            paused -= 1
            cur_v = max(cur_v - 1.5 * DT * 4, 0.0)
        else:
            if rng.random() < 0.01:
                paused = int(rng.integers(10, 40))
            if rng.random() < 0.004:
                base = base + math.pi
            cur_v = min(cur_v + 1.0 * DT * 4, speed)
        dth = 0.9 * dth + rng.normal(0.0, heading_noise)
        th = th + dth + 0.08 * math.sin(base - th)
        # Stay inside the walking strip: steer back along the street near its edges.
        if (y <= y_lo and math.sin(th) < 0) or (y >= y_hi and math.sin(th) > 0):
            th = math.atan2(-0.3 * math.sin(th), math.cos(th))
        x += cur_v * DT * math.cos(th)
        y = min(max(y + cur_v * DT * math.sin(th), y_lo), y_hi)
        pose[t] = (x, y, th)
        v[t] = cur_v
    pose[:, 2] = (pose[:, 2] + math.pi) % (2 * math.pi) - math.pi
    return pose, v
