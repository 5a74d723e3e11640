"""The Gymnasium environment for 3D single-object tracking in LiDAR point clouds.

One episode is one tracklet: the target's box is given in frame 0, and at every later frame the
agent moves the box. See :class:`TrackingEnv` for the full contract and ``DESIGN.md`` ("The
environment contract"). The registered ids (``pointtrack/Synthetic-v0``, ``pointtrack/KITTI-v0``)
are built by :func:`make_synthetic_env` and :func:`make_kitti_env`. :func:`make_toy_dataset`
builds a tiny in-memory dataset (a box-shaped target moving along a line, plus clutter) for tests
and examples.
"""

from __future__ import annotations

import math
import os
from collections import OrderedDict
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from typing import Any

import gymnasium as gym
import numpy as np
from gymnasium import spaces

from envs.data.tracklet import Tracklet
from envs.geometry import apply_offset_pair, iou_bev, iou_pair, offset_between_pair
from envs.observation import (
    SEARCH_OFFSET_M,
    SEARCH_SCALE,
    SEARCH_SIZE,
    TEMPLATE_SCALE,
    TEMPLATE_SIZE,
    box_frame,
    crop_box_frame,
    crop_extents,
    crop_parts,
    extent_threshold,
    resample_into,
)

__all__ = [
    "DEFAULT_MAX_ACTION",
    "REFERENCE_MODES",
    "REWARDS",
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

TEMPLATE_MODES = ("first_and_previous", "first", "previous", "all")
REFERENCE_MODES = ("prediction", "previous_gt", "current_gt")
REWARDS = ("iou_3d", "iou_bev", "neg_center_error")
SAMPLING_MODES = ("sequential", "random")
RESET_OPTIONS = ("tracklet",)
DEFAULT_MAX_ACTION = (5.0, 5.0, 3.0, math.pi)

POINT_BOUND_M = 100.0
"""Bound of the point observation spaces (metres, box frame); crops never reach it for boxes
smaller than ~150 m."""
SIZE_BOUND_M = 100.0
MOTION_BOUND_M = 100.0
TEMPLATE_ENLARGEMENT = (TEMPLATE_SCALE, 0.0)
SEARCH_ENLARGEMENT = (SEARCH_SCALE, SEARCH_OFFSET_M)
"""``(scale, offset_m)`` of the template and search crops."""
ROUND_OFF = 1e-9
"""IoUs above ``1 - ROUND_OFF`` are reported as 1 and centre errors below it (metres) as 0: the
exact ground-truth offset reproduces the ground-truth box only up to float round-off (~1e-15),
and OPE's last Success threshold (IoU >= 1) and first Precision threshold (error <= 0) are exact.
"""

ScanTransform = Callable[[np.ndarray, str, int], np.ndarray]
"""``scan_transform(points (N, 4) float32, tracklet_id, scene_frame) -> (N', 4) float32``: applied
to the whole scan of a frame before any cropping (the weather hook). Must be picklable and
deterministic given ``(tracklet_id, scene_frame)`` (corrupted scans are cached)."""


# --------------------------------------------------------------------------- spatial cache


def _cells(xy: np.ndarray, cell_m: float) -> tuple[np.ndarray, np.ndarray]:
    """Global grid cell indices ``(ix, iy)`` int64 of points ``(N, 2+)`` (cells of ``cell_m``)."""
    ix = np.floor(xy[:, 0].astype(np.float64) / cell_m).astype(np.int64)
    iy = np.floor(xy[:, 1].astype(np.float64) / cell_m).astype(np.int64)
    return ix, iy


def _canonical(local: np.ndarray, world_xy: np.ndarray, cell_m: float) -> np.ndarray:
    """Reorder a crop (rows in scan order) into the canonical order: by global cell ``(ix, iy)``,
    ties in scan order. Both cache paths produce this order, so they agree exactly."""
    if len(local) < 2:
        return local
    ix, iy = _cells(world_xy, cell_m)
    return local[np.lexsort((iy, ix))]


def crop_canonical(
    points: np.ndarray, box: np.ndarray, scale: float, offset_m: float, cell_m: float = 1.0
) -> np.ndarray:
    """What the env crops: ``crop_box_frame(points[:, :3], box, scale, offset_m)`` ``(M, 3)``
    float32, rows in the canonical order (by global ``cell_m`` grid cell of the world x, y;
    ties in scan order) that the corridor cache produces without sorting."""
    xyz = np.asarray(points)[:, :3]
    # carry the world x, y through the crop (extra columns pass unchanged) for the order
    cropped = crop_box_frame(np.concatenate([xyz, xyz[:, :2]], axis=1), box, scale, offset_m)
    return _canonical(cropped[:, :3], cropped[:, 3:5], cell_m)


class _Corridor:
    """The cells of a global xy grid near a tracklet's trajectory.

    Every box of the tracklet is treated as a position a reference box may take (boxes are in
    their own frame's LiDAR frame; a prediction that ignores ego motion stays near them). A cell
    is in the corridor when it overlaps the square of half side ``r + margin_m`` around a box
    centre, ``r`` the circumscribed radius of the box's search region. Covers ``nx * ny`` cells
    from global cell ``(ix0, iy0)``.
    """

    def __init__(self, boxes: np.ndarray, size0: np.ndarray, margin_m: float, cell_m: float):
        sizes = np.maximum(boxes[:, 3:5], size0[None, :2])
        half = sizes * (0.5 * SEARCH_SCALE) + SEARCH_OFFSET_M
        reach = np.hypot(half[:, 0], half[:, 1]) + margin_m  # (T,)
        lo = np.floor((boxes[:, :2] - reach[:, None]) / cell_m).astype(np.int64)
        hi = np.floor((boxes[:, :2] + reach[:, None]) / cell_m).astype(np.int64)
        self.cell = float(cell_m)
        self.ix0, self.iy0 = (int(v) for v in lo.min(0))
        self.nx = int(hi[:, 0].max()) - self.ix0 + 1
        self.ny = int(hi[:, 1].max()) - self.iy0 + 1
        occ = np.zeros((self.nx, self.ny), dtype=bool)
        for (a0, b0), (a1, b1) in zip(lo, hi, strict=True):
            occ[a0 - self.ix0 : a1 - self.ix0 + 1, b0 - self.iy0 : b1 - self.iy0 + 1] = True
        self.occupancy = occ
        # summed-area table (Python lists: a query reads 4 entries, no numpy call)
        sat = np.zeros((self.nx + 1, self.ny + 1), dtype=np.int64)
        sat[1:, 1:] = occ.cumsum(0).cumsum(1)
        self._sat = sat.tolist()
        # rough footprint (the SAT's Python ints ~32 B each)
        self.nbytes = occ.nbytes + 40 * sat.size

    def cell_ranges(
        self, box: np.ndarray, enlargements: Sequence[tuple[float, float]]
    ) -> list[tuple[int, int, int, int] | None]:
        """For every ``(scale, offset_m)``: the corridor-local cells ``(x0, x1, y0, y1)``
        covering the xy bound of ``box`` so enlarged, or ``None`` when part of it lies outside
        the corridor."""
        bx, by, _, bl, bw, _, yaw = box.tolist()
        c, s = abs(math.cos(yaw)), abs(math.sin(yaw))
        sat, cell, out = self._sat, self.cell, []
        for scale, offset_m in enlargements:
            hl = 0.5 * scale * bl + offset_m
            hw = 0.5 * scale * bw + offset_m
            ex = c * hl + s * hw + 1e-3  # pad: a bound only; the exact crop follows
            ey = s * hl + c * hw + 1e-3
            x0 = math.floor((bx - ex) / cell) - self.ix0
            x1 = math.floor((bx + ex) / cell) - self.ix0
            y0 = math.floor((by - ey) / cell) - self.iy0
            y1 = math.floor((by + ey) / cell) - self.iy0
            inside = x0 >= 0 and y0 >= 0 and x1 < self.nx and y1 < self.ny
            if inside:  # and every cell occupied
                occupied = sat[x1 + 1][y1 + 1] - sat[x0][y1 + 1] - sat[x1 + 1][y0] + sat[x0][y0]
                inside = occupied == (x1 - x0 + 1) * (y1 - y0 + 1)
            out.append((x0, x1, y0, y1) if inside else None)
        return out


@dataclass
class _FrameIndex:
    """Corridor points of one frame in canonical order (by cell, row-major; ties in scan
    order), as coordinate rows (what :func:`envs.observation.box_frame` reads), with the first
    point of every cell of the corridor's grid: the points of cells ``y0..y1`` of grid row
    ``x`` are ``xyz[:, starts[x, y0] : starts[x, y1 + 1]]`` (``starts[x, ny]`` ends the row)."""

    xyz: np.ndarray  # (3, M) float32
    starts: np.ndarray  # (nx, ny + 1) int32
    target_points: int  # scan points inside the frame's ground-truth box

    @property
    def nbytes(self) -> int:
        return self.xyz.nbytes + self.starts.nbytes


BRIDGE_POINTS = 64
"""Consecutive row runs of a corridor gather are joined when at most this many points lie
between them: a separate run costs a slice and a concatenated piece (~1 us), a gathered point
~20 ns of array work, and the points in between (cells outside the query) never pass the exact
crop."""


class _TrackletScans:
    """Per-tracklet crops: lazily built per-frame corridor indices, a whole-scan fallback.

    Every crop equals ``crop_box_frame(whole scan, box, scale, offset_m)`` up to the row order,
    which is canonical (see :func:`_canonical`) on both paths, so the cache never changes an
    observation. With ``corridor=None`` every crop reads the whole scan (the no-cache baseline).
    """

    def __init__(
        self,
        tracklet: Tracklet,
        transform: ScanTransform | None,
        corridor: _Corridor | None,
        cell_m: float,
    ):
        self.tracklet = tracklet
        self.transform = transform
        self.corridor = corridor
        self.cell = float(cell_m)
        self.frames: dict[int, _FrameIndex] = {}
        self.nbytes = 0 if corridor is None else corridor.nbytes
        self._full: OrderedDict[int, np.ndarray] = OrderedDict()  # last whole scans (fallback)
        self._thresholds: dict[tuple[float, ...], np.ndarray] = {}
        self.first_crop: np.ndarray | None = None  # frame 0's template crop, set by the env

    def scan(self, t: int) -> np.ndarray:
        """Whole (transformed) scan of the tracklet's ``t``-th frame ``(N, 4)`` float32."""
        pts = self._full.get(t)
        if pts is not None:
            return pts
        pts = self._load(t)
        if self.corridor is not None:  # keep a couple for the fallback
            self._full[t] = pts
            if len(self._full) > 2:
                self._full.popitem(last=False)
        return pts

    def _load(self, t: int) -> np.ndarray:
        tr = self.tracklet
        pts = tr.points_with_intensity(t)
        if self.transform is not None:
            pts = np.asarray(
                self.transform(pts, tr.tracklet_id, int(tr.frames[t])), dtype=np.float32
            )
            if pts.ndim != 2 or pts.shape[1] < 3:
                raise ValueError(
                    f"scan_transform returned shape {pts.shape} for {tr.tracklet_id} frame "
                    f"{int(tr.frames[t])}; expected (N, 4)"
                )
        return pts

    def index(self, t: int) -> _FrameIndex:
        idx = self.frames.get(t)
        if idx is None:
            idx = self._build(t)
            self.frames[t] = idx
            self.nbytes += idx.nbytes
        return idx

    def _build(self, t: int) -> _FrameIndex:
        cor = self.corridor
        xyz = self.scan(t)[:, :3]  # kept for a possible fallback in this episode
        ix, iy = _cells(xyz, cor.cell)
        ix -= cor.ix0
        iy -= cor.iy0
        inside = (ix >= 0) & (ix < cor.nx) & (iy >= 0) & (iy < cor.ny)
        key = np.where(inside, ix * cor.ny + iy, 0)
        keep = inside & cor.occupancy.reshape(-1)[key]  # queries never read other cells
        sel = np.flatnonzero(keep)
        key = key[sel]
        perm = np.argsort(key, kind="stable")
        rows = np.ascontiguousarray(xyz[sel[perm]].T, dtype=np.float32)
        firsts = np.searchsorted(key[perm], np.arange(cor.nx * cor.ny + 1))
        cells = np.arange(cor.nx)[:, None] * cor.ny + np.arange(cor.ny + 1)
        starts = firsts[cells].astype(np.int32)
        gt = np.asarray(self.tracklet.boxes[t], dtype=np.float64)
        target = len(crop_box_frame(rows.T, gt)) if rows.shape[1] else 0
        return _FrameIndex(rows, starts, target)

    def _full_crop(self, t: int, box: np.ndarray, scale: float, offset_m: float) -> np.ndarray:
        return crop_canonical(self.scan(t)[:, :3], box, scale, offset_m, self.cell)

    def crops(
        self, box: np.ndarray, frames: Sequence[int], enlargements: tuple[tuple[float, float], ...]
    ) -> tuple[list[np.ndarray], int]:
        """The points of every frame ``frames[i]`` in ``box`` enlarged by ``enlargements[i]``
        ``(scale, offset_m)``, in its box frame ``(M, 3)`` float32 (canonical order); and how
        many of them the corridor served. The corridor's crops share one gather, one box-frame
        transform and one selection (numpy's per-call cost dominates these small sets)."""
        if self.corridor is None:
            cells = [None] * len(frames)
        else:
            cells = self.corridor.cell_ranges(box, enlargements)
        out: list[np.ndarray | None] = [None] * len(frames)
        pieces: list[np.ndarray] = []
        served: list[int] = []  # requests the corridor serves, in gathering order
        widths: list[int] = []  # their numbers of gathered points
        for i, (t, rect) in enumerate(zip(frames, cells, strict=True)):
            if rect is None:
                out[i] = self._full_crop(t, box, *enlargements[i])
                continue
            x0, x1, y0, y1 = rect
            idx = self.index(t)
            # one run of points per grid row: columns y0 and y1 + 1 of starts (a strided view);
            # gaps of at most BRIDGE_POINTS points between runs are bridged
            runs = idx.starts[x0 : x1 + 1, y0 : y1 + 2 : y1 + 1 - y0].tolist()
            width, (start, stop) = 0, runs[0]
            for a, b in runs[1:]:
                if a - stop > BRIDGE_POINTS:
                    pieces.append(idx.xyz[:, start:stop])
                    width += stop - start
                    start = a
                stop = b
            pieces.append(idx.xyz[:, start:stop])
            served.append(i)
            widths.append(width + stop - start)
        if served:
            xyz = pieces[0] if len(pieces) == 1 else np.concatenate(pieces, axis=1)
            if len(served) < len(frames):
                enlargements = tuple(enlargements[i] for i in served)
            threshold = self._threshold(box, enlargements)
            if len(served) > 1:  # each gathered point gets its request's extent
                threshold = threshold.repeat(widths, axis=1)
            crops = crop_parts(box_frame(xyz, box), threshold, widths)
            for i, crop in zip(served, crops, strict=True):
                out[i] = crop
        return out, len(served)

    def _threshold(
        self, box: np.ndarray, enlargements: tuple[tuple[float, float], ...]
    ) -> np.ndarray:
        """:func:`extent_threshold` of the float32 crops, memoised: a tracklet's boxes take few
        sizes (the predictions all have frame 0's)."""
        key = (*box[3:6].tolist(), enlargements)
        threshold = self._thresholds.get(key)
        if threshold is None:
            threshold = extent_threshold(crop_extents(box, enlargements), np.float32)
            self._thresholds[key] = threshold
        return threshold

    def target_points(self, t: int) -> int:
        if self.corridor is None:
            return len(crop_box_frame(self.scan(t)[:, :3], self.tracklet.boxes[t]))
        return self.index(t).target_points


# --------------------------------------------------------------------------- the environment


def _is_pathlike(x: Any) -> bool:
    return isinstance(x, str | os.PathLike)


class TrackingEnv(gym.Env):
    """3D single-object tracking in LiDAR point clouds, one tracklet per episode.

    ## Description
    The target's box is given in the first frame of a tracklet; at every later frame the agent
    moves the box (P2B / BAT / GPT act as policies; OPE Success / Precision is the step-wise
    evaluation). Boxes are ``(x, y, z, l, w, h, yaw)`` in each frame's LiDAR frame (metres,
    radians, geometric centre); observations are in box-local frames.

    ## Observation Space
    ``Dict`` of float32 arrays (fresh arrays on every call):

    - ``template (512, 3)``: target points, see the template modes below (box frames), m;
    - ``search (1024, 3)``: the current frame's points inside the reference box scaled 1.25 plus
      2 m on every axis, in the reference box frame, m;
    - ``size (3,)``: the target's ``l, w, h`` (frame 0), m;
    - ``motion (4,)``: the last predicted motion ``(dx, dy, dz, dyaw)``: the offset from the
      prediction two frames back to the last one, in the former's frame (zeros at the first
      step), so motion-aware trackers stay stateless.

    Template modes (``template_mode``): ``"first_and_previous"`` (default; 256 points from frame
    0 cropped with the ground-truth box scaled 1.25 plus 256 from the previous frame cropped with
    the previous prediction scaled 1.25, each in its own box frame, concatenated), ``"first"``
    (512 from frame 0), ``"previous"`` (512 from the previous frame), ``"all"`` (the crops of
    frame 0 and of every previous prediction, each in its own box frame, merged and resampled to
    512 — P2B's "all previous results"). Point sets are resampled with ``self.np_random``
    (duplicates when too few, a random subset when too many), or, when ``episode_seed`` is set,
    with a generator seeded by ``(episode_seed, tracklet id)`` at every reset; an empty set gives
    zeros and ``info["empty_template"]`` / ``info["empty_search"]`` say so.

    ## Action Space
    ``Box(-max_action, max_action, (4,), float32)``: ``(dx, dy, dz, dyaw)`` in metres and radians
    in the reference box's frame; new box = reference box moved by ``R(yaw_ref) @ (dx, dy, dz)``,
    ``yaw + dyaw``, with frame 0's size. Default ``max_action = (5, 5, 3, pi)``. Wrap in
    ``gymnasium.wrappers.RescaleAction`` for a ``[-1, 1]`` space. A NaN/inf action raises
    ``ValueError``; an out-of-range action is clipped and ``info["action_clipped"]`` is set.
    Actions are used in float64, so the exact ground-truth offset yields the ground-truth box
    (IoU and centre error within 1e-9 of 1 and 0 are reported as exactly 1 and 0).

    ## Rewards
    ``"iou_3d"`` (default, oriented 3D IoU of the new box with the ground truth), ``"iou_bev"``,
    ``"neg_center_error"`` (minus the centre distance, metres), or a picklable callable
    ``reward(pred_box (7,), gt_box (7,)) -> float``.

    ## Starting State
    ``reset`` starts the next tracklet: ``sampling="sequential"`` visits the tracklets in order
    (``tracklet_order``, default all, wrapping around), ``"random"`` draws one with
    ``self.np_random``; ``options={"tracklet": i}`` (index or tracklet id) picks one. Reset with a
    seed restarts the sequential order. The first observation is for frame 1; reset ``info``
    holds ``tracklet``, ``category``, ``observed``, ``init_box`` (frame 0's ground truth),
    ``empty_template``, ``empty_search``.

    ## Episode End
    ``terminated`` at the tracklet's last frame (the final observation repeats the last one); a
    lost target never ends an episode (OPE tracks to the end); ``truncated`` is always ``False``
    (only a ``TimeLimit`` wrapper truncates). ``step`` before ``reset`` or after the end raises.

    ## Step info
    ``iou``, ``center_error`` (m), ``pred_box`` (7,), ``gt_box`` (7,), ``category``,
    ``observed``, ``tracklet`` (id), ``frame`` (index in the tracklet, 1..T-1), ``target_points``
    (scan points in the ground-truth box), ``action_clipped``, ``empty_template``,
    ``empty_search``; plus ``weather`` when the scan transform has an ``info`` attribute.

    ## Arguments
    - ``dataset``: anything with ``.tracklets`` (``envs.data.KittiTracking``,
      :func:`make_toy_dataset`), or a KITTI-layout root folder (then ``split`` is used).
    - ``setting``: a class-agnostic setting name (``"kitti-1"``...) or ``envs.data.Setting``;
      ``observed`` flags follow it; by default its observed and unseen categories are used.
    - ``categories``: restrict to these categories (within the setting if one is given).
    - ``split``: the split to read when ``dataset`` is a folder; otherwise only checked against
      ``dataset.split`` and quoted in errors.
    - ``sampling``, ``template_mode``, ``reference`` (``"prediction"`` default, ``"previous_gt"``,
      ``"current_gt"``: the box the search region is cropped around, Table 7 of ``002_…``),
      ``reward``, ``max_action``, ``render_mode`` (``None`` or ``"rgb_array"``).
    - ``episode_seed``: ``None`` (default: episodes draw from ``self.np_random`` one after the
      other) or an int: every episode draws its resampling from its own generator seeded by
      ``(episode_seed, tracklet id)``, so what it observes for given actions depends only on its
      tracklet — not on the episodes before it, the tracklet order or filter, or the vector
      sub-env that runs it. Settable between episodes (``training.evaluate`` sets it).
    - ``scan_transform``: see :data:`ScanTransform` (the weather hook). If it has an ``info``
      attribute, that value is reported as ``info["weather"]``.
    - ``corridor_m``: margin (m) of the per-tracklet corridor cache: each frame of a tracklet
      keeps, indexed by ``cell_m`` xy cells, the scan points within reach of any of the
      tracklet's boxes (search region plus ``corridor_m``); a crop reads only the cells it
      covers. Crops leaving the corridor fall back to the whole scan, so the cache never changes
      an observation. ``None``: crop whole scans every step. ``cache_mb``: memory budget of the
      cache (LRU over tracklets).

    Cropped point sets are the points ``envs.observation.crop_box_frame`` selects, with rows in
    a canonical order (by global ``cell_m`` xy cell, then scan order; see
    :func:`crop_canonical`) that the cached and whole-scan paths share.

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
        reward: str | Callable[[np.ndarray, np.ndarray], float] = "iou_3d",
        max_action: Sequence[float] = DEFAULT_MAX_ACTION,
        render_mode: str | None = None,
        scan_transform: ScanTransform | None = None,
        corridor_m: float | None = 2.0,
        cell_m: float = 1.0,
        cache_mb: float = 512.0,
        episode_seed: int | None = None,
    ) -> None:
        _check_choice("sampling", sampling, SAMPLING_MODES)
        _check_choice("template_mode", template_mode, TEMPLATE_MODES)
        _check_choice("reference", reference, REFERENCE_MODES)
        if not callable(reward):
            _check_choice("reward", reward, REWARDS)
        if render_mode is not None:
            _check_choice("render_mode", render_mode, tuple(self.metadata["render_modes"]))
        if scan_transform is not None and not callable(scan_transform):
            raise TypeError(f"scan_transform must be callable; got {type(scan_transform).__name__}")
        a_max = np.asarray(max_action, dtype=np.float64)
        if a_max.shape != (4,) or not np.all(np.isfinite(a_max)) or np.any(a_max <= 0):
            raise ValueError(f"max_action must be 4 positive finite numbers; got {max_action!r}")
        if corridor_m is not None and not (corridor_m >= 0 and cell_m > 0):
            raise ValueError(f"corridor_m must be >= 0 and cell_m > 0; got {corridor_m}, {cell_m}")

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
        self.tracklets: list[Tracklet] = tracklets
        self.dataset = dataset
        self.sampling = sampling
        self.template_mode = template_mode
        self.reference = reference
        self.reward_mode = reward
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
        self._motion_hi = motion_hi.astype(np.float64).tolist()
        self._max_action_list = a_max.tolist()
        self._cache: OrderedDict[int, Any] = OrderedDict()
        self._cache_bytes = 0
        self.cache_stats = {"corridor": 0, "full_scan": 0}
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
        """Index in the tracklet of the frame the current observation is for (1..T-1)."""
        return self._t

    @property
    def reference_box(self) -> np.ndarray:
        """``(7,)`` the box the current search region was cropped around (actions are offsets
        in its frame): a copy."""
        return self._ref.copy()

    @property
    def tracklet_lengths(self) -> list[int]:
        """Frames of each served tracklet (episode ``i`` has ``tracklet_lengths[i] - 1`` steps)."""
        return [len(tr) for tr in self.tracklets]

    @property
    def episode_seed(self) -> int | None:
        """Seed of the per-episode resampling generators (``None``: ``self.np_random``)."""
        return self._episode_seed

    @episode_seed.setter
    def episode_seed(self, seed: int | None) -> None:
        if seed is not None and (isinstance(seed, bool) or not isinstance(seed, int | np.integer)):
            raise TypeError(f"episode_seed must be None or an int; got {seed!r}")
        if seed is not None and seed < 0:
            raise ValueError(f"episode_seed must be non-negative; got {seed}")
        self._episode_seed = None if seed is None else int(seed)

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
        self._cache.clear()
        self._cache_bytes = 0
        if self._tracklet is not None:
            self._entry = self._scans(self._index)

    def clone(self) -> TrackingEnv:
        """A fresh copy of this env sharing its (read-only) dataset and tracklets, with its own
        episode state and cache (e.g. the sub-envs of a ``SyncVectorEnv``)."""
        import copy

        memo = {id(self.dataset): self.dataset, id(self.scan_transform): self.scan_transform}
        memo.update({id(tr): tr for tr in self.tracklets})
        twin = copy.deepcopy(self, memo)
        twin._cache = OrderedDict()
        twin._cache_bytes = 0
        twin._entry = twin._scans(twin._index) if twin._tracklet is not None else None
        twin.cache_stats = {"corridor": 0, "full_scan": 0}
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
        index = None
        if options:
            unknown = sorted(set(options) - set(RESET_OPTIONS))
            if unknown:
                raise ValueError(f"unknown reset options {unknown}; valid: {list(RESET_OPTIONS)}")
            if "tracklet" in options and options["tracklet"] is not None:
                index = self._tracklet_index(options["tracklet"])
        if index is None:
            if self.sampling == "random":
                index = int(self.np_random.integers(len(self.tracklets)))
            else:
                order = self.tracklet_order
                if not order:
                    raise RuntimeError("tracklet_order is empty; nothing to visit")
                index = order[self._cursor % len(order)]
                self._cursor += 1
        self._start(index)
        obs, empty_t, empty_s = self._observe()
        self._render_state = None
        tr = self._tracklet
        info = {
            "tracklet": tr.tracklet_id,
            "category": tr.category,
            "observed": self._observed,
            "init_box": tr.boxes[0].astype(np.float64, copy=True),
            "empty_template": empty_t,
            "empty_search": empty_s,
        }
        self._add_weather(info)
        return obs, info

    def step(self, action: Any) -> tuple[dict[str, np.ndarray], float, bool, bool, dict[str, Any]]:
        if self._tracklet is None:
            raise RuntimeError("step() called before reset(); call env.reset() first")
        if self._done:
            raise RuntimeError(
                f"step() called after the episode of tracklet {self._tracklet.tracklet_id} "
                "terminated; call env.reset() to start the next one"
            )
        a = np.asarray(action, dtype=np.float64)
        if a.shape != (4,):
            raise ValueError(f"action must have shape (4,) (dx, dy, dz, dyaw); got {a.shape}")
        values = a.tolist()
        if not all(map(math.isfinite, values)):
            raise ValueError(f"action contains NaN or inf: {values} (dx, dy, dz, dyaw)")
        clipped = _clip(values, self._max_action_list)
        action_clipped = clipped != values

        tr, t = self._tracklet, self._t
        # the boxes as Python floats for the scalar math; arrays only where they are kept
        pred_box = apply_offset_pair(self._ref.tolist(), clipped)
        pred_box[3:6] = self._size_box  # frame 0's size
        pred = np.array(pred_box)
        gt = tr.boxes[t]
        gt_box = gt.tolist()
        iou = _snap_iou(iou_pair(pred_box, gt_box))
        center_error = math.dist(pred_box[:3], gt_box[:3])
        if center_error < ROUND_OFF:
            center_error = 0.0
        reward = self._reward(pred, gt, iou, center_error)
        self._motion = np.array(  # float32: the observation's dtype
            _clip(offset_between_pair(self._pred_box, pred_box), self._motion_hi), np.float32
        )
        self._pred_box = pred_box
        self._preds.append(pred)
        terminated = t == self._last_frame
        self._render_state = (self._search_crop, self._ref, gt, pred)
        info = {
            "iou": iou,
            "center_error": float(center_error),
            "pred_box": pred.copy(),
            "gt_box": gt.astype(np.float64, copy=True),
            "category": tr.category,
            "observed": self._observed,
            "tracklet": tr.tracklet_id,
            "frame": t,
            "target_points": self._target_points(t),
            "action_clipped": action_clipped,
        }
        if terminated:
            self._done = True
            obs = {k: v.copy() for k, v in self._last_obs.items()}
            info["empty_template"], info["empty_search"] = self._last_empty
        else:
            self._t = t + 1
            obs, info["empty_template"], info["empty_search"] = self._observe()
        self._add_weather(info)
        return obs, float(reward), bool(terminated), False, info

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
        half = 0.5 * SEARCH_SCALE * float(max(ref[3], ref[4])) + SEARCH_OFFSET_M
        return render_birds_eye(points, boxes, frame_box=ref, extent_m=half)

    def close(self) -> None:
        self._cache.clear()
        self._cache_bytes = 0

    # ------------------------------------------------------------------ pickling

    def __getstate__(self) -> dict[str, Any]:
        state = self.__dict__.copy()
        state["_cache"] = OrderedDict()  # the corridor cache is rebuilt lazily
        state["_cache_bytes"] = 0
        state["_entry"] = None
        return state

    def __setstate__(self, state: dict[str, Any]) -> None:
        self.__dict__.update(state)
        if self._tracklet is not None:
            self._entry = self._scans(self._index)

    # ------------------------------------------------------------------ internals

    def _clear_episode(self) -> None:
        self._tracklet: Tracklet | None = None
        self._entry = None
        self._index = -1
        self._t = 0
        self._last_frame = 0
        self._done = False
        self._preds: list[np.ndarray] = []
        self._ref = np.zeros(7)
        self._size0 = np.zeros(3)
        self._size_box = [0.0] * 3
        self._size_obs = np.zeros(3, np.float32)
        self._pred_box = [0.0] * 7
        self._motion = np.zeros(4, np.float32)
        self._observed = True
        self._first_crop = None
        self._prev_crop = None
        self._all_crops: list[np.ndarray] = []
        self._last_obs = None
        self._last_empty = (False, False)
        self._search_crop = np.zeros((0, 3), np.float32)
        self._render_state = None

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

    def _scans(self, index: int):
        """The per-tracklet crop provider (LRU by bytes; never changes an observation)."""
        entry = self._cache.get(index)
        if entry is not None:
            self._cache.move_to_end(index)
            return entry
        tr = self.tracklets[index]
        corridor = None
        if self.corridor_m is not None:
            boxes = np.asarray(tr.boxes, dtype=np.float64)
            corridor = _Corridor(boxes, boxes[0, 3:6], self.corridor_m, self.cell_m)
        entry = _TrackletScans(tr, self.scan_transform, corridor, self.cell_m)
        self._cache[index] = entry
        self._evict(keep=index)
        return entry

    def _evict(self, keep: int) -> None:
        budget = self.cache_mb * 2**20
        total = sum(e.nbytes for e in self._cache.values())
        while total > budget and len(self._cache) > 1:
            idx, entry = next(iter(self._cache.items()))
            if idx == keep:
                break
            self._cache.popitem(last=False)
            total -= entry.nbytes
        self._cache_bytes = total

    def _crops(
        self, box: np.ndarray, frames: Sequence[int], enlargements: tuple[tuple[float, float], ...]
    ) -> list[np.ndarray]:
        """:meth:`_TrackletScans.crops` with the cache's statistics and budget."""
        entry = self._entry
        before = entry.nbytes
        crops, hits = entry.crops(box, frames, enlargements)
        self.cache_stats["corridor"] += hits
        self.cache_stats["full_scan"] += len(frames) - hits
        if entry.nbytes != before:
            self._evict(keep=self._index)
        return crops

    def _target_points(self, t: int) -> int:
        entry = self._entry
        before = entry.nbytes
        n = entry.target_points(t)
        if entry.nbytes != before:
            self._evict(keep=self._index)
        return n

    def _start(self, index: int) -> None:
        if self._entry is not None:  # whole scans kept for fallbacks live for one episode only
            self._entry._full.clear()
        self._clear_episode()
        tr = self.tracklets[index]
        self._tracklet = tr
        self._index = index
        self._entry = self._scans(index)
        self._observed = bool(self.is_observed(tr.category))
        if self._episode_seed is None:
            self._resample_rng = self.np_random
        else:  # the id's bytes, not the index: indices change with the category filter
            key = [self._episode_seed, *tr.tracklet_id.encode()]
            self._resample_rng = np.random.default_rng(key)
        box0 = np.asarray(tr.boxes[0], dtype=np.float64).copy()
        self._size0 = box0[3:6].copy()
        self._size_box = self._size0.tolist()
        self._size_obs = self._size0.astype(np.float32)
        self._preds = [box0]
        self._pred_box = box0.tolist()  # the last prediction's values (motion's reference)
        self._t = 1
        self._last_frame = len(tr) - 1
        entry = self._entry
        if entry.first_crop is None:  # frame 0's template crop: the same in every episode
            (entry.first_crop,) = self._crops(box0, (0,), (TEMPLATE_ENLARGEMENT,))
        self._first_crop = entry.first_crop
        self._prev_crop = self._first_crop
        self._all_crops = [self._first_crop]

    def _reference_box(self, t: int) -> np.ndarray:
        if self.reference == "prediction":
            return self._preds[t - 1]
        if self.reference == "previous_gt":
            return np.asarray(self._tracklet.boxes[t - 1], dtype=np.float64)
        return np.asarray(self._tracklet.boxes[t], dtype=np.float64)

    def _observe(self) -> tuple[dict[str, np.ndarray], bool, bool]:
        """Observation for frame ``self._t`` (uses the predictions up to ``t - 1``)."""
        t, mode = self._t, self.template_mode
        ref = self._reference_box(t)
        if t >= 2 and mode != "first":  # previous frame's crop around the previous prediction
            if self.reference == "prediction":  # one box for both crops: one pass
                self._prev_crop, search_pts = self._crops(
                    ref, (t - 1, t), (TEMPLATE_ENLARGEMENT, SEARCH_ENLARGEMENT)
                )
            else:
                prev_box = self._preds[t - 1]
                (self._prev_crop,) = self._crops(prev_box, (t - 1,), (TEMPLATE_ENLARGEMENT,))
                (search_pts,) = self._crops(ref, (t,), (SEARCH_ENLARGEMENT,))
            if mode == "all":
                self._all_crops.append(self._prev_crop)
        else:
            (search_pts,) = self._crops(ref, (t,), (SEARCH_ENLARGEMENT,))
        template = np.empty((TEMPLATE_SIZE, 3), np.float32)
        search = np.empty((SEARCH_SIZE, 3), np.float32)
        half = TEMPLATE_SIZE // 2
        if mode == "first_and_previous":
            sets, outs = [self._first_crop, self._prev_crop], [template[:half], template[half:]]
        elif mode == "first":
            sets, outs = [self._first_crop], [template]
        elif mode == "previous":
            sets, outs = [self._prev_crop], [template]
        else:
            crops = self._all_crops
            sets, outs = [np.concatenate(crops) if len(crops) > 1 else crops[0]], [template]
        *counts, n_search = resample_into([*sets, search_pts], [*outs, search], self._resample_rng)
        n_template = sum(counts)
        self._ref = ref
        self._search_crop = search_pts
        obs = {
            "template": template,
            "search": search,
            "size": self._size_obs.copy(),
            "motion": self._motion,  # a new array every step: handed over as it is
        }
        empty = (n_template == 0, n_search == 0)
        if t == self._last_frame:
            # the next step terminates and repeats this observation: keep a copy the caller
            # cannot modify (earlier observations are handed over without one)
            self._last_obs = {k: v.copy() for k, v in obs.items()}
            self._last_empty = empty
        return obs, *empty

    def _reward(self, pred: np.ndarray, gt: np.ndarray, iou: float, center_error: float) -> float:
        mode = self.reward_mode
        if mode == "iou_3d":
            return iou
        if mode == "iou_bev":
            return _snap_iou(float(iou_bev(pred, gt)))
        if mode == "neg_center_error":
            return -center_error
        value = float(mode(pred.copy(), np.asarray(gt, dtype=np.float64).copy()))
        if not math.isfinite(value):
            raise ValueError(f"the reward callable returned {value}")
        return value

    def _add_weather(self, info: dict[str, Any]) -> None:
        weather = getattr(self.scan_transform, "info", None)
        if weather is not None:
            info["weather"] = weather


def _clip(values: Sequence[float], bound: Sequence[float]) -> list[float]:
    """``min(max(v, -m), m)`` for every value (NaN passes), in conditional expressions: the
    builtins cost several times more on this per-step path."""
    return [m if v > m else -m if v < -m else v for v, m in zip(values, bound, strict=True)]


def _snap_iou(iou: float) -> float:
    """IoUs within :data:`ROUND_OFF` of 1 are round-off of the polygon clipping: report 1."""
    return 1.0 if iou > 1.0 - ROUND_OFF else iou


def _check_choice(name: str, value: Any, valid: Sequence[str]) -> None:
    if value not in valid:
        raise ValueError(f"unknown {name} {value!r}; valid: {', '.join(map(repr, valid))}")


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


# --------------------------------------------------------------------------- toy dataset


class _ToyScans:
    """Picklable scan loader of :func:`make_toy_dataset`: frame -> ``(N, 4)`` float32.

    Each frame: ``num_clutter`` uniform clutter points in a 60 m square around the origin, a flat
    ground grid, and for every target its box surface sampled with ``target_points`` points.
    Deterministic in ``(seed, frame)``.
    """

    def __init__(
        self,
        seed: int,
        boxes_per_frame: dict[int, list[np.ndarray]],
        target_points: int,
        num_clutter: int,
    ) -> None:
        self.seed = seed
        self.boxes_per_frame = boxes_per_frame
        self.target_points = target_points
        self.num_clutter = num_clutter

    def __call__(self, frame: int) -> np.ndarray:
        rng = np.random.default_rng([self.seed, frame])
        clutter = np.column_stack(
            [rng.uniform(-30, 30, (self.num_clutter, 2)), rng.uniform(-1.5, 2.5, self.num_clutter)]
        )
        parts = [clutter]
        for box in self.boxes_per_frame.get(frame, []):
            local = rng.uniform(-0.5, 0.5, (self.target_points, 3)) * box[3:6]
            face = rng.integers(0, 3, self.target_points)
            sign = np.where(rng.random(self.target_points) < 0.5, -0.5, 0.5)
            local[np.arange(self.target_points), face] = sign * box[3:6][face]
            c, s = math.cos(box[6]), math.sin(box[6])
            world = np.column_stack(
                [
                    box[0] + c * local[:, 0] - s * local[:, 1],
                    box[1] + s * local[:, 0] + c * local[:, 1],
                    box[2] + local[:, 2],
                ]
            )
            parts.append(world)
        xyz = np.concatenate(parts)
        intensity = rng.random((len(xyz), 1))
        return np.hstack([xyz, intensity]).astype(np.float32)


@dataclass
class ToyDataset:
    """What :func:`make_toy_dataset` returns: ``.tracklets``, ``.split``, ``.categories``."""

    tracklets: list[Tracklet]
    split: str = "test"
    categories: tuple[str, ...] | None = None

    def write_kitti(self, root: str | os.PathLike, scene: str = "0019") -> str:
        """Write the dataset in the KITTI tracking layout under ``root`` as scene ``scene``
        (``0019``: the test split) with a KITTI-like calibration; returns ``root``."""
        from pathlib import Path

        from envs.data.kitti import (
            Calibration,
            LabelRow,
            declare_scenes,
            lidar_to_camera_boxes,
            write_calibration,
            write_labels,
            write_scan,
        )

        root = Path(root)
        velo_to_cam = np.array(
            [[0.0, -1.0, 0.0, 0.0], [0.0, 0.0, -1.0, -0.08], [1.0, 0.0, 0.0, -0.27]]
        )
        calib = Calibration(tr_velo_to_cam=velo_to_cam)
        write_calibration(root / "calib" / f"{scene}.txt", calib)
        rows, frames = [], set()
        for tr in self.tracklets:
            cam = lidar_to_camera_boxes(tr.boxes, calib)
            for f, box in zip(tr.frames, cam, strict=True):
                rows.append(LabelRow.from_box(int(f), tr.track_id, tr.category, box))
                frames.add(int(f))
        rows.sort(key=lambda r: (r.frame, r.track_id))
        write_labels(root / "label_02" / f"{scene}.txt", rows)
        loader = self.tracklets[0].scans
        for f in range(max(frames) + 1):
            write_scan(root / "velodyne" / scene / f"{f:06d}.bin", loader(f))
        declare_scenes(root, [scene])  # a one-scene root: its split needs only this scene
        return str(root)


_TOY_SIZES = {
    "Car": (4.0, 1.8, 1.5),
    "Van": (5.0, 2.0, 2.2),
    "Pedestrian": (0.8, 0.6, 1.75),
    "Cyclist": (1.8, 0.6, 1.7),
}


def make_toy_dataset(
    categories: Sequence[str] = ("Car", "Pedestrian", "Van", "Cyclist"),
    num_frames: int | Sequence[int] = 8,
    seed: int = 0,
    target_points: int = 300,
    num_clutter: int = 4000,
    speed_mps: float = 8.0,
) -> ToyDataset:
    """A tiny in-memory dataset: one scene, one target per category moving along a straight line
    (10 Hz; heading turning slowly), plus clutter; ``num_frames`` per tracklet (an int or one per
    category). Deterministic in ``seed``; picklable. For tests and examples."""
    rng = np.random.default_rng(seed)
    if isinstance(num_frames, int):
        num_frames = [num_frames] * len(categories)
    boxes_per_frame: dict[int, list[np.ndarray]] = {}
    specs = []
    for k, (cat, n) in enumerate(zip(categories, num_frames, strict=True)):
        l, w, h = _TOY_SIZES.get(cat, (2.0, 1.0, 1.5))
        start = np.array([rng.uniform(-15, 15), rng.uniform(-15, 15)])
        yaw0 = rng.uniform(-math.pi, math.pi)
        speed = speed_mps * (0.25 if cat == "Pedestrian" else 1.0)
        t = np.arange(n)
        yaw = yaw0 + 0.02 * t
        xy = (
            start
            + np.cumsum(np.column_stack([np.cos(yaw), np.sin(yaw)]) * speed * 0.1, axis=0)
            - np.array([math.cos(yaw0), math.sin(yaw0)]) * speed * 0.1
        )
        boxes = np.column_stack(
            [
                xy,
                np.full(n, -1.0 + h / 2),
                np.full((n, 3), (l, w, h)),
                (yaw + math.pi) % (2 * math.pi) - math.pi,
            ]
        )
        frames = np.arange(n) + k  # staggered starts
        for f, b in zip(frames, boxes, strict=True):
            boxes_per_frame.setdefault(int(f), []).append(b)
        specs.append((k, cat, frames, boxes))
    loader = _ToyScans(seed, boxes_per_frame, target_points, num_clutter)
    tracklets = [
        Tracklet(f"0000/{k}", "0000", k, cat, frames, boxes, loader)
        for k, cat, frames, boxes in specs
    ]
    return ToyDataset(tracklets, "test", tuple(categories))
