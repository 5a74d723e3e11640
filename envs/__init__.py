"""The world the agent lives in: data, geometry, metrics, weather and the Gymnasium environment.

Importing :mod:`envs` registers the Gymnasium ids (idempotently):

- ``pointtrack/Synthetic-v0``: the synthetic world; kwargs ``preset``, ``sensor``, ``seed``,
  ``split``, ``setting`` or ``categories`` (generated into the cache on first use);
- ``pointtrack/KITTI-v0``: the KITTI tracking layout; kwargs ``root``, ``split``, ``setting`` or
  ``categories``;
- ``pointtrack/NuScenes-v0``: the nuScenes v1.0 layout; kwargs ``root``, ``version``, ``split``
  (default ``val``, the SOT test split), ``setting`` or ``categories``; or ``preset`` instead of
  ``root`` for the synthetic world in nuScenes layout.

Any other :class:`envs.tracking_env.TrackingEnv` keyword passes through. In a fresh process,
``gymnasium.make("envs:pointtrack/Synthetic-v0")`` imports this module first.
"""

from __future__ import annotations

import gymnasium

ENV_IDS = ("pointtrack/Synthetic-v0", "pointtrack/KITTI-v0", "pointtrack/NuScenes-v0")


def register_envs() -> None:
    """Register the pointtrack ids with Gymnasium (no-op when already registered)."""
    if "pointtrack/Synthetic-v0" not in gymnasium.registry:
        gymnasium.register(
            id="pointtrack/Synthetic-v0",
            entry_point="envs.tracking_env:make_synthetic_env",
            kwargs={"preset": "small", "sensor": "hdl64", "seed": 0, "split": "train"},
        )
    if "pointtrack/KITTI-v0" not in gymnasium.registry:
        gymnasium.register(
            id="pointtrack/KITTI-v0",
            entry_point="envs.tracking_env:make_kitti_env",
            kwargs={"split": "test"},
        )
    if "pointtrack/NuScenes-v0" not in gymnasium.registry:
        gymnasium.register(
            id="pointtrack/NuScenes-v0",
            entry_point="envs.nuscenes_env:make_nuscenes_env",
            kwargs={"split": "val"},
        )


register_envs()
