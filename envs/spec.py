"""The env's contract in one leaf module: observation keys and shapes, crop geometry, the
template / reference / sampling modes, the action bound, and :class:`EnvOptions` (the user
options of :class:`envs.tracking_env.TrackingEnv`, validated in one place).

Everyone reads it — the env, :mod:`envs.observation`, the trackers (``trackers.base``,
``trackers.registry``) and training — so it imports nothing of the project (numpy only, and
only here at module level: ``trackers`` imports it on every start).
"""

from __future__ import annotations

import dataclasses
import math
import numbers
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, fields
from typing import Any

__all__ = [
    "DEFAULT_MAX_ACTION",
    "DEFAULT_MEMORY_FRAMES",
    "DEFAULT_SPLITS",
    "MAX_MEMORY_FRAMES",
    "MEMORY_BOX_CHANNELS",
    "MEMORY_CHANNELS",
    "MEMORY_KEYS",
    "NUSCENES_MAX_ACTION",
    "OBSERVATION_KEYS",
    "OBS_SHAPES",
    "OPTIONAL_OBSERVATION_KEYS",
    "OPTIONAL_OBS_SHAPES",
    "PREVIOUS_SEARCH_CHANNELS",
    "REFERENCE_MODES",
    "RENDER_MODES",
    "RESET_OPTIONS",
    "SAMPLING_MODES",
    "SEARCH_ENLARGEMENT",
    "SEARCH_OFFSET_M",
    "SEARCH_SCALE",
    "SEARCH_SIZE",
    "SOURCES",
    "TEMPLATE_ENLARGEMENT",
    "TEMPLATE_MODES",
    "TEMPLATE_SCALE",
    "TEMPLATE_SIZE",
    "TRACKER_OPTION_KEYS",
    "EnvOptions",
    "check_max_steps",
    "check_memory_frames",
    "check_observation_keys",
    "check_seed",
    "check_start_frame",
]

# ---------------------------------------------------------------- observation

TEMPLATE_SIZE = 512
"""Points of the ``template`` observation."""
SEARCH_SIZE = 1024
"""Points of the ``search`` (and ``previous_search``) observation."""
TEMPLATE_SCALE = 1.25
"""Scale of the box a template crop is taken with (no offset)."""
SEARCH_SCALE = 1.25
SEARCH_OFFSET_M = 2.0
"""The default search crop: the reference box scaled 1.25 plus 2 m on every axis."""
SEARCH_ENLARGEMENT = (SEARCH_SCALE, SEARCH_OFFSET_M)
"""The default ``(scale, offset_m)`` of the search crop (``EnvOptions.search_enlargement``)."""
TEMPLATE_ENLARGEMENT = (TEMPLATE_SCALE, 0.0)
"""``(scale, offset_m)`` of a template crop (and of ``previous_search``'s box mask)."""

OBSERVATION_KEYS = ("template", "search", "size", "motion")
"""The default observation (always present)."""
MEMORY_KEYS = ("memory", "memory_boxes")
"""The opt-in keys of the env's memory of past frames (:mod:`envs.memory`; memory-network
trackers such as MBPTrack: Xu et al., "MBPTrack: Improving 3D Point Cloud Tracking with Memory
Networks and Box Priors", ICCV 2023)."""
OPTIONAL_OBSERVATION_KEYS = ("previous_search", *MEMORY_KEYS)
"""Opt-in observation keys (``observation_keys=``)."""
PREVIOUS_SEARCH_CHANNELS = ("x", "y", "z", "time", "mask")
"""Columns of the opt-in ``previous_search`` observation (M2-Track's input layout: Zheng et al.,
"Beyond 3D Siamese Tracking: A Motion-Centric Paradigm for 3D Single Object Tracking in Point
Clouds", CVPR 2022): the previous frame's points, their time, their previous-box mask."""
MEMORY_CHANNELS = ("x", "y", "z", "mask")
"""Columns of ``memory``: a past frame's search points (in the frame of the box it was cropped
around) and the target mask of the agent's box for that frame."""
MEMORY_BOX_CHANNELS = ("x", "y", "z", "yaw", "valid")
"""Columns of ``memory_boxes``: each memory frame's crop box in the reference box frame (m,
rad) and whether its slot holds a frame with points."""
DEFAULT_MEMORY_FRAMES = 3
"""The memory slots ``M`` by default (``EnvOptions.memory_frames``): MBPTrack's evaluation
memory in the reference configuration."""
MAX_MEMORY_FRAMES = 8
"""The most memory slots (the MBPTrack reference samples 8 frames per training tracklet)."""
OBS_SHAPES: dict[str, tuple[int, ...]] = {
    "template": (TEMPLATE_SIZE, 3),
    "search": (SEARCH_SIZE, 3),
    "size": (3,),
    "motion": (4,),
}
"""Per-sample shapes of the default observation's keys (float32; points in m, box frames)."""
OPTIONAL_OBS_SHAPES: dict[str, tuple[int, ...]] = {
    "previous_search": (SEARCH_SIZE, len(PREVIOUS_SEARCH_CHANNELS)),
    "memory": (DEFAULT_MEMORY_FRAMES, SEARCH_SIZE, len(MEMORY_CHANNELS)),
    "memory_boxes": (DEFAULT_MEMORY_FRAMES, len(MEMORY_BOX_CHANNELS)),
}
"""Per-sample shapes of the opt-in keys; the memory keys' first axis is ``memory_frames``
(shown at its default)."""

# ---------------------------------------------------------------- modes and bounds

TEMPLATE_MODES = ("first_and_previous", "first", "previous", "all", "first_and_previous_merged")
REFERENCE_MODES = ("prediction", "previous_gt", "current_gt")
SAMPLING_MODES = ("sequential", "random")
RENDER_MODES = ("rgb_array",)
RESET_OPTIONS = ("tracklet", "category", "start_frame", "max_steps", "episode_seed")
"""The keys ``reset(options=...)`` accepts."""
DEFAULT_MAX_ACTION = (5.0, 5.0, 3.0, math.pi)
"""The action bound ``a_max`` ``(dx, dy, dz, dyaw)``: metres, metres, metres, radians."""
# Key frames are 0.5 s apart (2 Hz), five times the KITTI frame interval, so the largest offset
# one step may apply is five times the KITTI default in the ground plane (the same 50 m/s bound
# on relative speed); a static object passed by an ego at 50 km/h already moves 7 m per step.
NUSCENES_MAX_ACTION = (25.0, 25.0, 3.0, math.pi)
"""The action bound of nuScenes envs (``pointtrack/NuScenes-v1``)."""
SOURCES = ("synthetic", "kitti", "nuscenes")
"""The named data sources of ``envs.tracking_env.make_tracking_env``."""
DEFAULT_SPLITS = {"synthetic": "train", "kitti": "test", "nuscenes": "val"}
"""The split each named source reads by default (the registered ids' defaults)."""

TRACKER_OPTION_KEYS = ("template_mode", "search_enlargement")
"""The options a tracker may record (``tracker.env_options``): those where training and
evaluation must agree (the template composition, the search region)."""


# ---------------------------------------------------------------- checks


def _is_int(value: Any) -> bool:
    return isinstance(value, numbers.Integral) and not isinstance(value, bool)


def check_seed(seed: Any, name: str) -> int | None:
    """``None`` or a non-negative int (``TypeError`` / ``ValueError`` naming ``name``)."""
    if seed is None:
        return None
    if not _is_int(seed):
        raise TypeError(f"{name} must be None or an int; got {seed!r}")
    if seed < 0:
        raise ValueError(f"{name} must be non-negative; got {seed}")
    return int(seed)


def check_start_frame(value: Any, name: str) -> int | str:
    """A frame index ``>= 0`` or ``"random"`` (``ValueError`` naming ``name``)."""
    if isinstance(value, str) and value == "random":
        return value
    if not _is_int(value) or value < 0:
        raise ValueError(f"{name} must be a frame index >= 0 or 'random'; got {value!r}")
    return int(value)


def check_max_steps(value: Any, name: str) -> int | None:
    """``None`` or an int ``>= 1`` (``ValueError`` naming ``name``)."""
    if value is None:
        return None
    if not _is_int(value) or value < 1:
        raise ValueError(f"{name} must be None or an int >= 1; got {value!r}")
    return int(value)


def check_memory_frames(value: Any) -> int:
    """``memory_frames`` as an int in ``1..MAX_MEMORY_FRAMES`` (``ValueError`` naming it)."""
    if not _is_int(value) or not 1 <= value <= MAX_MEMORY_FRAMES:
        raise ValueError(
            f"memory_frames={value!r}: expected an integer in 1..{MAX_MEMORY_FRAMES} "
            f"(frames the env keeps in the 'memory' observation)"
        )
    return int(value)


def _check_choice(name: str, value: Any, valid: Sequence[str]) -> None:
    if value not in valid:
        raise ValueError(f"unknown {name} {value!r}; valid: {', '.join(map(repr, valid))}")


def _finite_floats(value: Any) -> tuple[float, ...] | None:
    """``value`` (a sequence or a 1-d array of real numbers) as a tuple of finite floats, or
    ``None`` when it is not one."""
    if isinstance(value, str | bytes):
        return None
    try:
        items = list(value)
    except TypeError:
        return None
    if not all(isinstance(v, numbers.Real) for v in items):
        return None
    out = tuple(float(v) for v in items)
    return out if all(map(math.isfinite, out)) else None


def check_observation_keys(keys: str | Sequence[str]) -> tuple[str, ...]:
    """The default keys plus any opt-in keys, each once (``ValueError`` naming them)."""
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


# ---------------------------------------------------------------- options


@dataclass(frozen=True)
class EnvOptions:
    """The user options of :class:`envs.tracking_env.TrackingEnv` (everything but the data:
    ``dataset``, ``setting``, ``categories``, ``split``), validated and normalised on
    construction: a bad value raises ``ValueError`` (``TypeError`` for a wrong type) naming the
    field and the value.

    - ``sampling``: ``"sequential"`` (visit the tracklets in order) or ``"random"``.
    - ``template_mode``: one of :data:`TEMPLATE_MODES` (see :mod:`envs.template`).
    - ``reference``: the box the search region is cropped around: ``"prediction"`` (default),
      ``"previous_gt"``, ``"current_gt"``.
    - ``reward``, ``reward_kwargs``: a reward name of :mod:`envs.rewards` built with the
      kwargs, or a picklable callable ``(pred, gt, prev_pred, step, info) -> float``. Checked
      for its type here; :func:`envs.rewards.make_reward` resolves the name when the env is built.
    - ``max_action``: the action bound ``(4,)`` (m, m, m, rad); stored as a tuple of floats.
    - ``render_mode``: ``None`` or ``"rgb_array"``.
    - ``scan_transform``: see :data:`envs.scan_cache.ScanTransform` (the weather hook). If it
      has an ``info`` attribute, that value is reported as ``info["weather"]``.
    - ``corridor_m``: margin (m) of the per-tracklet corridor of the crop cache
      (:mod:`envs.scan_cache`): each frame keeps, indexed by ``cell_m`` xy cells, the scan
      points within reach of any of the tracklet's boxes; crops elsewhere read a whole-scan
      cell index built on demand. Neither changes an observation. ``None``: crop whole scans
      every step (the no-cache baseline). ``cache_mb``: memory budget of the cache (LRU over
      tracklets).
    - ``episode_seed``: ``None`` (default: episodes draw from the env's ``np_random`` one after
      the other) or an int: every episode draws its resampling from its own generator seeded
      by ``(episode_seed, tracklet id)``, so what it observes for given actions depends only on
      its tracklet (and start frame) — not on the episodes before it, the tracklet order or
      filter, or the vector sub-env that runs it. Settable on the env between episodes.
    - ``start_frame``, ``max_steps``: the defaults of the reset options (``0``, ``None``: whole
      tracklets); ``start_frame`` may be ``"random"``.
    - ``observation_keys``: :data:`OBSERVATION_KEYS` plus any of
      :data:`OPTIONAL_OBSERVATION_KEYS`.
    - ``search_enlargement``: ``(scale, offset_m)`` of the search crop (default ``(1.25, 2.0)``;
      GPT's paper crops ``(1.0, 4.0)``); trackers must be evaluated with the region they were
      trained with. Stored as a tuple of floats.
    - ``memory_frames``: the slots ``M`` of the opt-in :data:`MEMORY_KEYS` (default
      :data:`DEFAULT_MEMORY_FRAMES`, at most :data:`MAX_MEMORY_FRAMES`); unused without them.
    """

    sampling: str = "sequential"
    template_mode: str = "first_and_previous"
    reference: str = "prediction"
    reward: str | Callable[..., float] = "iou_3d"
    reward_kwargs: Mapping[str, Any] | None = None
    max_action: Sequence[float] = DEFAULT_MAX_ACTION
    render_mode: str | None = None
    scan_transform: Callable[..., Any] | None = None
    corridor_m: float | None = 2.0
    cell_m: float = 1.0
    cache_mb: float = 512.0
    episode_seed: int | None = None
    start_frame: int | str = 0
    max_steps: int | None = None
    observation_keys: Sequence[str] = OBSERVATION_KEYS
    search_enlargement: Sequence[float] = SEARCH_ENLARGEMENT
    memory_frames: int = DEFAULT_MEMORY_FRAMES

    def __post_init__(self) -> None:
        self.check()

    def check(self) -> None:
        """Validate every field and store the normalised values (tuples, ints, floats)."""
        _check_choice("sampling", self.sampling, SAMPLING_MODES)
        _check_choice("template_mode", self.template_mode, TEMPLATE_MODES)
        _check_choice("reference", self.reference, REFERENCE_MODES)
        if self.render_mode is not None:
            _check_choice("render_mode", self.render_mode, RENDER_MODES)
        if not (isinstance(self.reward, str) or callable(self.reward)):
            raise TypeError(f"reward must be a name or a callable; got {self.reward!r}")
        if self.reward_kwargs is not None:
            if not isinstance(self.reward_kwargs, Mapping):
                raise TypeError(f"reward_kwargs must be a dict; got {self.reward_kwargs!r}")
            if self.reward_kwargs and not isinstance(self.reward, str):
                raise ValueError("reward_kwargs apply to a reward name, not to a callable")
        if self.scan_transform is not None and not callable(self.scan_transform):
            raise TypeError(f"scan_transform must be callable; got {self.scan_transform!r}")
        a_max = _finite_floats(self.max_action)
        if a_max is None or len(a_max) != 4 or min(a_max) <= 0:
            raise ValueError(
                f"max_action must be 4 positive finite numbers; got {self.max_action!r}"
            )
        corridor_ok = self.corridor_m is None or (
            isinstance(self.corridor_m, numbers.Real) and self.corridor_m >= 0
        )
        cell_ok = isinstance(self.cell_m, numbers.Real) and self.cell_m > 0
        if not (corridor_ok and cell_ok):
            raise ValueError(
                f"corridor_m must be >= 0 and cell_m > 0; got {self.corridor_m}, {self.cell_m}"
            )
        if not (isinstance(self.cache_mb, numbers.Real) and self.cache_mb >= 0):
            raise ValueError(f"cache_mb must be a number >= 0; got {self.cache_mb!r}")
        enlargement = _finite_floats(self.search_enlargement)
        if (
            enlargement is None
            or len(enlargement) != 2
            or not (enlargement[0] > 0 and enlargement[1] >= 0)
        ):
            raise ValueError(
                f"search_enlargement must be (scale > 0, offset_m >= 0), got "
                f"{self.search_enlargement!r}"
            )
        normalised = {
            "max_action": a_max,
            "search_enlargement": enlargement,
            "episode_seed": check_seed(self.episode_seed, "episode_seed"),
            "start_frame": check_start_frame(self.start_frame, "start_frame"),
            "max_steps": check_max_steps(self.max_steps, "max_steps"),
            "observation_keys": check_observation_keys(self.observation_keys),
            "memory_frames": check_memory_frames(self.memory_frames),
            "cell_m": float(self.cell_m),
            "cache_mb": float(self.cache_mb),
        }
        for name, value in normalised.items():
            object.__setattr__(self, name, value)

    @classmethod
    def names(cls) -> tuple[str, ...]:
        """The option names, in declaration order."""
        return tuple(f.name for f in fields(cls))

    def replace(self, **changes: Any) -> EnvOptions:
        """A copy with ``changes`` (validated; an unknown name is a ``TypeError`` naming it)."""
        return dataclasses.replace(self, **changes)

    def to_kwargs(self) -> dict[str, Any]:
        """The options as ``TrackingEnv`` keywords (a shallow dict of the fields)."""
        return {name: getattr(self, name) for name in self.names()}

    def tracker_options(self) -> dict[str, Any]:
        """The :data:`TRACKER_OPTION_KEYS` entries (what a tracker's ``env_options`` holds)."""
        return {name: getattr(self, name) for name in TRACKER_OPTION_KEYS}
