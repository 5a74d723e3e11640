"""The weather benchmark on vector envs (``run_weather_benchmark(num_envs=...)``, ``pointtrack eval
--weather --num-envs``) gives the single-env result."""

from __future__ import annotations

import math

import pytest

from envs.tracking_env import TrackingEnv, make_toy_dataset
from training.robustness import run_weather_benchmark


def _same(a, b) -> None:
    """Two benchmark results agree on every score, per tracklet and in the analysis."""
    assert a["kinds"] == b["kinds"] and a["levels"] == b["levels"]
    reports = [(a["clean"], b["clean"])] + [
        (a["weather"][k][lv], b["weather"][k][lv]) for k in a["kinds"] for lv in a["levels"]
    ]
    for ra, rb in reports:
        assert ra["per_tracklet"] == rb["per_tracklet"]
        assert ra["frames"] == rb["frames"] and ra["tracklets"] == rb["tracklets"]
        for cat in ra["categories"]:
            for key in ("success", "precision", "frames"):
                assert ra["categories"][cat][key] == rb["categories"][cat][key]
    for kind in a["kinds"]:
        for g, ea in a["robustness"][kind].items():
            eb = b["robustness"][kind][g]
            for key in ("clean", "levels", "DR", "R", "Sd"):
                assert _nan_equal(ea[key], eb[key]), (kind, g, key)
        assert a["analysis"][kind] == b["analysis"][kind]


def _nan_equal(x, y) -> bool:
    if isinstance(x, list | tuple):
        return len(x) == len(y) and all(_nan_equal(u, v) for u, v in zip(x, y, strict=True))
    if isinstance(x, float) and math.isnan(x):
        return isinstance(y, float) and math.isnan(y)
    return x == y


@pytest.mark.slow
def test_vector_with_one_env_equals_single_env_tiny_world(one_torch_thread):
    import trackers
    from envs.tracking_env import make_synthetic_env

    base = make_synthetic_env(preset="tiny", split="test", setting="kitti-1")
    tracker = trackers.load("p2b-kitti1-u")
    subset = [0, 5]
    kw = {"tracklets": subset, "seed": 0, "weather_seed": 3}
    single = run_weather_benchmark(tracker, base.clone, ("fog", "snow"), (5,), **kw)
    vector = run_weather_benchmark(tracker, base.clone, ("fog", "snow"), (5,), num_envs=1, **kw)
    _same(single, vector)
    assert vector["num_envs"] == 1 and single["fog_mode"] == "reference"
    assert vector["clean"]["env"]["num_envs"] == 1  # really the vector runner
    # the weather changed something, so the comparison is not between two clean runs
    assert any(
        single["weather"][k][lv]["per_tracklet"] != single["clean"]["per_tracklet"]
        for k in ("fog", "snow")
        for lv in (5,)
    )


def test_vector_equals_single_env_for_a_deterministic_tracker():
    """previous_box has no batched forward, so any number of sub-envs gives the single-env result
    (the extra episodes of finished sub-envs must not leak into the analysis)."""
    from trackers.baselines import PreviousBox

    toy = make_toy_dataset(
        categories=("Car", "Pedestrian", "Van", "Cyclist", "Truck"),
        num_frames=(6, 3, 5, 4, 7),
        num_clutter=2000,
    )

    def make_env():
        return TrackingEnv(toy)

    single = run_weather_benchmark(PreviousBox(), make_env, "rain", (1, 5), weather_seed=1)
    for n in (2, 3, 7):  # 7 sub-envs for 5 tracklets: some sub-envs have nothing to do
        vector = run_weather_benchmark(
            PreviousBox(), make_env, "rain", (1, 5), weather_seed=1, num_envs=n
        )
        _same(single, vector)
        assert vector["clean"]["env"]["num_envs"] == n
        frames = single["analysis"]["rain"][5]["frames"]
        assert frames == sum(len(tr) - 1 for tr in toy.tracklets)


def test_bad_num_envs_and_fog_mode():
    from trackers.baselines import PreviousBox

    toy = make_toy_dataset(categories=("Car",), num_frames=3, num_clutter=500)
    for bad in (0, -1, 1.5, True):
        with pytest.raises(ValueError, match="num_envs"):
            run_weather_benchmark(
                PreviousBox(), lambda: TrackingEnv(toy), "fog", (1,), num_envs=bad
            )
    with pytest.raises(ValueError, match="reference, lossy"):
        run_weather_benchmark(
            PreviousBox(), lambda: TrackingEnv(toy), "fog", (1,), fog_mode="shifted"
        )


def test_cli_weather_with_num_envs(tmp_path, capsys):
    import json

    from training.cli import main

    rc = main(
        [
            "eval",
            "--tracker",
            "previous_box",
            "--preset",
            "tiny",
            "--weather",
            "fog,snow",
            "--weather-levels",
            "5",
            "--num-envs",
            "3",
            "--max-tracklets",
            "4",
            "--fog-mode",
            "lossy",
            "--no-progress",
            "--out",
            str(tmp_path),
        ]
    )
    assert rc == 0
    assert "Fog" in capsys.readouterr().out
    res = json.loads((tmp_path / "weather_previous_box" / "weather.json").read_text())
    assert res["num_envs"] == 3 and res["fog_mode"] == "lossy"
    assert res["clean"]["tracklets"] == 4 and res["clean"]["env"]["num_envs"] == 3
    # the analysis has every stepped frame once (the report also counts each first frame)
    frames = res["clean"]["frames"] - res["clean"]["tracklets"]
    assert res["analysis"]["snow"]["5"]["frames"] == res["analysis"]["fog"]["5"]["frames"] == frames


@pytest.mark.slow
def test_forked_workers_give_the_one_process_result(one_torch_thread):
    """The conditions are independent: two worker processes give the one-process result, per
    tracklet and in the analysis (shipped P2B on the tiny world, so the tracker's own sampling
    state would show if it leaked between conditions)."""
    import trackers
    from envs.tracking_env import make_synthetic_env

    base = make_synthetic_env(preset="tiny", split="test", setting="kitti-1")
    tracker = trackers.load("p2b-kitti1-u")
    kw = {"tracklets": [0, 5], "seed": 0, "weather_seed": 3}
    single = run_weather_benchmark(tracker, base.clone, ("fog", "rain"), (2, 5), **kw)
    forked = run_weather_benchmark(tracker, base.clone, ("fog", "rain"), (2, 5), workers=2, **kw)
    _same(single, forked)


def test_map_forked_keeps_order_and_names_a_failing_item():
    from training.parallel import map_forked

    seen = []
    assert map_forked(lambda x: x * x, [1, 2, 3, 4, 5], 2, lambda i, r: seen.append(i)) == [
        1,
        4,
        9,
        16,
        25,
    ]
    assert sorted(seen) == [1, 2, 3, 4, 5]

    def boom(x):
        if x == ("rain", 3):
            raise ValueError("bad level")
        return x

    with pytest.raises(RuntimeError, match=r"(?s)\('rain', 3\) failed in a worker.*bad level"):
        map_forked(boom, [("fog", 1), ("rain", 3)], 2)
    with pytest.raises(ValueError, match="workers must be None or an integer >= 1; got 0"):
        run_weather_benchmark(None, None, "fog", (1,), workers=0)
