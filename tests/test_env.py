"""TrackingEnv: the Gymnasium contract, observations, modes, caching, bad input.

All tests run on the in-memory toy dataset of ``envs.tracking_env.make_toy_dataset`` (fast and
exact); the registered ids over a generated world are in ``test_env_registration.py``.
"""

from __future__ import annotations

import math
import pickle
import warnings

import numpy as np
import pytest

from envs.data import SETTINGS
from envs.geometry import apply_offset, boxes_in_frame, offset_between, points_in_box
from envs.observation import TEMPLATE_SCALE, crop_box_frame
from envs.tracking_env import (
    REFERENCE_MODES,
    TEMPLATE_MODES,
    TrackingEnv,
    crop_canonical,
    make_toy_dataset,
)


@pytest.fixture(scope="module")
def toy():
    return make_toy_dataset(num_frames=[8, 10, 6, 7], seed=3)


@pytest.fixture(scope="module")
def clean():
    """No clutter: every scan point is a target point."""
    return make_toy_dataset(num_frames=6, seed=5, num_clutter=0, target_points=400)


def oracle_action(env: TrackingEnv) -> np.ndarray:
    u = env.unwrapped
    return offset_between(u.reference_box, u.current_tracklet.boxes[u.current_frame])


def run_episode(env, policy, seed=None, options=None):
    obs, info = env.reset(seed=seed, options=options)
    observations, infos = [obs], [info]
    while True:
        obs, reward, terminated, truncated, info = env.step(policy(env, obs))
        observations.append(obs)
        infos.append(info)
        if terminated or truncated:
            return observations, infos


def zero_policy(env, obs):
    return np.zeros(4, np.float32)


def assert_obs_equal(a, b):
    assert a.keys() == b.keys()
    for k in a:
        np.testing.assert_array_equal(a[k], b[k], err_msg=k)


# --------------------------------------------------------------------------- API checkers


def test_gymnasium_check_env(toy):
    from gymnasium.utils.env_checker import check_env

    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        check_env(TrackingEnv(toy))
        check_env(TrackingEnv(toy, sampling="random", template_mode="all"))


def test_sb3_check_env_rescaled(toy):
    from gymnasium.wrappers import RescaleAction
    from stable_baselines3.common.env_checker import check_env

    env = RescaleAction(TrackingEnv(toy), np.full(4, -1, np.float32), np.ones(4, np.float32))
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        check_env(env, warn=True)


def test_spaces_and_types(toy):
    env = TrackingEnv(toy)
    obs, info = env.reset(seed=0)
    assert env.observation_space.contains(obs)
    for key, shape in {
        "template": (512, 3),
        "search": (1024, 3),
        "size": (3,),
        "motion": (4,),
    }.items():
        assert obs[key].shape == shape and obs[key].dtype == np.float32
    assert set(info) == {
        "tracklet",
        "category",
        "observed",
        "init_box",
        "start_frame",
        "empty_template",
        "empty_search",
    }
    np.testing.assert_array_equal(info["init_box"], toy.tracklets[0].boxes[0])
    np.testing.assert_array_equal(obs["motion"], 0)
    np.testing.assert_allclose(obs["size"], toy.tracklets[0].boxes[0, 3:6], rtol=1e-6)
    obs2, r, term, trunc, info = env.step(np.zeros(4, np.float32))
    assert type(r) is float and type(term) is bool and type(trunc) is bool
    assert set(info) == {
        "iou",
        "center_error",
        "pred_box",
        "gt_box",
        "category",
        "observed",
        "tracklet",
        "frame",
        "target_points",
        "action_clipped",
        "empty_template",
        "empty_search",
    }
    assert info["frame"] == 1 and info["target_points"] > 0 and not info["action_clipped"]
    assert env.action_space.shape == (4,)
    np.testing.assert_allclose(env.action_space.high, [5, 5, 3, math.pi], rtol=1e-6)


def test_fresh_arrays(toy):
    env = TrackingEnv(toy)
    obs, _ = env.reset(seed=0)
    obs["search"][:] = 123.0
    obs2, *_ = env.step(np.zeros(4))
    assert not np.any(obs2["search"] == 123.0)


# --------------------------------------------------------------------------- episodes


def test_sequential_and_random_sampling(toy):
    env = TrackingEnv(toy)
    ids = [env.reset(seed=0 if i == 0 else None)[1]["tracklet"] for i in range(6)]
    names = [t.tracklet_id for t in toy.tracklets]
    assert ids == names + names[:2]
    assert env.reset(seed=1)[1]["tracklet"] == names[0]  # a seed restarts the order
    assert env.reset(options={"tracklet": 2})[1]["tracklet"] == names[2]
    assert env.reset(options={"tracklet": names[3]})[1]["tracklet"] == names[3]
    env = TrackingEnv(toy, sampling="random")
    a = [env.reset(seed=7 if i == 0 else None)[1]["tracklet"] for i in range(12)]
    b = [env.reset(seed=7 if i == 0 else None)[1]["tracklet"] for i in range(12)]
    assert a == b and len(set(a)) > 1


def test_episode_length_and_termination(toy):
    env = TrackingEnv(toy)
    for i, tr in enumerate(toy.tracklets):
        _, infos = run_episode(env, zero_policy, options={"tracklet": i})
        assert len(infos) == len(tr)  # reset + T-1 steps
        assert [inf["frame"] for inf in infos[1:]] == list(range(1, len(tr)))


def test_short_tracklets_skipped():
    ds = make_toy_dataset(num_frames=[1, 5], categories=("Car", "Van"))
    env = TrackingEnv(ds)
    assert env.num_tracklets == 1 and env.tracklets[0].category == "Van"


def test_seed_determinism(toy):
    def policy(env, obs, rng=None):
        return env.unwrapped._test_rng.uniform(-1, 1, 4)

    runs = []
    for _ in range(2):
        env = TrackingEnv(toy)
        env._test_rng = np.random.default_rng(0)
        runs.append(run_episode(env, policy, seed=42, options={"tracklet": 1}))
    for a, b in zip(runs[0][0], runs[1][0], strict=True):
        assert_obs_equal(a, b)
    other = TrackingEnv(toy)
    other._test_rng = np.random.default_rng(0)
    obs, _ = run_episode(other, policy, seed=43, options={"tracklet": 1})
    assert not np.array_equal(obs[0]["search"], runs[0][0][0]["search"])


def test_episode_seed_makes_episodes_independent(toy):
    def policy(env, obs):
        return np.array([0.3, -0.2, 0.0, 0.05], np.float32)

    def obs_of(env, **reset):
        return run_episode(env, policy, **reset)[0]

    fresh = obs_of(TrackingEnv(toy, episode_seed=7), options={"tracklet": 2})
    env = TrackingEnv(toy, episode_seed=7)
    for index in (0, 3, 1):  # other episodes first, and a seeded reset of np_random
        obs_of(env, options={"tracklet": index}, seed=index)
    again = obs_of(env, options={"tracklet": 2})
    vans = obs_of(TrackingEnv(toy, episode_seed=7, categories=["Van"]))  # index 0 there
    for a, b, c in zip(fresh, again, vans, strict=True):
        assert_obs_equal(a, b)
        assert_obs_equal(a, c)
    env.episode_seed = 8
    assert not np.array_equal(obs_of(env, options={"tracklet": 2})[0]["search"], fresh[0]["search"])
    env.episode_seed = None  # back to np_random: the episode after a seeded reset repeats
    first = obs_of(env, options={"tracklet": 2}, seed=3)
    second = obs_of(env, options={"tracklet": 2}, seed=3)
    for a, b in zip(first, second, strict=True):
        assert_obs_equal(a, b)
    with pytest.raises(TypeError, match="episode_seed must be None or an int; got 1.5"):
        TrackingEnv(toy, episode_seed=1.5)
    with pytest.raises(ValueError, match="episode_seed must be non-negative; got -1"):
        env.episode_seed = -1


def test_oracle_iou_one_and_ope_100(toy):
    from envs.metrics import OPEAccumulator

    acc = OPEAccumulator()
    for reference in REFERENCE_MODES:
        env = TrackingEnv(toy, reference=reference)
        for i in range(env.num_tracklets):
            _, infos = run_episode(env, lambda e, o: oracle_action(e), options={"tracklet": i})
            steps = infos[1:]
            assert all(inf["iou"] == 1.0 and inf["center_error"] == 0.0 for inf in steps)
            acc.add(
                infos[0]["tracklet"] + reference,
                infos[0]["category"],
                True,
                [s["iou"] for s in steps],
                [s["center_error"] for s in steps],
            )
    report = acc.report()
    assert report["mean"]["success"] == pytest.approx(100.0)
    assert report["mean"]["precision"] == pytest.approx(100.0)


def test_rewards(toy):
    env = TrackingEnv(toy, reward="neg_center_error")
    env.reset(seed=0)
    _, r, *_, info = env.step(np.zeros(4))
    assert r == pytest.approx(-info["center_error"])
    env = TrackingEnv(toy, reward="iou_bev")
    env.reset(seed=0)
    _, r, *_, info = env.step(np.zeros(4))
    assert r >= info["iou"] - 1e-12
    env = TrackingEnv(toy, reward=lambda pred, gt, prev_pred, step, info: 7.0)
    env.reset(seed=0)
    assert env.step(np.zeros(4))[1] == 7.0


# --------------------------------------------------------------------------- geometry


def test_observation_geometry(clean):
    """Search and template points land where the ground-truth offsets say."""
    env = TrackingEnv(clean)
    obs, info = env.reset(seed=0, options={"tracklet": 0})
    tr = clean.tracklets[0]
    size = tr.boxes[0, 3:6]
    origin_box = np.concatenate([[0, 0, 0], size, [0]])
    tol = 1e-4
    for t in range(1, len(tr)):
        ref = env.unwrapped.reference_box
        gt_in_ref = boxes_in_frame(tr.boxes[t], ref)
        assert points_in_box(obs["search"], gt_in_ref, offset_m=tol).all()
        # template: first half from frame 0's ground truth, second from the previous prediction
        assert points_in_box(obs["template"][:256], origin_box, offset_m=tol).all()
        prev_gt_in_pred = boxes_in_frame(tr.boxes[t - 1], env.unwrapped._preds[t - 1])
        assert points_in_box(obs["template"][256:], prev_gt_in_pred, scale=1.0, offset_m=tol).all()
        # a half-way action: the prediction lags, so the next search is off-centre
        obs, _, term, _, info = env.step(0.5 * oracle_action(env))
        if term:
            break
    # the search crop is the whole scan's crop around the reference box, in canonical order
    env.reset(seed=0, options={"tracklet": 0})
    full = crop_box_frame(tr.points(1), env.unwrapped.reference_box, 1.25, 2.0)
    got = env.unwrapped._search_crop
    np.testing.assert_array_equal(
        got, crop_canonical(tr.points(1), env.unwrapped.reference_box, 1.25, 2.0)
    )
    assert sorted(map(tuple, got)) == sorted(map(tuple, full))


def test_motion_observation(clean):
    env = TrackingEnv(clean)
    env.reset(seed=0)
    a1 = np.array([0.3, -0.2, 0.05, 0.1])
    obs, *_ = env.step(a1)
    np.testing.assert_allclose(obs["motion"], a1, atol=1e-6)
    a2 = np.array([0.1, 0.0, 0.0, -0.2])
    obs, *_ = env.step(a2)
    np.testing.assert_allclose(obs["motion"], a2, atol=1e-6)


@pytest.mark.parametrize("mode", TEMPLATE_MODES)
def test_template_modes(clean, mode):
    env = TrackingEnv(clean, template_mode=mode)
    obs, _ = env.reset(seed=1, options={"tracklet": 1})
    tr = clean.tracklets[1]
    size = tr.boxes[0, 3:6]
    origin_box = np.concatenate([[0, 0, 0], size, [0]])
    preds = [tr.boxes[0]]
    # drive with a lagging policy so predictions differ from the ground truth
    for _ in range(3):
        a = 0.7 * oracle_action(env)
        obs, _, _, _, info = env.step(a)
        preds.append(info["pred_box"])
    t = env.unwrapped.current_frame
    crops = [crop_box_frame(tr.points(i), preds[i], TEMPLATE_SCALE) for i in range(t)]
    first, prev = crops[0], crops[t - 1]

    def rows_in(rows, pool):
        pool_set = {tuple(p) for p in pool}
        return all(tuple(r) in pool_set for r in rows)

    tpl = obs["template"]
    if mode == "first_and_previous":
        assert rows_in(tpl[:256], first) and rows_in(tpl[256:], prev)
    elif mode == "first":
        assert rows_in(tpl, first)
        assert points_in_box(tpl, origin_box, scale=TEMPLATE_SCALE, offset_m=1e-4).all()
    elif mode == "previous":
        assert rows_in(tpl, prev) and not rows_in(tpl, first)
    elif mode == "first_and_previous_merged":
        assert rows_in(tpl, np.concatenate([first, prev]))
        crop_sets = [{tuple(p) for p in c} for c in (first, prev)]
        assert all(any(tuple(r) in c for r in tpl) for c in crop_sets)  # rows from both
    else:
        merged = np.concatenate(crops)
        assert rows_in(tpl, merged)
        crop_sets = [{tuple(p) for p in c} for c in crops]
        sources = {i for i, c in enumerate(crop_sets) for r in map(tuple, tpl) if r in c}
        assert len(sources) == t  # rows from every previous crop


@pytest.mark.parametrize("reference", REFERENCE_MODES)
def test_reference_modes(toy, reference):
    env = TrackingEnv(toy, reference=reference)
    env.reset(seed=0, options={"tracklet": 1})
    tr = toy.tracklets[1]
    for t in range(1, len(tr)):
        ref = env.unwrapped.reference_box
        expected = {
            "prediction": None,
            "previous_gt": tr.boxes[t - 1],
            "current_gt": tr.boxes[t],
        }[reference]
        if expected is not None:
            np.testing.assert_array_equal(ref, expected)
        a = np.array([0.2, 0.1, 0.0, 0.05])
        _, _, term, _, info = env.step(a)
        pred = apply_offset(ref, a)
        pred[3:6] = tr.boxes[0, 3:6]
        np.testing.assert_allclose(info["pred_box"], pred, atol=1e-12)
        if reference == "prediction" and not term:
            np.testing.assert_allclose(env.unwrapped.reference_box, pred, atol=1e-12)
        if term:
            break


@pytest.mark.parametrize("setting", sorted(SETTINGS))
def test_unseen_flags(toy, setting):
    s = SETTINGS[setting]
    present = {tr.category for tr in toy.tracklets} & set(s.categories)
    if not present:
        pytest.skip("toy dataset has none of the setting's categories")
    env = TrackingEnv(toy, setting=setting)
    assert {tr.category for tr in env.tracklets} == present
    for i in range(env.num_tracklets):
        _, info = env.reset(options={"tracklet": i})
        assert info["observed"] == (info["category"] in s.observed)
        _, _, _, _, info = env.step(np.zeros(4))
        assert info["observed"] == (info["category"] in s.observed)
    observed_only = (
        TrackingEnv(toy, setting=setting, categories=s.observed[:1])
        if (set(s.observed[:1]) & present)
        else None
    )
    if observed_only is not None:
        assert all(tr.category == s.observed[0] for tr in observed_only.tracklets)


def test_categories_without_setting(toy):
    env = TrackingEnv(toy, categories="Van")
    assert [tr.category for tr in env.tracklets] == ["Van"]
    assert env.reset()[1]["observed"] is True


# --------------------------------------------------------------------------- cache


def _random_walk(env, obs):
    return env.unwrapped._test_rng.uniform(-4, 4, 4) * np.array([1, 1, 0.2, 0.3])


def test_corridor_cache_is_exact(toy):
    """Corridor (warm and cold) and whole-scan cropping give identical observations, also when
    the predictions drift out of the corridor (fallback)."""
    runs = []
    envs = [
        TrackingEnv(toy, corridor_m=2.0),
        TrackingEnv(toy, corridor_m=2.0, cache_mb=0.0),  # evicts all but the current tracklet
        TrackingEnv(toy, corridor_m=None),
    ]
    for env in envs:
        obs_all = []
        for _ in range(2):  # second pass: warm cache
            env._test_rng = np.random.default_rng(11)
            for i in range(env.num_tracklets):
                obs, infos = run_episode(
                    env, _random_walk, seed=5 if i == 0 else None, options={"tracklet": i}
                )
                obs_all.append((obs, [inf["target_points"] for inf in infos[1:]]))
        runs.append(obs_all)
    assert envs[0].cache_stats["corridor"] > 0 and envs[0].cache_stats["cell_index"] > 0
    assert envs[0].cache_stats["full_scan"] == 0
    assert envs[2].cache_stats["corridor"] == envs[2].cache_stats["cell_index"] == 0
    for other in runs[1:]:
        for (oa, ta), (ob, tb) in zip(runs[0], other, strict=True):
            assert ta == tb
            for a, b in zip(oa, ob, strict=True):
                assert_obs_equal(a, b)
    # warm pass == cold pass
    half = len(runs[0]) // 2
    for (oa, _), (ob, _) in zip(runs[0][:half], runs[0][half:], strict=True):
        for a, b in zip(oa, ob, strict=True):
            assert_obs_equal(a, b)


class Shift:
    """A deterministic scan transform: drop points by a keyed hash, lift the rest by 1 cm."""

    info = {"kind": "test", "level": 1}

    def __call__(self, points, tracklet_id, frame):
        rng = np.random.default_rng([frame, len(tracklet_id)])
        keep = rng.random(len(points)) < 0.7
        out = points[keep].copy()
        out[:, 2] += 0.01
        return out


def test_scan_transform_hook(toy):
    env = TrackingEnv(toy, scan_transform=Shift())
    obs, info = env.reset(seed=0, options={"tracklet": 0})
    assert info["weather"] == Shift.info
    tr = toy.tracklets[0]
    scan = Shift()(tr.points_with_intensity(1), tr.tracklet_id, int(tr.frames[1]))
    expected = crop_canonical(scan, tr.boxes[0], 1.25, 2.0)
    np.testing.assert_array_equal(env.unwrapped._search_crop, expected)
    _, _, _, _, info = env.step(np.zeros(4))
    assert info["weather"] == Shift.info
    full = TrackingEnv(toy, scan_transform=Shift(), corridor_m=None)
    a = run_episode(env, zero_policy, seed=3, options={"tracklet": 2})[0]
    b = run_episode(full, zero_policy, seed=3, options={"tracklet": 2})[0]
    for x, y in zip(a, b, strict=True):
        assert_obs_equal(x, y)


# --------------------------------------------------------------------------- pickling, render


def test_pickle_mid_episode(toy):
    env = TrackingEnv(toy)
    env.reset(seed=4, options={"tracklet": 1})
    env.step(np.array([0.1, 0.0, 0.0, 0.0]))
    blob = pickle.dumps(env)
    assert len(blob) < 200_000
    twin = pickle.loads(blob)
    for _ in range(3):
        a = np.array([0.2, -0.1, 0.0, 0.01])
        ra = env.step(a)
        rb = twin.step(a)
        assert_obs_equal(ra[0], rb[0])
        assert ra[1:4] == rb[1:4]
    fresh = pickle.loads(pickle.dumps(TrackingEnv(toy)))
    assert fresh.reset(seed=0)[1]["tracklet"] == toy.tracklets[0].tracklet_id


def test_clone_is_independent(toy):
    env = TrackingEnv(toy)
    twin = env.clone()
    assert twin.tracklets[0] is env.tracklets[0]
    a = run_episode(env, zero_policy, seed=2)[0]
    b = run_episode(twin, zero_policy, seed=2)[0]
    assert_obs_equal(a[-1], b[-1])


def test_render(toy):
    env = TrackingEnv(toy, render_mode="rgb_array")
    env.reset(seed=0)
    img = env.render()
    assert img.shape == (256, 256, 3) and img.dtype == np.uint8
    env.step(np.zeros(4))
    img = env.render()
    colors = {tuple(c) for c in img.reshape(-1, 3)}
    assert (230, 40, 40) in colors and (40, 200, 40) in colors and (200, 200, 200) in colors
    with pytest.warns(UserWarning, match="render_mode=None"):
        assert TrackingEnv(toy).render() is None


def test_record_video_wrapper(toy, tmp_path):
    """Gymnasium's RecordVideo (moviepy, the video extra) records the env's rgb_array: one video
    frame after reset and one per step."""
    pytest.importorskip("moviepy", reason="the video extra (moviepy) is not installed")
    iio = pytest.importorskip("imageio.v3", reason="the video extra is not installed")
    from gymnasium.wrappers import RecordVideo

    env = RecordVideo(
        TrackingEnv(toy, render_mode="rgb_array"),
        str(tmp_path / "v"),
        episode_trigger=lambda e: True,
    )
    steps = len(run_episode(env, zero_policy, seed=0, options={"tracklet": 2})[1]) - 1
    env.close()
    (video,) = (tmp_path / "v").glob("*.mp4")
    frames = iio.imread(video, index=None, plugin="FFMPEG")
    assert steps == len(toy.tracklets[2]) - 1
    assert frames.shape == (steps + 1, 256, 256, 3)


# --------------------------------------------------------------------------- bad input


@pytest.mark.parametrize("bad", [np.nan, np.inf, -np.inf])
def test_nonfinite_action(toy, bad):
    env = TrackingEnv(toy)
    env.reset(seed=0)
    with pytest.raises(ValueError, match="NaN or inf"):
        env.step(np.array([0.0, bad, 0.0, 0.0]))


def test_out_of_range_action_clipped(toy):
    env = TrackingEnv(toy)
    env.reset(seed=0)
    ref = env.unwrapped.reference_box
    _, _, _, _, info = env.step(np.array([50.0, 0.0, 0.0, 0.0]))
    assert info["action_clipped"] is True
    np.testing.assert_allclose(info["pred_box"], apply_offset(ref, [5.0, 0, 0, 0]), atol=1e-12)


def test_wrong_action_shape(toy):
    env = TrackingEnv(toy)
    env.reset(seed=0)
    with pytest.raises(ValueError, match=r"shape \(4,\)"):
        env.step(np.zeros(3))


def test_step_before_reset_and_after_end(toy):
    env = TrackingEnv(toy)
    with pytest.raises(RuntimeError, match="before reset"):
        env.step(np.zeros(4))
    run_episode(env, zero_policy, seed=0)
    with pytest.raises(RuntimeError, match="terminated"):
        env.step(np.zeros(4))


def test_bad_options_and_modes(toy):
    env = TrackingEnv(toy)
    with pytest.raises(ValueError, match="valid: \\['tracklet', 'category', 'start_frame'"):
        env.reset(options={"tracklett": 0})
    with pytest.raises(ValueError, match="out of range"):
        env.reset(options={"tracklet": 99})
    with pytest.raises(ValueError, match="unknown tracklet id"):
        env.reset(options={"tracklet": "nope"})
    for kwargs, valid in [
        ({"template_mode": "both"}, "first_and_previous"),
        ({"reference": "gt"}, "previous_gt"),
        ({"reward": "iou"}, "iou_3d"),
        ({"sampling": "shuffle"}, "sequential"),
        ({"render_mode": "human"}, "rgb_array"),
    ]:
        with pytest.raises(ValueError, match=valid):
            TrackingEnv(toy, **kwargs)
    with pytest.raises(ValueError, match="kitti-1"):
        TrackingEnv(toy, setting="kitti-9")
    with pytest.raises(ValueError, match="max_action"):
        TrackingEnv(toy, max_action=(1, 1, 1))


def test_no_tracklets_for_categories(toy):
    with pytest.raises(ValueError, match=r"Bus.*split 'test'"):
        TrackingEnv(toy, categories=["Bus"])
    with pytest.raises(ValueError, match="not in setting"):
        TrackingEnv(toy, setting="kitti-1", categories=["Bus"])


def test_set_scan_transform_clears_cache(toy):
    env = TrackingEnv(toy)
    clean = run_episode(env, zero_policy, seed=3, options={"tracklet": 0})[0]
    env.set_scan_transform(Shift())
    obs, info = env.reset(seed=3, options={"tracklet": 0})
    assert info["weather"] == Shift.info
    assert not np.array_equal(obs["search"], clean[0]["search"])
    ref = TrackingEnv(toy, scan_transform=Shift())
    assert_obs_equal(obs, ref.reset(seed=3, options={"tracklet": 0})[0])
    env.set_scan_transform(None)
    assert_obs_equal(env.reset(seed=3, options={"tracklet": 0})[0], clean[0])
    with pytest.raises(TypeError):
        env.set_scan_transform(3)
