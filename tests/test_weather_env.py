"""The weather hook, the wrapper and the robustness benchmark (envs.weather.wrapper,
training.robustness)."""

from __future__ import annotations

import math
import pickle

import numpy as np
import pytest
from gymnasium.utils.env_checker import check_env

from envs.tracking_env import TrackingEnv, make_toy_dataset
from envs.weather import WeatherTransform, WeatherWrapper
from training.robustness import (
    format_weather_table,
    hausdorff,
    robustness_metrics,
    run_weather_benchmark,
    weather_kinds,
)


@pytest.fixture(scope="module")
def toy():
    return make_toy_dataset(categories=("Car", "Pedestrian"), num_frames=5, num_clutter=3000)


def scan(seed=0, n=4000):
    rng = np.random.default_rng(seed)
    xyz = rng.uniform(-40, 40, (n, 3)).astype(np.float32)
    return np.column_stack([xyz, rng.random(n).astype(np.float32)])


def test_transform_keyed_by_scene_and_frame():
    t = WeatherTransform("snow", 5, seed=3)
    s = scan()
    a = t(s, "0004/1", 10)
    b = WeatherTransform("snow", 5, seed=3)(s, "0004/7", 10)  # other tracklet, same frame
    np.testing.assert_array_equal(a, b)
    assert a.shape[1] == 4 and a.dtype == np.float32
    assert not np.array_equal(a, t(s, "0004/1", 11))
    assert not np.array_equal(a, t(s, "0005/1", 10))
    assert not np.array_equal(a, WeatherTransform("snow", 5, seed=4)(s, "0004/1", 10))
    t2 = pickle.loads(pickle.dumps(t))
    assert t2 == t and t2._cache == {}
    np.testing.assert_array_equal(t2(s, "0004/1", 10), a)
    assert t.info == {
        "kind": "snow",
        "level": 5,
        "parameter": 7.29,
        "unit": "snowfall mm/h (w.e.)",
        "seed": 3,
    }
    with pytest.raises(ValueError, match=r"\(N, 4\)"):
        t(s[:, :3], "0004/1", 12)
    with pytest.raises(ValueError, match="fog, rain, snow"):
        WeatherTransform("smog", 1)
    with pytest.raises(ValueError, match="1, 2, 3, 4, 5"):
        WeatherTransform("fog", 9)


@pytest.mark.filterwarnings("ignore:.*different from the unwrapped")
@pytest.mark.filterwarnings("ignore:.*symmetric and normalized space")
def test_wrapper_check_env_and_info(toy):
    check_env(TrackingEnv(toy, scan_transform=WeatherTransform("fog", 5)), skip_render_check=True)
    env = WeatherWrapper(TrackingEnv(toy), "rain", 5, seed=0)
    check_env(env, skip_render_check=True)
    obs, info = env.reset(seed=0)
    assert info["weather"]["kind"] == "rain" and info["weather"]["level"] == 5
    _, _, _, _, info = env.step(np.zeros(4, np.float32))
    assert info["weather"]["parameter"] == 7.29


def test_wrapper_reproducible_and_clean_unaffected(toy):
    def episode(env):
        obs, _ = env.reset(seed=1, options={"tracklet": 0})
        out = [obs["search"]]
        done = False
        while not done:
            obs, _, done, _, _ = env.step(np.zeros(4, np.float32))
            out.append(obs["search"])
        return np.stack(out)

    clean = episode(TrackingEnv(toy))
    clean2 = episode(TrackingEnv(toy))
    np.testing.assert_array_equal(clean, clean2)
    a = episode(WeatherWrapper(TrackingEnv(toy), "rain", 5, seed=0))
    b = episode(WeatherWrapper(TrackingEnv(toy), "rain", 5, seed=0))
    np.testing.assert_array_equal(a, b)
    assert not np.array_equal(a, clean)
    # pickling (subprocess vector envs) keeps the weather
    w2 = pickle.loads(pickle.dumps(WeatherWrapper(TrackingEnv(toy), "rain", 5, seed=0)))
    assert w2.unwrapped.scan_transform == WeatherTransform("rain", 5, seed=0)
    np.testing.assert_array_equal(episode(w2), a)
    # the env option gives the same episodes as the wrapper
    c = episode(TrackingEnv(toy, scan_transform=WeatherTransform("rain", 5, seed=0)))
    np.testing.assert_array_equal(a, c)
    # close() restores the clean env
    base = TrackingEnv(toy)
    w = WeatherWrapper(base, "fog", 2)
    episode(w)
    w.close()
    assert base.scan_transform is None
    np.testing.assert_array_equal(episode(base), clean)


def test_robustness_metrics_match_table_iii():
    # Table III, BAT, rain, Car: clean 62.83, Lv-1..5 -> DR 0.42, R 1.33, S.d 0.50
    m = robustness_metrics(62.83, [36.41, 36.82, 36.73, 36.08, 37.41])
    assert m["DR"] == pytest.approx(0.42, abs=0.005)
    assert m["R"] == pytest.approx(1.33, abs=1e-9)
    assert m["Sd"] == pytest.approx(0.50, abs=0.005)
    # by hand: levels 10, 20, 30, 40, 50 over clean 50
    m = robustness_metrics(50.0, [10, 20, 30, 40, 50])
    assert m["dr"] == pytest.approx([0.2, 0.4, 0.6, 0.8, 1.0])
    assert m["DR"] == pytest.approx(0.4)
    assert m["R"] == pytest.approx(40.0)
    assert m["Sd"] == pytest.approx(math.sqrt(250.0))  # sum of squares 1000 / (5 - 1)
    # Table III, MBPTrack, fog, Ped (precision): clean 90.92 -> DR 0.60, R 26.54, S.d 12.06
    m = robustness_metrics(90.92, [54.12, 42.66, 27.68, 27.72, 27.58])
    assert (m["DR"], m["R"], m["Sd"]) == pytest.approx((0.60, 26.54, 12.06), abs=0.006)
    assert math.isnan(robustness_metrics(0.0, [1, 2])["DR"])


def test_hausdorff():
    rng = np.random.default_rng(0)
    a, b = rng.normal(size=(300, 3)), rng.normal(size=(200, 3))
    d = np.linalg.norm(a[:, None] - b[None], axis=2)
    assert hausdorff(a, b, chunk=64) == pytest.approx(max(d.min(1).max(), d.min(0).max()))
    assert hausdorff(a, a) == pytest.approx(0.0, abs=1e-6)
    assert hausdorff(np.zeros((0, 3)), np.zeros((0, 3))) == 0.0
    assert math.isnan(hausdorff(a, np.zeros((0, 3))))


def test_weather_kinds():
    assert weather_kinds("all") == ("fog", "rain", "snow")
    assert weather_kinds("rain,snow") == ("rain", "snow")
    with pytest.raises(ValueError, match="fog, rain, snow"):
        weather_kinds("sleet")


def test_benchmark_runner_smoke(toy, tmp_path):
    from trackers.baselines import PreviousBox

    lines = []
    res = run_weather_benchmark(
        PreviousBox(),
        lambda: TrackingEnv(toy),
        "rain",
        (1, 5),
        out_dir=tmp_path,
        log=lines.append,
    )
    assert len(lines) == 3
    rob = res["robustness"]["rain"]
    assert {"Car", "Pedestrian", "mean"} <= set(rob)
    e = rob["mean"]
    assert len(e["levels"]) == 2 and len(e["dr"]) == 2
    assert e["dr"][0][0] == pytest.approx(e["levels"][0][0] / e["clean"][0])
    an = res["analysis"]["rain"][5]
    assert an["frames"] == sum(len(tr) - 1 for tr in toy.tracklets)
    assert sum(an["distance"]["count"]) == an["frames"]
    table = format_weather_table(res)
    assert "Rain" in table and "Lv-5" in table and "S.d" in table
    for f in ("weather.json", "weather_table.txt", "weather_success.png", "weather_analysis.png"):
        assert (tmp_path / f).stat().st_size > 0
