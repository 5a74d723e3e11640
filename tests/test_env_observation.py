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
