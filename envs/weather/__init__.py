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

from collections.abc import Callable

import numpy as np

from envs.weather import fog as _fog_module
from envs.weather import precipitation as _precipitation_module
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

Corruption = Callable[
    [np.ndarray, np.ndarray, np.random.Generator, int], tuple[np.ndarray, np.ndarray]
]

CORRUPTIONS: dict[str, Corruption] = {
    "fog": _fog_module.fog,
    "rain": _precipitation_module.rain,
    "snow": _precipitation_module.snow,
}
"""kind -> corruption function (``envs.weather.fog.fog``, ``envs.weather.precipitation.rain`` /
``snow``; the submodule names stay modules, so ``import envs.weather.fog`` works)."""


def corrupt(
    kind: str,
    points: np.ndarray,
    intensity: np.ndarray,
    rng: np.random.Generator,
    level: int,
    *,
    fog_mode: str = "reference",
) -> tuple[np.ndarray, np.ndarray]:
    """Apply weather ``kind`` at ``level`` to a whole scan; see the module docstring.
    ``fog_mode`` (fog only): ``"reference"`` (the released code's rule, never removes a point)
    or ``"lossy"`` (:mod:`envs.weather.fog`).

    Raises ValueError listing the valid kinds / levels / fog modes for unknown ones, and a clear
    error when ``intensity`` is missing.
    """
    check_kind(kind)
    check_level(level)
    check_fog_mode(fog_mode)
    if not isinstance(rng, np.random.Generator):
        raise TypeError(f"rng must be a numpy.random.Generator; got {type(rng).__name__}")
    if kind == "fog":
        return _fog_module.fog(points, intensity, rng, level, mode=fog_mode)
    return CORRUPTIONS[kind](points, intensity, rng, level)


from envs.weather.wrapper import WeatherTransform, WeatherWrapper  # noqa: E402

__all__ = [
    "CORRUPTIONS",
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
