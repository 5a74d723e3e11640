"""Physics sanity, determinism and bad input of the weather corruptions (envs.weather)."""

from __future__ import annotations

import pickle

import numpy as np
import pytest

import envs.weather as weather
from envs.weather import KINDS, LEVELS, corrupt, domain_randomize
from envs.weather.fog import fog_alpha, soft_target_table
from envs.weather.precipitation import gunn_marshall, marshall_palmer, precipitation_rate


def make_scan(n: int = 20000, seed: int = 0, r_max: float = 120.0, scale: float = 1.0):
    """Random rays with ranges 2..r_max m (more far ones than a real scan has, on purpose)."""
    rng = np.random.default_rng(seed)
    d = rng.normal(size=(n, 3))
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    d[:, 2] = -0.2 * np.abs(d[:, 2])
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    r = rng.uniform(2.0, r_max, n)
    inten = scale * rng.uniform(0.05, 1.0, n)
    return (d * r[:, None]).astype(np.float32), inten.astype(np.float32)


def run(kind, pts, inten, rng, param, return_source=False, fog_mode="reference"):
    if kind == "fog":
        return fog_alpha(pts, inten, rng, param, return_source=return_source, mode=fog_mode)
    return precipitation_rate(pts, inten, rng, kind, param, return_source=return_source)


@pytest.mark.parametrize("kind", KINDS)
def test_zero_parameter_changes_nothing(kind):
    pts, inten = make_scan(3000)
    out_p, out_i = run(kind, pts, inten, np.random.default_rng(0), 0.0)
    np.testing.assert_array_equal(out_p, pts)
    np.testing.assert_array_equal(out_i, inten)


@pytest.mark.parametrize("kind", KINDS)
@pytest.mark.parametrize("level", LEVELS)
def test_points_only_lost_or_closer(kind, level):
    # fog: the lossy rule caps relocated points at their range (the reference rule does not,
    # tests/test_weather_reference.py)
    pts, inten = make_scan(8000, seed=level)
    p = weather.parameter(kind, level)
    out_p, out_i, src = run(
        kind, pts, inten, np.random.default_rng(1), p, return_source=True, fog_mode="lossy"
    )
    assert out_p.dtype == np.float32 and out_i.dtype == np.float32
    assert len(out_p) == len(out_i) == len(src) <= len(pts)
    r_in = np.linalg.norm(pts[src], axis=1)
    r_out = np.linalg.norm(out_p, axis=1)
    assert np.all(r_out <= r_in * (1 + 1e-6) + 1e-5)
    assert np.all(r_out > 0)  # lost points are removed, never left at the origin
    # same ray: direction unchanged
    cos = (out_p * pts[src]).sum(1) / (r_out * r_in)
    assert np.all(cos > 1 - 1e-5)
    assert np.all(out_i <= np.maximum(inten[src], 1.0) + 1e-6)


@pytest.mark.parametrize("kind", KINDS)
def test_far_returns_fall_monotonically_with_level(kind):
    pts, inten = make_scan(30000, seed=3)
    counts = []
    for level in LEVELS:
        out_p, _ = corrupt(kind, pts, inten, np.random.default_rng(7), level)
        counts.append(int((np.linalg.norm(out_p, axis=1) > 40).sum()))
    assert all(a >= b for a, b in zip(counts, counts[1:], strict=False)), counts
    assert counts[-1] < int((np.linalg.norm(pts, axis=1) > 40).sum())


def test_fog_dense_removes_far_returns_and_adds_near_fog():
    pts, inten = make_scan(20000, seed=4)
    out_p, _ = corrupt("fog", pts, inten, np.random.default_rng(0), 5)
    r_out = np.linalg.norm(out_p, axis=1)
    r_in = np.linalg.norm(pts, axis=1)
    assert (r_out > 50).sum() == 0  # MOR 50 m: nothing survives beyond ~40 m
    assert (r_out < 5).sum() > 5 * (r_in < 5).sum()  # fog returns near the sensor


def test_fog_table_physical():
    r0, integral, dist = soft_target_table(0.06)
    assert np.all(np.diff(integral) >= -1e-20)  # a farther target truncates less fog
    assert np.all(dist <= r0 + 1e-9)
    assert 0.9 < dist[-1] < 6.0  # the fog peak sits a few metres from the sensor


@pytest.mark.parametrize("kind", ["rain", "snow"])
def test_precipitation_scatters_near_sensor(kind):
    pts, inten = make_scan(30000, seed=5)
    p = weather.parameter(kind, 5)
    out_p, out_i, src = run(kind, pts, inten, np.random.default_rng(2), p, return_source=True)
    r_in = np.linalg.norm(pts[src], axis=1)
    r_out = np.linalg.norm(out_p, axis=1)
    moved = r_out < r_in - 0.5  # scatter points, not range noise
    assert moved.sum() > 50
    assert np.all(r_out[moved] < 30.0) and np.median(r_out[moved]) < 8.0
    assert np.all(r_out[moved] >= 1.5)  # not inside the blind range
    assert len(out_p) < len(pts)  # and some returns are lost


def test_extinction_and_distributions():
    # heavier precipitation extinguishes more; snow more than rain at the same water rate
    a_rain = [marshall_palmer(r).extinction for r in weather.levels.RAIN_RATE_MM_H]
    a_snow = [gunn_marshall(r).extinction for r in weather.levels.SNOW_RATE_MM_H]
    assert np.all(np.diff(a_rain) > 0) and np.all(np.diff(a_snow) > 0)
    assert gunn_marshall(1.0).extinction > marshall_palmer(1.0).extinction
    # closed form pi 1e-6 N0 / lam^3 against a numerical integral of (pi/4) Q_ext D^2 N(D)
    m = marshall_palmer(3.125)
    d = np.linspace(0, 30, 300001)
    num = np.pi / 4 * 2 * 1e-6 * np.trapezoid(d**2 * m.n0 * np.exp(-m.lam * d), d)
    assert m.extinction == pytest.approx(num, rel=1e-6)


@pytest.mark.parametrize("kind", KINDS)
def test_intensity_falls_with_attenuation(kind):
    pts, inten = make_scan(10000, seed=6)
    means = []
    for level in (1, 5):
        out_p, out_i, src = run(
            kind,
            pts,
            inten,
            np.random.default_rng(0),
            weather.parameter(kind, level),
            return_source=True,
        )
        # hard returns (not moved to a scatterer / fog)
        same = np.linalg.norm(out_p, axis=1) > np.linalg.norm(pts[src], axis=1) - 0.5
        assert np.all(out_i[same] <= inten[src][same] + 1e-7)
        means.append(float((out_i[same] / np.maximum(inten[src][same], 1e-6)).mean()))
    assert means[1] < means[0] < 1.0


def test_intensity_scale_is_kept():
    pts, inten = make_scan(5000, seed=8, scale=255.0)
    for kind in KINDS:
        _, out_i = corrupt(kind, pts, inten, np.random.default_rng(0), 3)
        assert out_i.max() <= 255.0 and out_i.max() > 1.0


@pytest.mark.parametrize("kind", KINDS)
def test_determinism_by_seed(kind):
    pts, inten = make_scan(5000)
    a = corrupt(kind, pts, inten, np.random.default_rng(42), 4)
    b = corrupt(kind, pts, inten, np.random.default_rng(42), 4)
    c = corrupt(kind, pts, inten, np.random.default_rng(43), 4)
    np.testing.assert_array_equal(a[0], b[0])
    np.testing.assert_array_equal(a[1], b[1])
    assert len(a[0]) != len(c[0]) or not np.array_equal(a[0], c[0])


def test_bad_input():
    pts, inten = make_scan(100)
    rng = np.random.default_rng(0)
    with pytest.raises(ValueError, match="fog, rain, snow"):
        corrupt("hail", pts, inten, rng, 1)
    for bad in (0, 6, 2.5, "3", True):
        with pytest.raises(ValueError, match="1, 2, 3, 4, 5"):
            corrupt("rain", pts, inten, rng, bad)
    for kind in KINDS:
        with pytest.raises(ValueError, match="intensity"):
            corrupt(kind, pts, None, rng, 1)
        with pytest.raises(ValueError, match="intensity"):
            corrupt(kind, pts, inten[:-1], rng, 1)
        with pytest.raises(ValueError, match=r"\(N, 3\)"):
            corrupt(kind, np.zeros((5, 4), np.float32), np.zeros(5, np.float32), rng, 1)
        bad_pts = pts.copy()
        bad_pts[0, 0] = np.nan
        with pytest.raises(ValueError, match="NaN"):
            corrupt(kind, bad_pts, inten, rng, 1)
        p, i = corrupt(kind, np.zeros((0, 3), np.float32), np.zeros(0, np.float32), rng, 5)
        assert p.shape == (0, 3) and i.shape == (0,)
    with pytest.raises(TypeError, match="Generator"):
        corrupt("fog", pts, inten, 0, 1)


def test_domain_randomization():
    rng = np.random.default_rng(0)
    pts = np.random.default_rng(1).normal(size=(500, 4)).astype(np.float32)
    outs = [domain_randomize(pts, np.random.default_rng(s)) for s in range(200)]
    same = sum(o.shape == pts.shape and np.array_equal(o, pts) for o in outs)
    assert 70 < same < 150  # skipped with p = 0.5 (plus the rare all-steps-off case)
    sizes = {len(o) for o in outs}
    assert min(sizes) >= 500 - 150 and max(sizes) <= 500 + 50
    a = domain_randomize(pts, np.random.default_rng(5))
    b = domain_randomize(pts, np.random.default_rng(5))
    np.testing.assert_array_equal(a, b)
    assert domain_randomize(np.zeros((0, 3)), rng).shape == (0, 3)
    # always on: every step applied
    full = domain_randomize(pts, rng, p_skip=0.0, p_step=1.0)
    assert full.dtype == np.float32 and full.shape[1] == 4
    assert not np.array_equal(full[:10], pts[:10])
    dr = weather.DomainRandomization(jitter_m=0.05)
    assert pickle.loads(pickle.dumps(dr)) == dr
    with pytest.raises(ValueError):
        domain_randomize(pts, rng, p_skip=2.0)
