"""The weather level tables: the one place where the five levels of each kind are defined.

Levels are 1 (light) .. 5 (heavy), as in the KITTI-A / nuScenes-A benchmark of Zhao et al.
(Zhao et al., adverse-weather SOT, Sec. III-B), which simulates fog after Hahner et al. (ICCV 2021)
and rain and snow
with LISA (Kilic et al. 2021) at five settings each.

- **fog**: attenuation (extinction) coefficient ``alpha`` in 1/m. The values are those of the
  3D corruption benchmark of Dong et al. (CVPR 2023): 0.005, 0.01, 0.02, 0.03, 0.06 m^-1, i.e. a
  meteorological optical range ``MOR = ln(20) / alpha`` (5 % contrast threshold, as Hahner et al.
  define it) of about 599, 300, 150, 100 and 50 m — light mist to dense fog.
- **rain**: rain rate in mm/h, Dong et al.'s LISA settings: 0.20, 0.73, 1.5625, 3.125, 7.29 mm/h
  (drizzle to moderate/heavy rain).
- **snow**: water-equivalent snowfall rate in mm/h, the same five rates as rain (0.20, 0.73,
  1.5625, 3.125, 7.29 mm/h) with LISA's snow (Gunn–Marshall) particle model: that is the
  configuration the benchmark's released code uses (Dong et al. reuse the rain rates for LISA
  snow), so we align with it. An earlier version of this module used 0.5-2.5 mm/h (the range of
  Hahner et al., *LiDAR Snowfall Simulation*, CVPR 2022); :data:`SNOW_RATE_MM_H_HAHNER` keeps
  those values for comparison (docs/weather.md measures both on one scan).
"""

from __future__ import annotations

import math

KINDS: tuple[str, ...] = ("fog", "rain", "snow")
"""Valid weather kinds, in the order reports list them."""

LEVELS: tuple[int, ...] = (1, 2, 3, 4, 5)
"""Valid levels: 1 (light) .. 5 (heavy)."""

FOG_ALPHA_PER_M: tuple[float, ...] = (0.005, 0.01, 0.02, 0.03, 0.06)
RAIN_RATE_MM_H: tuple[float, ...] = (0.20, 0.73, 1.5625, 3.125, 7.29)
SNOW_RATE_MM_H: tuple[float, ...] = RAIN_RATE_MM_H
SNOW_RATE_MM_H_HAHNER: tuple[float, ...] = (0.5, 1.0, 1.5, 2.0, 2.5)

PARAMETERS: dict[str, tuple[float, ...]] = {
    "fog": FOG_ALPHA_PER_M,
    "rain": RAIN_RATE_MM_H,
    "snow": SNOW_RATE_MM_H,
}
"""kind -> the physical parameter of levels 1..5 (fog: alpha in 1/m; rain, snow: mm/h)."""

UNITS: dict[str, str] = {
    "fog": "alpha 1/m",
    "rain": "rain rate mm/h",
    "snow": "snowfall mm/h (w.e.)",
}


def check_kind(kind: str) -> str:
    """Return ``kind`` if valid, else raise a ValueError that lists the valid kinds."""
    if kind not in KINDS:
        raise ValueError(f"unknown weather kind {kind!r}; valid kinds: {', '.join(KINDS)}")
    return kind


def check_level(level: int) -> int:
    """Return ``level`` as an int if valid (1..5), else raise a ValueError listing the levels."""
    try:
        ok = int(level) == level and int(level) in LEVELS
    except (TypeError, ValueError):
        ok = False
    if not ok or isinstance(level, bool):
        raise ValueError(
            f"unknown weather level {level!r}; valid levels: {', '.join(map(str, LEVELS))}"
        )
    return int(level)


def parameter(kind: str, level: int) -> float:
    """The physical parameter of ``kind`` at ``level`` (fog: alpha 1/m; rain/snow: mm/h)."""
    return PARAMETERS[check_kind(kind)][check_level(level) - 1]


def fog_mor_m(alpha: float) -> float:
    """Meteorological optical range (m) of fog with attenuation ``alpha`` (1/m): ln(20)/alpha."""
    return math.log(20.0) / alpha if alpha > 0 else math.inf


def describe(kind: str, level: int) -> str:
    """A short human label, e.g. ``"fog L3 (alpha=0.02/m, MOR 150 m)"``."""
    value = parameter(kind, level)
    if kind == "fog":
        return f"fog L{level} (alpha={value:g}/m, MOR {fog_mor_m(value):.0f} m)"
    return f"{kind} L{level} ({value:g} mm/h)"
