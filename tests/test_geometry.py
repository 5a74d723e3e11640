"""Box geometry: hand-computed cases, a Shapely reference (test-only) and invariants."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from envs.geometry import (
    apply_offset,
    apply_offset_pair,
    box_corners,
    box_corners_torch,
    box_to_world,
    box_to_world_torch,
    boxes_in_frame,
    center_distance,
    iou_3d,
    iou_bev,
    offset_between,
    offset_between_pair,
    points_in_box,
    rotation_z,
    world_to_box,
    world_to_box_torch,
    wrap_yaw,
)


def box(x=0.0, y=0.0, z=0.0, l=2.0, w=2.0, h=2.0, yaw=0.0) -> np.ndarray:
    return np.array([x, y, z, l, w, h, yaw], dtype=np.float64)


def random_boxes(rng: np.random.Generator, n: int) -> tuple[np.ndarray, np.ndarray]:
    a = np.column_stack(
        [
            rng.uniform(-5, 5, (n, 2)),
            rng.uniform(-1, 1, n),
            rng.uniform(0.3, 5, (n, 3)),
            rng.uniform(-np.pi, np.pi, n),
        ]
    )
    b = a.copy()
    b[:, :2] += rng.normal(0, 1.0, (n, 2))
    b[:, 2] += rng.normal(0, 0.3, n)
    b[:, 3:6] *= rng.uniform(0.7, 1.3, (n, 3))
    b[:, 6] = rng.uniform(-np.pi, np.pi, n)
    return a, b


def degenerate_boxes(rng: np.random.Generator, n: int) -> tuple[np.ndarray, np.ndarray]:
    """Pairs on a coarse grid: shared edges, collinear sides, identical and quarter-turned boxes."""
    a = np.column_stack(
        [
            rng.uniform(-3, 3, (n, 2)).round(1),
            np.zeros(n),
            rng.uniform(1, 4, (n, 3)).round(1),
            rng.choice([0.0, np.pi / 2, np.pi, -np.pi / 2, 0.3, -2.0], n),
        ]
    )
    b = a.copy()
    shift = rng.choice([-2.0, -1.0, -0.5, 0.0, 0.5, 1.0, 2.0], (n, 2)) * rng.choice([0, 1], (n, 1))
    c, s = np.cos(a[:, 6]), np.sin(a[:, 6])
    b[:, 0] += c * shift[:, 0] - s * shift[:, 1]
    b[:, 1] += s * shift[:, 0] + c * shift[:, 1]
    b[:, 6] += rng.choice([0.0, np.pi / 2, np.pi, 2 * np.pi, -np.pi, 1e-12], n)
    swap = rng.random(n) < 0.3
    b[swap, 3], b[swap, 4] = a[swap, 4], a[swap, 3]
    return a, b


def shapely_iou(a: np.ndarray, b: np.ndarray, vertical: bool = True) -> np.ndarray:
    """Independent reference: Shapely polygon intersection per pair (test-only dependency)."""
    shapely_geometry = pytest.importorskip("shapely.geometry")

    def polygon(bx):
        x, y, _, l, w, _, yaw = bx
        c, s = math.cos(yaw), math.sin(yaw)
        pts = [(l / 2, w / 2), (-l / 2, w / 2), (-l / 2, -w / 2), (l / 2, -w / 2)]
        return shapely_geometry.Polygon([(x + c * u - s * v, y + s * u + c * v) for u, v in pts])

    out = []
    for pa, pb in zip(a, b, strict=True):
        inter = polygon(pa).intersection(polygon(pb)).area
        va, vb = pa[3] * pa[4], pb[3] * pb[4]
        if vertical:
            dz = min(pa[2] + pa[5] / 2, pb[2] + pb[5] / 2) - max(
                pa[2] - pa[5] / 2, pb[2] - pb[5] / 2
            )
            inter *= max(dz, 0.0)
            va, vb = va * pa[5], vb * pb[5]
        out.append(inter / (va + vb - inter))
    return np.array(out)


# --------------------------------------------------------------------------- IoU: hand-computed


def test_iou_half_overlap_along_x():
    a, b = box(), box(x=1.0)
    # intersection 1 x 2 x 2 = 4, union 8 + 8 - 4 = 12
    assert iou_3d(a, b) == pytest.approx(1 / 3, abs=1e-12)
    assert iou_bev(a, b) == pytest.approx(1 / 3, abs=1e-12)


def test_iou_vertical_offset_only():
    a, b = box(), box(z=1.0)
    assert iou_3d(a, b) == pytest.approx(1 / 3, abs=1e-12)
    assert iou_bev(a, b) == pytest.approx(1.0, abs=1e-12)


def test_iou_square_rotated_45_degrees():
    a, b = box(l=1, w=1, h=1), box(l=1, w=1, h=1, yaw=math.pi / 4)
    octagon = 2 * (math.sqrt(2) - 1)  # regular octagon of the two unit squares
    expected = octagon / (2 - octagon)
    assert iou_bev(a, b) == pytest.approx(expected, abs=1e-12)
    assert iou_3d(a, b) == pytest.approx(expected, abs=1e-12)


def test_iou_contained_box():
    big, small = box(l=4, w=4, h=4, yaw=0.4), box(x=0.3, l=1, w=1, h=1, yaw=-1.1)
    assert iou_3d(big, small) == pytest.approx(1 / 64, abs=1e-12)
    assert iou_bev(big, small) == pytest.approx(1 / 16, abs=1e-12)


def test_iou_cross_shape():
    # a 4 x 1 bar and the same bar turned 90 degrees: intersection 1 x 1, union 4 + 4 - 1
    a, b = box(l=4, w=1, h=1), box(l=4, w=1, h=1, yaw=math.pi / 2)
    assert iou_3d(a, b) == pytest.approx(1 / 7, abs=1e-12)


@pytest.mark.parametrize("yaw", [0.0, 0.3, math.pi / 2, -math.pi, 2.5])
def test_iou_identical_is_one(yaw):
    a = box(1.0, -2.0, 0.5, 4.0, 1.8, 1.5, yaw)
    assert iou_3d(a, a) == 1.0
    assert iou_bev(a, a) == 1.0
    assert iou_3d(a[None].repeat(3, 0), a[None].repeat(3, 0)) == pytest.approx([1.0] * 3, abs=1e-15)


@pytest.mark.parametrize("yaw", [0.0, 0.7, -2.9])
def test_iou_yaw_plus_two_pi_and_half_turn(yaw):
    a = box(0.5, 0.2, 0.0, 4.0, 1.8, 1.5, yaw)
    b = box(0.8, -0.1, 0.1, 3.9, 1.7, 1.4, yaw + 0.1)
    turned = b.copy()
    turned[6] += 2 * np.pi
    assert iou_3d(a, turned) == pytest.approx(iou_3d(a, b), abs=1e-12)
    assert iou_3d(a, a + np.array([0, 0, 0, 0, 0, 0, 2 * np.pi])) == pytest.approx(1.0, abs=1e-12)
    # a box turned by pi is the same solid
    flipped = a + np.array([0, 0, 0, 0, 0, 0, np.pi])
    assert iou_3d(a, flipped) == pytest.approx(1.0, abs=1e-12)


def test_iou_zero_for_separated_and_touching():
    a = box()
    assert iou_3d(a, box(x=5.0)) == 0.0
    assert iou_3d(a, box(z=3.0)) == 0.0
    assert iou_bev(a, box(z=3.0)) == 1.0
    # sharing a face: zero volume
    assert iou_3d(a, box(x=2.0)) == pytest.approx(0.0, abs=1e-12)
    assert iou_3d(a, box(x=2.0, yaw=math.pi)) == pytest.approx(0.0, abs=1e-12)
    assert iou_3d(a, box(z=2.0)) == pytest.approx(0.0, abs=1e-12)
    batch = iou_3d(np.stack([a, a]), np.stack([box(x=5.0), box(x=2.0)]))
    assert np.allclose(batch, 0.0, atol=1e-12)


def test_iou_shared_edge_same_direction():
    # b overlaps a's left half exactly, its sides collinear with a's
    a, b = box(l=4, w=2, h=2), box(x=-1, l=2, w=2, h=2)
    assert iou_3d(a, b) == pytest.approx(0.5, abs=1e-12)
    assert iou_3d(b, a) == pytest.approx(0.5, abs=1e-12)
    # the same with b given as a quarter turn of a 2 x 2 footprint
    c = box(x=-1, l=2, w=2, h=2, yaw=math.pi / 2)
    assert iou_3d(a, c) == pytest.approx(0.5, abs=1e-12)


# --------------------------------------------------------------------------- IoU: reference


def test_iou_matches_shapely_random():
    a, b = random_boxes(np.random.default_rng(0), 400)
    ref = shapely_iou(a, b)
    assert np.abs(iou_3d(a, b) - ref).max() < 1e-9
    assert np.abs(iou_bev(a, b) - shapely_iou(a, b, vertical=False)).max() < 1e-9
    single = np.array([iou_3d(x, y) for x, y in zip(a, b, strict=True)])
    assert np.abs(single - ref).max() < 1e-9


def test_iou_matches_shapely_degenerate():
    a, b = degenerate_boxes(np.random.default_rng(1), 400)
    ref = shapely_iou(a, b)
    assert np.abs(iou_3d(a, b) - ref).max() < 1e-9
    single = np.array([iou_3d(x, y) for x, y in zip(a, b, strict=True)])
    assert np.abs(single - ref).max() < 1e-9
    assert np.abs(iou_3d(b, a) - ref).max() < 1e-9


@pytest.mark.parametrize("dyaw", [1e-12, 0.99e-8, 1.01e-8, 3e-8, 1e-7, 1e-5])
def test_iou_nearly_parallel_collinear_sides(dyaw):
    # Sides collinear up to a tiny relative yaw: near the snapping band of the implementation.
    a, b = degenerate_boxes(np.random.default_rng(8), 300)
    b[:, 6] += dyaw
    b[:100, 6] += np.pi / 2
    ref = shapely_iou(a, b)
    assert np.abs(iou_3d(a, b) - ref).max() < 1e-6
    assert np.abs(iou_3d(b, a) - ref).max() < 1e-6
    single = np.array([iou_3d(x, y) for x, y in zip(a[:60], b[:60], strict=True)])
    assert np.abs(single - ref[:60]).max() < 1e-6


def test_iou_larger_coordinates_and_thin_boxes():
    rng = np.random.default_rng(2)
    a, b = random_boxes(rng, 200)
    a[:, :2] += 80.0
    b[:, :2] += 80.0
    a[:50, 4] = 0.05  # thin slabs
    assert np.abs(iou_3d(a, b) - shapely_iou(a, b)).max() < 1e-9


# --------------------------------------------------------------------------- IoU: invariants


def test_iou_symmetric():
    a, b = random_boxes(np.random.default_rng(3), 1000)
    assert np.abs(iou_3d(a, b) - iou_3d(b, a)).max() < 1e-12
    assert np.abs(iou_bev(a, b) - iou_bev(b, a)).max() < 1e-12


def test_iou_invariant_under_common_rigid_motion():
    rng = np.random.default_rng(4)
    a, b = random_boxes(rng, 500)
    theta, t = 1.234, np.array([30.0, -12.0, 3.0])
    rot = rotation_z(theta)

    def move(boxes):
        out = boxes.copy()
        out[:, :3] = boxes[:, :3] @ rot.T + t
        out[:, 6] = wrap_yaw(boxes[:, 6] + theta)
        return out

    assert np.abs(iou_3d(move(a), move(b)) - iou_3d(a, b)).max() < 1e-9


def test_iou_range_broadcast_and_scalar_path():
    a, b = random_boxes(np.random.default_rng(5), 60)
    out = iou_3d(a.reshape(5, 1, 12, 7)[:, :, :3], b.reshape(5, 12, 7)[None, :, :3])
    assert out.shape == (5, 5, 3)
    assert np.all((out >= 0) & (out <= 1))
    batched = iou_3d(a, b)
    for i in range(0, 60, 7):
        assert float(iou_3d(a[i], b[i])) == pytest.approx(batched[i], abs=1e-12)
    assert iou_3d(a[:1], b[0]).shape == (1,)
    assert isinstance(float(iou_3d(a[0], b[0])), float)


def test_iou_bad_shape_and_nan():
    with pytest.raises(ValueError, match="7"):
        iou_3d(np.zeros(6), np.zeros(7))
    a = box()
    bad = box(x=float("nan"))
    assert math.isnan(float(iou_3d(a, bad)))
    assert math.isnan(iou_3d(np.stack([a, a]), np.stack([bad, a]))[0])


# --------------------------------------------------------------------------- transforms


def test_wrap_yaw_range():
    yaws = np.array([-np.pi, np.pi, 3 * np.pi, -7.0, 0.0, 2 * np.pi - 1e-12])
    w = wrap_yaw(yaws)
    assert np.all((w >= -np.pi) & (w < np.pi))
    assert np.allclose(np.cos(w), np.cos(yaws)) and np.allclose(np.sin(w), np.sin(yaws))
    assert wrap_yaw(np.pi) == pytest.approx(-np.pi)


def test_box_corners_hand_computed():
    corners = box_corners(box(1.0, 2.0, 3.0, 4.0, 2.0, 1.0, math.pi / 2))
    assert corners.shape == (8, 3)
    # front-left bottom corner: local (2, 1, -0.5) turned by 90 degrees -> (-1, 2, -0.5)
    assert np.allclose(corners[0], [1 - 1, 2 + 2, 2.5])
    assert np.allclose(corners.mean(0), [1, 2, 3])
    assert np.allclose(corners[:, 2].min(), 2.5) and np.allclose(corners[:, 2].max(), 3.5)


def test_world_box_round_trip_and_torch_twins():
    rng = np.random.default_rng(6)
    boxes = np.column_stack(
        [rng.normal(0, 10, (4, 3)), rng.uniform(1, 4, (4, 3)), rng.uniform(-3, 3, 4)]
    )
    pts = rng.normal(0, 10, (4, 50, 4)).astype(np.float64)
    local = world_to_box(pts, boxes)
    assert local.shape == pts.shape
    assert np.allclose(local[..., 3], pts[..., 3])
    assert np.allclose(box_to_world(local, boxes), pts)
    assert world_to_box(pts.astype(np.float32), boxes).dtype == np.float32
    tb, tp = torch.from_numpy(boxes), torch.from_numpy(pts[..., :3])
    assert np.allclose(world_to_box_torch(tp, tb).numpy(), local[..., :3])
    assert np.allclose(
        box_to_world_torch(torch.from_numpy(local[..., :3]), tb).numpy(), pts[..., :3]
    )
    assert np.allclose(box_corners_torch(tb).numpy(), box_corners(boxes))
    # the corners are at +-half extents in the box frame
    assert np.allclose(np.abs(world_to_box(box_corners(boxes), boxes)), boxes[:, None, 3:6] / 2)


def test_points_in_box_scale_and_offset():
    b = box(10.0, 0.0, 0.0, 4.0, 2.0, 2.0, math.pi / 2)  # length along +y
    pts = np.array(
        [
            [10.0, 1.9, 0.0],  # inside (along the length)
            [11.9, 0.0, 0.0],  # outside: across is only +-1
            [10.0, 2.0, 0.0],  # on the boundary: in
            [10.0, 2.4, 0.0],  # in with scale 1.25 (half length 2.5)
            [10.0, 0.0, 1.2],  # above: in with scale 1.25 (half height 1.25)
            [10.0, 4.4, 0.0],  # in only with offset 2 m (half length 1.25 * 2 + 2 = 4.5)
        ]
    )
    assert points_in_box(pts, b).tolist() == [True, False, True, False, False, False]
    assert points_in_box(pts, b, scale=1.25).tolist() == [True, False, True, True, True, False]
    assert points_in_box(pts, b, scale=1.25, offset_m=2.0).tolist() == [True] * 6
    batched = points_in_box(np.stack([pts, pts]), np.stack([b, box(100.0)]))
    assert batched.shape == (2, 6) and not batched[1].any()


def test_apply_offset_and_offset_between_are_inverse():
    rng = np.random.default_rng(7)
    ref = np.column_stack(
        [rng.normal(0, 5, (20, 3)), rng.uniform(1, 4, (20, 3)), rng.uniform(-3, 3, 20)]
    )
    off = np.column_stack([rng.normal(0, 1, (20, 3)), rng.uniform(-3, 3, 20)])
    moved = apply_offset(ref, off)
    assert np.allclose(moved[:, 3:6], ref[:, 3:6])
    assert np.all((moved[:, 6] >= -np.pi) & (moved[:, 6] < np.pi))
    back = offset_between(ref, moved)
    assert np.allclose(back[:, :3], off[:, :3])
    assert np.allclose(wrap_yaw(back[:, 3] - off[:, 3]), 0.0, atol=1e-12)
    assert np.allclose(apply_offset(ref, back), moved)
    # hand-computed: facing +y, moving 1 m forward goes to +y
    assert np.allclose(apply_offset(box(yaw=math.pi / 2), [1.0, 0, 0, 0])[:3], [0, 1, 0])


def test_scalar_box_offsets_equal_the_vectorised_ones():
    """The env's per-step Python-float twins of apply_offset / offset_between."""
    rng = np.random.default_rng(8)
    ref = np.column_stack(
        [rng.normal(0, 5, (50, 3)), rng.uniform(1, 4, (50, 3)), rng.uniform(-3.2, 3.2, 50)]
    )
    off = np.column_stack([rng.normal(0, 1, (50, 3)), rng.uniform(-4, 4, 50)])
    moved = np.array(
        [apply_offset_pair(r, o) for r, o in zip(ref.tolist(), off.tolist(), strict=True)]
    )
    np.testing.assert_allclose(moved, apply_offset(ref, off), rtol=0, atol=1e-12)
    back = np.array(
        [offset_between_pair(r, m) for r, m in zip(ref.tolist(), moved.tolist(), strict=True)]
    )
    np.testing.assert_allclose(back, offset_between(ref, moved), rtol=0, atol=1e-12)


def test_boxes_in_frame_and_center_distance():
    ref = box(1.0, 1.0, 0.0, yaw=math.pi / 2)
    target = box(1.0, 3.0, 0.5, yaw=math.pi / 2)
    local = boxes_in_frame(target, ref)
    assert np.allclose(local, [2.0, 0.0, 0.5, 2, 2, 2, 0.0])
    assert center_distance(ref, target) == pytest.approx(math.hypot(2.0, 0.5))
