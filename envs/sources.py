"""Where an env's tracklets come from: the named data sources (:data:`envs.spec.SOURCES`) opened
as datasets — a synthetic world (generated into the cache on first use), a KITTI tracking
layout, a nuScenes v1.0 layout (real, or the synthetic world written in it).

:func:`envs.tracking_env.make_tracking_env` is the one factory built on it.
"""

from __future__ import annotations

import os
import warnings
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np

from envs.data import KittiTracking, Setting, get_setting
from envs.data.nuscenes import NuScenesTracking
from envs.data.tracklet import Tracklet
from envs.observation import SIZE_BOUND_M
from envs.spec import SOURCES
from envs.synthetic import ensure_world
from envs.synthetic.nuscenes_layout import DEFAULT_VERSION, ensure_nuscenes_world

__all__ = ["SOURCE_KEYWORDS", "EnvData", "is_pathlike", "open_dataset"]

SOURCE_KEYWORDS = (
    "root",
    "preset",
    "sensor",
    "seed",
    "version",
    "cache_dir",
    "allow_missing_scenes",
    "frame",
)
"""The keywords of :func:`open_dataset` that describe a named source."""


def is_pathlike(x: Any) -> bool:
    """Whether ``x`` names a folder (a ``str`` or ``os.PathLike``)."""
    return isinstance(x, str | os.PathLike)


def open_dataset(
    source: str,
    split: str,
    categories: Sequence[str] | None = None,
    *,
    root: str | os.PathLike | None = None,
    preset: str | None = None,
    sensor: str | None = None,
    seed: int = 0,
    version: str | None = None,
    cache_dir: str | os.PathLike | None = None,
    allow_missing_scenes: bool = False,
    frame: str | None = None,
) -> KittiTracking | NuScenesTracking:
    """The tracklets of ``split`` of a named source, of ``categories`` (``None``: all).

    Args:
        source: ``"synthetic"``: the world ``(preset, sensor, seed)`` (defaults ``"small"``,
            ``"hdl64"``), or the generated world at ``root``; ``"kitti"``: the KITTI tracking
            layout at ``root`` (required); ``"nuscenes"``: the nuScenes layout at ``root``
            (table folder ``version``, default ``v1.0-trainval``), or, with ``preset`` and no
            ``root``, the synthetic world written in it (sensor default ``"hdl32"``, version
            default ``v1.0-mini``).
        allow_missing_scenes: KITTI layouts only: skip the scenes of ``split`` whose files are
            missing (see :class:`envs.data.KittiTracking`).
        frame: nuScenes layouts only: the LiDAR frame scans and boxes are served in,
            ``"lidar"`` (default: each key frame's own) or ``"scene"`` (the scene's first key
            frame's: ego motion removed); see :mod:`envs.data.nuscenes`.
    """
    if source not in SOURCES:
        raise ValueError(f"unknown source {source!r}; valid: {list(SOURCES)} or a dataset")
    if allow_missing_scenes and source == "nuscenes":
        raise ValueError("allow_missing_scenes applies to KITTI layouts, not to nuscenes")
    if frame is not None and source != "nuscenes":
        raise ValueError(f"frame={frame!r} applies to the nuscenes source, not to {source!r}")
    if source == "nuscenes":
        if root is None:
            if preset is None:
                raise ValueError(
                    "pointtrack/NuScenes-v1 needs root=<nuScenes dataroot> (with version=...) or "
                    "preset=<tiny|small|default> for the synthetic world in nuScenes layout"
                )
            version = version or DEFAULT_VERSION
            root = ensure_nuscenes_world(preset, sensor or "hdl32", seed, version, cache_dir)
        return NuScenesTracking(
            str(root), version or "v1.0-trainval", split, categories, frame=frame or "lidar"
        )
    if source == "synthetic" and root is None:
        root = ensure_world(
            preset=preset or "small", sensor=sensor or "hdl64", seed=seed, cache_dir=cache_dir
        )
    if root is None:
        raise ValueError(
            "pointtrack/KITTI-v1 needs root=<folder with label_02/, calib/, velodyne/>"
        )
    return KittiTracking(str(root), split, categories, allow_missing_scenes=allow_missing_scenes)


@dataclass(frozen=True)
class EnvData:
    """What an env serves: its dataset, split, setting, categories and tracklets (those of at
    least two frames, of the categories)."""

    dataset: Any
    split: str | None
    setting: Setting | None
    categories: tuple[str, ...] | None
    tracklets: list[Tracklet]

    @classmethod
    def select(
        cls,
        dataset: Any,
        *,
        split: str | None = None,
        setting: str | Setting | None = None,
        categories: str | Sequence[str] | None = None,
    ) -> EnvData:
        """The env's data (the arguments of :class:`envs.tracking_env.TrackingEnv`).

        ``dataset``: anything with ``.tracklets``, or a KITTI-layout folder (read at ``split``,
        default all). ``categories`` default to the setting's (observed and unseen). Raises
        ``ValueError`` for a split other than the dataset's, a category outside the setting, no
        tracklet left, or a box larger than the observation bounds; warns (``UserWarning``) when
        a train split serves the setting's unseen categories (that breaks the class-agnostic
        protocol)."""
        if isinstance(categories, str):
            categories = (categories,)
        if is_pathlike(dataset):
            dataset = open_dataset("kitti", split or "all", root=dataset)
        elif split is not None and getattr(dataset, "split", split) != split:
            raise ValueError(f"split={split!r} but the dataset holds split {dataset.split!r}")
        split = split if split is not None else getattr(dataset, "split", None)
        resolved = None if setting is None else get_setting(setting)
        if resolved is not None:
            wanted = tuple(categories) if categories is not None else resolved.categories
            for c in wanted:
                resolved.is_observed(c)  # ValueError naming the valid ones
        else:
            wanted = tuple(categories) if categories is not None else None
        tracklets = [
            tr
            for tr in dataset.tracklets
            if len(tr) >= 2 and (wanted is None or tr.category in wanted)
        ]
        if not tracklets:
            present = sorted({tr.category for tr in dataset.tracklets})
            raise ValueError(
                f"no tracklets of at least two frames for categories "
                f"{list(wanted) if wanted else 'any'} in split {split!r} "
                f"(the dataset has {len(dataset.tracklets)} tracklets of categories {present})"
            )
        for tr in tracklets:
            if np.abs(tr.boxes[:, 3:6]).max() > SIZE_BOUND_M:
                raise ValueError(f"tracklet {tr.tracklet_id}: box size above {SIZE_BOUND_M} m")
        if split == "train" and resolved is not None:
            leaked = [c for c in resolved.unseen if c in (wanted or ())]
            if leaked:
                warnings.warn(
                    f"TrackingEnv on split 'train' serves the unseen categories {leaked} of "
                    f"setting {resolved.name!r}: a policy trained here sees them; pass "
                    f"categories={list(resolved.observed)} to train class-agnostically",
                    UserWarning,
                    stacklevel=4,  # the caller of TrackingEnv(...)
                )
        return cls(dataset, split, resolved, wanted, tracklets)
