"""The ``pointtrack/NuScenes-v0`` entry point: a :class:`~envs.tracking_env.TrackingEnv` over
the nuScenes v1.0 layout (real nuScenes, or the synthetic world written in that layout)."""

from __future__ import annotations

import math
from collections.abc import Sequence
from typing import Any

from envs.tracking_env import TrackingEnv

__all__ = ["NUSCENES_MAX_ACTION", "make_nuscenes_env"]

# Key frames are 0.5 s apart (2 Hz), five times the KITTI frame interval, so the largest offset
# one step may apply is five times the KITTI default in the ground plane (the same 50 m/s bound
# on relative speed); a static object passed by an ego at 50 km/h already moves 7 m per step.
NUSCENES_MAX_ACTION = (25.0, 25.0, 3.0, math.pi)


def make_nuscenes_env(
    root: str | None = None,
    version: str | None = None,
    split: str = "val",
    setting: str | None = None,
    categories: str | Sequence[str] | None = None,
    *,
    preset: str | None = None,
    sensor: str = "hdl32",
    seed: int = 0,
    cache_dir: str | None = None,
    **env_kwargs: Any,
) -> TrackingEnv:
    """The nuScenes tracklets of ``split`` as a :class:`TrackingEnv`.

    Args:
        root: a nuScenes dataroot; or ``None`` with ``preset`` for the synthetic world in
            nuScenes layout (generated into the cache on first use).
        version: the table folder (default ``v1.0-trainval`` for a root, ``v1.0-mini`` for the
            synthetic world).
        split: an official split; ``"val"`` (default) is the SOT test split.
        setting: as for :class:`TrackingEnv` (``nuscenes-1``, ``nuscenes-2``...).
        categories: as for :class:`TrackingEnv`.
        preset: the synthetic world's preset, when ``root`` is ``None``.
        sensor: the synthetic world's LiDAR profile, when ``root`` is ``None``.
        seed: the synthetic world's seed, when ``root`` is ``None``.
        cache_dir: where the synthetic world is generated (default: the cache).
        env_kwargs: any other :class:`TrackingEnv` keyword; ``max_action`` defaults to
            :data:`NUSCENES_MAX_ACTION`.
    """
    from envs.data import get_setting
    from envs.data.nuscenes import NuScenesTracking

    if root is None:
        if preset is None:
            raise ValueError(
                "pointtrack/NuScenes-v0 needs root=<nuScenes dataroot> (with version=...) or "
                "preset=<tiny|small|default> for the synthetic world in nuScenes layout"
            )
        from envs.synthetic.nuscenes_layout import DEFAULT_VERSION, ensure_nuscenes_world

        version = version or DEFAULT_VERSION
        root = str(ensure_nuscenes_world(preset, sensor, seed, version, cache_dir))
    version = version or "v1.0-trainval"
    if isinstance(categories, str):
        categories = (categories,)
    load = categories
    if load is None and setting is not None:
        load = get_setting(setting).categories
    dataset = NuScenesTracking(root, version, split, load)
    env_kwargs.setdefault("max_action", NUSCENES_MAX_ACTION)
    return TrackingEnv(dataset, setting=setting, categories=categories, split=split, **env_kwargs)
