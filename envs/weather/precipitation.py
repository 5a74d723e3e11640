"""Rain and snow after LISA (Kilic et al., *Lidar Light Scattering Augmentation*, 2021), with the
particle-size distributions LISA uses — our own vectorised implementation.

Physical model (one code path, two particle-size distributions):

- Particle-size distribution ``N(D) = N0 exp(-lam D)`` (m^-3 per mm of diameter):
  **rain**, Marshall–Palmer: ``N0 = 8000``, ``lam = 4.1 R^-0.21`` (R: rain rate, mm/h);
  **snow**, Gunn–Marshall: ``N0 = 7600 R^-0.87``, ``lam = 2.55 R^-0.48`` (R: water-equivalent
  snowfall rate, mm/h; D: melted diameter).
- Extinction (Beer–Lambert): ``alpha = (pi/4) Q_ext int D^2 N(D) dD = pi 1e-6 N0 / lam^3`` (1/m)
  with ``Q_ext = 2``, the large-particle limit of Mie theory (every sampled diameter, >= 0.05 mm,
  is > 50 wavelengths of a 905 nm laser). The hard-target return keeps
  ``P0 = rho exp(-2 alpha r) / r^2`` of LISA's normalised power; it is detected if
  ``P0 >= P_min = 0.9 / r_max^2`` (r_max = 200 m).
- Scatterers in the beam: the beam is a cone of divergence 3 mrad (diameter ``Db(s) = 3 s`` mm);
  a particle of diameter D at distance s returns ``P = rho_p exp(-2 alpha s) min(D^2/Db^2, 1) /
  s^2`` with the Fresnel reflectance ``rho_p = ((n-1)/(n+1))^2`` (water n = 1.328, ice n = 1.3031).
  Particles nearer than the bistatic blind range ``r_min = 1.5 m`` are invisible.
  LISA samples every particle of every beam (hundreds per beam in heavy rain). We sample only
  those that can matter: particles with ``P >= P_min`` form a Poisson process along the beam
  whose intensity ``f(s) = area(s) N0 exp(-lam max(D_st, D_min(s))) / lam`` (D_min(s): the
  diameter needed at s) we tabulate once per rate; each beam draws ``K ~ Poisson(int f)`` such
  particles, their distances from the tabulated distribution and their diameters from the
  exponential tail above ``D_min(s)`` (exactly, by memorylessness). LISA's strongest-return rule
  then decides per beam: the brightest particle beats the target -> a **scatter point** on the
  same ray at the particle's distance (intensity ``rho_p exp(-2 alpha s) min(D^2/Db^2, 1)`` of the
  full scale); else the target is detected -> kept, intensity ``i exp(-2 alpha r)``, range noise;
  else the return is **lost** and removed.
- Range noise: LISA's ``sigma = dR / sqrt(2 SNR)`` (dR = 9 cm, SNR = P0/P_min). The clean scan
  already carries the sensor's clear-weather noise, so we add only the excess variance
  ``dR^2/2 (1/SNR_weather - 1/SNR_clear)``, toward the sensor (half-normal: the early trigger
  of a pulse whose leading edge picks up backscatter); so rate 0 changes nothing and no return
  ever moves farther.
- Reflectivity: ``rho = intensity / full_scale``, at least 5 % (a reported return is not black)
  and at least what makes the return detectable in clear weather (``P_min r^2``): the point was
  seen, so the model must see it too at rate 0.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from functools import lru_cache

import numpy as np

from envs.weather.common import (
    P_MIN,
    REFLECTIVITY_FLOOR,
    check_scan,
    full_scale,
    move_along_rays,
)
from envs.weather.levels import parameter

R_MIN_M = 1.5
"""Bistatic blind range: no particle returns from nearer than this."""
BEAM_DIVERGENCE_RAD = 3e-3
D_START_MM = 0.05
"""Smallest particle diameter sampled (smaller ones cannot out-shine a target)."""
RANGE_ACCURACY_M = 0.09
Q_EXT = 2.0
N_WATER = 1.328
N_ICE = 1.3031


@dataclass(frozen=True)
class ParticleModel:
    """An exponential particle-size distribution at one rate, plus the particles' optics."""

    name: str
    rate_mm_h: float
    n0: float  # m^-3 mm^-1
    lam: float  # 1/mm
    refractive_index: float

    @property
    def extinction(self) -> float:
        """Extinction coefficient alpha (1/m)."""
        return math.pi / 4 * Q_EXT * 1e-6 * 2 * self.n0 / self.lam**3

    @property
    def fresnel(self) -> float:
        n = self.refractive_index
        return ((n - 1) / (n + 1)) ** 2

    def number_density(self, d_min_mm) -> np.ndarray:
        """Particles per m^3 with diameter >= ``d_min_mm``."""
        return self.n0 * np.exp(-self.lam * np.asarray(d_min_mm)) / self.lam


def marshall_palmer(rate_mm_h: float) -> ParticleModel:
    """Rain drops: Marshall–Palmer (1948)."""
    return ParticleModel("rain", rate_mm_h, 8000.0, 4.1 * rate_mm_h**-0.21, N_WATER)


def gunn_marshall(rate_mm_h: float) -> ParticleModel:
    """Snow flakes (melted diameters): Gunn–Marshall (1958)."""
    return ParticleModel(
        "snow", rate_mm_h, 7.6e3 * rate_mm_h**-0.87, 2.55 * rate_mm_h**-0.48, N_ICE
    )


MODELS = {"rain": marshall_palmer, "snow": gunn_marshall}


def _beam_diameter_mm(s):
    return 1e3 * math.tan(BEAM_DIVERGENCE_RAD) * s


def _min_diameter_mm(model: ParticleModel, s):
    """Diameter a particle at ``s`` needs to return at least P_min (may exceed the beam)."""
    alpha = model.extinction
    return _beam_diameter_mm(s) * s * np.sqrt(P_MIN * np.exp(2 * alpha * s) / model.fresnel)


@lru_cache(maxsize=64)
def scatterer_table(kind: str, rate_mm_h: float) -> tuple[np.ndarray, np.ndarray]:
    """``(s_grid, cumulative)``: the expected number of detectable particles (P >= P_min) in a
    beam between ``R_MIN_M`` and ``s``. Flat beyond the last grid point."""
    model = MODELS[kind](rate_mm_h)
    alpha = model.extinction
    # beyond s_hi no particle (even one filling the beam) reaches P_min
    s_hi = math.sqrt(model.fresnel / P_MIN)
    ds = 0.01
    s = np.arange(R_MIN_M, s_hi + ds, ds)
    d_min = _min_diameter_mm(model, s)
    valid = (d_min <= _beam_diameter_mm(s)) & (
        model.fresnel * np.exp(-2 * alpha * s) / s**2 >= P_MIN
    )
    area = math.pi * (math.tan(BEAM_DIVERGENCE_RAD) * s / 2) ** 2
    f = np.where(valid, area * model.number_density(np.maximum(D_START_MM, d_min)), 0.0)
    cum = np.concatenate([[0.0], np.cumsum((f[1:] + f[:-1]) / 2 * ds)])
    return s, cum


def precipitation_rate(
    points: np.ndarray,
    intensity: np.ndarray,
    rng: np.random.Generator,
    kind: str,
    rate_mm_h: float,
    return_source: bool = False,
):
    """Rain or snow (``kind``) of ``rate_mm_h`` on a whole scan; see the module docstring.

    Returns ``(points, intensity)``, plus with ``return_source`` the index ``(N',)`` of the input
    point (the beam) each output point comes from.
    """
    if kind not in MODELS:
        raise ValueError(f"unknown precipitation kind {kind!r}; valid: {', '.join(MODELS)}")
    pts, inten = check_scan(points, intensity)
    if rate_mm_h < 0:
        raise ValueError(f"{kind} rate must be >= 0 mm/h, got {rate_mm_h}")
    if len(pts) == 0 or rate_mm_h == 0:
        out = (pts.copy(), inten.copy())
        return out + (np.arange(len(pts)),) if return_source else out
    model = MODELS[kind](rate_mm_h)
    alpha = model.extinction
    scale = full_scale(inten)
    n = len(pts)

    p64 = pts.astype(np.float64)
    r = np.sqrt(np.einsum("ij,ij->i", p64, p64))
    r_safe = np.maximum(r, 1e-6)
    rho = np.maximum(inten / scale, REFLECTIVITY_FLOOR)
    rho = np.maximum(rho, P_MIN * r_safe**2)  # seen in clear weather
    atten = np.exp(-2 * alpha * r)
    p_clear = rho / r_safe**2
    p_hard = p_clear * atten

    # --- scatterers: Poisson number of detectable particles per beam ---
    s_grid, cum = scatterer_table(kind, float(rate_mm_h))
    # uniform grid from R_MIN_M: a direct index instead of a binary search (1 cm resolution)
    ds = s_grid[1] - s_grid[0]
    cell = np.clip(np.rint((r - R_MIN_M) / ds), 0, len(cum) - 1).astype(np.int64)
    expected = np.where(r > R_MIN_M, cum[cell], 0.0)
    k = rng.poisson(expected)
    total = int(k.sum())
    scatter = np.zeros(n, dtype=bool)
    s_best = np.zeros(n)
    i_scatter = np.zeros(n)
    if total:
        beam = np.repeat(np.arange(n), k)
        u = rng.random(total) * expected[beam]
        s = np.interp(u, cum, s_grid)
        d = np.maximum(D_START_MM, _min_diameter_mm(model, s)) + rng.exponential(
            1.0 / model.lam, size=total
        )
        fill = np.minimum((d / _beam_diameter_mm(s)) ** 2, 1.0)
        refl = model.fresnel * np.exp(-2 * alpha * s) * fill
        power = refl / s**2
        order = np.lexsort((-power, beam))
        first = order[np.unique(beam[order], return_index=True)[1]]
        b = beam[first]
        wins = power[first] > p_hard[b]
        b = b[wins]
        scatter[b] = True
        s_best[b] = s[first][wins]
        i_scatter[b] = scale * refl[first][wins]

    detected = p_hard >= P_MIN
    keep_hard = ~scatter & detected
    alive = scatter | keep_hard

    # --- range noise on kept hard returns: excess over clear weather, toward the sensor ---
    snr_w = p_hard / P_MIN
    snr_c = p_clear / P_MIN
    var = RANGE_ACCURACY_M**2 / 2 * np.maximum(1.0 / np.maximum(snr_w, 1e-12) - 1.0 / snr_c, 0)
    noise = np.abs(rng.standard_normal(n)) * np.sqrt(var)
    new_r = np.where(scatter, s_best, np.maximum(r - noise, 0.0))
    new_i = np.where(scatter, i_scatter, inten * atten)
    out = move_along_rays(pts, r, new_r)
    if return_source:
        return out[alive], new_i[alive].astype(np.float32), np.flatnonzero(alive)
    return out[alive], new_i[alive].astype(np.float32)


def rain(
    points: np.ndarray, intensity: np.ndarray, rng: np.random.Generator, level: int
) -> tuple[np.ndarray, np.ndarray]:
    """Rain at ``level`` 1..5 (Marshall–Palmer, rate from :mod:`envs.weather.levels`)."""
    return precipitation_rate(points, intensity, rng, "rain", parameter("rain", level))


def snow(
    points: np.ndarray, intensity: np.ndarray, rng: np.random.Generator, level: int
) -> tuple[np.ndarray, np.ndarray]:
    """Snow at ``level`` 1..5 (Gunn–Marshall, rate from :mod:`envs.weather.levels`)."""
    return precipitation_rate(points, intensity, rng, "snow", parameter("snow", level))
