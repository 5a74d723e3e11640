"""Fog after Hahner, Sakaridis, Dai and Van Gool, *Fog Simulation on Real LiDAR Point Clouds for
3D Object Detection in Adverse Weather* (ICCV 2021) — our own vectorised implementation.

Physical model (the paper's linear-system LiDAR model with a sin^2 pulse):

- Transmitted pulse ``P_T(t) = P_0 sin^2(pi t / (2 tau_H))`` for ``0 <= t <= 2 tau_H``, half-power
  width ``tau_H = 20 ns`` (so the pulse spans ``c tau_H ~ 6 m`` of range).
- **Hard target** at range ``r0``: the clear-weather return is attenuated twice by Beer–Lambert,
  ``i_hard = i * exp(-2 alpha r0)``.
- **Soft target** (fog backscatter): the received power at range ``R`` is
  ``P_soft(R) = C_A P_0 beta int_0^{2 tau_H} sin^2(pi t / (2 tau_H)) exp(-2 alpha s) xi(s) / s^2
  H(r0 - s) dt`` with ``s = R - c t / 2``: fog at every distance ``s`` in front of the target
  scatters light back, weighted by the pulse shape. ``beta = 0.046 / MOR`` (1/(m sr)) is the
  backscattering coefficient, ``MOR = ln(20) / alpha``; ``xi(s)`` is the overlap of the
  transmitter and receiver fields of view (0 below ``R_1 = 0.9 m``, 1 beyond ``R_2 = 1.0 m``,
  linear between). The soft response's maximum over ``R`` and its position are tabulated once
  per alpha (two tables, see the rules below).
- Relative to the hard target's clear return (differential reflectivity ``beta_0 = Gamma / pi``,
  ``Gamma = 1e-6`` as in the paper's code), the fog response in intensity units is
  ``i_soft = i * r0^2 * (beta / beta_0) * I(r0)`` (capped at the scan's full scale).
- The stronger of the two returns is what the sensor reports. Two rules (``mode``):

  ``"reference"`` (the default, the benchmark's): the released code of Hahner et al.
  (``fog_simulation.py`` with its *original* integral tables) on the 8-bit intensity scale. The
  hard return is ``round(255/full_scale * i * exp(-2 alpha r0))``; the fog response uses the
  original intensity, the table's maximum over ``R <= r0`` (the generator zeroes the response
  beyond the target) and its unshifted range ``R`` (about 4.6 m for a far target); it is capped
  at 255. A point whose fog response beats its rounded hard return is **relocated** on its ray
  to the fog peak plus ``10 m * Beta(2, 20)`` (noise variant ``v4``, not capped at the original
  range); every other point keeps its place with the rounded intensity. **No point is ever
  removed**: a return rounded to 0 stays, with intensity 0.

  ``"lossy"`` (this project's first model): the fog peak's range is shifted by
  ``c tau_H / 2`` so that a hard target would peak at its true range (about 1.6 m for a far
  target), the relocated point never lies beyond its original range, and a return weaker than
  the detection floor ``min(0.5/255 * full_scale, i)`` is lost and removed (the 8-bit
  quantisation expressed on the scan's own scale; the ``min`` keeps points the sensor
  reported with intensity 0 in clear weather). Fewer points survive on far targets.

alpha = 0 returns the scan unchanged.
"""

from __future__ import annotations

import math
from functools import lru_cache

import numpy as np

from envs.weather.common import check_scan, full_scale, move_along_rays
from envs.weather.levels import parameter

SPEED_OF_LIGHT = 299_792_458.0
TAU_H_S = 20e-9
"""Half-power pulse width (s)."""
GAMMA_HARD = 1e-6
"""Hard-target reflectivity Gamma of the paper's released code; beta_0 = Gamma / pi."""
BETA_TIMES_MOR = 0.046
"""Backscattering coefficient times MOR (1/sr)."""
R1_M, R2_M = 0.9, 1.0
"""Receiver field of view starts to / fully covers the transmitted beam at these ranges."""
FOG_NOISE_M = 10.0
"""Scale of the Beta(2, 20) range offset of fog returns (paper's noise variant v4)."""
QUANTUM = 0.5 / 255.0
"""Detection floor as a fraction of the intensity full scale."""

FOG_MODES: tuple[str, ...] = ("reference", "lossy")
"""``reference``: the released code's rule (default); ``lossy``: this project's earlier model."""

_TABLE_STEP_M = 0.05
_TABLE_MAX_M = 20.0


@lru_cache(maxsize=32)
def _response_grid(alpha: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """``(r0 (K,), R (L,), response (K, L))``: the normalised soft-target integral (s/m^2) of a
    hard target at ``r0`` received at range ``R`` (``R = c t / 2``, no shift)."""
    length = SPEED_OF_LIGHT * TAU_H_S  # range extent of the pulse, ~6 m
    ds = 0.02
    s = np.arange(0.0, _TABLE_MAX_M + ds / 2, ds)  # scatterer distance
    xi = np.clip((s - R1_M) / (R2_M - R1_M), 0.0, 1.0)
    g = np.zeros_like(s)
    pos = s > 0
    g[pos] = np.exp(-2 * alpha * s[pos]) * xi[pos] / s[pos] ** 2
    dr = 0.04
    big_r = np.arange(0.0, _TABLE_MAX_M + dr / 2, dr)  # receive-time range R
    lag = big_r[:, None] - s[None, :]  # R - s = c t / 2, must lie in [0, c tau_H]
    w = np.where((lag >= 0) & (lag <= length), np.sin(np.pi * lag / length) ** 2, 0.0)
    # dt = 2 ds / c; cumulative over s so the target cut-off H(r0 - s) is a lookup
    cum = np.cumsum(w * g[None, :], axis=1) * (2.0 * ds / SPEED_OF_LIGHT)
    r0 = np.arange(0.0, _TABLE_MAX_M + _TABLE_STEP_M / 2, _TABLE_STEP_M)
    s_idx = np.clip(np.round(r0 / ds).astype(int), 0, len(s) - 1)
    # P(R; r0) = cum[R, min(R, r0)]
    cut = np.minimum(s_idx[:, None], np.clip(np.round(big_r / ds).astype(int), 0, len(s) - 1))
    resp = cum[np.arange(len(big_r))[None, :], cut]  # (len(r0), len(R))
    return r0, big_r, resp


@lru_cache(maxsize=32)
def soft_target_table(alpha: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The fog response table of one alpha, ``fog_mode="lossy"``.

    Returns ``(r0_grid (K,), integral (K,), distance (K,))``: for a hard target at ``r0``, the
    maximum over ``R`` of the normalised soft-target integral (s/m^2) and the range of that
    maximum shifted by ``c tau_H / 2`` (so that a hard target would peak at its true range),
    capped at ``r0``. Beyond the table's last range (20 m) both are constant (the maximum lies
    a few metres from the sensor, where the target no longer truncates the fog), so callers
    clamp.
    """
    r0, big_r, resp = _response_grid(float(alpha))
    length = SPEED_OF_LIGHT * TAU_H_S
    best = np.argmax(resp, axis=1)
    integral = resp[np.arange(len(r0)), best]
    distance = np.minimum(np.maximum(big_r[best] - length / 2, 0.0), r0)
    return r0, integral, distance


@lru_cache(maxsize=32)
def reference_table(alpha: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The fog response table of one alpha as the released code's *original* lookup tables
    define it (``fog_mode="reference"``): the maximum over receive ranges ``R <= r0`` only
    (the table generator sets the response beyond the target to zero) and the range ``R`` of
    that maximum, not shifted. Same layout as :func:`soft_target_table`; the fog peak lies at
    about 4.6 m for a far target, ``c tau_H / 2 = 3 m`` beyond the shifted table's 1.6 m.
    """
    r0, big_r, resp = _response_grid(float(alpha))
    masked = np.where(big_r[None, :] <= r0[:, None] + 1e-9, resp, 0.0)
    best = np.argmax(masked, axis=1)
    integral = masked[np.arange(len(r0)), best]
    return r0, integral, big_r[best]


def fog_relative_response(
    alpha: float, r0: np.ndarray, mode: str = "reference"
) -> tuple[np.ndarray, np.ndarray]:
    """For targets at ranges ``r0 (N,)`` (m): the fog response relative to the clear hard return
    (``r0^2 beta/beta_0 I(r0)``) and the fog peak's range (m), from the table of ``mode``."""
    table = reference_table if check_fog_mode(mode) == "reference" else soft_target_table
    grid, integral, distance = table(float(alpha))
    idx = np.minimum(np.rint(r0 / _TABLE_STEP_M).astype(np.int64), len(grid) - 1)
    mor = math.log(20.0) / alpha
    beta = BETA_TIMES_MOR / mor
    beta_0 = GAMMA_HARD / math.pi
    rel = r0.astype(np.float64) ** 2 * (beta / beta_0) * integral[idx]
    return rel, distance[idx]


def check_fog_mode(mode: str) -> str:
    """Return ``mode`` if it is one of :data:`FOG_MODES`, else raise a ValueError listing them."""
    if mode not in FOG_MODES:
        raise ValueError(f"unknown fog mode {mode!r}; valid fog modes: {', '.join(FOG_MODES)}")
    return mode


def fog_alpha(
    points: np.ndarray,
    intensity: np.ndarray,
    rng: np.random.Generator,
    alpha: float,
    return_source: bool = False,
    mode: str = "reference",
):
    """Fog of attenuation ``alpha`` (1/m) on a whole scan ``points (N, 3)``, ``intensity (N,)``;
    ``mode`` ``"reference"`` (default) or ``"lossy"``, see the module docstring.

    Returns ``(points, intensity)``, plus with ``return_source`` the index ``(N',)`` of the input
    point (the beam) each output point comes from (``arange(N)`` in the reference mode, which
    never removes a point).
    """
    check_fog_mode(mode)
    pts, inten = check_scan(points, intensity)
    if alpha < 0:
        raise ValueError(f"fog alpha must be >= 0, got {alpha}")
    if len(pts) == 0 or alpha == 0:
        out = (pts.copy(), inten.copy())
        return out + (np.arange(len(pts)),) if return_source else out
    if mode == "reference":
        out_pts, out_i = _fog_reference(pts, inten, rng, float(alpha))
        return (out_pts, out_i, np.arange(len(pts))) if return_source else (out_pts, out_i)
    scale = full_scale(inten)
    p64 = pts.astype(np.float64)
    r0 = np.sqrt(np.einsum("ij,ij->i", p64, p64))
    hard_rel = np.exp(-2.0 * alpha * r0)
    soft_rel, fog_dist = fog_relative_response(alpha, r0, mode="lossy")
    i64 = inten.astype(np.float64)
    i_hard = i64 * hard_rel
    i_soft = np.minimum(i64 * soft_rel, scale)
    fog_wins = soft_rel > hard_rel
    floor = np.minimum(QUANTUM * scale, i64)
    strongest = np.where(fog_wins, i_soft, i_hard)
    alive = strongest >= floor
    # fog points: the fog peak's range plus the v4 offset, never beyond the original point
    new_r = r0.copy()
    k = np.flatnonzero(fog_wins)
    offset = FOG_NOISE_M * rng.beta(2.0, 20.0, size=len(k))
    new_r[k] = np.minimum(fog_dist[k] + offset, r0[k])
    out_pts = move_along_rays(pts, r0, new_r)
    out_i = strongest.astype(np.float32)
    if return_source:
        return out_pts[alive], out_i[alive], np.flatnonzero(alive)
    return out_pts[alive], out_i[alive]


def _fog_reference(
    pts: np.ndarray, inten: np.ndarray, rng: np.random.Generator, alpha: float
) -> tuple[np.ndarray, np.ndarray]:
    """The released code's rule on the 8-bit intensity scale: the hard return rounded to an
    integer, the fog response (original intensity, unshifted table) capped at 255; a point whose
    fog response beats its rounded hard return is relocated to the fog peak plus the v4 offset,
    every other point keeps its place and its rounded intensity. No point is removed."""
    scale = full_scale(inten)
    to_8bit = 255.0 / scale
    p64 = pts.astype(np.float64)
    r0 = np.sqrt(np.einsum("ij,ij->i", p64, p64))
    i8 = inten.astype(np.float64) * to_8bit
    hard8 = np.round(np.exp(-2.0 * alpha * r0) * i8)
    rel, fog_dist = fog_relative_response(alpha, r0, mode="reference")
    soft8 = np.minimum(i8 * rel, 255.0)
    fog_wins = soft8 > hard8
    k = np.flatnonzero(fog_wins)
    new_r = r0.copy()
    new_r[k] = fog_dist[k] + FOG_NOISE_M * rng.beta(2.0, 20.0, size=len(k))
    out_pts = move_along_rays(pts, r0, new_r)
    out_i = (np.where(fog_wins, soft8, hard8) / to_8bit).astype(np.float32)
    return out_pts, out_i


def fog(
    points: np.ndarray,
    intensity: np.ndarray,
    rng: np.random.Generator,
    level: int,
    mode: str = "reference",
) -> tuple[np.ndarray, np.ndarray]:
    """Fog at ``level`` 1..5 (alpha from :mod:`envs.weather.levels`), ``mode`` as in
    :func:`fog_alpha`."""
    return fog_alpha(points, intensity, rng, parameter("fog", level), mode=mode)
