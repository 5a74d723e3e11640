"""The one-pass ``crop_box_frame`` equals its reference formula bit for bit; ``resample``."""

from __future__ import annotations

import numpy as np
import pytest

from envs.geometry import points_in_box, world_to_box
from envs.observation import crop_box_frame, resample


def _reference_crop(points, box, scale, offset_m):
    mask = points_in_box(points[:, :3], box, scale=scale, offset_m=offset_m)
    return world_to_box(points[mask], box).astype(np.float32, copy=False)


@pytest.mark.parametrize("dtype", [np.float32, np.float64])
@pytest.mark.parametrize("columns", [3, 4])
def test_crop_matches_reference(dtype, columns):
    rng = np.random.default_rng(0)
    for _ in range(20):
        box = np.concatenate([rng.uniform(-5, 5, 3), rng.uniform(0.5, 6, 3), rng.uniform(-4, 4, 1)])
        pts = rng.uniform(-9, 9, (3000, columns)).astype(dtype)
        # points exactly on the (enlarged) boundary
        corners = world_to_box(pts[:20, :3], box)  # any points; now put some on faces
        local = np.zeros((20, 3))
        local[:, 0] = box[3] * 0.625 + 2.0
        local[:, 1:] = corners[:, 1:] * 0.01
        from envs.geometry import box_to_world

        edge = box_to_world(local, box).astype(dtype)
        pts[:20, :3] = edge
        for scale, off in ((1.0, 0.0), (1.25, 2.0), (1.25, 0.0)):
            got = crop_box_frame(pts, box, scale, off)
            ref = _reference_crop(pts, box, scale, off)
            assert got.dtype == np.float32 and got.shape == ref.shape
            np.testing.assert_array_equal(got, ref)


def test_crop_empty():
    out = crop_box_frame(np.zeros((0, 4), np.float32), np.array([0, 0, 0, 1, 1, 1, 0.0]))
    assert out.shape == (0, 4)


def test_resample_contract():
    rng = np.random.default_rng(0)
    pts = rng.normal(size=(10, 3)).astype(np.float32)
    out, m = resample(pts, 32, np.random.default_rng(1))
    assert m == 10 and out.shape == (32, 3) and out.flags.c_contiguous
    np.testing.assert_array_equal(out[:10], pts)  # all points first, then duplicates
    sub, m = resample(pts, 4, np.random.default_rng(1))
    assert m == 10 and len({tuple(r) for r in sub}) == 4
    zero, m = resample(np.zeros((0, 3), np.float32), 8, rng)
    assert m == 0 and not zero.any() and zero.shape == (8, 3)


def test_uniform_indices_exact():
    from envs.observation import uniform_indices

    rng = np.random.default_rng(3)
    # bound 3 * 2**30: a quarter of the draws is rejected; without the rejection the residues
    # mod 3 of the results would be skewed (1/2, 1/4, 1/4)
    big = uniform_indices(rng, np.full(120_000, 3 * 2**30))
    assert big.max() < 3 * 2**30
    np.testing.assert_allclose(np.bincount(big % 3) / len(big), 1 / 3, atol=0.01)
    small = uniform_indices(rng, np.repeat([1, 7, 100], 70_000))
    assert not small[:70_000].any()
    np.testing.assert_allclose(np.bincount(small[70_000:140_000]) / 70_000, 1 / 7, atol=0.01)
    assert small[140_000:].max() == 99 and small[140_000:].min() == 0
    a = uniform_indices(np.random.default_rng(5), np.array([5, 9, 2**32]))
    b = uniform_indices(np.random.default_rng(5), np.array([5, 9, 2**32]))
    np.testing.assert_array_equal(a, b)


def test_resample_into_sets():
    from envs.observation import resample_into

    rng = np.random.default_rng(0)
    sets = [rng.normal(size=(m, 3)).astype(np.float32) for m in (5, 0, 300, 40)]
    outs = [np.full((n, 3), 7.0, np.float32) for n in (16, 8, 256, 1024)]
    counts = resample_into(sets, outs, np.random.default_rng(1))
    assert counts == [5, 0, 300, 40]
    np.testing.assert_array_equal(outs[0][:5], sets[0])  # all points first, then duplicates
    assert {tuple(r) for r in outs[0][5:]} <= {tuple(r) for r in sets[0]}
    assert not outs[1].any()
    assert len({tuple(r) for r in outs[2]}) == 256  # a subset without replacement
    assert {tuple(r) for r in outs[2]} <= {tuple(r) for r in sets[2]}
    np.testing.assert_array_equal(outs[3][:40], sets[3])
    # the duplicates are uniform over the set
    hits = np.unique(outs[3][40:], axis=0, return_counts=True)[1]
    assert len(hits) == 40 and hits.min() > 5
    again = [np.empty_like(o) for o in outs]
    resample_into(sets, again, np.random.default_rng(1))
    for x, y in zip(outs, again, strict=True):
        np.testing.assert_array_equal(x, y)


def test_extent_threshold_matches_float64_comparison():
    from envs.observation import extent_threshold

    rng = np.random.default_rng(2)
    half = rng.uniform(0.1, 9.0, (3, 1))
    half[0, 0] = float(np.float32(2.5))  # exactly representable in float32
    thr = extent_threshold(half, np.float32)
    assert thr.dtype == np.float32
    # float32 values around each threshold, and random ones
    near = thr + np.arange(-3, 4)[None, :] * np.spacing(thr)
    x = np.concatenate([near, -near, rng.uniform(-10, 10, (3, 200)).astype(np.float32)], axis=1)
    np.testing.assert_array_equal(np.abs(x) <= thr, np.abs(x).astype(np.float64) <= half)


def test_uniform_indices_32_bit_generator():
    from envs.observation import uniform_indices

    # MT19937's raw draws carry 32 random bits (64-bit generators give two words a draw)
    rng = np.random.Generator(np.random.MT19937(4))
    draws = uniform_indices(rng, np.full(70_000, 7))
    assert draws.dtype == np.int64
    np.testing.assert_allclose(np.bincount(draws, minlength=7) / len(draws), 1 / 7, atol=0.01)
