"""The world the agent lives in: data, geometry, metrics, weather and the Gymnasium environment.

Importing :mod:`envs` registers the Gymnasium ids (idempotently):

- ``pointtrack/Synthetic-v1``: the synthetic world; kwargs ``preset``, ``sensor``, ``seed``,
  ``split``, ``setting`` or ``categories`` (generated into the cache on first use);
- ``pointtrack/KITTI-v1``: the KITTI tracking layout; kwargs ``root``, ``split``, ``setting`` or
  ``categories``;
- ``pointtrack/NuScenes-v1``: the nuScenes v1.0 layout; kwargs ``root``, ``version``, ``split``
  (default ``val``, the SOT test split), ``setting`` or ``categories``; or ``preset`` instead of
  ``root`` for the synthetic world in nuScenes layout.

Any other :class:`envs.tracking_env.TrackingEnv` keyword passes through. In a fresh process,
``gymnasium.make("envs:pointtrack/Synthetic-v1")`` imports this module first.

The ``-v0`` ids (:data:`DEPRECATED_ENV_IDS`) build the same envs as their ``-v1`` ids; making
one warns (Gymnasium's ``DeprecationWarning``: "out of date", once per ``make``). See the
version history of :class:`envs.tracking_env.TrackingEnv` (and docs/env.md) for what ``-v0``
meant over time.
"""

from __future__ import annotations

from typing import Any

import gymnasium

ENV_IDS = ("pointtrack/Synthetic-v1", "pointtrack/KITTI-v1", "pointtrack/NuScenes-v1")
"""The current ids."""
DEPRECATED_ENV_IDS = {env_id.replace("-v1", "-v0"): env_id for env_id in ENV_IDS}
"""Old id -> the current id it is an alias of."""

_ENTRY_POINTS: dict[str, tuple[str, dict[str, Any]]] = {
    "pointtrack/Synthetic-v1": (
        "envs.tracking_env:make_synthetic_env",
        {"preset": "small", "sensor": "hdl64", "seed": 0, "split": "train"},
    ),
    "pointtrack/KITTI-v1": ("envs.tracking_env:make_kitti_env", {"split": "test"}),
    "pointtrack/NuScenes-v1": ("envs.nuscenes_env:make_nuscenes_env", {"split": "val"}),
}


def register_envs() -> None:
    """Register the pointtrack ids and their ``-v0`` aliases with Gymnasium (no-op for those
    already registered)."""
    aliases = {new: old for old, new in DEPRECATED_ENV_IDS.items()}
    for env_id, (entry_point, kwargs) in _ENTRY_POINTS.items():
        for registered in (env_id, aliases[env_id]):
            if registered not in gymnasium.registry:
                gymnasium.register(id=registered, entry_point=entry_point, kwargs=dict(kwargs))


register_envs()
