"""The ``pointtrack/NuScenes-v1`` entry point: a :class:`~envs.tracking_env.TrackingEnv` over
the nuScenes v1.0 layout (real nuScenes, or the synthetic world written in that layout)."""

from __future__ import annotations

from typing import Any

from envs.spec import NUSCENES_MAX_ACTION
from envs.tracking_env import TrackingEnv, make_tracking_env

__all__ = ["NUSCENES_MAX_ACTION", "make_nuscenes_env"]


def make_nuscenes_env(**kwargs: Any) -> TrackingEnv:
    """The nuScenes tracklets of ``split`` as a :class:`TrackingEnv`:
    :func:`~envs.tracking_env.make_tracking_env` of source ``"nuscenes"``.

    Keywords: ``root`` (a nuScenes dataroot) with ``version`` (the table folder, default
    ``v1.0-trainval``); or ``preset`` without ``root`` for the synthetic world in nuScenes layout
    (``sensor`` default ``"hdl32"``, ``seed``, ``cache_dir``; version default ``v1.0-mini``;
    generated into the cache on first use); ``split``: an official split, ``"val"`` (default)
    is the SOT test split; ``setting``, ``categories`` (``nuscenes-1``, ``nuscenes-2``...) and
    any :class:`TrackingEnv` option; ``max_action`` defaults to :data:`NUSCENES_MAX_ACTION`.
    """
    return make_tracking_env("nuscenes", **kwargs)
