"""The weather corruptions by kind, and :func:`corrupt`, the one entry point that checks its
arguments (see :mod:`envs.weather` for the models)."""

from __future__ import annotations

from collections.abc import Callable

import numpy as np

from envs.weather import fog as _fog_module
from envs.weather import precipitation as _precipitation_module
from envs.weather.fog import check_fog_mode
from envs.weather.levels import check_kind, check_level

__all__ = ["CORRUPTIONS", "Corruption", "corrupt"]

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
