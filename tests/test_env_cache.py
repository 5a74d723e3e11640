"""The crop cache (envs.scan_cache): every path gives exactly the direct whole-scan crop, rows in
the canonical order, wherever the box is; and the env under uniform random actions observes
exactly what it observes without the cache."""

from __future__ import annotations

import numpy as np
import pytest

from envs import scan_cache
from envs.observation import SEARCH_OFFSET_M, SEARCH_SCALE, TEMPLATE_SCALE, crop_box_frame
from envs.scan_cache import Corridor, CropCache, TrackletScans, crop_canonical
from envs.tracking_env import TrackingEnv, make_toy_dataset

ENLARGEMENTS = ((TEMPLATE_SCALE, 0.0), (SEARCH_SCALE, SEARCH_OFFSET_M))


@pytest.fixture(scope="module")
def toy():
    return make_toy_dataset(num_frames=[8, 10, 6, 7], seed=3)


def scans_of(tracklet, corridor_m=2.0, cell_m=1.0, transform=None):
    boxes = np.asarray(tracklet.boxes, dtype=np.float64)
    corridor = Corridor(boxes, boxes[0, 3:6], corridor_m, cell_m)
    return TrackletScans(tracklet, transform, corridor, cell_m)


def random_boxes(rng, n, spread_m):
    """Boxes anywhere in (and beyond) the 60 m clutter square, any heading and size."""
    return np.column_stack(
        [
            rng.uniform(-spread_m, spread_m, (n, 2)),
            rng.uniform(-2, 2, n),
            rng.uniform(0.5, 6.0, (n, 3)),
            rng.uniform(-np.pi, np.pi, n),
        ]
    )


@pytest.mark.parametrize("cell_m", [1.0, 0.7])
def test_cell_index_crops_equal_direct_crops_anywhere(toy, cell_m):
    tr = toy.tracklets[1]
    scans = scans_of(tr, cell_m=cell_m)
    rng = np.random.default_rng(0)
    for box in random_boxes(rng, 60, 45.0):
        t = int(rng.integers(1, len(tr)))
        got = scans.crops(box, (t - 1, t), ENLARGEMENTS)
        for crop, f, (scale, off) in zip(got, (t - 1, t), ENLARGEMENTS, strict=True):
            want = crop_canonical(tr.points(f), box, scale, off, cell_m)
            assert crop.dtype == np.float32 and crop.shape == want.shape
            np.testing.assert_array_equal(crop, want)
            # the set is crop_box_frame's (the order aside)
            plain = crop_box_frame(tr.points(f), box, scale, off)
            assert sorted(map(tuple, plain)) == sorted(map(tuple, crop))
    assert scans.stats["cell_index"] > 50 and scans.stats["full_scan"] == 0
    assert len(scans.grids) == len(tr)  # one whole-scan index per frame


def test_mixed_requests_share_one_gather(toy):
    """One request in the corridor, one outside it, in one call."""
    tr = toy.tracklets[0]
    scans = scans_of(tr)
    inside, outside = tr.boxes[2], tr.boxes[2].copy()
    outside[:2] += 25.0
    for box, frames in ((inside, (1, 2)), (outside, (1, 2))):
        got = scans.crops(box, frames, ENLARGEMENTS)
        for crop, f, (scale, off) in zip(got, frames, ENLARGEMENTS, strict=True):
            np.testing.assert_array_equal(crop, crop_canonical(tr.points(f), box, scale, off))
    assert scans.stats["corridor"] == 2 and scans.stats["cell_index"] == 2


def test_spread_scans_and_empty_scans_fall_back(toy, monkeypatch):
    tr = toy.tracklets[2]
    monkeypatch.setattr(scan_cache, "MAX_GRID_CELLS", 16)  # every scan is "too spread"
    scans = scans_of(tr)
    box = tr.boxes[1].copy()
    box[:2] += 20.0
    (crop,) = scans.crops(box, (1,), ENLARGEMENTS[1:])
    np.testing.assert_array_equal(crop, crop_canonical(tr.points(1), box, *ENLARGEMENTS[1]))
    assert scans.stats["full_scan"] == 1 and scans.grid(1) is None
    empty = scans_of(tr, transform=lambda pts, tid, frame: pts[:0])
    got = empty.crops(box, (1, 2), ENLARGEMENTS)
    assert [c.shape for c in got] == [(0, 3), (0, 3)]


def test_crop_cache_budget_keeps_the_current_tracklet(toy):
    cache = CropCache(2.0, 1.0, 0.0, None)  # no budget: only the current entry stays
    first = cache.entry(0, toy.tracklets[0])
    cache.crops(first, 0, toy.tracklets[0].boxes[1], (1,), ENLARGEMENTS[1:])
    assert cache.nbytes == first.nbytes > 0
    second = cache.entry(1, toy.tracklets[1])
    cache.crops(second, 1, toy.tracklets[1].boxes[1], (1,), ENLARGEMENTS[1:])
    assert list(cache._entries) == [1]
    assert cache.stats["corridor"] == 2  # evicted entries' counts are kept
    # whole-scan indices: shared by the scene's tracklets, evicted first, the last two kept
    far = toy.tracklets[1].boxes[1].copy()
    far[:2] += 30.0
    for t in range(1, 5):
        cache.crops(second, 1, far, (t,), ENLARGEMENTS[1:])
    assert len(cache.grids) == 2 and list(cache._entries) == [1]
    third = cache.entry(2, toy.tracklets[2])  # same scene: frame 4 of the scene is shared
    frame = int(toy.tracklets[1].frames[4])
    t3 = int(np.flatnonzero(toy.tracklets[2].frames == frame)[0])
    n = len(cache.grids)
    cache.crops(third, 2, far, (t3,), ENLARGEMENTS[1:])
    assert third.stats["cell_index"] == 1 and len(cache.grids) == n


def test_uniform_random_actions_observe_exactly_the_uncached_env(toy):
    """The issue's exploration case: uniform actions over the whole action space."""
    envs = [TrackingEnv(toy), TrackingEnv(toy, corridor_m=None)]
    runs = []
    for env in envs:
        rng = np.random.default_rng(2)
        obs_seq = []
        for i in range(env.num_tracklets):
            obs, _ = env.reset(seed=1 if i == 0 else None, options={"tracklet": i})
            obs_seq.append(obs)
            done = False
            while not done:
                action = rng.uniform(env.action_space.low, env.action_space.high)
                obs, _, term, trunc, info = env.step(action)
                obs_seq.append((obs, info["target_points"]))
                done = term or trunc
        runs.append(obs_seq)
    assert envs[0].cache_stats["cell_index"] > 0 and envs[0].cache_stats["full_scan"] == 0
    for a, b in zip(*runs, strict=True):
        if isinstance(a, tuple):
            assert a[1] == b[1]
            a, b = a[0], b[0]
        for key in a:
            np.testing.assert_array_equal(a[key], b[key], err_msg=key)


@pytest.mark.parametrize("cell_m", [1.0, 0.7, 0.25])
def test_compiled_corridor_index_equals_the_numpy_build(toy, cell_m, monkeypatch):
    """The compiled corridor build (envs.kernels.cell_sort_kernel) against the numpy one: the
    same rows in the same order and the same cell starts, on scans with points exactly on cell
    borders (both signs), copies of points with other heights (the stable order of ties), and
    points far outside the corridor; also a corridor scan without a point in it."""
    if scan_cache.cell_sort_kernel() is None:
        pytest.skip("numba is not installed (pip install 'pointtrack[fast]')")
    tr = toy.tracklets[1]
    rng = np.random.default_rng(4)

    def edgy(pts, tid, frame):
        centre = tr.boxes[0, :2]
        borders = (np.floor(centre / cell_m) + rng.integers(-6, 7, (40, 2))) * cell_m
        extra = np.column_stack([borders, rng.normal(0, 1, (40, 2))]).astype(np.float32)
        twins = pts[: len(pts) // 3].copy()
        twins[:, 2] += 0.5
        far = np.array([[1e4, -1e4, 0, 0], [-3e3, 5, 0, 0]], np.float32)
        return np.concatenate([pts, extra, -extra, twins, far]).astype(np.float32)

    def nothing_near(pts, tid, frame):
        return pts[:3] + np.float32(500.0)

    for transform in (edgy, nothing_near):
        built = []
        for kernel in (scan_cache.cell_sort_kernel, lambda: None):
            monkeypatch.setattr(scan_cache, "cell_sort_kernel", kernel)
            scans = scans_of(tr, cell_m=cell_m, transform=transform)
            rng = np.random.default_rng(4)  # the same extra points for both builds
            built.append([scans.index(t) for t in range(len(tr))])
        for fast, plain in zip(*built, strict=True):
            assert fast.xyz.dtype == plain.xyz.dtype == np.float32
            np.testing.assert_array_equal(fast.xyz, plain.xyz)
            np.testing.assert_array_equal(fast.starts, plain.starts)
            assert fast.starts.dtype == plain.starts.dtype == np.int32
            assert (fast.target_points, fast.ix0, fast.iy0) == (
                plain.target_points,
                plain.ix0,
                plain.iy0,
            )
        if transform is edgy:
            assert sum(idx.xyz.shape[1] for idx in built[0]) > 100
        else:
            assert all(idx.xyz.shape[1] == 0 for idx in built[0])
