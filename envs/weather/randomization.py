"""Domain randomisation of Algorithm 1 in Zhao et al. (adverse-weather SOT, DRCT), as a point-set
augmentation for training.

With probability ``p_skip = 0.5`` the set is returned unchanged; otherwise each of three steps is
applied independently with probability ``p_step = 0.5``:

1. **add noise points**: ``n ~ U{1..N_max}`` Gaussian points, drawn per axis from
   ``N(mean(P), std(P)^2)`` of the input set (so they land in the same region whatever frame the
   set is in: a whole scan, or a template / search crop in a box frame);
2. **drop points**: ``r ~ U{1..floor(max_drop * N)}`` points of the input removed at random;
3. **jitter**: every point moved by ``delta ~ U(-a, a)^3``.

``P' = (P ∪ P_noise \\ P_dropout) + delta``. The paper leaves ``N_max``, the number of removed
points and ``a`` open; our defaults: ``N_max = 10 %`` of the set, at most 30 % dropped,
``a = 0.02 m``. Extra columns (intensity) pass through; noise points copy the extra columns of
random input points. Vectorised, deterministic from the generator.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np


def domain_randomize(
    points: np.ndarray,
    rng: np.random.Generator,
    *,
    p_skip: float = 0.5,
    p_step: float = 0.5,
    max_noise_ratio: float = 0.1,
    max_drop_ratio: float = 0.3,
    jitter_m: float = 0.02,
    return_source: bool = False,
) -> np.ndarray | tuple[np.ndarray, np.ndarray]:
    """Algorithm 1 on a point set ``(N, C)`` (C >= 3, xyz first) -> ``(N', C)`` float32.

    With ``return_source`` also ``(N',)`` int64: the input index of each output point, ``-1``
    for an added noise point (so per-point labels can follow the points). The random stream is
    the same either way."""
    pts = np.asarray(points, dtype=np.float32)
    if pts.ndim != 2 or pts.shape[1] < 3:
        raise ValueError(f"points must be (N, C>=3); got shape {pts.shape}")
    for name, v in (
        ("p_skip", p_skip),
        ("p_step", p_step),
        ("max_noise_ratio", max_noise_ratio),
        ("max_drop_ratio", max_drop_ratio),
    ):
        if not 0.0 <= v <= 1.0:
            raise ValueError(f"{name} must be in [0, 1]; got {v}")
    if jitter_m < 0:
        raise ValueError(f"jitter_m must be >= 0; got {jitter_m}")
    # draw all decisions up front so the stream does not depend on the set's size
    u = rng.random(4)
    n = len(pts)
    if u[0] < p_skip or n == 0:
        return (pts.copy(), np.arange(n)) if return_source else pts.copy()
    keep = np.ones(n, dtype=bool)
    if u[2] < p_step:  # dropout (indices of the input set only)
        max_drop = int(max_drop_ratio * n)
        if max_drop >= 1:
            r = int(rng.integers(1, max_drop + 1))
            keep[rng.choice(n, size=r, replace=False)] = False
    parts = [pts[keep]]
    sources = [np.flatnonzero(keep)]
    if u[1] < p_step:  # Gaussian noise points
        n_max = max(1, int(max_noise_ratio * n))
        k = int(rng.integers(1, n_max + 1))
        mean = pts[:, :3].mean(axis=0)
        std = pts[:, :3].std(axis=0) + 1e-3
        noise = np.empty((k, pts.shape[1]), np.float32)
        noise[:, :3] = rng.normal(mean, std, size=(k, 3))
        if pts.shape[1] > 3:
            noise[:, 3:] = pts[rng.integers(0, n, size=k), 3:]
        parts.append(noise)
        sources.append(np.full(k, -1, dtype=np.int64))
    out = np.concatenate(parts) if len(parts) > 1 else parts[0].copy()
    if u[3] < p_step and jitter_m > 0:
        out[:, :3] += rng.uniform(-jitter_m, jitter_m, size=(len(out), 3)).astype(np.float32)
    return (out, np.concatenate(sources)) if return_source else out


@dataclass(frozen=True)
class DomainRandomization:
    """Picklable callable form of :func:`domain_randomize` for datasets / samplers:
    ``DomainRandomization(jitter_m=0.02)(points, rng)``."""

    p_skip: float = 0.5
    p_step: float = 0.5
    max_noise_ratio: float = 0.1
    max_drop_ratio: float = 0.3
    jitter_m: float = 0.02

    def __call__(self, points: np.ndarray, rng: np.random.Generator) -> np.ndarray:
        return domain_randomize(
            points,
            rng,
            p_skip=self.p_skip,
            p_step=self.p_step,
            max_noise_ratio=self.max_noise_ratio,
            max_drop_ratio=self.max_drop_ratio,
            jitter_m=self.jitter_m,
        )

    def randomize_with_source(
        self, points: np.ndarray, rng: np.random.Generator
    ) -> tuple[np.ndarray, np.ndarray]:
        """``(points (N', C), source (N',))``: :func:`domain_randomize` with
        ``return_source=True`` (``-1`` marks an added noise point)."""
        return domain_randomize(
            points,
            rng,
            p_skip=self.p_skip,
            p_step=self.p_step,
            max_noise_ratio=self.max_noise_ratio,
            max_drop_ratio=self.max_drop_ratio,
            jitter_m=self.jitter_m,
            return_source=True,
        )
