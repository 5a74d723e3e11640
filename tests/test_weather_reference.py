"""The corruptions as the released reference code defines them: the fog rule of Hahner et al.'s
``fog_simulation.py`` (relocate, never remove; unshifted tables) and the snow levels of the
benchmark's released configuration (the rain rates with the Gunn-Marshall model)."""

from __future__ import annotations

import math

import numpy as np
import pytest

import envs.weather as weather
from envs.weather import WeatherTransform, corrupt
from envs.weather.fog import (
    BETA_TIMES_MOR,
    FOG_MODES,
    GAMMA_HARD,
    SPEED_OF_LIGHT,
    TAU_H_S,
    fog_alpha,
    reference_table,
    soft_target_table,
)
from envs.weather.levels import RAIN_RATE_MM_H, SNOW_RATE_MM_H_HAHNER
from envs.weather.precipitation import precipitation_rate


def make_scan(n: int, seed: int = 0, r_max: float = 80.0, scale: float = 1.0):
    rng = np.random.default_rng(seed)
    d = rng.normal(size=(n, 3))
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    r = rng.uniform(0.5, r_max, n)
    inten = scale * rng.uniform(0.0, 1.0, n)
    return (d * r[:, None]).astype(np.float32), inten.astype(np.float32)


def per_point_reference(pts, inten, rng, alpha, scale):
    """The released code's loop, point by point (``P_R_fog_hard`` then ``P_R_fog_soft`` with
    noise variant v4), on the 8-bit scale, reading our copy of the original integral table."""
    grid, integral, distance = reference_table(alpha)
    beta = BETA_TIMES_MOR * alpha / math.log(20.0)
    beta_0 = GAMMA_HARD / math.pi
    out_p = pts.astype(np.float64).copy()
    out_i = np.zeros(len(pts))
    for i in range(len(pts)):
        r0 = float(np.linalg.norm(pts[i].astype(np.float64)))
        i8 = float(inten[i]) * 255.0 / scale
        hard = round(math.exp(-2 * alpha * r0) * i8)
        k = min(int(round(r0 / (grid[1] - grid[0]))), len(grid) - 1)
        soft = min(integral[k] * i8 * r0**2 * beta / beta_0, 255.0)
        if soft > hard:
            new_dist = distance[k] + 10.0 * rng.beta(2.0, 20.0)
            out_p[i] = pts[i] * (new_dist / r0)
            out_i[i] = soft
        else:
            out_i[i] = hard
    return out_p, out_i * scale / 255.0


@pytest.mark.parametrize("level", [1, 3, 5])
@pytest.mark.parametrize("scale", [1.0, 255.0])
def test_fog_reference_matches_the_per_point_rule(level, scale):
    pts, inten = make_scan(400, seed=level, scale=scale)
    alpha = weather.parameter("fog", level)
    got_p, got_i = fog_alpha(pts, inten, np.random.default_rng(9), alpha)
    want_p, want_i = per_point_reference(pts, inten, np.random.default_rng(9), alpha, scale)
    np.testing.assert_allclose(got_p, want_p, rtol=1e-5, atol=1e-5)
    np.testing.assert_allclose(got_i, want_i, rtol=1e-5, atol=1e-6 * scale)


@pytest.mark.parametrize("level", [1, 2, 3, 4, 5])
def test_fog_reference_relocates_and_never_removes(level):
    pts, inten = make_scan(5000, seed=10 + level)
    inten[:50] = 0.0  # returns the sensor reported with intensity 0 stay too
    out_p, out_i, src = fog_alpha(
        pts, inten, np.random.default_rng(0), weather.parameter("fog", level), return_source=True
    )
    assert len(out_p) == len(pts) and np.array_equal(src, np.arange(len(pts)))
    moved = np.any(out_p != pts, axis=1)
    assert moved.any()
    # unmoved points are exactly where they were; moved ones stay on their ray
    r_in = np.linalg.norm(pts, axis=1)
    r_out = np.linalg.norm(out_p, axis=1)
    cos = (out_p * pts).sum(1) / (r_out * r_in)
    assert np.all(cos[moved] > 1 - 1e-5)
    # relocated to the unshifted fog peak plus 10 m * Beta(2, 20) (below 10 m)
    _, _, dist = reference_table(weather.parameter("fog", level))
    assert np.all(r_out[moved] >= dist.min() - 1e-4)
    assert np.all(r_out[moved] < dist.max() + 10.0)
    # the same input through the lossy rule does remove points at the heavy levels
    if level == 5:
        lossy = fog_alpha(
            pts, inten, np.random.default_rng(0), weather.parameter("fog", 5), mode="lossy"
        )[0]
        assert len(lossy) < len(pts)


def test_reference_table_is_unshifted():
    shift = SPEED_OF_LIGHT * TAU_H_S / 2  # ~3 m
    for alpha in (0.005, 0.06):
        r0, i_ref, d_ref = reference_table(alpha)
        _, i_lossy, d_lossy = soft_target_table(alpha)
        assert 4.0 < d_ref[-1] < 5.2  # the released tables: fog returns near 4.6 m
        assert d_ref[-1] - d_lossy[-1] == pytest.approx(shift, abs=0.05)
        assert np.all(d_ref <= r0 + 1e-9)  # the maximum is taken over R <= r0 only
        assert i_ref[-1] == pytest.approx(i_lossy[-1], rel=1e-9)  # far: the same maximum
        assert np.all(i_ref <= i_lossy + 1e-30)  # a restricted maximum is never larger


def test_fog_mode_through_corrupt_and_transform():
    pts, inten = make_scan(3000, seed=2)
    a = corrupt("fog", pts, inten, np.random.default_rng(1), 4)
    b = fog_alpha(pts, inten, np.random.default_rng(1), weather.parameter("fog", 4))
    np.testing.assert_array_equal(a[0], b[0])
    c = corrupt("fog", pts, inten, np.random.default_rng(1), 4, fog_mode="lossy")
    d = fog_alpha(pts, inten, np.random.default_rng(1), weather.parameter("fog", 4), mode="lossy")
    np.testing.assert_array_equal(c[0], d[0])
    scan = np.column_stack([pts, inten]).astype(np.float32)
    t_ref = WeatherTransform("fog", 4, seed=1)
    t_lossy = WeatherTransform("fog", 4, seed=1, fog_mode="lossy")
    assert t_ref != t_lossy and t_ref.info["fog_mode"] == "reference"
    assert len(t_ref(scan, "s/0", 0)) == len(scan) > len(t_lossy(scan, "s/0", 0))
    assert "fog_mode" not in WeatherTransform("rain", 1).info
    for bad in ("shifted", "", None):
        with pytest.raises(ValueError, match="valid fog modes: " + ", ".join(FOG_MODES)):
            corrupt("fog", pts, inten, np.random.default_rng(0), 1, fog_mode=bad)
        with pytest.raises(ValueError, match="reference, lossy"):
            WeatherTransform("fog", 1, fog_mode=bad)


def test_snow_levels_as_configured():
    # the benchmark's released configuration: the rain rates with the Gunn-Marshall model
    assert RAIN_RATE_MM_H == (0.20, 0.73, 1.5625, 3.125, 7.29)
    assert [weather.parameter("snow", lv) for lv in weather.LEVELS] == list(RAIN_RATE_MM_H)
    assert SNOW_RATE_MM_H_HAHNER == (0.5, 1.0, 1.5, 2.0, 2.5)
    pts, inten = make_scan(4000, seed=4)
    for level, rate in zip(weather.LEVELS, RAIN_RATE_MM_H, strict=True):
        got = corrupt("snow", pts, inten, np.random.default_rng(level), level)
        want = precipitation_rate(pts, inten, np.random.default_rng(level), "snow", rate)
        np.testing.assert_array_equal(got[0], want[0])
        np.testing.assert_array_equal(got[1], want[1])
        rain = corrupt("rain", pts, inten, np.random.default_rng(level), level)
        assert len(rain[0]) != len(got[0]) or not np.array_equal(rain[0], got[0])
    assert WeatherTransform("snow", 3).info["parameter"] == 1.5625
