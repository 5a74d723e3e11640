"""Where the env's crops come from: per-tracklet scan indices that make a crop cost a few
gathers instead of a pass over the whole scan, with observations identical to the direct crop.

Every crop the env takes is ``crop_box_frame(whole scan, box, scale, offset_m)`` with rows in a
canonical order (by global ``cell_m`` grid cell of the world x, y; ties in scan order; see
:func:`crop_canonical`). Three paths produce exactly that set in exactly that order:

- the **corridor** index of a frame: the scan points in the grid cells near the tracklet's
  trajectory (any of its boxes' search regions plus a margin), sorted by cell, built on the
  first crop of the frame; compact (a few per cent of a scan), serves every crop of a policy
  that stays near the target;
- the **cell index** of a frame: the whole scan sorted by cell, built lazily on the first crop
  that leaves the corridor (exploration: a random action puts the box anywhere), so such crops
  cost about what a corridor crop costs instead of a whole-scan pass; shared by the tracklets
  of a scene (a :class:`GridStore` keyed by scene frame; by tracklet and frame under a scan
  transform, which may differ per tracklet);
- the **direct** crop of the whole scan (:func:`crop_canonical`): with the cache off
  (``corridor_m=None``, the no-cache baseline), or when a scan is too spread out for a grid of
  at most :data:`MAX_GRID_CELLS` cells.

:class:`CropCache` keeps the per-tracklet indices (:class:`TrackletScans`) in an LRU by bytes.
"""

from __future__ import annotations

import math
from collections import OrderedDict
from collections.abc import Callable, Sequence
from dataclasses import dataclass

import numpy as np

from envs.data.tracklet import Tracklet
from envs.geometry import invert_rigid, map_points
from envs.kernels import cell_sort_kernel
from envs.observation import (
    SEARCH_OFFSET_M,
    SEARCH_SCALE,
    box_frame,
    crop_box_frame,
    crop_extents,
    crop_parts,
    extent_threshold,
)

__all__ = [
    "BRIDGE_POINTS",
    "MAX_GRID_CELLS",
    "CellRect",
    "Corridor",
    "CropCache",
    "FrameIndex",
    "GridStore",
    "ScanTransform",
    "TrackletScans",
    "check_scan_transform",
    "crop_canonical",
]

ScanTransform = Callable[[np.ndarray, str, int], np.ndarray]
"""``scan_transform(points (N, 4) float32, tracklet_id, scene_frame) -> (N', 4) float32``: applied
to the whole scan of a frame before any cropping (the weather hook), in the scan's own LiDAR
frame (the sensor at the origin) whatever frame the data is served in. Must be picklable and
deterministic given ``(tracklet_id, scene_frame)`` (corrupted scans are cached)."""


def check_scan_transform(transform: ScanTransform | None) -> ScanTransform | None:
    """``transform`` itself, once it is ``None`` or a callable."""
    if transform is not None and not callable(transform):
        raise TypeError(f"scan_transform must be callable; got {type(transform).__name__}")
    return transform


CellRect = tuple[int, int, int, int]
"""``(x0, x1, y0, y1)``: an inclusive rectangle of grid cells."""

BRIDGE_POINTS = 64
"""Consecutive row runs of a gather are joined when at most this many points lie between them:
a separate run costs a slice and a concatenated piece (~1 us), a gathered point ~20 ns of array
work, and the points in between (cells outside the query) never pass the exact crop."""

MAX_GRID_CELLS = 1 << 22
"""Largest cell index of a whole scan (16 MiB of int32 starts): a scan spread wider (e.g. far
outliers of a scan transform) is cropped directly instead."""


def _cells(xy: np.ndarray, cell_m: float) -> tuple[np.ndarray, np.ndarray]:
    """Global grid cell indices ``(ix, iy)`` int64 of points ``(N, 2+)`` (cells of ``cell_m``)."""
    ix = np.floor(xy[:, 0].astype(np.float64) / cell_m).astype(np.int64)
    iy = np.floor(xy[:, 1].astype(np.float64) / cell_m).astype(np.int64)
    return ix, iy


def _canonical(local: np.ndarray, world_xy: np.ndarray, cell_m: float) -> np.ndarray:
    """Reorder a crop (rows in scan order) into the canonical order: by global cell ``(ix, iy)``,
    ties in scan order. Every cache path produces this order, so they agree exactly."""
    if len(local) < 2:
        return local
    ix, iy = _cells(world_xy, cell_m)
    return local[np.lexsort((iy, ix))]


def crop_canonical(
    points: np.ndarray, box: np.ndarray, scale: float, offset_m: float, cell_m: float = 1.0
) -> np.ndarray:
    """What the env crops: ``crop_box_frame(points[:, :3], box, scale, offset_m)`` ``(M, 3)``
    float32, rows in the canonical order (by global ``cell_m`` grid cell of the world x, y;
    ties in scan order) that the cell indices produce without sorting."""
    xyz = np.asarray(points)[:, :3]
    # carry the world x, y through the crop (extra columns pass unchanged) for the order
    cropped = crop_box_frame(np.concatenate([xyz, xyz[:, :2]], axis=1), box, scale, offset_m)
    return _canonical(cropped[:, :3], cropped[:, 3:5], cell_m)


def cell_rects(
    box: np.ndarray, enlargements: Sequence[tuple[float, float]], cell_m: float
) -> list[CellRect]:
    """The global cells covering the xy bound of ``box`` ``(7,)`` enlarged by each
    ``(scale, offset_m)`` (a superset of the crop: the exact test follows), in Python scalars
    (this runs twice a step; numpy's per-call cost would dominate)."""
    bx, by, _, bl, bw, _, yaw = box.tolist()
    c, s = abs(math.cos(yaw)), abs(math.sin(yaw))
    out = []
    for scale, offset_m in enlargements:
        hl = 0.5 * scale * bl + offset_m
        hw = 0.5 * scale * bw + offset_m
        ex = c * hl + s * hw + 1e-3  # pad: a bound only
        ey = s * hl + c * hw + 1e-3
        out.append(
            (
                math.floor((bx - ex) / cell_m),
                math.floor((bx + ex) / cell_m),
                math.floor((by - ey) / cell_m),
                math.floor((by + ey) / cell_m),
            )
        )
    return out


class Corridor:
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

    def local(self, rect: CellRect) -> CellRect | None:
        """The corridor-local cells of a global rectangle, or ``None`` when part of it lies
        outside the corridor."""
        x0, x1, y0, y1 = rect
        x0, x1, y0, y1 = x0 - self.ix0, x1 - self.ix0, y0 - self.iy0, y1 - self.iy0
        if not (x0 >= 0 and y0 >= 0 and x1 < self.nx and y1 < self.ny):
            return None
        sat = self._sat
        occupied = sat[x1 + 1][y1 + 1] - sat[x0][y1 + 1] - sat[x1 + 1][y0] + sat[x0][y0]
        return (x0, x1, y0, y1) if occupied == (x1 - x0 + 1) * (y1 - y0 + 1) else None


@dataclass
class FrameIndex:
    """Points of one frame sorted by grid cell (row-major; ties in scan order), as coordinate
    rows (what :func:`envs.observation.box_frame` reads), with the first point of every cell:
    the points of cells ``y0..y1`` of grid row ``x`` are ``xyz[:, starts[x, y0] :
    starts[x, y1 + 1]]`` (``starts[x, ny]`` ends the row). Grid cell ``(0, 0)`` is global cell
    ``(ix0, iy0)``."""

    xyz: np.ndarray  # (3, M) float32
    starts: np.ndarray  # (nx, ny + 1) int32
    target_points: int  # scan points inside the frame's ground-truth box
    ix0: int = 0
    iy0: int = 0

    @property
    def nbytes(self) -> int:
        return self.xyz.nbytes + self.starts.nbytes

    def clip(self, rect: CellRect) -> CellRect | None:
        """The grid-local part of a global rectangle (cells outside the grid hold no points),
        or ``None`` when it misses the grid."""
        nx, ny1 = self.starts.shape
        x0, x1, y0, y1 = rect
        x0, x1 = max(x0 - self.ix0, 0), min(x1 - self.ix0, nx - 1)
        y0, y1 = max(y0 - self.iy0, 0), min(y1 - self.iy0, ny1 - 2)
        return (x0, x1, y0, y1) if x0 <= x1 and y0 <= y1 else None

    def gather(self, rect: CellRect, pieces: list[np.ndarray]) -> int:
        """Append the coordinate rows of the local cells ``rect`` to ``pieces`` (one run per
        grid row, gaps of at most :data:`BRIDGE_POINTS` bridged); returns how many points."""
        x0, x1, y0, y1 = rect
        # columns y0 and y1 + 1 of starts (a strided view): one run per grid row
        runs = self.starts[x0 : x1 + 1, y0 : y1 + 2 : y1 + 1 - y0].tolist()
        width, (start, stop) = 0, runs[0]
        for a, b in runs[1:]:
            if a - stop > BRIDGE_POINTS:
                pieces.append(self.xyz[:, start:stop])
                width += stop - start
                start = a
            stop = b
        pieces.append(self.xyz[:, start:stop])
        return width + stop - start


def _sorted_rows(
    xyz: np.ndarray, sel: np.ndarray | None, key: np.ndarray, cells: int
) -> tuple[np.ndarray, np.ndarray]:
    """The points ``xyz[sel]`` (``xyz (N, 3)``; ``sel (M,)`` increasing indices, ``None``: all)
    sorted by their grid-local cell keys ``key (M,)`` (of ``cells`` cells), ties in scan order,
    as coordinate rows ``(3, M)`` float32, and the first row of every key ``(cells + 1,)``
    (what :func:`envs.kernels.cell_sort_kernel` returns)."""
    # stable: ties stay in scan order; 16-bit keys take numpy's radix sort (linear time, the
    # same permutation: a stable sort's result is unique)
    perm = np.argsort(key.astype(np.uint16) if cells <= 1 << 16 else key, kind="stable")
    # coordinate rows first, then one gather along them: gathering (N, 3) rows of a strided
    # scan view and transposing costs several times more
    rows = np.ascontiguousarray(xyz.T, dtype=np.float32).take(
        perm if sel is None else sel[perm], axis=1
    )
    firsts = np.zeros(cells + 1, np.int64)
    np.cumsum(np.bincount(key, minlength=cells), out=firsts[1:])
    return rows, firsts


def _index_of_rows(
    rows: np.ndarray,
    firsts: np.ndarray,
    nx: int,
    ny: int,
    gt: np.ndarray | None,
    ix0: int,
    iy0: int,
) -> FrameIndex:
    """:class:`FrameIndex` of coordinate rows ``(3, M)`` sorted by grid-local cell key, with the
    first row of every key ``firsts (nx * ny + 1,)``."""
    cells = np.arange(nx)[:, None] * ny + np.arange(ny + 1)
    starts = firsts[cells].astype(np.int32)
    target = len(crop_box_frame(rows.T, gt)) if gt is not None and rows.shape[1] else 0
    return FrameIndex(rows, starts, target, ix0, iy0)


def grid_index(xyz: np.ndarray, cell_m: float) -> FrameIndex | None:
    """The whole-scan cell index of points ``xyz (N, 3)``: the grid spans their cells; ``None``
    when that is more than :data:`MAX_GRID_CELLS` cells."""
    if len(xyz) == 0:
        return FrameIndex(np.zeros((3, 0), np.float32), np.zeros((1, 2), np.int32), 0)
    ix, iy = _cells(xyz, cell_m)
    ix0, iy0 = int(ix.min()), int(iy.min())
    nx, ny = int(ix.max()) - ix0 + 1, int(iy.max()) - iy0 + 1
    if nx * ny > MAX_GRID_CELLS:
        return None
    rows, firsts = _sorted_rows(xyz, None, (ix - ix0) * ny + (iy - iy0), nx * ny)
    return _index_of_rows(rows, firsts, nx, ny, None, ix0, iy0)


class GridStore:
    """Whole-scan cell indices by key (scene and frame, or tracklet and frame), least recently
    used first: their owner (:class:`CropCache`) evicts them within its budget."""

    def __init__(self) -> None:
        self._grids: OrderedDict[tuple, FrameIndex | None] = OrderedDict()
        self.nbytes = 0

    def __len__(self) -> int:
        return len(self._grids)

    def get(self, key: tuple, xyz: Callable[[], np.ndarray], cell_m: float) -> FrameIndex | None:
        """The index of ``key``, built from the points ``xyz()`` on first use."""
        if key in self._grids:
            self._grids.move_to_end(key)
            return self._grids[key]
        idx = grid_index(xyz(), cell_m)
        self._grids[key] = idx
        self.nbytes += 0 if idx is None else idx.nbytes
        return idx

    def pop_oldest(self) -> None:
        _, idx = self._grids.popitem(last=False)
        self.nbytes -= 0 if idx is None else idx.nbytes

    def clear(self) -> None:
        self._grids.clear()
        self.nbytes = 0


def _corridor_rows(
    xyz: np.ndarray, cor: Corridor, bounds: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """The numpy build of a corridor's sorted rows (:func:`_sorted_rows`) from a scan's points
    ``xyz (N, 3)``: ``bounds`` (float32 ``x_lo, x_hi, y_lo, y_hi``) first, then the exact cell
    and the occupancy on the few points left."""
    x, y = xyz[:, 0], xyz[:, 1]
    near = np.flatnonzero((x >= bounds[0]) & (x < bounds[1]) & (y >= bounds[2]) & (y < bounds[3]))
    xyz = xyz[near]
    ix, iy = _cells(xyz, cor.cell)
    ix -= cor.ix0
    iy -= cor.iy0
    inside = (ix >= 0) & (ix < cor.nx) & (iy >= 0) & (iy < cor.ny)
    key = np.where(inside, ix * cor.ny + iy, 0)
    keep = inside & cor.occupancy.reshape(-1)[key]  # queries never read other cells
    sel = np.flatnonzero(keep)
    return _sorted_rows(xyz, sel, key[sel], cor.nx * cor.ny)


class TrackletScans:
    """Per-tracklet crops: lazily built per-frame corridor and whole-scan cell indices.

    Every crop equals ``crop_box_frame(whole scan, box, scale, offset_m)`` with rows in the
    canonical order (see :func:`crop_canonical`) on every path, so the cache never changes an
    observation. With ``corridor=None`` every crop reads the whole scan (the no-cache baseline).
    """

    def __init__(
        self,
        tracklet: Tracklet,
        transform: ScanTransform | None,
        corridor: Corridor | None,
        cell_m: float,
        grids: GridStore | None = None,
    ):
        self.tracklet = tracklet
        self.transform = transform
        self.corridor = corridor
        self.cell = float(cell_m)
        self.frames: dict[int, FrameIndex] = {}  # corridor indices
        self.grids = GridStore() if grids is None else grids  # whole-scan indices
        self.nbytes = 0 if corridor is None else corridor.nbytes
        self._full: OrderedDict[int, np.ndarray] = OrderedDict()  # last whole scans
        self._thresholds: dict[tuple, np.ndarray] = {}
        self.template_crops: dict[int, np.ndarray] = {}  # start frame -> its first template crop
        self.stats = {"corridor": 0, "cell_index": 0, "full_scan": 0}

    def end_episode(self) -> None:
        """Drop the whole scans kept for index builds and direct crops (they live for one
        episode; the indices stay)."""
        self._full.clear()

    def scan(self, t: int) -> np.ndarray:
        """Whole (transformed) scan of the tracklet's ``t``-th frame ``(N, 4)`` float32."""
        pts = self._full.get(t)
        if pts is not None:
            return pts
        pts = self._load(t)
        if self.corridor is not None:  # keep a couple: an index build may follow a crop
            self._full[t] = pts
            if len(self._full) > 2:
                self._full.popitem(last=False)
        return pts

    def _load(self, t: int) -> np.ndarray:
        tr = self.tracklet
        pts = tr.points_with_intensity(t)
        if self.transform is None:
            return pts
        # the weather models range from the sensor: a scan served in another frame (nuScenes'
        # scene frame) is transformed in its own LiDAR frame and mapped back
        pose = None if tr.sensor_poses is None else tr.sensor_poses[t]
        if pose is not None:
            pts = map_points(pts, invert_rigid(pose))
        pts = np.asarray(self.transform(pts, tr.tracklet_id, int(tr.frames[t])), dtype=np.float32)
        if pts.ndim != 2 or pts.shape[1] < 3:
            raise ValueError(
                f"scan_transform returned shape {pts.shape} for {tr.tracklet_id} frame "
                f"{int(tr.frames[t])}; expected (N, 4)"
            )
        return pts if pose is None else map_points(pts, pose)

    def index(self, t: int) -> FrameIndex:
        """The corridor index of frame ``t`` (built on first use)."""
        idx = self.frames.get(t)
        if idx is None:
            idx = self._build_corridor(t)
            self.frames[t] = idx
            self.nbytes += idx.nbytes
        return idx

    def grid(self, t: int) -> FrameIndex | None:
        """The whole-scan cell index of frame ``t`` (built on first use, shared with the
        scene's other tracklets when no scan transform is set); ``None`` when the scan spans
        more than :data:`MAX_GRID_CELLS` cells."""
        tr = self.tracklet
        owner = tr.scene if self.transform is None else tr.tracklet_id
        key = (owner, int(tr.frames[t]), self.cell)
        return self.grids.get(key, lambda: self.scan(t)[:, :3], self.cell)

    def _build_corridor(self, t: int) -> FrameIndex:
        cor = self.corridor
        scan = self.scan(t)
        gt = np.asarray(self.tracklet.boxes[t], dtype=np.float64)
        # the corridor's bounds widened by a cell: a cheap float superset of its points, so the
        # exact cell test runs on a few thousand points instead of the whole scan (same result)
        bounds = np.array(
            [(cor.ix0 - 1) * cor.cell, (cor.ix0 + cor.nx + 1) * cor.cell]
            + [(cor.iy0 - 1) * cor.cell, (cor.iy0 + cor.ny + 1) * cor.cell],
            dtype=np.float32,
        )
        kernel = cell_sort_kernel()
        if kernel is not None:  # the same rows in one compiled pass
            grid = (cor.cell, cor.ix0, cor.iy0, cor.nx, cor.ny, cor.occupancy.reshape(-1))
            rows, firsts = kernel(np.ascontiguousarray(scan, dtype=np.float32), *grid, bounds)
        else:
            rows, firsts = _corridor_rows(scan[:, :3], cor, bounds)
        return _index_of_rows(rows, firsts, cor.nx, cor.ny, gt, cor.ix0, cor.iy0)

    def _direct_crop(self, t: int, box: np.ndarray, scale: float, offset_m: float) -> np.ndarray:
        return crop_canonical(self.scan(t)[:, :3], box, scale, offset_m, self.cell)

    def crops(
        self, box: np.ndarray, frames: Sequence[int], enlargements: tuple[tuple[float, float], ...]
    ) -> list[np.ndarray]:
        """The points of every frame ``frames[i]`` in ``box`` ``(7,)`` enlarged by
        ``enlargements[i]`` ``(scale, offset_m)``, in its box frame ``(M_i, 3)`` float32
        (canonical order). The indexed crops share one gather, one box-frame transform and one
        selection (numpy's per-call cost dominates these small sets)."""
        out: list[np.ndarray | None] = [None] * len(frames)
        if self.corridor is None:
            for i, t in enumerate(frames):
                out[i] = self._direct_crop(t, box, *enlargements[i])
            self.stats["full_scan"] += len(frames)
            return out
        rects = cell_rects(box, enlargements, self.cell)
        pieces: list[np.ndarray] = []
        served: list[int] = []  # requests an index serves, in gathering order
        widths: list[int] = []  # their numbers of gathered points
        for i, (t, rect) in enumerate(zip(frames, rects, strict=True)):
            local = self.corridor.local(rect)
            if local is not None:
                widths.append(self.index(t).gather(local, pieces))
                self.stats["corridor"] += 1
            else:
                grid = self.grid(t)
                if grid is None:
                    out[i] = self._direct_crop(t, box, *enlargements[i])
                    self.stats["full_scan"] += 1
                    continue
                local = grid.clip(rect)
                widths.append(0 if local is None else grid.gather(local, pieces))
                self.stats["cell_index"] += 1
            served.append(i)
        if served:
            if not pieces:
                xyz = np.zeros((3, 0), np.float32)
            else:
                xyz = pieces[0] if len(pieces) == 1 else np.concatenate(pieces, axis=1)
            if len(served) < len(frames):
                enlargements = tuple(enlargements[i] for i in served)
            threshold = self._threshold(box, enlargements)
            if len(served) > 1:  # each gathered point gets its request's extent
                threshold = threshold.repeat(widths, axis=1)
            crops = crop_parts(box_frame(xyz, box), threshold, widths)
            for i, crop in zip(served, crops, strict=True):
                out[i] = crop
        return out

    def _threshold(
        self, box: np.ndarray, enlargements: tuple[tuple[float, float], ...]
    ) -> np.ndarray:
        """:func:`extent_threshold` of the float32 crops, memoised: a tracklet's boxes take few
        sizes (the predictions all have the first box's)."""
        key = (*box[3:6].tolist(), enlargements)
        threshold = self._thresholds.get(key)
        if threshold is None:
            threshold = extent_threshold(crop_extents(box, enlargements), np.float32)
            self._thresholds[key] = threshold
        return threshold

    def target_points(self, t: int) -> int:
        """Scan points inside the ground-truth box of frame ``t``."""
        if self.corridor is None:
            return len(crop_box_frame(self.scan(t)[:, :3], self.tracklet.boxes[t]))
        return self.index(t).target_points


class CropCache:
    """The :class:`TrackletScans` of an env's tracklets and their shared :class:`GridStore`,
    within ``budget_mb``: whole-scan indices are evicted first (least recently used, the last
    two kept: a step crops two frames), then tracklets (least recently used; the current one
    always stays). Holds no state an observation depends on: dropping it (pickling,
    :meth:`clear`) only costs rebuilds."""

    def __init__(
        self,
        corridor_m: float | None,
        cell_m: float,
        budget_mb: float,
        transform: ScanTransform | None,
    ) -> None:
        self.corridor_m = corridor_m
        self.cell_m = float(cell_m)
        self.budget_mb = float(budget_mb)
        self.transform = transform
        self._entries: OrderedDict[int, TrackletScans] = OrderedDict()
        self.grids = GridStore()
        self.nbytes = 0
        self._evicted_stats = {"corridor": 0, "cell_index": 0, "full_scan": 0}

    @property
    def stats(self) -> dict[str, int]:
        """Crops served by each path since the cache was made: ``corridor``, ``cell_index``
        (the whole-scan cell index) and ``full_scan`` (direct crops of the whole scan)."""
        total = dict(self._evicted_stats)
        for entry in self._entries.values():
            for key, n in entry.stats.items():
                total[key] += n
        return total

    def clear(self, transform: ScanTransform | None = None) -> None:
        """Drop every index (and install ``transform`` for the scans read from now on)."""
        for entry in self._entries.values():
            self._forget(entry)
        self._entries.clear()
        self.grids.clear()
        self.nbytes = 0
        self.transform = transform

    def entry(self, index: int, tracklet: Tracklet) -> TrackletScans:
        """The crop provider of tracklet ``index``, made most recently used."""
        entry = self._entries.get(index)
        if entry is not None:
            self._entries.move_to_end(index)
            return entry
        corridor = None
        if self.corridor_m is not None:
            boxes = np.asarray(tracklet.boxes, dtype=np.float64)
            corridor = Corridor(boxes, boxes[0, 3:6], self.corridor_m, self.cell_m)
        entry = TrackletScans(tracklet, self.transform, corridor, self.cell_m, self.grids)
        self._entries[index] = entry
        self.evict(keep=index)
        return entry

    def crops(
        self,
        entry: TrackletScans,
        index: int,
        box: np.ndarray,
        frames: Sequence[int],
        enlargements: tuple[tuple[float, float], ...],
    ) -> list[np.ndarray]:
        """:meth:`TrackletScans.crops` of ``entry`` (tracklet ``index``) within the budget."""
        before = entry.nbytes + self.grids.nbytes
        crops = entry.crops(box, frames, enlargements)
        if entry.nbytes + self.grids.nbytes != before:
            self.evict(keep=index)
        return crops

    def target_points(self, entry: TrackletScans, index: int, t: int) -> int:
        """:meth:`TrackletScans.target_points` of ``entry`` (tracklet ``index``) within the
        budget."""
        before = entry.nbytes
        n = entry.target_points(t)
        if entry.nbytes != before:
            self.evict(keep=index)
        return n

    def evict(self, keep: int) -> None:
        """Drop whole-scan indices, then tracklets (never ``keep``), least recently used
        first, until within the budget."""
        budget = self.budget_mb * 2**20
        entries = sum(e.nbytes for e in self._entries.values())
        while entries + self.grids.nbytes > budget and len(self.grids) > 2:
            self.grids.pop_oldest()
        while entries + self.grids.nbytes > budget and len(self._entries) > 1:
            idx, entry = next(iter(self._entries.items()))
            if idx == keep:
                break
            self._entries.popitem(last=False)
            self._forget(entry)
            entries -= entry.nbytes
        self.nbytes = entries + self.grids.nbytes

    def _forget(self, entry: TrackletScans) -> None:
        for key, n in entry.stats.items():
            self._evicted_stats[key] += n
