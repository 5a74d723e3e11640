"""The Gymnasium environment for 3D single-object tracking in LiDAR point clouds.

One episode is one tracklet (or a clip of one). See :class:`TrackingEnv` for the contract and
its version history; :func:`make_tracking_env` is the one factory (the entry points of the
registered ids, :func:`make_synthetic_env` and :func:`make_kitti_env`, call it). Around the env:
:mod:`envs.spec` (contract, options), :mod:`envs.episodes` (scheduling), :mod:`envs.template`,
:mod:`envs.scan_cache` (crops), :mod:`envs.rewards`, :mod:`envs.observation`, :mod:`envs.sources`.
"""

from __future__ import annotations

import copy
import math
from collections.abc import Sequence
from types import MappingProxyType
from typing import Any

import gymnasium as gym
import numpy as np

from envs.data import Setting, check_setting_layout, get_setting
from envs.data.toy import make_toy_dataset
from envs.data.tracklet import Tracklet
from envs.episodes import EpisodeSchedule
from envs.geometry import apply_offset_pair, iou_pair, offset_between_pair
from envs.memory import FrameMemory
from envs.observation import (
    SEARCH_SIZE,
    TEMPLATE_SIZE,
    observation_space,
    previous_search_points,
    resample_into,
)
from envs.render import render_birds_eye, render_search_region
from envs.rewards import (
    ROUND_OFF,
    RewardFn,
    available_rewards,
    check_reward,
    finite_reward,
    make_reward,
    snap_iou,
)
from envs.scan_cache import (
    CropCache,
    ScanTransform,
    TrackletScans,
    check_scan_transform,
    crop_canonical,
)
from envs.sources import SOURCE_KEYWORDS, EnvData, open_dataset
from envs.spec import (
    DEFAULT_SPLITS,
    MEMORY_KEYS,
    NUSCENES_MAX_ACTION,
    OBSERVATION_KEYS,
    OPTIONAL_OBSERVATION_KEYS,
    REFERENCE_MODES,
    RESET_OPTIONS,
    TEMPLATE_ENLARGEMENT,
    TEMPLATE_MODES,
    EnvOptions,
)
from envs.template import TemplateCrops

__all__ = [
    "OBSERVATION_KEYS",
    "OPTIONAL_OBSERVATION_KEYS",
    "REFERENCE_MODES",
    "RESET_OPTIONS",
    "REWARDS",
    "TEMPLATE_MODES",
    "EnvOptions",
    "TrackingEnv",
    "crop_canonical",
    "make_kitti_env",
    "make_synthetic_env",
    "make_toy_dataset",
    "make_tracking_env",
]

REWARDS = available_rewards()
"""The built-in reward names (:func:`envs.rewards.available_rewards` also lists registered ones)."""


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
    ``yaw + dyaw``, with the given box's size. Default ``max_action = (5, 5, 3, pi)``. A NaN/inf
    action raises ``ValueError``; an out-of-range one is clipped (``info["action_clipped"]``).
    Actions are used in float64: the exact ground-truth offset yields the ground-truth box (IoU
    and centre error within 1e-9 of 1 and 0 are reported as exactly 1 and 0).

    ## Observation Space
    ``Dict`` of float32 arrays (fresh arrays on every call):

    - ``template (512, 3)``: target points, see the template modes below (box frames), m;
    - ``search (1024, 3)``: the current frame's points inside the reference box scaled 1.25 plus
      2 m on every axis, in the reference box frame, m;
    - ``size (3,)``: the target's ``l, w, h`` (the given box's), m;
    - ``motion (4,)``: the last predicted motion ``(dx, dy, dz, dyaw)``: the offset from the
      prediction two frames back to the last one, in the former's frame (zeros at the first
      step), so motion-aware trackers stay stateless.

    Opt-in (``observation_keys=(*OBSERVATION_KEYS, "previous_search")``), M2-Track's input
    (Zheng et al., CVPR 2022): ``previous_search (1024, 5)``, the previous frame cropped and
    resampled like the search region around the same reference box, columns ``x, y, z, time,
    mask`` (:func:`envs.observation.previous_search_points`); zeros when the crop is empty
    (``info["empty_previous_search"]``). Opt-in ``memory (M, 1024, 4)`` and ``memory_boxes (M,
    5)`` (``M = memory_frames``): the last M frames' search regions as the agent saw them, with
    the mask of its box for each, and their crop boxes (:mod:`envs.memory`; MBPTrack's input).

    Template modes: ``template_mode`` of :class:`envs.template.TemplateCrops` (default
    ``"first_and_previous"``). Point sets are resampled with ``self.np_random``, or with a
    generator seeded by ``(episode_seed, tracklet id)`` when an episode seed is set; an empty
    set gives zeros and ``info["empty_template"]`` / ``info["empty_search"]`` say so.

    ## Rewards
    ``reward``: a name of :mod:`envs.rewards` (``"iou_3d"``, the default: the oriented 3D IoU of
    the new box with the ground truth; ``"iou_bev"``, ``"neg_center_error"``, ``"iou_delta"``,
    ``"success"``, or one registered with :func:`envs.rewards.register_reward`) built with
    ``reward_kwargs``; or a picklable callable ``reward(pred (7,), gt (7,), prev_pred (7,), step,
    info) -> float`` (``info``: this step's, read-only; a non-finite value raises ``ValueError``).

    ## Starting State
    ``reset`` starts the next tracklet: ``sampling="sequential"`` visits the tracklets in order
    (``tracklet_order``, default all, wrapping around), ``"random"`` draws one with
    ``self.np_random``. Reset with a seed restarts the sequential order. The episode's first
    frame is ``start_frame`` (default 0; its ground-truth box is the given box) and the first
    observation is for the frame after it. Reset ``info``: ``tracklet``, ``category``,
    ``observed``, ``init_box`` (the given box), ``start_frame``, ``empty_template``,
    ``empty_search`` (plus ``weather``, see the step info). ``reset(options=...)`` takes
    ``tracklet`` (index or id), ``category``, ``start_frame`` (or ``"random"``), ``max_steps``
    (a clip) and ``episode_seed`` (see :meth:`envs.episodes.EpisodeSchedule.options`); the
    constructor's options of those names are their defaults.

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
    - ``dataset``, ``setting``, ``categories``, ``split``: what the env serves (see
      :meth:`envs.sources.EnvData.select`): a dataset (anything with ``.tracklets``) or a
      KITTI-layout folder, the class-agnostic setting (``observed`` flags follow it), the
      categories (default: the setting's). Tracklets shorter than two frames are skipped.
    - ``options`` (an :class:`envs.spec.EnvOptions`) and keywords naming its fields (they
      override ``options``'s; every field is documented and validated there).

    ## Version History
    An id's version names what an agent observes and earns for given seeds and actions; the
    ``-v0`` ids changed that twice before versions were kept:

    - v1 (2026-12-05): ``pointtrack/{Synthetic,KITTI,NuScenes}-v1``, behaving as v0 at its
      last state; the ``-v0`` ids stay as aliases that warn (``DeprecationWarning``).
    - v0, 2026-12-03 (4c81984): reward callables take ``(pred, gt, prev_pred, step, info)``;
      named rewards; reset options and clips. v0, 2026-12-02 (fcd21bc): ``episode_seed``.
      v0, 2026-11-25 (1255736): the first env. Additions that change no existing agent's
      observations or rewards, and the details: docs/env.md's version history.
    """

    metadata = {"render_modes": ["rgb_array"], "render_fps": 10}

    def __init__(
        self,
        dataset: Any,
        *,
        setting: str | Setting | None = None,
        categories: str | Sequence[str] | None = None,
        split: str | None = None,
        options: EnvOptions | None = None,
        **option_kwargs: Any,
    ) -> None:
        if options is None:
            options = EnvOptions(**option_kwargs)
        elif option_kwargs:
            options = options.replace(**option_kwargs)
        reward, reward_kwargs = options.reward, dict(options.reward_kwargs or {})
        if isinstance(reward, str):
            self.reward_fn: RewardFn = make_reward(reward, **reward_kwargs)
        else:
            self.reward_fn = check_reward(reward)
        self.reward_mode = reward
        self.reward_kwargs = reward_kwargs
        self.observation_keys = options.observation_keys
        self._previous_search = "previous_search" in self.observation_keys
        wants_memory = bool(set(MEMORY_KEYS) & set(self.observation_keys))
        self._memory = FrameMemory(options.memory_frames) if wants_memory else None
        data = EnvData.select(dataset, split=split, setting=setting, categories=categories)
        self.dataset, self.split, self.setting = data.dataset, data.split, data.setting
        self.categories, self.tracklets = data.categories, data.tracklets
        self.sampling, self.template_mode = options.sampling, options.template_mode
        self.search_enlargement, self.reference = options.search_enlargement, options.reference
        self.max_action = a_max = np.array(options.max_action, dtype=np.float64)
        self.render_mode = options.render_mode
        self.scan_transform = check_scan_transform(options.scan_transform)
        self.corridor_m, self.cell_m = options.corridor_m, options.cell_m
        self.cache_mb = options.cache_mb
        self._schedule = EpisodeSchedule(self.tracklets, options)
        self.action_space = gym.spaces.Box(
            -a_max.astype(np.float32), a_max.astype(np.float32), (4,), np.float32
        )
        self.observation_space = observation_space(self.observation_keys, options.memory_frames)
        self._motion_hi = self.observation_space["motion"].high.astype(np.float64).tolist()
        self._max_action_list = a_max.tolist()
        self._crop_cache = self._new_crop_cache()
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
        return self._schedule.episode_seed

    @episode_seed.setter
    def episode_seed(self, seed: int | None) -> None:
        self._schedule.episode_seed = seed

    @property
    def cache_stats(self) -> dict[str, int]:
        """Crops served by the corridor indices, the whole-scan cell indices and whole scans
        (``corridor``, ``cell_index``, ``full_scan``) since the env was made, cloned or loaded."""
        return self._crop_cache.stats

    @property
    def cache_bytes(self) -> int:
        """Bytes held by the crop cache."""
        return self._crop_cache.nbytes

    @property
    def tracklet_order(self) -> list[int]:
        """Indices visited by sequential sampling (settable, e.g. per vector sub-env)."""
        return self._schedule.tracklet_order

    @tracklet_order.setter
    def tracklet_order(self, order: Sequence[int] | None) -> None:
        self._schedule.tracklet_order = order

    def set_scan_transform(self, transform: ScanTransform | None) -> None:
        """Install (or remove, ``None``) the whole-scan transform and drop the scan cache, so no
        scan made under the previous transform is served again. Crops already taken in the
        current episode (its templates) stay; install before ``reset`` for clean episodes."""
        self.scan_transform = check_scan_transform(transform)
        self._crop_cache.clear(transform)
        if self._tracklet is not None:
            self._entry = self._scans(self._index)

    def clone(self) -> TrackingEnv:
        """A fresh copy of this env sharing its (read-only) dataset and tracklets, with its own
        episode state and cache (e.g. the sub-envs of a ``SyncVectorEnv``)."""
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
            self._schedule.cursor = 0
        opts = self._schedule.options(options)
        index = self._schedule.choose(opts["tracklet"], opts["category"], self.np_random)
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
        if self._tracklet is None:
            return render_birds_eye(np.zeros((0, 3), np.float32), [], frame_box=None, extent_m=10.0)
        # just after reset: the first search region, no prediction yet
        state = self._render_state or (
            self._search_crop,
            self._ref,
            self._tracklet.boxes[self._t],
            None,
        )
        return render_search_region(*state, self.search_enlargement)

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
        fn, gt = self.reward_fn, np.array(gt, dtype=np.float64)
        return finite_reward(
            fn(pred.copy(), gt, prev_pred.copy(), step, MappingProxyType(info)), fn
        )

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
            "target_points": self._crop_cache.target_points(self._entry, self._index, self._t),
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
        self._first_crop: np.ndarray | None = None
        self._templates: TemplateCrops | None = None
        self._last_obs = None
        self._last_empty: dict[str, bool] = {}
        self._search_crop = np.zeros((0, 3), np.float32)
        self._render_state = None
        if self._memory is not None:
            self._memory.clear()

    def _start(self, index: int, opts: dict[str, Any]) -> None:
        """Episode state for tracklet ``index`` (no observation: see :meth:`_observation`)."""
        if self._entry is not None:
            self._entry.end_episode()
        self._clear_episode()
        tr = self.tracklets[index]
        start = self._schedule.first_frame(tr, opts["start_frame"], self.np_random)
        self._tracklet = tr
        self._index = index
        self._entry = self._scans(index)
        self._observed = bool(self.is_observed(tr.category))
        self._resample_rng = self._schedule.resample_rng(
            opts["episode_seed"], tr, start, self.np_random
        )
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
        first = self._entry.template_crops.get(start)
        if first is None:  # the given box's crop: the same in every episode from this frame
            (first,) = self._crops(box0, (start,), (TEMPLATE_ENLARGEMENT,))
            self._entry.template_crops[start] = first
        self._first_crop = first
        self._templates = TemplateCrops(self.template_mode, first)

    def _reference_box(self, t: int) -> np.ndarray:
        if self.reference == "prediction":
            return self._preds[t - 1 - self._start_frame]
        if self.reference == "previous_gt":
            return np.asarray(self._tracklet.boxes[t - 1], dtype=np.float64)
        return np.asarray(self._tracklet.boxes[t], dtype=np.float64)

    def _observation(self) -> tuple[dict[str, np.ndarray], dict[str, bool]]:
        """The observation for frame ``self._t`` (uses the predictions up to ``t - 1``) and its
        ``empty_*`` flags: every crop and the resampling."""
        t, start, templates = self._t, self._start_frame, self._templates
        ref = self._reference_box(t)
        # the crops around the reference box, taken in one pass: the search region, the opt-in
        # previous search region, and the previous template when its box is the reference
        frames, enlargements = [t], [self.search_enlargement]
        if self._previous_search:
            frames.append(t - 1)
            enlargements.append(self.search_enlargement)
        new_prev = templates.needs_previous(t, start)
        if new_prev and self.reference == "prediction":
            frames.append(t - 1)
            enlargements.append(TEMPLATE_ENLARGEMENT)
        crops = self._crops(ref, tuple(frames), tuple(enlargements))
        search_pts = crops[0]
        if new_prev:
            if self.reference == "prediction":
                templates.add_previous(crops[-1])
            else:
                prev_box = self._preds[t - 1 - start]
                (prev,) = self._crops(prev_box, (t - 1,), (TEMPLATE_ENLARGEMENT,))
                templates.add_previous(prev)
        template = np.empty((TEMPLATE_SIZE, 3), np.float32)
        search = np.empty((SEARCH_SIZE, 3), np.float32)
        sets, outs = templates.point_sets(template)
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
            # the reference box is the previous frame's ground truth: the given box at the
            # first step, or previous_gt; otherwise a prediction (or frame t's box): uncertain
            certain = self.reference == "previous_gt" or (
                self.reference == "prediction" and t == start + 1
            )
            obs["previous_search"] = previous_search_points(previous, ref, counts[-1], certain)
            empty["empty_previous_search"] = counts[-1] == 0
        if self._memory is not None:  # frame t - 1 as the agent saw it, with its box for it
            if t == start + 1:  # the episode's first frame: a crop around the given box
                (crop,) = self._crops(self._preds[0], (start,), (self.search_enlargement,))
                self._memory.add_crop(crop, self._preds[0], self._resample_rng)
            memory = self._memory.step(self._preds[t - 1 - start], search, n_search, ref)
            obs.update({k: v for k, v in memory.items() if k in self.observation_keys})
        if t == self._last_frame:
            # the next step terminates and repeats this observation: keep a copy the caller
            # cannot modify (earlier observations are handed over without one)
            self._last_obs = {k: v.copy() for k, v in obs.items()}
            self._last_empty = empty
        return obs, empty

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

    def _add_weather(self, info: dict[str, Any]) -> None:
        weather = getattr(self.scan_transform, "info", None)
        if weather is not None:
            info["weather"] = weather


def _clip(values: Sequence[float], bound: Sequence[float]) -> list[float]:
    """``min(max(v, -m), m)`` for every value (NaN passes), in conditional expressions: the
    builtins cost several times more on this per-step path."""
    return [m if v > m else -m if v < -m else v for v, m in zip(values, bound, strict=True)]


# --------------------------------------------------------------------------- factories


def make_tracking_env(
    source: Any = "synthetic",
    *,
    split: str | None = None,
    setting: str | Setting | None = None,
    categories: str | Sequence[str] | None = None,
    options: EnvOptions | None = None,
    **kwargs: Any,
) -> TrackingEnv:
    """The one factory of :class:`TrackingEnv`: a data source and the options.

    Args:
        source: a named source of :data:`envs.spec.SOURCES` (``"synthetic"``, ``"kitti"``,
            ``"nuscenes"``), read at ``split`` (default :data:`envs.spec.DEFAULT_SPLITS`), or a
            dataset (anything with ``.tracklets``; shared, not copied).
        setting: the class-agnostic setting (a named source's: ``ValueError`` otherwise).
        categories: the categories to serve (default: the setting's); a named source reads only
            these categories.
        options: the env's :class:`envs.spec.EnvOptions`.
        kwargs: a named source's keywords (:data:`envs.sources.SOURCE_KEYWORDS`: ``root``,
            ``preset``, ``sensor``, ``seed``, ``version``, ``cache_dir``,
            ``allow_missing_scenes``; see :func:`envs.sources.open_dataset`), and option fields
            (they override ``options``'s). Without ``options``, a nuScenes source's
            ``max_action`` defaults to :data:`envs.spec.NUSCENES_MAX_ACTION`.
    """
    source_kwargs = {k: kwargs.pop(k) for k in SOURCE_KEYWORDS if k in kwargs}
    if isinstance(source, str):
        if setting is not None:  # a setting of the source's layout, before any data is read
            check_setting_layout(setting, "nuscenes" if source == "nuscenes" else "kitti")
        split = DEFAULT_SPLITS.get(source) if split is None else split
        load = (categories,) if isinstance(categories, str) else categories
        if load is None and setting is not None:
            load = get_setting(setting).categories
        dataset = open_dataset(source, split, load, **source_kwargs)
        if source == "nuscenes" and options is None:
            kwargs.setdefault("max_action", NUSCENES_MAX_ACTION)
    elif source_kwargs:
        raise ValueError(f"{sorted(source_kwargs)} apply to a named source, not to a dataset")
    else:
        dataset = source
    return TrackingEnv(
        dataset, setting=setting, categories=categories, split=split, options=options, **kwargs
    )


def make_synthetic_env(**kwargs: Any) -> TrackingEnv:
    """Entry point of ``pointtrack/Synthetic-v1``: :func:`make_tracking_env` of the synthetic world
    ``(preset, sensor, seed)`` (default small / hdl64 / 0, cached, KITTI layout), split train."""
    return make_tracking_env("synthetic", **kwargs)


def make_kitti_env(**kwargs: Any) -> TrackingEnv:
    """Entry point of ``pointtrack/KITTI-v1``: :func:`make_tracking_env` of the KITTI tracking
    layout under ``root`` (required), split ``"test"`` by default."""
    return make_tracking_env("kitti", **kwargs)
