"""The Gymnasium environment for 3D single-object tracking in LiDAR point clouds.

One episode is one tracklet (or a clip of one): the target's box is given in the first frame,
and at every later frame the agent moves the box. See :class:`TrackingEnv` for the full contract.
The registered ids (``pointtrack/Synthetic-v0``, ``pointtrack/KITTI-v0``) are built by
:func:`make_synthetic_env` and :func:`make_kitti_env`.

Around the env: :mod:`envs.scan_cache` (where crops come from: the per-tracklet cell indices),
:mod:`envs.rewards` (the named rewards and their registry), :mod:`envs.observation` (cropping
and resampling), :mod:`envs.data.toy` (:func:`make_toy_dataset`, re-exported here).
"""

from __future__ import annotations

import math
import os
import warnings
from collections.abc import Sequence
from types import MappingProxyType
from typing import Any

import gymnasium as gym
import numpy as np
from gymnasium import spaces

from envs.data.toy import ToyDataset, make_toy_dataset
from envs.data.tracklet import Tracklet
from envs.geometry import apply_offset_pair, iou_pair, offset_between_pair
from envs.observation import (
    MASK_GT,
    MASK_PREDICTED,
    PREVIOUS_SEARCH_CHANNELS,
    PREVIOUS_TIME,
    SEARCH_OFFSET_M,
    SEARCH_SCALE,
    SEARCH_SIZE,
    TEMPLATE_SCALE,
    TEMPLATE_SIZE,
    crop_extents,
    extent_threshold,
    in_extent,
    resample_into,
)
from envs.rewards import (
    ROUND_OFF,
    RewardFn,
    available_rewards,
    check_reward,
    finite_reward,
    make_reward,
    snap_iou,
)
from envs.scan_cache import CropCache, ScanTransform, TrackletScans, crop_canonical

__all__ = [
    "DEFAULT_MAX_ACTION",
    "OBSERVATION_KEYS",
    "OPTIONAL_OBSERVATION_KEYS",
    "REFERENCE_MODES",
    "RESET_OPTIONS",
    "REWARDS",
    "ROUND_OFF",
    "SAMPLING_MODES",
    "TEMPLATE_MODES",
    "ScanTransform",
    "ToyDataset",
    "TrackingEnv",
    "crop_canonical",
    "make_kitti_env",
    "make_synthetic_env",
    "make_toy_dataset",
]

TEMPLATE_MODES = ("first_and_previous", "first", "previous", "all", "first_and_previous_merged")
REFERENCE_MODES = ("prediction", "previous_gt", "current_gt")
REWARDS = available_rewards()
"""The built-in reward names (:func:`envs.rewards.available_rewards` also lists registered ones)."""
SAMPLING_MODES = ("sequential", "random")
RESET_OPTIONS = ("tracklet", "category", "start_frame", "max_steps", "episode_seed")
DEFAULT_MAX_ACTION = (5.0, 5.0, 3.0, math.pi)
OBSERVATION_KEYS = ("template", "search", "size", "motion")
"""The default observation (always present)."""
OPTIONAL_OBSERVATION_KEYS = ("previous_search",)
"""Opt-in observation keys (``observation_keys=``)."""

POINT_BOUND_M = 100.0
"""Bound of the point observation spaces (metres, box frame); crops never reach it for boxes
smaller than ~150 m."""
SIZE_BOUND_M = 100.0
MOTION_BOUND_M = 100.0
TEMPLATE_ENLARGEMENT = (TEMPLATE_SCALE, 0.0)
SEARCH_ENLARGEMENT = (SEARCH_SCALE, SEARCH_OFFSET_M)
"""``(scale, offset_m)`` of the template and search crops."""


def _is_pathlike(x: Any) -> bool:
    return isinstance(x, str | os.PathLike)


class TrackingEnv(gym.Env):
    """3D single-object tracking in LiDAR point clouds, one tracklet (or a clip of one) per
    episode.

    ## Description
    The target's box is given in the first frame of the episode; at every later frame the agent
    moves the box (P2B / BAT / GPT act as policies; OPE Success / Precision is the step-wise
    evaluation). Boxes are ``(x, y, z, l, w, h, yaw)`` in each frame's LiDAR frame (metres,
    radians, geometric centre); observations are in box-local frames.

    ## Action Space
    ``Box(-max_action, max_action, (4,), float32)``: ``(dx, dy, dz, dyaw)`` in metres and radians
    in the reference box's frame; new box = reference box moved by ``R(yaw_ref) @ (dx, dy, dz)``,
    ``yaw + dyaw``, with the given box's size. Default ``max_action = (5, 5, 3, pi)``. Wrap in
    ``gymnasium.wrappers.RescaleAction`` for a ``[-1, 1]`` space. A NaN/inf action raises
    ``ValueError``; an out-of-range action is clipped and ``info["action_clipped"]`` is set.
    Actions are used in float64, so the exact ground-truth offset yields the ground-truth box
    (IoU and centre error within 1e-9 of 1 and 0 are reported as exactly 1 and 0).

    ## Observation Space
    ``Dict`` of float32 arrays (fresh arrays on every call):

    - ``template (512, 3)``: target points, see the template modes below (box frames), m;
    - ``search (1024, 3)``: the current frame's points inside the reference box scaled 1.25 plus
      2 m on every axis, in the reference box frame, m;
    - ``size (3,)``: the target's ``l, w, h`` (the given box's), m;
    - ``motion (4,)``: the last predicted motion ``(dx, dy, dz, dyaw)``: the offset from the
      prediction two frames back to the last one, in the former's frame (zeros at the first
      step), so motion-aware trackers stay stateless.

    Opt-in (``observation_keys=(*OBSERVATION_KEYS, "previous_search")``), the input of
    motion-centric trackers (M2-Track, Zheng et al., CVPR 2022):

    - ``previous_search (1024, 5)``: the previous frame's points cropped and transformed like the
      search region (around the same reference box, same enlargement, same frame), resampled
      likewise, with columns ``x, y, z, time, mask`` (``envs.observation.PREVIOUS_SEARCH_
      CHANNELS``): ``time`` is ``PREVIOUS_TIME`` (0; M2-Track gives the current frame's points
      ``CURRENT_TIME`` = 0.1), ``mask`` says whether the point lies in the reference box scaled
      1.25: 1 / 0 when that box is the previous frame's ground truth (the given box at the first
      step, or ``reference="previous_gt"``), else M2-Track's softened 0.8 / 0.2; zeros when the
      crop is empty (``info["empty_previous_search"]``).

    Template modes (``template_mode``): ``"first_and_previous"`` (default; 256 points from the
    first frame cropped with the given box scaled 1.25 plus 256 from the previous frame cropped
    with the previous prediction scaled 1.25, each in its own box frame, concatenated),
    ``"first"`` (512 from the first frame), ``"previous"`` (512 from the previous frame),
    ``"all"`` (the crops of the first frame and of every previous prediction, each in its own box
    frame, merged and resampled to 512 — P2B's "all previous results"),
    ``"first_and_previous_merged"`` (the first and previous crops merged, first then previous,
    and resampled to 512 together: Open3DSOT's ``firstandprevious`` shape aggregation).
    Point sets are resampled with ``self.np_random`` (duplicates when too few, a random subset
    when too many), or, when an
    episode seed is set, with a generator seeded by ``(episode_seed, tracklet id)`` at every
    reset; an empty set gives zeros and ``info["empty_template"]`` / ``info["empty_search"]``
    say so. Cropped point sets are the points ``envs.observation.crop_box_frame`` selects, rows
    in a canonical order (see :func:`envs.scan_cache.crop_canonical`).

    ## Rewards
    ``reward``: a name of :mod:`envs.rewards` — ``"iou_3d"`` (default: the oriented 3D IoU of the
    new box with the ground truth), ``"iou_bev"``, ``"neg_center_error"`` (minus the centre
    distance, m), ``"iou_delta"`` (IoU gain over keeping the previous box), ``"success"`` (1 if
    the IoU reaches ``reward_kwargs["threshold"]``, default 0.5), or one registered with
    :func:`envs.rewards.register_reward` — built with ``reward_kwargs``; or a picklable callable
    ``reward(pred (7,), gt (7,), prev_pred (7,), step, info) -> float`` (``info``: this step's
    info, read-only; a non-finite value raises ``ValueError``).

    ## Starting State
    ``reset`` starts the next tracklet: ``sampling="sequential"`` visits the tracklets in order
    (``tracklet_order``, default all, wrapping around), ``"random"`` draws one with
    ``self.np_random``. Reset with a seed restarts the sequential order. The episode's first
    frame is ``start_frame`` (default 0; its ground-truth box is the given box) and the first
    observation is for the frame after it. Reset ``info``: ``tracklet``, ``category``,
    ``observed``, ``init_box`` (the given box), ``start_frame``, ``empty_template``,
    ``empty_search`` (plus ``weather``, see the step info).

    ``reset(options=...)`` (any other key raises ``ValueError`` naming the valid ones; ``None``
    values mean "not given"):

    - ``tracklet``: an index into ``self.tracklets`` or a tracklet id;
    - ``category``: a category name or a list of them: the next tracklet (sequential: in
      ``tracklet_order`` from the cursor on; random: uniformly among them) of those categories;
    - ``start_frame``: an index in the tracklet (``0 .. T-2``) or ``"random"`` (uniform over
      them, drawn with ``self.np_random``);
    - ``max_steps``: the clip length, at least 1;
    - ``episode_seed``: this episode's resampling seed (overrides the env's ``episode_seed``).

    The constructor's ``start_frame``, ``max_steps`` and ``episode_seed`` are the defaults of
    the options of the same names; ``categories`` and ``sampling`` / ``tracklet_order`` play
    that part for ``category`` and ``tracklet``.

    ## Episode End
    ``terminated`` at the tracklet's last frame (the final observation repeats the last one).
    ``truncated`` when a clip (``max_steps``) ends before the tracklet does; its final
    observation is the next frame's real one (for bootstrapping). A lost target never ends an
    episode (OPE tracks to the end). ``step`` before ``reset`` or after the end raises.

    ## Step info
    ``iou``, ``center_error`` (m), ``pred_box`` (7,), ``gt_box`` (7,), ``category``,
    ``observed``, ``tracklet`` (id), ``frame`` (index in the tracklet), ``target_points``
    (scan points in the ground-truth box), ``action_clipped``, ``empty_template``,
    ``empty_search``; plus ``weather`` when the scan transform has an ``info`` attribute.

    ## Arguments
    - ``dataset``: anything with ``.tracklets`` (``envs.data.KittiTracking``,
      :func:`make_toy_dataset`), or a KITTI-layout root folder (then ``split`` is used).
    - ``setting``: a class-agnostic setting name (``"kitti-1"``...) or ``envs.data.Setting``;
      ``observed`` flags follow it; by default its observed and unseen categories are used. An
      env of split ``train`` whose categories include the setting's unseen ones warns (at
      construction) naming them: training on them breaks the class-agnostic protocol.
    - ``categories``: restrict to these categories (within the setting if one is given).
    - ``split``: the split to read when ``dataset`` is a folder; otherwise only checked against
      ``dataset.split`` and quoted in errors.
    - ``sampling``, ``template_mode``, ``reference`` (``"prediction"`` default, ``"previous_gt"``,
      ``"current_gt"``: the box the search region is cropped around), ``reward``,
      ``reward_kwargs``, ``max_action``, ``render_mode`` (``None`` or ``"rgb_array"``).
    - ``search_enlargement``: ``(scale, offset_m)`` of the search crop (default ``(1.25, 2.0)``;
      GPT's paper crops ``(1.0, 4.0)``); trackers must be evaluated with the region they were
      trained with.
    - ``start_frame``, ``max_steps``: the defaults of the reset options (``0``, ``None``: whole
      tracklets).
    - ``episode_seed``: ``None`` (default: episodes draw from ``self.np_random`` one after the
      other) or an int: every episode draws its resampling from its own generator seeded by
      ``(episode_seed, tracklet id)``, so what it observes for given actions depends only on its
      tracklet (and start frame) — not on the episodes before it, the tracklet order or filter,
      or the vector sub-env that runs it. Settable between episodes (``training.evaluate`` sets
      it).
    - ``scan_transform``: see :data:`envs.scan_cache.ScanTransform` (the weather hook). If it has
      an ``info`` attribute, that value is reported as ``info["weather"]``.
    - ``corridor_m``: margin (m) of the per-tracklet corridor of the crop cache
      (:mod:`envs.scan_cache`): each frame keeps, indexed by ``cell_m`` xy cells, the scan
      points within reach of any of the tracklet's boxes; crops elsewhere read a whole-scan
      cell index built on demand. Neither changes an observation. ``None``: crop whole scans
      every step (the no-cache baseline). ``cache_mb``: memory budget of the cache (LRU over
      tracklets).

    Tracklets shorter than two frames are skipped.
    """

    metadata = {"render_modes": ["rgb_array"], "render_fps": 10}

    def __init__(
        self,
        dataset: Any,
        *,
        setting: Any = None,
        categories: str | Sequence[str] | None = None,
        split: str | None = None,
        sampling: str = "sequential",
        template_mode: str = "first_and_previous",
        reference: str = "prediction",
        reward: str | RewardFn = "iou_3d",
        reward_kwargs: dict[str, Any] | None = None,
        max_action: Sequence[float] = DEFAULT_MAX_ACTION,
        render_mode: str | None = None,
        scan_transform: ScanTransform | None = None,
        corridor_m: float | None = 2.0,
        cell_m: float = 1.0,
        cache_mb: float = 512.0,
        episode_seed: int | None = None,
        start_frame: int | str = 0,
        max_steps: int | None = None,
        observation_keys: Sequence[str] = OBSERVATION_KEYS,
        search_enlargement: tuple[float, float] = SEARCH_ENLARGEMENT,
    ) -> None:
        _check_choice("sampling", sampling, SAMPLING_MODES)
        _check_choice("template_mode", template_mode, TEMPLATE_MODES)
        _check_choice("reference", reference, REFERENCE_MODES)
        if render_mode is not None:
            _check_choice("render_mode", render_mode, tuple(self.metadata["render_modes"]))
        if scan_transform is not None and not callable(scan_transform):
            raise TypeError(f"scan_transform must be callable; got {type(scan_transform).__name__}")
        a_max = np.asarray(max_action, dtype=np.float64)
        if a_max.shape != (4,) or not np.all(np.isfinite(a_max)) or np.any(a_max <= 0):
            raise ValueError(f"max_action must be 4 positive finite numbers; got {max_action!r}")
        if corridor_m is not None and not (corridor_m >= 0 and cell_m > 0):
            raise ValueError(f"corridor_m must be >= 0 and cell_m > 0; got {corridor_m}, {cell_m}")
        if isinstance(reward, str):
            self.reward_fn: RewardFn = make_reward(reward, **(reward_kwargs or {}))
        else:
            if reward_kwargs:
                raise ValueError("reward_kwargs apply to a reward name, not to a callable")
            self.reward_fn = check_reward(reward)
        self.reward_mode = reward
        self.reward_kwargs = dict(reward_kwargs or {})
        self._default_start = _check_start_frame(start_frame, "start_frame")
        self._default_max_steps = _check_max_steps(max_steps, "max_steps")
        self.observation_keys = _check_observation_keys(observation_keys)
        self._previous_search = "previous_search" in self.observation_keys

        if isinstance(categories, str):
            categories = (categories,)
        if _is_pathlike(dataset):
            from envs.data import KittiTracking

            dataset = KittiTracking(dataset, split or "all", None)
        elif split is not None and getattr(dataset, "split", split) != split:
            raise ValueError(f"split={split!r} but the dataset holds split {dataset.split!r}")
        self.split = split if split is not None else getattr(dataset, "split", None)
        self.setting = None
        if setting is not None:
            from envs.data import get_setting

            self.setting = get_setting(setting)
            wanted = tuple(categories) if categories is not None else self.setting.categories
            for c in wanted:
                self.setting.is_observed(c)  # ValueError naming the valid ones
        else:
            wanted = tuple(categories) if categories is not None else None
        self.categories = wanted
        tracklets = [
            tr
            for tr in dataset.tracklets
            if len(tr) >= 2 and (wanted is None or tr.category in wanted)
        ]
        if not tracklets:
            present = sorted({tr.category for tr in dataset.tracklets})
            raise ValueError(
                f"no tracklets of at least two frames for categories "
                f"{list(wanted) if wanted else 'any'} in split {self.split!r} "
                f"(the dataset has {len(dataset.tracklets)} tracklets of categories {present})"
            )
        for tr in tracklets:
            if np.abs(tr.boxes[:, 3:6]).max() > SIZE_BOUND_M:
                raise ValueError(f"tracklet {tr.tracklet_id}: box size above {SIZE_BOUND_M} m")
        self._warn_unseen_in_training()
        self.tracklets: list[Tracklet] = tracklets
        self.dataset = dataset
        self.sampling = sampling
        self.template_mode = template_mode
        scale, offset_m = (float(v) for v in search_enlargement)
        if not (scale > 0 and offset_m >= 0):
            raise ValueError(
                f"search_enlargement must be (scale > 0, offset_m >= 0), got "
                f"{tuple(search_enlargement)}"
            )
        self.search_enlargement = (scale, offset_m)
        self.reference = reference
        self.max_action = a_max
        self.render_mode = render_mode
        self.scan_transform = scan_transform
        self.corridor_m = corridor_m
        self.cell_m = float(cell_m)
        self.cache_mb = float(cache_mb)
        self._tracklet_order: list[int] | None = None
        self.episode_seed = episode_seed

        self.action_space = spaces.Box(
            -a_max.astype(np.float32), a_max.astype(np.float32), (4,), np.float32
        )
        motion_hi = np.array([MOTION_BOUND_M] * 3 + [math.pi], dtype=np.float32)
        self.observation_space = spaces.Dict(
            {
                "template": spaces.Box(
                    -POINT_BOUND_M, POINT_BOUND_M, (TEMPLATE_SIZE, 3), np.float32
                ),
                "search": spaces.Box(-POINT_BOUND_M, POINT_BOUND_M, (SEARCH_SIZE, 3), np.float32),
                "size": spaces.Box(0.0, SIZE_BOUND_M, (3,), np.float32),
                "motion": spaces.Box(-motion_hi, motion_hi, (4,), np.float32),
            }
        )
        if self._previous_search:
            n = len(PREVIOUS_SEARCH_CHANNELS)
            hi = np.array([POINT_BOUND_M] * 3 + [1.0, 1.0], np.float32)
            lo = np.array([-POINT_BOUND_M] * 3 + [0.0, 0.0], np.float32)
            self.observation_space["previous_search"] = spaces.Box(
                np.tile(lo, (SEARCH_SIZE, 1)),
                np.tile(hi, (SEARCH_SIZE, 1)),
                (SEARCH_SIZE, n),
                np.float32,
            )
        self._motion_hi = motion_hi.astype(np.float64).tolist()
        self._max_action_list = a_max.tolist()
        self._crop_cache = self._new_crop_cache()
        self._cursor = 0
        self._clear_episode()

    # ------------------------------------------------------------------ public helpers

    @property
    def num_tracklets(self) -> int:
        """Number of tracklets the env serves (after category selection and length filter)."""
        return len(self.tracklets)

    @property
    def current_tracklet(self) -> Tracklet | None:
        """The episode's tracklet (``None`` before the first reset)."""
        return self._tracklet

    @property
    def current_frame(self) -> int:
        """Index in the tracklet of the frame the current observation is for."""
        return self._t

    @property
    def start_frame(self) -> int:
        """Index in the tracklet of the episode's first frame (the given box's)."""
        return self._start_frame

    @property
    def reference_box(self) -> np.ndarray:
        """``(7,)`` the box the current search region was cropped around (actions are offsets
        in its frame): a copy."""
        return self._ref.copy()

    @property
    def tracklet_lengths(self) -> list[int]:
        """Frames of each served tracklet (a whole-tracklet episode of tracklet ``i`` has
        ``tracklet_lengths[i] - 1`` steps)."""
        return [len(tr) for tr in self.tracklets]

    @property
    def episode_seed(self) -> int | None:
        """Seed of the per-episode resampling generators (``None``: ``self.np_random``)."""
        return self._episode_seed

    @episode_seed.setter
    def episode_seed(self, seed: int | None) -> None:
        self._episode_seed = _check_seed(seed, "episode_seed")

    @property
    def cache_stats(self) -> dict[str, int]:
        """Crops served by the corridor indices, the whole-scan cell indices and direct
        whole-scan crops (``corridor``, ``cell_index``, ``full_scan``) since the env was made
        (or cloned / unpickled)."""
        return self._crop_cache.stats

    @property
    def cache_bytes(self) -> int:
        """Bytes held by the crop cache."""
        return self._crop_cache.nbytes

    @property
    def tracklet_order(self) -> list[int]:
        """Indices visited by sequential sampling (settable, e.g. per vector sub-env)."""
        if self._tracklet_order is None:
            return list(range(len(self.tracklets)))
        return list(self._tracklet_order)

    @tracklet_order.setter
    def tracklet_order(self, order: Sequence[int] | None) -> None:
        if order is None:
            self._tracklet_order = None
            return
        order = [int(i) for i in order]
        bad = [i for i in order if not 0 <= i < len(self.tracklets)]
        if bad:
            raise ValueError(
                f"tracklet_order indices {bad} out of range 0..{len(self.tracklets) - 1}"
            )
        self._tracklet_order = order
        self._cursor = 0

    def set_scan_transform(self, transform: ScanTransform | None) -> None:
        """Install (or remove, ``None``) the whole-scan transform and drop the scan cache, so no
        scan made under the previous transform is served again. Crops already taken in the
        current episode (its templates) stay; install before ``reset`` for clean episodes."""
        if transform is not None and not callable(transform):
            raise TypeError(f"scan_transform must be callable; got {type(transform).__name__}")
        self.scan_transform = transform
        self._crop_cache.clear(transform)
        if self._tracklet is not None:
            self._entry = self._scans(self._index)

    def clone(self) -> TrackingEnv:
        """A fresh copy of this env sharing its (read-only) dataset and tracklets, with its own
        episode state and cache (e.g. the sub-envs of a ``SyncVectorEnv``)."""
        import copy

        memo = {id(self.dataset): self.dataset, id(self.scan_transform): self.scan_transform}
        memo.update({id(tr): tr for tr in self.tracklets})
        memo[id(self._crop_cache)] = None  # not copied: replaced below
        memo[id(self._entry)] = None
        twin = copy.deepcopy(self, memo)
        twin._crop_cache = twin._new_crop_cache()
        twin._entry = twin._scans(twin._index) if twin._tracklet is not None else None
        return twin

    def is_observed(self, category: str) -> bool:
        """Whether ``category`` is observed under the env's setting (always ``True`` without)."""
        return True if self.setting is None else self.setting.is_observed(category)

    # ------------------------------------------------------------------ Gymnasium API

    def reset(
        self, *, seed: int | None = None, options: dict[str, Any] | None = None
    ) -> tuple[dict[str, np.ndarray], dict[str, Any]]:
        super().reset(seed=seed)
        if seed is not None:
            self._cursor = 0
        opts = self._episode_options(options)
        index = self._choose_tracklet(opts["tracklet"], opts["category"])
        self._start(index, opts)
        obs, empty = self._observation()
        self._render_state = None
        tr = self._tracklet
        info = {
            "tracklet": tr.tracklet_id,
            "category": tr.category,
            "observed": self._observed,
            "init_box": tr.boxes[self._start_frame].astype(np.float64, copy=True),
            "start_frame": self._start_frame,
            **empty,
        }
        self._add_weather(info)
        return obs, info

    def step(self, action: Any) -> tuple[dict[str, np.ndarray], float, bool, bool, dict[str, Any]]:
        if self._tracklet is None:
            raise RuntimeError("step() called before reset(); call env.reset() first")
        if self._done:
            raise RuntimeError(
                f"step() called after the episode of tracklet {self._tracklet.tracklet_id} "
                f"{self._done}; call env.reset() to start the next one"
            )
        values, clipped, pred_box = self._decode_action(action)
        t = self._t
        pred = np.array(pred_box)
        gt = self._tracklet.boxes[t]
        prev_pred = self._preds[-1]
        self._motion = np.array(  # float32: the observation's dtype
            _clip(offset_between_pair(self._pred_box, pred_box), self._motion_hi), np.float32
        )
        self._pred_box = pred_box
        self._preds.append(pred)
        self._render_state = (self._search_crop, self._ref, gt, pred)
        terminated, truncated = self._is_terminated(), self._is_truncated()
        info = self._info(pred, gt, action_clipped=clipped != values)
        if terminated:
            obs = {k: v.copy() for k, v in self._last_obs.items()}
            empty = self._last_empty
        else:
            self._t = t + 1
            obs, empty = self._observation()
        info.update(empty)
        self._add_weather(info)
        self._done = "terminated" if terminated else "truncated" if truncated else ""
        reward = self._reward(pred, gt, prev_pred, t - self._start_frame - 1, info)
        return obs, reward, terminated, truncated, info

    def reward_for_action(self, action: Any) -> float:
        """The reward ``step(action)`` would return now, without stepping (nothing changes).

        For self-critical baselines (``training.rl.SelfCriticalReward``): the reward of the
        policy's mean action at the same state. The reward's ``info`` has the prediction's
        entries (``iou``, ``center_error``, ``pred_box``, ``gt_box``, ...) but not the next
        observation's ``empty_*`` flags or the weather entries (no observation is made)."""
        if self._tracklet is None or self._done:
            raise RuntimeError(
                "reward_for_action() needs a running episode (call reset(), and again after "
                "the episode ends)"
            )
        values, clipped, pred_box = self._decode_action(action)
        pred = np.array(pred_box)
        gt = self._tracklet.boxes[self._t]
        info = self._info(pred, gt, action_clipped=clipped != values)
        return self._reward(pred, gt, self._preds[-1], self._t - self._start_frame - 1, info)

    def _decode_action(self, action: Any) -> tuple[list[float], list[float], list[float]]:
        """``(values, clipped, pred_box)`` of an action: its four numbers, them clipped to
        ``max_action``, and the box ``(7,)`` (Python floats, for the scalar math) it makes from
        the reference box, with the given box's size."""
        a = np.asarray(action, dtype=np.float64)
        if a.shape != (4,):
            raise ValueError(f"action must have shape (4,) (dx, dy, dz, dyaw); got {a.shape}")
        values = a.tolist()
        if not all(map(math.isfinite, values)):
            raise ValueError(f"action contains NaN or inf: {values} (dx, dy, dz, dyaw)")
        clipped = _clip(values, self._max_action_list)
        pred_box = apply_offset_pair(self._ref.tolist(), clipped)
        pred_box[3:6] = self._size_box
        return values, clipped, pred_box

    def render(self) -> np.ndarray | None:
        """``rgb_array``: a bird's-eye ``(H, W, 3)`` uint8 image of the current search region
        with its points (grey), the reference box (blue), the ground truth (green) and the last
        prediction (red), in the reference box frame."""
        if self.render_mode is None:
            gym.logger.warn("render() called with render_mode=None; pass render_mode='rgb_array'")
            return None
        from envs.render import render_birds_eye

        if self._tracklet is None:
            return render_birds_eye(np.zeros((0, 3), np.float32), [], frame_box=None, extent_m=10.0)
        if self._render_state is not None:
            points, ref, gt, pred = self._render_state
        else:  # just after reset: the first search region, no prediction yet
            points, ref, gt, pred = (
                self._search_crop,
                self._ref,
                self._tracklet.boxes[self._t],
                None,
            )
        boxes = [(ref, (70, 110, 255)), (gt, (40, 200, 40))]
        if pred is not None:
            boxes.append((pred, (230, 40, 40)))
        scale, offset_m = self.search_enlargement
        half = 0.5 * scale * float(max(ref[3], ref[4])) + offset_m
        return render_birds_eye(points, boxes, frame_box=ref, extent_m=half)

    def close(self) -> None:
        self._crop_cache.clear(self.scan_transform)

    # ------------------------------------------------------------------ pickling

    def __getstate__(self) -> dict[str, Any]:
        state = self.__dict__.copy()
        state["_crop_cache"] = None  # rebuilt lazily: it never changes an observation
        state["_entry"] = None
        return state

    def __setstate__(self, state: dict[str, Any]) -> None:
        self.__dict__.update(state)
        self._crop_cache = self._new_crop_cache()
        if self._tracklet is not None:
            self._entry = self._scans(self._index)

    # ------------------------------------------------------------------ hooks

    def _reward(
        self,
        pred: np.ndarray,
        gt: np.ndarray,
        prev_pred: np.ndarray,
        step: int,
        info: dict[str, Any],
    ) -> float:
        """The reward of step ``step`` (0 first) that predicted ``pred`` for ``gt`` after
        ``prev_pred``: :attr:`reward_fn` on copies, its info read-only."""
        fn = self.reward_fn
        value = fn(
            pred.copy(),
            np.array(gt, dtype=np.float64),
            prev_pred.copy(),
            step,
            MappingProxyType(info),
        )
        return finite_reward(value, fn)

    def _is_terminated(self) -> bool:
        """Whether the current step ends the tracklet (its last frame)."""
        return self._t == self._last_frame

    def _is_truncated(self) -> bool:
        """Whether the current step ends the clip before the tracklet's end."""
        return self._t == self._clip_end and self._t < self._last_frame

    def _info(self, pred: np.ndarray, gt: np.ndarray, action_clipped: bool) -> dict[str, Any]:
        """The step info of the prediction ``pred`` for frame ``self._t`` (before the next
        observation adds its ``empty_*`` flags)."""
        pred_box, gt_box = pred.tolist(), gt.tolist()
        center_error = math.dist(pred_box[:3], gt_box[:3])
        tr = self._tracklet
        return {
            "iou": snap_iou(iou_pair(pred_box, gt_box)),
            "center_error": 0.0 if center_error < ROUND_OFF else float(center_error),
            "pred_box": pred.copy(),
            "gt_box": gt.astype(np.float64, copy=True),
            "category": tr.category,
            "observed": self._observed,
            "tracklet": tr.tracklet_id,
            "frame": self._t,
            "target_points": self._target_points(self._t),
            "action_clipped": action_clipped,
        }

    # ------------------------------------------------------------------ episodes

    def _clear_episode(self) -> None:
        self._tracklet: Tracklet | None = None
        self._entry: TrackletScans | None = None
        self._index = -1
        self._start_frame = 0
        self._t = 0
        self._last_frame = 0
        self._clip_end = 0
        self._done = ""  # "terminated" or "truncated" once the episode ended
        self._preds: list[np.ndarray] = []
        self._ref = np.zeros(7)
        self._size_box = [0.0] * 3
        self._size_obs = np.zeros(3, np.float32)
        self._pred_box = [0.0] * 7
        self._motion = np.zeros(4, np.float32)
        self._observed = True
        self._resample_rng: np.random.Generator | None = None
        self._first_crop = None
        self._prev_crop = None
        self._all_crops: list[np.ndarray] = []
        self._last_obs = None
        self._last_empty: dict[str, bool] = {}
        self._search_crop = np.zeros((0, 3), np.float32)
        self._render_state = None

    def _episode_options(self, options: dict[str, Any] | None) -> dict[str, Any]:
        """The reset options validated, with the constructor's defaults for missing ones."""
        options = dict(options or {})
        unknown = sorted(set(options) - set(RESET_OPTIONS))
        if unknown:
            raise ValueError(f"unknown reset options {unknown}; valid: {list(RESET_OPTIONS)}")
        opts = {k: options.get(k) for k in RESET_OPTIONS}
        if opts["start_frame"] is None:
            opts["start_frame"] = self._default_start
        else:
            _check_start_frame(opts["start_frame"], "options['start_frame']")
        if opts["max_steps"] is None:
            opts["max_steps"] = self._default_max_steps
        else:
            _check_max_steps(opts["max_steps"], "options['max_steps']")
        if opts["episode_seed"] is None:
            opts["episode_seed"] = self._episode_seed
        else:
            opts["episode_seed"] = _check_seed(opts["episode_seed"], "options['episode_seed']")
        category = opts["category"]
        if category is not None:
            wanted = (category,) if isinstance(category, str) else tuple(category)
            served = sorted({tr.category for tr in self.tracklets})
            bad = [c for c in wanted if c not in served]
            if bad or not wanted:
                raise ValueError(
                    f"options['category']={category!r}: no tracklets of {bad or 'no category'} "
                    f"in this env; valid: {served}"
                )
            opts["category"] = wanted
        return opts

    def _choose_tracklet(self, tracklet: Any, category: tuple[str, ...] | None) -> int:
        """The index of the episode's tracklet (draws from ``self.np_random`` when random)."""
        if tracklet is not None:
            index = self._tracklet_index(tracklet)
            found = self.tracklets[index].category
            if category is not None and found not in category:
                raise ValueError(
                    f"options['tracklet']={tracklet!r} is a {found}, not of "
                    f"options['category']={list(category)}"
                )
            return index
        if self.sampling == "random":
            if category is None:
                return int(self.np_random.integers(len(self.tracklets)))
            pool = [i for i, tr in enumerate(self.tracklets) if tr.category in category]
            return pool[int(self.np_random.integers(len(pool)))]
        order = self.tracklet_order
        if not order:
            raise RuntimeError("tracklet_order is empty; nothing to visit")
        for k in range(len(order)):
            index = order[(self._cursor + k) % len(order)]
            if category is None or self.tracklets[index].category in category:
                self._cursor += k + 1
                return index
        raise ValueError(f"tracklet_order visits no tracklet of options['category']={category}")

    def _tracklet_index(self, value: Any) -> int:
        if isinstance(value, str):
            for i, tr in enumerate(self.tracklets):
                if tr.tracklet_id == value:
                    return i
            raise ValueError(f"unknown tracklet id {value!r}; {len(self.tracklets)} tracklets")
        if isinstance(value, bool) or not isinstance(value, int | np.integer):
            raise ValueError(
                f"options['tracklet'] must be an int index or a tracklet id; got {value!r}"
            )
        if not 0 <= int(value) < len(self.tracklets):
            raise ValueError(
                f"options['tracklet']={value} out of range 0..{len(self.tracklets) - 1}"
            )
        return int(value)

    def _start(self, index: int, opts: dict[str, Any]) -> None:
        """Episode state for tracklet ``index`` (no observation: see :meth:`_observation`)."""
        if self._entry is not None:
            self._entry.end_episode()
        self._clear_episode()
        tr = self.tracklets[index]
        start = opts["start_frame"]
        if start == "random":
            start = int(self.np_random.integers(len(tr) - 1))
        elif start > len(tr) - 2:
            raise ValueError(
                f"start_frame={start} leaves no step in tracklet {tr.tracklet_id} of {len(tr)} "
                f"frames (valid: 0..{len(tr) - 2} or 'random')"
            )
        self._tracklet = tr
        self._index = index
        self._entry = self._scans(index)
        self._observed = bool(self.is_observed(tr.category))
        seed = opts["episode_seed"]
        if seed is None:
            self._resample_rng = self.np_random
        else:  # the id's bytes, not the index: indices change with the category filter
            key = [seed, *tr.tracklet_id.encode()]
            if start:  # other start frames draw other samples (256 + start: never an id byte)
                key.append(256 + start)
            self._resample_rng = np.random.default_rng(key)
        box0 = np.asarray(tr.boxes[start], dtype=np.float64).copy()
        self._size_box = box0[3:6].tolist()
        self._size_obs = box0[3:6].astype(np.float32)
        self._preds = [box0]
        self._pred_box = box0.tolist()  # the last prediction's values (motion's reference)
        self._start_frame = start
        self._t = start + 1
        self._last_frame = len(tr) - 1
        max_steps = opts["max_steps"]
        self._clip_end = self._last_frame if max_steps is None else start + max_steps

    def _reference_box(self, t: int) -> np.ndarray:
        if self.reference == "prediction":
            return self._preds[t - 1 - self._start_frame]
        if self.reference == "previous_gt":
            return np.asarray(self._tracklet.boxes[t - 1], dtype=np.float64)
        return np.asarray(self._tracklet.boxes[t], dtype=np.float64)

    def _observation(self) -> tuple[dict[str, np.ndarray], dict[str, bool]]:
        """The observation for frame ``self._t`` (uses the predictions up to ``t - 1``) and its
        ``empty_*`` flags: every crop and the resampling."""
        t, mode, start = self._t, self.template_mode, self._start_frame
        entry = self._entry
        first = entry.template_crops.get(start)
        if first is None:  # the given box's crop: the same in every episode from this frame
            (first,) = self._crops(self._preds[0], (start,), (TEMPLATE_ENLARGEMENT,))
            entry.template_crops[start] = first
        if t == start + 1:
            self._first_crop, self._prev_crop, self._all_crops = first, first, [first]
        ref = self._reference_box(t)
        # the crops around the reference box, taken in one pass: the search region, the opt-in
        # previous search region, and the previous template when its box is the reference
        frames, enlargements = [t], [self.search_enlargement]
        if self._previous_search:
            frames.append(t - 1)
            enlargements.append(self.search_enlargement)
        new_prev = t >= start + 2 and mode != "first"  # the previous frame's template crop
        if new_prev and self.reference == "prediction":
            frames.append(t - 1)
            enlargements.append(TEMPLATE_ENLARGEMENT)
        crops = self._crops(ref, tuple(frames), tuple(enlargements))
        search_pts = crops[0]
        if new_prev:
            if self.reference == "prediction":
                self._prev_crop = crops[-1]
            else:
                prev_box = self._preds[t - 1 - start]
                (self._prev_crop,) = self._crops(prev_box, (t - 1,), (TEMPLATE_ENLARGEMENT,))
            if mode == "all":
                self._all_crops.append(self._prev_crop)
        template = np.empty((TEMPLATE_SIZE, 3), np.float32)
        search = np.empty((SEARCH_SIZE, 3), np.float32)
        half = TEMPLATE_SIZE // 2
        if mode == "first_and_previous":
            sets, outs = [self._first_crop, self._prev_crop], [template[:half], template[half:]]
        elif mode == "first":
            sets, outs = [self._first_crop], [template]
        elif mode == "previous":
            sets, outs = [self._prev_crop], [template]
        elif mode == "first_and_previous_merged":
            sets, outs = [np.concatenate([self._first_crop, self._prev_crop])], [template]
        else:
            merged = self._all_crops
            sets, outs = [np.concatenate(merged) if len(merged) > 1 else merged[0]], [template]
        sets.append(search_pts)
        outs.append(search)
        if self._previous_search:  # last: the default sets' draws stay those of the default
            previous = np.empty((SEARCH_SIZE, 3), np.float32)
            sets.append(crops[1])
            outs.append(previous)
        counts = resample_into(sets, outs, self._resample_rng)
        n_search = counts[-2] if self._previous_search else counts[-1]
        n_template = sum(counts[: len(sets) - 1 - self._previous_search])
        self._ref = ref
        self._search_crop = search_pts
        obs = {
            "template": template,
            "search": search,
            "size": self._size_obs.copy(),
            "motion": self._motion,  # a new array every step: handed over as it is
        }
        empty = {"empty_template": n_template == 0, "empty_search": n_search == 0}
        if self._previous_search:
            obs["previous_search"] = self._with_channels(previous, ref, counts[-1], t)
            empty["empty_previous_search"] = counts[-1] == 0
        if t == self._last_frame:
            # the next step terminates and repeats this observation: keep a copy the caller
            # cannot modify (earlier observations are handed over without one)
            self._last_obs = {k: v.copy() for k, v in obs.items()}
            self._last_empty = empty
        return obs, empty

    def _with_channels(self, xyz: np.ndarray, ref: np.ndarray, count: int, t: int) -> np.ndarray:
        """``previous_search`` ``(SEARCH_SIZE, 5)`` float32 from its resampled points ``xyz``
        (reference box frame): the time and previous-box mask columns."""
        out = np.zeros((len(xyz), len(PREVIOUS_SEARCH_CHANNELS)), np.float32)
        if count == 0:
            return out
        out[:, :3] = xyz
        out[:, 3] = PREVIOUS_TIME
        # the reference box is the previous frame's ground truth: the given box at the first
        # step, or previous_gt; otherwise it is a prediction (or frame t's box) and uncertain
        certain = self.reference == "previous_gt" or (
            self.reference == "prediction" and t == self._start_frame + 1
        )
        outside, inside = MASK_GT if certain else MASK_PREDICTED
        threshold = extent_threshold(crop_extents(ref, [TEMPLATE_ENLARGEMENT]), np.float32)
        out[:, 4] = np.where(in_extent(xyz.T, threshold), inside, outside)
        return out

    # ------------------------------------------------------------------ crop cache

    def _new_crop_cache(self) -> CropCache:
        return CropCache(self.corridor_m, self.cell_m, self.cache_mb, self.scan_transform)

    def _scans(self, index: int) -> TrackletScans:
        """The per-tracklet crop provider (LRU by bytes; never changes an observation)."""
        return self._crop_cache.entry(index, self.tracklets[index])

    def _crops(
        self, box: np.ndarray, frames: Sequence[int], enlargements: tuple[tuple[float, float], ...]
    ) -> list[np.ndarray]:
        """:meth:`envs.scan_cache.TrackletScans.crops` of the episode's tracklet."""
        return self._crop_cache.crops(self._entry, self._index, box, frames, enlargements)

    def _target_points(self, t: int) -> int:
        return self._crop_cache.target_points(self._entry, self._index, t)

    def _add_weather(self, info: dict[str, Any]) -> None:
        weather = getattr(self.scan_transform, "info", None)
        if weather is not None:
            info["weather"] = weather

    def _warn_unseen_in_training(self) -> None:
        """Warn when a training split serves the setting's unseen (test-only) categories."""
        if self.split != "train" or self.setting is None:
            return
        leaked = [c for c in self.setting.unseen if c in (self.categories or ())]
        if leaked:
            warnings.warn(
                f"TrackingEnv on split 'train' serves the unseen categories {leaked} of setting "
                f"{self.setting.name!r}: a policy trained here sees them; pass "
                f"categories={list(self.setting.observed)} to train class-agnostically",
                UserWarning,
                stacklevel=3,
            )


def _clip(values: Sequence[float], bound: Sequence[float]) -> list[float]:
    """``min(max(v, -m), m)`` for every value (NaN passes), in conditional expressions: the
    builtins cost several times more on this per-step path."""
    return [m if v > m else -m if v < -m else v for v, m in zip(values, bound, strict=True)]


def _check_choice(name: str, value: Any, valid: Sequence[str]) -> None:
    if value not in valid:
        raise ValueError(f"unknown {name} {value!r}; valid: {', '.join(map(repr, valid))}")


def _is_int(value: Any) -> bool:
    return isinstance(value, int | np.integer) and not isinstance(value, bool)


def _check_seed(seed: Any, name: str) -> int | None:
    if seed is None:
        return None
    if not _is_int(seed):
        raise TypeError(f"{name} must be None or an int; got {seed!r}")
    if seed < 0:
        raise ValueError(f"{name} must be non-negative; got {seed}")
    return int(seed)


def _check_start_frame(value: Any, name: str) -> int | str:
    if isinstance(value, str) and value == "random":
        return value
    if not _is_int(value) or value < 0:
        raise ValueError(f"{name} must be a frame index >= 0 or 'random'; got {value!r}")
    return int(value)


def _check_observation_keys(keys: Sequence[str]) -> tuple[str, ...]:
    keys = (keys,) if isinstance(keys, str) else tuple(keys)
    valid = OBSERVATION_KEYS + OPTIONAL_OBSERVATION_KEYS
    bad = [k for k in keys if k not in valid]
    missing = [k for k in OBSERVATION_KEYS if k not in keys]
    if bad or missing or len(set(keys)) != len(keys):
        raise ValueError(
            f"observation_keys={list(keys)}: must hold {list(OBSERVATION_KEYS)} (the default "
            f"contract) plus any of {list(OPTIONAL_OBSERVATION_KEYS)}, each once"
            + (f"; unknown: {bad}" if bad else "")
        )
    return keys


def _check_max_steps(value: Any, name: str) -> int | None:
    if value is None:
        return None
    if not _is_int(value) or value < 1:
        raise ValueError(f"{name} must be None or an int >= 1; got {value!r}")
    return int(value)


# --------------------------------------------------------------------------- factories


def make_synthetic_env(
    preset: str = "small",
    sensor: str = "hdl64",
    seed: int = 0,
    split: str = "train",
    setting: str | None = None,
    categories: str | Sequence[str] | None = None,
    cache_dir: str | None = None,
    **env_kwargs: Any,
) -> TrackingEnv:
    """Entry point of ``pointtrack/Synthetic-v0``: the synthetic world ``(preset, sensor, seed)``,
    generated into the cache on first use, read as KITTI; other kwargs go to :class:`TrackingEnv`.
    """
    from envs.synthetic import ensure_world

    root = ensure_world(preset=preset, sensor=sensor, seed=seed, cache_dir=cache_dir)
    return make_kitti_env(
        root=str(root), split=split, setting=setting, categories=categories, **env_kwargs
    )


def make_kitti_env(
    root: str | None = None,
    split: str = "test",
    setting: str | None = None,
    categories: str | Sequence[str] | None = None,
    **env_kwargs: Any,
) -> TrackingEnv:
    """Entry point of ``pointtrack/KITTI-v0``: the KITTI tracking layout under ``root``."""
    from envs.data import KittiTracking, get_setting

    if root is None:
        raise ValueError(
            "pointtrack/KITTI-v0 needs root=<folder with label_02/, calib/, velodyne/>"
        )
    if isinstance(categories, str):
        categories = (categories,)
    load = categories
    if load is None and setting is not None:
        load = get_setting(setting).categories
    dataset = KittiTracking(root, split, load)
    return TrackingEnv(dataset, setting=setting, categories=categories, split=split, **env_kwargs)
