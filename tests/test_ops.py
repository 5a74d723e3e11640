"""trackers.ops against brute-force references (Python loops / numpy, float64)."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from trackers import kernels, ops


def _points(b=2, n=300, seed=0, scale=1.0):
    g = torch.Generator().manual_seed(seed)
    return torch.rand(b, n, 3, generator=g) * scale


def _ball_query_ref(radius, k, xyz, centres):
    xyz, centres = xyz.double().numpy(), centres.double().numpy()
    b, m = centres.shape[:2]
    out = np.zeros((b, m, k), np.int64)
    for bi in range(b):
        for mi in range(m):
            hits = [
                j
                for j in range(xyz.shape[1])
                if ((xyz[bi, j] - centres[bi, mi]) ** 2).sum() < radius * radius
            ]
            hits = hits[:k]
            row = hits + [hits[0] if hits else 0] * (k - len(hits))
            out[bi, mi] = row
    return out


def _near_boundary(radius, xyz, centres, tol=1e-5):
    c, p = centres.double().numpy(), xyz.double().numpy()
    d = np.sqrt(((c[:, :, None] - p[:, None]) ** 2).sum(-1))
    return np.abs(d - radius).min() < tol


@pytest.mark.parametrize("radius,k", [(0.15, 8), (0.3, 32), (0.05, 4)])
def test_ball_query_matches_brute_force(radius, k):
    xyz = _points(n=200, seed=1)
    centres = torch.cat([xyz[:, :40], torch.full((2, 2, 3), 5.0)], dim=1)  # 2 centres with no hit
    assert not _near_boundary(radius, xyz, centres)
    idx, count = ops.ball_query(radius, k, xyz, centres, return_count=True)
    ref = _ball_query_ref(radius, k, xyz, centres)
    np.testing.assert_array_equal(idx.numpy(), ref)
    assert idx.dtype == torch.int64 and idx.shape == (2, 42, k)
    assert (count[:, -2:] == 0).all() and (count[:, :40] >= 1).all()
    assert (count <= k).all()


def test_ball_query_fewer_points_than_k():
    xyz = _points(n=5, seed=2)
    idx = ops.ball_query(10.0, 8, xyz, xyz[:, :2])
    np.testing.assert_array_equal(idx.numpy(), _ball_query_ref(10.0, 8, xyz, xyz[:, :2]))


@pytest.mark.parametrize("dim", [3, 32])
def test_knn_matches_brute_force(dim):
    g = torch.Generator().manual_seed(3)
    query, ref = torch.randn(2, 30, dim, generator=g), torch.randn(2, 50, dim, generator=g)
    d, idx = ops.knn(7, query, ref)
    dd = ((query.double()[:, :, None] - ref.double()[:, None]) ** 2).sum(-1).numpy()
    ref_idx = np.argsort(dd, axis=-1, kind="stable")[..., :7]
    np.testing.assert_array_equal(idx.numpy(), ref_idx)
    np.testing.assert_allclose(d.numpy(), np.take_along_axis(dd, ref_idx, -1), rtol=1e-4, atol=1e-5)


def test_knn_ties_lower_index_first_and_k_too_large():
    ref = torch.zeros(1, 6, 3)
    _, idx = ops.knn(3, torch.zeros(1, 1, 3), ref)
    assert idx.tolist() == [[[0, 1, 2]]]
    with pytest.raises(ValueError, match="exceeds"):
        ops.knn(7, torch.zeros(1, 1, 3), ref)


def test_pairwise_sqdist_and_gather_group():
    a, b = _points(n=20, seed=4), _points(n=30, seed=5)
    ref = ((a.double()[:, :, None] - b.double()[:, None]) ** 2).sum(-1)
    np.testing.assert_allclose(ops.pairwise_sqdist(a, b).numpy(), ref.numpy(), atol=1e-6)
    feats = torch.randn(2, 30, 64)
    np.testing.assert_allclose(ops.pairwise_sqdist(torch.randn(2, 5, 64), feats).shape, (2, 5, 30))
    idx = torch.randint(0, 30, (2, 7, 4))
    grouped = ops.group(feats, idx)
    assert grouped.shape == (2, 7, 4, 64)
    for bi in range(2):
        for m in range(7):
            for j in range(4):
                assert torch.equal(grouped[bi, m, j], feats[bi, idx[bi, m, j]])
    assert torch.equal(ops.gather(feats, idx[:, :, 0]), grouped[:, :, 0])


def _fps_ref(xyz, n):
    xyz = xyz.double().numpy()
    out = []
    for row in xyz:
        chosen = [0]
        mind = np.full(len(row), np.inf)
        for _ in range(n - 1):
            mind = np.minimum(mind, ((row - row[chosen[-1]]) ** 2).sum(-1))
            chosen.append(int(np.argmax(mind)))
        out.append(chosen)
    return np.array(out)


def test_farthest_point_sample_matches_brute_force():
    xyz = _points(n=150, seed=6)
    idx = ops.farthest_point_sample(xyz, 32)
    np.testing.assert_array_equal(idx.numpy(), _fps_ref(xyz, 32))
    assert len(set(idx[0].tolist())) == 32
    with pytest.raises(ValueError):
        ops.farthest_point_sample(xyz, 151)


def test_random_order():
    g1, g2 = torch.Generator().manual_seed(7), torch.Generator().manual_seed(7)
    o1, o2 = ops.random_order(3, 100, g1), ops.random_order(3, 100, g2)
    assert torch.equal(o1, o2)
    assert torch.equal(o1.sort(1).values, torch.arange(100).expand(3, 100))


def test_hash_order_is_invariant_to_input_order():
    xyz = _points(b=2, n=256, seed=8, scale=4.0)
    xyz[:, 100:110] = xyz[:, :10]  # exact duplicates are allowed
    perm = torch.randperm(256, generator=torch.Generator().manual_seed(9))
    a = ops.gather(xyz, ops.hash_order(xyz, seed=3))
    b = ops.gather(xyz[:, perm], ops.hash_order(xyz[:, perm], seed=3))
    assert torch.equal(a, b)
    other = ops.gather(xyz, ops.hash_order(xyz, seed=4))
    assert not torch.equal(a, other)  # the seed changes the sample
    # a prefix is a roughly uniform sample: neither the first nor the last points by index
    first_half = ops.hash_order(xyz, seed=3)[:, :128]
    assert 30 < (first_half < 128).sum(1).float().mean() < 98


def _hash_key_reference(xyz: torch.Tensor, seed: int) -> torch.Tensor:
    """hash_order's 63-bit coordinate key, one chain at a time in plain Python integers."""
    keys = []
    for point in xyz.reshape(-1, 3).tolist():
        q = [round(v / 1e-4) & 0xFFFFFFFF for v in point]
        h1 = (seed * 0x9E3779B1 + 0x7F4A7C15) & 0xFFFFFFFF
        h2 = (seed * 0x85EBCA77 + 0x165667B1) & 0xFFFFFFFF
        for v in q:
            h1 = _fmix32(h1 ^ v)
            h2 = _fmix32(h2 ^ (v * 0x27D4EB2F) % 2**32)
        keys.append(((h1 >> 1) << 32) | h2)
    return torch.tensor(keys).view(xyz.shape[:-1])


def _fmix32(h: int) -> int:
    h ^= h >> 16
    h = (h * 0x85EBCA6B) % 2**32
    h ^= h >> 13
    h = (h * 0xC2B2AE35) % 2**32
    return h ^ (h >> 16)


def test_hash_order_sorts_by_the_documented_key():
    """Distinct points (occurrence rank 0 everywhere): the order is by the rank-spread key,
    whose coordinate part is the two-chain murmur hash computed here in plain integers."""
    xyz = _points(b=2, n=64, seed=12, scale=4.0)
    key = _hash_key_reference(xyz.double(), seed=5)
    spread = ops._mix32(
        ops._mix32((key & 0xFFFFFFFF) ^ ops._mul32(torch.ones_like(key), 0x9E3779B1)) ^ (key >> 32)
    )
    final = ((spread >> 1) << 31) | (key >> 32)
    assert torch.equal(ops.hash_order(xyz, seed=5), final.argsort(dim=1, stable=True))


def test_mul32_exact():
    g = torch.Generator().manual_seed(0)
    h = torch.randint(0, 2**32, (500,), dtype=torch.long, generator=g)
    c = 0x85EBCA6B
    ref = torch.tensor([(int(x) * c) % 2**32 for x in h])
    assert torch.equal(ops._mul32(h, c), ref)


@pytest.mark.skipif(not torch.cuda.is_available(), reason="no GPU")
def test_ops_cpu_equals_gpu():  # pragma: no cover - GPU machines only
    xyz = _points(n=500, seed=10)
    centres = xyz[:, :100]
    assert torch.equal(
        ops.ball_query(0.2, 16, xyz, centres),
        ops.ball_query(0.2, 16, xyz.cuda(), centres.cuda()).cpu(),
    )
    assert torch.equal(ops.hash_order(xyz), ops.hash_order(xyz.cuda()).cpu())
    assert torch.equal(ops.knn(8, centres, xyz)[1], ops.knn(8, centres.cuda(), xyz.cuda())[1].cpu())
    assert torch.equal(
        ops.farthest_point_sample(xyz, 50), ops.farthest_point_sample(xyz.cuda(), 50).cpu()
    )


def test_hash_order_spreads_duplicates_like_a_random_permutation():
    """Padded clouds (few points, many copies): a prefix keeps as many distinct points as a
    random permutation's prefix would, and stays order invariant."""
    g = torch.Generator().manual_seed(11)
    unique = torch.rand(1, 100, 3, generator=g) * 4
    pts = torch.cat([unique, unique[:, torch.randint(0, 100, (412,), generator=g)]], dim=1)
    prefix = ops.gather(pts, ops.hash_order(pts)[:, :64])[0]
    assert torch.unique(prefix, dim=0).shape[0] >= 40  # a random prefix gives ~48 on average
    perm = torch.randperm(512, generator=g)
    assert torch.equal(prefix, ops.gather(pts[:, perm], ops.hash_order(pts[:, perm])[:, :64])[0])


def _ball_path(path: str, monkeypatch) -> None:
    """Force one path of ``ops.ball_query_pairs``: the compiled scan, the grid or every pair."""
    if path == "compiled":
        if kernels.ball_kernel() is None:
            pytest.skip("numba is not installed (pip install 'pointtrack[fast]')")
        return
    monkeypatch.setattr(kernels, "ball_kernel", lambda: None)
    monkeypatch.setattr(ops, "_DENSE_PAIRS", 0 if path == "grid" else 10**9)
    monkeypatch.setattr(ops, "_GRID_SHARE", 0)  # the grid even where its candidates are many


@pytest.mark.parametrize("path", ["compiled", "grid", "dense"])
@pytest.mark.parametrize("radius,k", [(0.15, 8), (0.3, 32), (10.0, 4), (0.05, 2)])
def test_ball_query_pairs_are_the_real_slots_of_ball_query(radius, k, path, monkeypatch):
    _ball_path(path, monkeypatch)
    xyz = _points(n=200, seed=4)
    xyz[:, 100:130] = xyz[:, 60:90]  # copies: equal keys in the sorted grid cells
    centres = torch.cat(
        [xyz[:, :40], torch.full((2, 2, 3), 5.0), torch.full((2, 1, 3), -5.0)], dim=1
    )  # 3 without a hit, beyond either end of the x range
    idx, count = ops.ball_query(radius, k, xyz, centres, return_count=True)
    group, point = ops.ball_query_pairs(radius, k, xyz, centres)
    b, m = count.shape
    valid = torch.arange(k) < count.clamp(min=1)[..., None]
    expected_group = torch.arange(b * m).view(b, m, 1).expand(b, m, k)[valid]
    expected_point = (idx + (torch.arange(b) * 200).view(b, 1, 1))[valid]
    assert torch.equal(group, expected_group) and torch.equal(point, expected_point)


@pytest.mark.parametrize("path", ["compiled", "grid", "dense"])
def test_ball_query_pairs_leave_out_what_the_keep_masks_drop(path, monkeypatch):
    """``keep_centres`` / ``keep_points`` give the pairs of the unmasked query filtered after
    it: a hit left out still counts towards the ``k`` (checked to fail when the compiled scan
    stops counting it), a centre left out lists nothing, centres without a hit keep their
    ``(centre, point 0)`` pair."""
    _ball_path(path, monkeypatch)
    radius, k = 0.3, 8
    xyz = _points(n=200, seed=6)
    xyz[:, 100:160] = xyz[:, 40:100]  # copies, as the env's resampling
    centres = torch.cat([xyz[:, :50], torch.full((2, 2, 3), 5.0)], dim=1)
    g = torch.Generator().manual_seed(1)
    keep_points = torch.rand(2, 200, generator=g) > 0.4
    keep_points[:, 0] = True
    keep_centres = torch.rand(2, 52, generator=g) > 0.3
    group, point = ops.ball_query_pairs(radius, k, xyz, centres)
    kept = keep_centres.flatten()[group] & keep_points.flatten()[point]
    got = ops.ball_query_pairs(radius, k, xyz, centres, keep_centres, keep_points)
    assert torch.equal(got[0], group[kept]) and torch.equal(got[1], point[kept])
    assert 0 < len(got[0]) < kept.numel() - 20  # both masks leave pairs out
    only_points = ops.ball_query_pairs(radius, k, xyz, centres, None, keep_points)
    assert torch.equal(only_points[1], point[keep_points.flatten()[point]])


def test_first_copy_matches_brute_force():
    g = torch.Generator().manual_seed(5)
    xyz = torch.randint(0, 3, (2, 60, 3), generator=g).float() * 0.5
    first = ops.first_copy(xyz)
    for b in range(2):
        for j in range(60):
            expected = min(i for i in range(60) if torch.equal(xyz[b, i], xyz[b, j]))
            assert first[b, j] == expected
    distinct = torch.rand(1, 50, 3, generator=g)
    assert torch.equal(ops.first_copy(distinct)[0], torch.arange(50))


def test_pairwise_sqdist_in_place_path_keeps_gradients():
    a = torch.rand(2, 5, 3, requires_grad=True)
    b = torch.rand(2, 7, 3)
    d = ops.pairwise_sqdist(a, b)
    d.sum().backward()
    with torch.no_grad():
        torch.testing.assert_close(ops.pairwise_sqdist(a, b), d, rtol=0, atol=0)
    assert a.grad is not None and torch.isfinite(a.grad).all()


def test_hash_orders_of_several_clouds_equal_one_call_each():
    g = torch.Generator().manual_seed(6)
    template = torch.rand(2, 64, 3, generator=g)
    search = torch.cat([template, torch.rand(2, 100, 3, generator=g)], dim=1)  # shared points
    search[:, 120:] = search[:, 80:124].clone()  # copies within the search cloud
    order_t, order_s = ops.hash_orders([template, search], [3, 4])
    assert torch.equal(order_t, ops.hash_order(template, seed=3))
    assert torch.equal(order_s, ops.hash_order(search, seed=4))


@pytest.mark.parametrize("seed", range(6))
def test_ball_query_grid_cells_find_every_hit(seed, monkeypatch):
    """The grid path against every pair, on clouds with points on cell boundaries, exactly one
    radius apart, copies and centres outside the cloud."""
    monkeypatch.setattr(ops, "_GRID_SHARE", 0)  # the grid even where its candidates are many
    g = torch.Generator().manual_seed(seed)
    radius, k = [0.3, 0.5, 0.7, 0.05, 2.0, 0.3][seed], [32, 16, 8, 4, 64, 1][seed]
    xyz = (torch.rand(2, 300, 3, generator=g) - 0.5) * 6
    xyz[:, :100] = torch.round(xyz[:, :100] / radius) * radius  # on the grid lines
    xyz[:, 250:] = xyz[:, 50:100].clone()
    centres = torch.cat(
        [
            xyz[:, :80],
            xyz[:, 80:120] + (torch.rand(2, 40, 3, generator=g) - 0.5) * 2 * radius,
            torch.full((2, 3, 3), 9.0),
        ],
        dim=1,
    )
    dense = ops._ball_dense(radius, k, xyz, centres)
    grid = ops._ball_grid(radius, k, xyz, centres)
    assert torch.equal(dense[0], grid[0]) and torch.equal(dense[1], grid[1])


@pytest.mark.parametrize("seed", range(4))
def test_ball_query_compiled_scan_equals_every_pair(seed):
    """The compiled scan against the dense torch test on clustered crops with copies, points
    exactly one radius away (float32 and float64) and centres without a hit."""
    if kernels.ball_kernel() is None:
        pytest.skip("numba is not installed (pip install 'pointtrack[fast]')")
    g = torch.Generator().manual_seed(seed)
    radius, k = [0.3, 0.5, 0.25, 1.0][seed], [32, 16, 48, 1][seed]
    xyz = torch.randn(3, 512, 3, generator=g) * torch.tensor([1.0, 0.6, 0.4])
    xyz[:, 300:] = xyz[:, :212].clone()  # the env's padding copies
    xyz[:, 100:140] = xyz[:, :40] + torch.tensor([radius, 0.0, 0.0])  # exactly one radius away
    centres = torch.cat([xyz[:, :200], torch.full((3, 2, 3), 9.0)], dim=1)
    for dtype in (torch.float32, torch.float64):
        x, c = xyz.to(dtype), centres.to(dtype)
        b, m, n = c.shape[0], c.shape[1], x.shape[1]
        group, point = ops.ball_query_pairs(radius, k, x, c)
        dense_group, dense_point = ops._ball_dense(radius, k, x, c)
        assert torch.equal(group, dense_group)
        row = torch.div(dense_group, m, rounding_mode="floor")
        assert torch.equal(point, dense_point + row * n)
        assert b * m <= len(group) <= b * m * k


@pytest.mark.parametrize("seed", range(3))
def test_knn_compiled_equals_the_stable_sort(seed, monkeypatch):
    """The compiled k nearest neighbours against the stable sort of every distance, with ties
    (coordinates on a coarse grid, every point twice, so the x-sorted scan meets runs of equal
    x), float32 and float64: the same distances and indices."""
    if kernels.knn_kernel() is None:
        pytest.skip("numba is not installed (pip install 'pointtrack[fast]')")
    g = torch.Generator().manual_seed(seed)
    b, m, n, k = 2, (5, 100, 512)[seed], (7, 300, 1024)[seed], (1, 8, 16)[seed]
    query, ref = torch.rand(b, m, 3, generator=g) * 4, torch.rand(b, n, 3, generator=g) * 4
    query, ref = (query * 2).round() / 2, (ref * 2).round() / 2
    ref[:, n // 2 :] = ref[:, : n - n // 2].clone()
    ref.requires_grad_(True)
    compiled = ops.knn(k, query, ref)
    compiled64 = ops.knn(k, query.double(), ref.detach().double())
    monkeypatch.setattr(kernels, "knn_kernel", lambda: None)
    reference = ops.knn(k, query, ref)
    assert torch.equal(compiled[1], reference[1]) and torch.equal(compiled[0], reference[0])
    reference64 = ops.knn(k, query.double(), ref.detach().double())
    assert torch.equal(compiled64[1], reference64[1]) and torch.equal(compiled64[0], reference64[0])
    compiled[0].sum().backward()  # the distances stay differentiable
    assert ref.grad is not None and torch.isfinite(ref.grad).all()


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_hash_orders_compiled_equal_the_torch_chains(dtype, monkeypatch):
    """The compiled hash against the torch chains: two clouds of several rows with duplicated
    points (occurrence ranks), negative coordinates and coordinates half a quantum apart
    (round half to even): the same orders bit for bit."""
    if kernels.hash_kernel() is None:
        pytest.skip("numba is not installed (pip install 'pointtrack[fast]')")
    g = torch.Generator().manual_seed(0)
    search = ((torch.rand(3, 1024, 3, generator=g) * 20 - 10) * 4).round() / 4
    search[:, 512:] = search[:, :512].clone()
    search[0, :8, 0] = (torch.arange(8, dtype=torch.float64) + 0.5) * 1e-4  # exact halves
    template = torch.randn(3, 5, 3, generator=g)
    clouds = [template.to(dtype), search.to(dtype)]
    compiled = ops.hash_orders(clouds, [3, 4])
    monkeypatch.setattr(kernels, "hash_kernel", lambda: None)
    reference = ops.hash_orders(clouds, [3, 4])
    assert all(torch.equal(a, b) for a, b in zip(compiled, reference, strict=True))


def test_nearest_distances_compiled_equal_torch(monkeypatch):
    """The compiled nearest distances against the torch path on an env-like cloud (resampled
    copies, padding rows, a mask), through the distinct points as the decision step's torch
    path takes them: the layout reads the cloud back, and the nearest and Chamfer distances are
    the same bit for bit."""
    if kernels.nearest_kernel() is None:
        pytest.skip("numba is not installed (pip install 'pointtrack[fast]')")
    g = torch.Generator().manual_seed(0)
    base = torch.rand(300, 3, generator=g) * 4 - 2
    cloud = base[torch.randint(0, 300, (1024,), generator=g)]  # copies, as the env resamples
    cloud[1000:] = 0  # padding
    cloud[::7, 2] += 0.5  # copies of (x, y) at another z
    mask = (cloud != 0).any(-1) & (torch.rand(1024, generator=g) > 0.1)
    crops = torch.rand(2, 64, 3, generator=g) * 4 - 2
    crop_in = torch.rand(2, 64, generator=g) > 0.2
    unique, layout = ops.distinct_points(cloud, mask)
    assert torch.equal(
        torch.where(mask[:, None], unique[layout.clamp(max=len(unique) - 1)], 0),
        torch.where(mask[:, None], cloud, 0),
    )
    assert bool((layout[~mask] == len(unique)).all())
    assert len(unique) < mask.sum() // 2  # the copies count once

    def run():
        near = ops.nearest_distances(crops, crop_in, unique)
        chamfer = ops.chamfer_distance(cloud[None], mask[None], crops[:1], crop_in[:1])
        return near, chamfer

    compiled = run()
    monkeypatch.setattr(kernels, "nearest_kernel", lambda: None)
    reference = run()
    assert torch.equal(compiled[0][0], reference[0][0])
    assert torch.equal(compiled[0][1], reference[0][1])
    assert torch.equal(compiled[1], reference[1])


def _chamfer_ref(a, am, b, bm):
    """Loops over the masked points, float64."""
    out = []
    rows = zip(a.double().numpy(), am.numpy(), b.double().numpy(), bm.numpy(), strict=True)
    for pa, ma, pb, mb in rows:
        sa, sb = pa[ma], pb[mb]
        if not len(sa) or not len(sb):
            out.append(np.inf)
            continue
        a_to_b = np.mean([min(np.linalg.norm(p - q) for q in sb) for p in sa])
        b_to_a = np.mean([min(np.linalg.norm(q - p) for p in sa) for q in sb])
        out.append(0.5 * (a_to_b + b_to_a))
    return np.array(out)


def test_chamfer_distance_matches_brute_force_with_masks():
    a, b = _points(3, 40, seed=1), _points(3, 30, seed=2, scale=2.0)
    g = torch.Generator().manual_seed(3)
    am, bm = torch.rand(3, 40, generator=g) < 0.6, torch.rand(3, 30, generator=g) < 0.5
    bm[2] = False  # an empty set: inf
    got = ops.chamfer_distance(a, am, b, bm).numpy()
    want = _chamfer_ref(a, am, b, bm)
    assert np.isinf(got[2]) and np.isinf(want[2])
    np.testing.assert_allclose(got[:2], want[:2], rtol=1e-5)
    # masked-out points may hold anything: moving them changes nothing
    far = torch.where(am[..., None], a, torch.full_like(a, 1e3))
    np.testing.assert_array_equal(ops.chamfer_distance(far, am, b, bm).numpy(), got)


def test_chamfer_distance_of_a_repeated_set_and_symmetry():
    a, b = _points(2, 50, seed=4), _points(2, 20, seed=5)
    ones_a, ones_b = torch.ones(2, 50, dtype=torch.bool), torch.ones(2, 20, dtype=torch.bool)
    d = ops.chamfer_distance(a, ones_a, b, ones_b)
    doubled = torch.cat([b, b], dim=1)  # every point twice: the same set, the same means
    ones_d = torch.ones(2, 40, dtype=torch.bool)
    np.testing.assert_allclose(ops.chamfer_distance(a, ones_a, doubled, ones_d), d, rtol=1e-6)
    np.testing.assert_allclose(ops.chamfer_distance(b, ones_b, a, ones_a), d, rtol=1e-6)
    assert (ops.chamfer_distance(a, ones_a, a, ones_a) == 0).all()


def test_chamfer_distance_of_a_row_does_not_depend_on_the_batch():
    g = torch.Generator().manual_seed(8)
    a, b = torch.randn(6, 300, 3, generator=g) * 2, torch.randn(6, 80, 3, generator=g)
    a_mask = torch.rand(6, 300, generator=g) < torch.linspace(0.05, 0.9, 6)[:, None]
    b_mask = torch.rand(6, 80, generator=g) < 0.7
    batched = ops.chamfer_distance(a, a_mask, b, b_mask)
    for i in range(6):  # alone, the rows are cut to their own masked counts: other sums
        alone = ops.chamfer_distance(
            a[i : i + 1], a_mask[i : i + 1], b[i : i + 1], b_mask[i : i + 1]
        )
        assert torch.equal(alone, batched[i : i + 1]), i


@pytest.mark.parametrize("channels", [1, 4, 13])
def test_unique_rows_equals_torch_unique(channels):
    g = torch.Generator().manual_seed(channels)
    rows = torch.randn(60, channels, generator=g)
    rows[::5, 0] = 0.0  # ties in the leading column, decided by the later ones
    x = rows[torch.randint(0, 60, (500,), generator=g)]
    unique, inverse = ops.unique_rows(x)
    ref_unique, ref_inverse = torch.unique(x, dim=0, return_inverse=True)
    assert torch.equal(unique, ref_unique)
    assert torch.equal(inverse, ref_inverse)
    assert torch.equal(unique[inverse], x)


def _fps_before(xyz: torch.Tensor, n: int, start: int = 0) -> torch.Tensor:
    """``ops.farthest_point_sample`` as it was before the compiled loop (the reference)."""
    b, npts, _ = xyz.shape
    mind = torch.full((b, npts), float("inf"), dtype=xyz.dtype)
    cur = torch.full((b,), start, dtype=torch.long)
    picks = []
    for _ in range(n):
        picks.append(cur)
        centre = torch.gather(xyz, 1, cur.view(b, 1, 1).expand(b, 1, 3))
        torch.minimum(mind, (xyz - centre).square_().sum(-1), out=mind)
        cur = mind.argmax(dim=1)
    return torch.stack(picks, dim=1)


@pytest.mark.parametrize("compiled", [True, False])
def test_farthest_point_sample_equals_the_previous_implementation(compiled, monkeypatch):
    if compiled and kernels.fps_kernel() is None:
        pytest.skip("numba is not installed (pip install 'pointtrack[fast]')")
    if not compiled:
        monkeypatch.setattr(kernels, "fps_kernel", lambda: None)
    g = torch.Generator().manual_seed(0)
    for trial in range(24):
        b, n = 1 + trial % 3, (7, 100, 1024, 513)[trial % 4]
        xyz = torch.rand(b, n, 3, generator=g) * torch.tensor([9.0, 6.0, 3.0])
        if trial % 2:  # ties: a coarse grid of coordinates, every point twice
            xyz = (xyz * 2).round() / 2
            xyz[:, n // 2 :] = xyz[:, : n - n // 2].clone()
        k, start = max(1, n // 2), trial % 3
        np.testing.assert_array_equal(
            ops.farthest_point_sample(xyz, k, start).numpy(), _fps_before(xyz, k, start).numpy()
        )
    assert ops.farthest_point_sample(xyz, 0).shape == (b, 0)


_EVERY_KERNEL = """
import json
from trackers import decision, kernels, ops
assert ops.load_kernels() and decision.load_kernels()
getters = ["hash_kernel", "fps_kernel", "ball_kernel", "knn_kernel", "nearest_kernel",
           "scene_kernel", "crop_distance_kernel"]
print(json.dumps({g: len(getattr(kernels, g)().stats.cache_misses) for g in getters}))
"""


def test_every_kernel_loads_from_numbas_disk_cache_in_a_new_process(tmp_path):
    """``ops.load_kernels`` and ``decision.load_kernels`` reach all seven kernels (the first
    process compiles each), and a second process compiles nothing: a closure that pickles
    differently per process (a dispatcher) made the hash kernel miss numba's cache every time,
    ~1-3 s in every `pointtrack eval` worker and a new cache file per run."""
    if kernels.hash_kernel() is None:
        pytest.skip("numba is not installed (pip install 'pointtrack[fast]')")
    import json
    import os
    import subprocess
    import sys
    from pathlib import Path

    root = Path(__file__).resolve().parents[1]
    env = {**os.environ, "NUMBA_CACHE_DIR": str(tmp_path), "PYTHONPATH": str(root)}
    runs = [
        subprocess.run(
            [sys.executable, "-c", _EVERY_KERNEL], env=env, capture_output=True, text=True
        )
        for _ in range(2)
    ]
    for run in runs:
        assert run.returncode == 0, run.stderr
    first, second = (json.loads(r.stdout.strip().splitlines()[-1]) for r in runs)
    assert all(first.values()), first  # the first process compiled every kernel ...
    assert not any(second.values()), second  # ... and the second loaded them all
