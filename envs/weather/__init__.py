"""Adverse weather for LiDAR scans: fog, rain and snow at five levels each, applied to whole
scans in the sensor frame, plus the domain-randomisation augmentation of Zhao et al.
(adverse-weather SOT) Algorithm 1.

Every corruption has the signature
``corruption(points (N, 3) float32, intensity (N,) float32, rng: numpy.random.Generator,
level: int 1..5) -> (points (N', 3) float32, intensity (N',) float32)``:
vectorised, deterministic from ``rng``, lost returns removed (never left at the origin; the
default fog rule, the released reference code's, loses none), an empty scan stays empty,
intensities stay on the scan's own scale. The physical parameters of the levels live in
:mod:`envs.weather.levels`.

- :func:`corrupt` — dispatch by kind name (``"fog"``, ``"rain"``, ``"snow"``).
- :class:`WeatherTransform` — the env's ``scan_transform`` hook: ``(N, 4)`` scans, seeded per
  (seed, kind, level, scene, frame).
- :class:`WeatherWrapper` — a ``gymnasium.Wrapper`` installing a transform on a built env.
- :func:`domain_randomize` / :class:`DomainRandomization` — training augmentation.
"""

from __future__ import annotations

from envs.weather.corruptions import CORRUPTIONS, Corruption, corrupt
from envs.weather.fog import FOG_MODES, check_fog_mode, fog_alpha
from envs.weather.levels import (
    KINDS,
    LEVELS,
    PARAMETERS,
    UNITS,
    check_kind,
    check_level,
    describe,
    parameter,
)
from envs.weather.precipitation import precipitation_rate
from envs.weather.randomization import DomainRandomization, domain_randomize
from envs.weather.wrapper import WeatherTransform, WeatherWrapper

__all__ = [
    "CORRUPTIONS",
    "Corruption",
    "FOG_MODES",
    "KINDS",
    "LEVELS",
    "PARAMETERS",
    "UNITS",
    "DomainRandomization",
    "WeatherTransform",
    "WeatherWrapper",
    "check_fog_mode",
    "check_kind",
    "check_level",
    "corrupt",
    "describe",
    "domain_randomize",
    "fog_alpha",
    "parameter",
    "precipitation_rate",
]
