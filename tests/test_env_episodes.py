"""Episode control and rewards of TrackingEnv: every reset option, the truncation / termination
rule, each named reward against a hand computation, the reward registry, the unseen-category
warning; and that Gymnasium's and SB3's checkers, vector envs and pickling accept clipped
episodes."""

from __future__ import annotations

import dataclasses
import functools
import math
import pickle
import warnings

import gymnasium as gym
import numpy as np
import pytest

from envs.data.toy import ToyDataset, _ToyScans
from envs.data.tracklet import Tracklet
from envs.geometry import offset_between
from envs.observation import SEARCH_OFFSET_M, SEARCH_SCALE, TEMPLATE_SCALE
from envs.rewards import available_rewards, make_reward, register_reward
from envs.scan_cache import crop_canonical
from envs.tracking_env import RESET_OPTIONS, TrackingEnv, make_toy_dataset


@pytest.fixture(scope="module")
def toy():
    return make_toy_dataset(num_frames=[8, 10, 6, 7], seed=3)


@pytest.fixture(scope="module")
def straight():
    """One Car (4 x 2 x 1.5 m, yaw 0) moving +1 m in x per frame: IoUs by hand."""
    boxes = np.array([[float(t), 0.0, -0.25, 4.0, 2.0, 1.5, 0.0] for t in range(6)])
    frames = np.arange(6)
    loader = _ToyScans(0, {int(f): [b] for f, b in zip(frames, boxes, strict=True)}, 200, 500)
    return ToyDataset([Tracklet("0000/0", "0000", 0, "Car", frames, boxes, loader)])


def episode(env, options=None, policy=None, seed=None):
    """(observations, rewards, terminated flags, truncated flags, infos) of one episode."""
    obs, info = env.reset(seed=seed, options=options)
    out = ([obs], [], [], [], [info])
    done = False
    while not done:
        action = np.zeros(4, np.float32) if policy is None else policy(env)
        obs, r, term, trunc, info = env.step(action)
        for lst, v in zip(out, (obs, r, term, trunc, info), strict=True):
            lst.append(v)
        done = term or trunc
    return out


def oracle(env):
    u = env.unwrapped
    return offset_between(u.reference_box, u.current_tracklet.boxes[u.current_frame])


def assert_obs_equal(a, b):
    assert a.keys() == b.keys()
    for k in a:
        np.testing.assert_array_equal(a[k], b[k], err_msg=k)


# --------------------------------------------------------------------------- options


def test_unknown_option_names_the_valid_ones(toy):
    env = TrackingEnv(toy)
    with pytest.raises(ValueError, match="unknown reset options \\['trackelt'\\]") as exc:
        env.reset(options={"trackelt": 0})
    for name in RESET_OPTIONS:
        assert name in str(exc.value)


def test_category_option_sequential_and_random(toy):
    env = TrackingEnv(toy)  # tracklets: Car, Pedestrian, Van, Cyclist
    assert env.reset(options={"category": "Van"})[1]["tracklet"] == "0000/2"
    assert env.reset()[1]["category"] == "Cyclist"  # the cursor moved past the Van
    seen = [env.reset(options={"category": ["Car", "Cyclist"]})[1]["category"] for _ in range(4)]
    assert seen == ["Car", "Cyclist", "Car", "Cyclist"]
    rand = TrackingEnv(toy, sampling="random")
    rand.reset(seed=0)
    cats = [
        rand.reset(options={"category": ("Pedestrian", "Van")})[1]["category"] for _ in range(40)
    ]
    assert set(cats) == {"Pedestrian", "Van"}
    with pytest.raises(ValueError, match="valid: \\['Car', 'Cyclist', 'Pedestrian', 'Van'\\]"):
        env.reset(options={"category": "Bus"})
    with pytest.raises(ValueError, match="is a Car, not of"):
        env.reset(options={"tracklet": 0, "category": "Van"})
    assert env.reset(options={"tracklet": 2, "category": ["Van"]})[1]["tracklet"] == "0000/2"
    only_van = TrackingEnv(toy)
    only_van.tracklet_order = [0, 1]
    with pytest.raises(ValueError, match="visits no tracklet"):
        only_van.reset(options={"category": "Van"})


def test_start_frame_option(toy):
    env = TrackingEnv(toy, template_mode="first")
    tr = toy.tracklets[1]  # 10 frames
    obs, rewards, terms, truncs, infos = episode(
        env, {"tracklet": 1, "start_frame": 3}, policy=oracle, seed=0
    )
    info0 = infos[0]
    assert info0["start_frame"] == 3 and env.start_frame == 3
    np.testing.assert_array_equal(info0["init_box"], tr.boxes[3])
    np.testing.assert_allclose(obs[0]["size"], tr.boxes[3, 3:6].astype(np.float32))
    assert [i["frame"] for i in infos[1:]] == list(range(4, 10))
    assert rewards == [1.0] * 6 and terms[-1] and not any(truncs)
    # the first search region: frame 4 around the given box; the template: frame 3's crop
    env.reset(options={"tracklet": 1, "start_frame": 3})
    search = crop_canonical(tr.points(4), tr.boxes[3], SEARCH_SCALE, SEARCH_OFFSET_M)
    np.testing.assert_array_equal(env._search_crop, search)
    first = crop_canonical(tr.points(3), tr.boxes[3], TEMPLATE_SCALE, 0.0)
    np.testing.assert_array_equal(env._first_crop, first)
    with pytest.raises(ValueError, match="start_frame=9 leaves no step in tracklet 0000/1 of 10"):
        env.reset(options={"tracklet": 1, "start_frame": 9})
    with pytest.raises(ValueError, match="frame index >= 0 or 'random'"):
        env.reset(options={"start_frame": -1})
    default = TrackingEnv(toy, start_frame=2)
    assert default.reset(options={"tracklet": 0})[1]["start_frame"] == 2
    assert default.reset(options={"tracklet": 0, "start_frame": 0})[1]["start_frame"] == 0


def test_random_start_frame_is_seeded_and_in_range(toy):
    env = TrackingEnv(toy, start_frame="random")
    env.reset(seed=5)
    starts = [env.reset(options={"tracklet": 3})[1]["start_frame"] for _ in range(60)]
    assert set(starts) == set(range(6))  # tracklet 3 has 7 frames: 0..5
    env.reset(seed=5)
    assert [env.reset(options={"tracklet": 3})[1]["start_frame"] for _ in range(60)] == starts


def test_max_steps_truncates_a_clip_with_the_real_next_observation(toy):
    env = TrackingEnv(toy, episode_seed=4)
    full = episode(env, {"tracklet": 1, "start_frame": 2})
    clip = episode(env, {"tracklet": 1, "start_frame": 2, "max_steps": 3})
    obs, rewards, terms, truncs, infos = clip
    assert len(rewards) == 3 and truncs == [False, False, True] and not any(terms)
    # resampled from the same generator: the clip is the full episode's beginning, its final
    # observation (frame 6) included
    for a, b in zip(obs, full[0][:4], strict=True):
        assert_obs_equal(a, b)
    assert rewards == full[1][:3]
    with pytest.raises(RuntimeError, match="ended \\(truncated\\)|truncated; call"):
        env.step(np.zeros(4))


def test_clip_reaching_the_tracklet_end_terminates(toy):
    env = TrackingEnv(toy)
    _, rewards, terms, truncs, _ = episode(env, {"tracklet": 1, "start_frame": 5, "max_steps": 10})
    assert len(rewards) == 4 and terms == [False] * 3 + [True] and not any(truncs)
    # a clip ending exactly at the last frame: terminated, not truncated
    _, rewards, terms, truncs, _ = episode(env, {"tracklet": 1, "max_steps": 9})
    assert len(rewards) == 9 and terms[-1] and not any(truncs)
    with pytest.raises(RuntimeError, match="terminated"):
        env.step(np.zeros(4))
    with pytest.raises(ValueError, match="max_steps'\\] must be None or an int >= 1"):
        env.reset(options={"max_steps": 0})
    with pytest.raises(ValueError, match="max_steps must be None or an int >= 1"):
        TrackingEnv(toy, max_steps=1.5)
    default = TrackingEnv(toy, max_steps=2)
    _, rewards, _, truncs, _ = episode(default, {"tracklet": 0})
    assert len(rewards) == 2 and truncs[-1]
    _, rewards, terms, _, _ = episode(default, {"tracklet": 0, "max_steps": 100})
    assert len(rewards) == 7 and terms[-1]


def test_episode_seed_option(toy):
    env = TrackingEnv(toy)
    a = episode(env, {"tracklet": 2, "episode_seed": 9}, seed=0)[0]
    episode(env, {"tracklet": 0})  # other draws in between
    b = episode(env, {"tracklet": 2, "episode_seed": 9})[0]
    for x, y in zip(a, b, strict=True):
        assert_obs_equal(x, y)
    assert env.episode_seed is None  # the option lasts one episode
    # the env-wide seed gives the same episode
    seeded = TrackingEnv(toy, episode_seed=9)
    for x, y in zip(episode(seeded, {"tracklet": 2})[0], a, strict=True):
        assert_obs_equal(x, y)
    other = episode(seeded, {"tracklet": 2, "episode_seed": 10})[0]
    assert not np.array_equal(other[0]["search"], a[0]["search"])
    # another start frame draws other samples
    late = TrackingEnv(toy, episode_seed=9).reset(options={"tracklet": 2, "start_frame": 1})[0]
    assert not np.array_equal(late["template"], a[0]["template"])
    with pytest.raises(TypeError, match="episode_seed'\\] must be None or an int"):
        env.reset(options={"episode_seed": 1.0})
    with pytest.raises(ValueError, match="non-negative"):
        env.reset(options={"episode_seed": -3})


# --------------------------------------------------------------------------- rewards


@pytest.mark.parametrize("d", [1.0, 2.0])
def test_named_rewards_by_hand(straight, d):
    """Step 1 from the given box (x = 0) to x = 1 + d; the truth is at x = 1: boxes 4 m long
    shifted by d along their length overlap (4 - d) / (4 + d); keeping the previous box
    (shift 1) would have scored 3 / 5."""
    iou = (4.0 - d) / (4.0 + d)
    expected = {
        "iou_3d": iou,
        "iou_bev": iou,
        "neg_center_error": -d,
        "iou_delta": iou - 0.6,
        "success": 1.0 if iou >= 0.5 else 0.0,
    }
    assert set(expected) <= set(available_rewards())
    for name, want in expected.items():
        env = TrackingEnv(straight, reward=name)
        env.reset(seed=0)
        _, r, *_, info = env.step(np.array([1.0 + d, 0.0, 0.0, 0.0]))
        assert r == pytest.approx(want, abs=1e-12), name
        assert info["center_error"] == pytest.approx(d)
    env = TrackingEnv(straight, reward="success", reward_kwargs={"threshold": 0.7})
    env.reset(seed=0)
    assert env.step(np.array([1.0 + d, 0.0, 0.0, 0.0]))[1] == 0.0  # 0.6 and 1/3 < 0.7
    # a perfect second step after a perfect first: iou_delta is 1 - IoU(shift 1) = 0.4
    env = TrackingEnv(straight, reward="iou_delta")
    env.reset(seed=0)
    assert env.step(np.array([1.0, 0, 0, 0]))[1] == pytest.approx(0.4)
    assert env.step(np.array([1.0, 0, 0, 0]))[1] == pytest.approx(0.4)


@pytest.mark.parametrize("name", ["iou_3d", "neg_center_error", "iou_delta", "success"])
def test_reward_for_action_is_the_step_reward_and_changes_nothing(toy, name):
    """The self-critical baseline's query: for any action, the reward step(action) returns,
    asked before the step; asking it leaves the episode byte-identical."""
    actions = np.random.default_rng(5).uniform(-2.0, 2.0, size=(6, 4))
    actions[:, 3] *= 0.2
    queried, plain = TrackingEnv(toy, reward=name), TrackingEnv(toy, reward=name)
    for env in (queried, plain):
        env.reset(seed=0, options={"tracklet": 1, "start_frame": 2})
    for a in actions:
        asked = [queried.reward_for_action(b) for b in (a, 0.5 * a, a)]
        out_q, out_p = queried.step(a), plain.step(a)
        assert asked[0] == asked[2] == out_q[1] == out_p[1]
        assert_obs_equal(out_q[0], out_p[0])
        assert out_q[2:4] == out_p[2:4]
        np.testing.assert_array_equal(out_q[4]["pred_box"], out_p[4]["pred_box"])
        if out_q[2] or out_q[3]:
            break
    with pytest.raises(RuntimeError, match="running episode"):
        TrackingEnv(toy).reward_for_action(np.zeros(4))
    env = TrackingEnv(toy)
    env.reset(seed=0)
    with pytest.raises(ValueError, match="shape \\(4,\\)"):
        env.reward_for_action(np.zeros(3))


def test_reward_callable_receives_its_arguments(straight):
    calls = []

    def spy(pred, gt, prev_pred, step, info):
        calls.append((pred.copy(), gt.copy(), prev_pred.copy(), step, dict(info)))
        pred[:] = 99.0  # the env's own boxes are untouched
        with pytest.raises(TypeError):
            info["iou"] = 5.0  # read-only
        return float(step)

    env = TrackingEnv(straight, reward=spy)
    _, rewards, _, _, infos = episode(env, {"start_frame": 1}, policy=oracle, seed=0)
    assert rewards == [0.0, 1.0, 2.0, 3.0]
    boxes = straight.tracklets[0].boxes
    for k, (pred, gt, prev, step, info) in enumerate(calls):
        assert step == k and info["frame"] == k + 2
        np.testing.assert_allclose(pred, boxes[k + 2], atol=1e-12)
        np.testing.assert_array_equal(gt, boxes[k + 2])
        np.testing.assert_allclose(prev, boxes[k + 1], atol=1e-12)
        np.testing.assert_array_equal(infos[k + 1]["pred_box"], pred)
        assert info["iou"] == 1.0 and "empty_search" in info


def test_reward_registry_and_bad_rewards(toy):
    @register_reward("test_close")
    @dataclasses.dataclass(frozen=True)
    class Close:
        radius_m: float = 1.0

        def __call__(self, pred, gt, prev_pred, step, info):
            return float(info["center_error"] <= self.radius_m)

    assert "test_close" in available_rewards()
    env = TrackingEnv(toy, reward="test_close", reward_kwargs={"radius_m": 100.0})
    env.reset(seed=0)
    assert env.step(np.zeros(4))[1] == 1.0
    with pytest.raises(ValueError, match="already registered"):
        register_reward("test_close", Close)
    register_reward("test_close", Close, overwrite=True)
    with pytest.raises(ValueError, match="unknown reward 'iou'; valid: 'iou_3d', 'iou_bev'"):
        TrackingEnv(toy, reward="iou")
    with pytest.raises(TypeError, match="reward 'success' with reward_kwargs"):
        make_reward("success", radius=1)
    with pytest.raises(ValueError, match="threshold must be in"):
        make_reward("success", threshold=2.0)
    with pytest.raises(TypeError, match="must accept \\(pred, gt, prev_pred, step, info\\)"):
        TrackingEnv(toy, reward=lambda pred, gt: 1.0)
    with pytest.raises(ValueError, match="reward_kwargs apply to a reward name"):
        TrackingEnv(toy, reward=make_reward("success"), reward_kwargs={"threshold": 0.1})
    env = TrackingEnv(toy, reward=lambda *args: math.nan)
    env.reset(seed=0)
    with pytest.raises(ValueError, match="returned nan"):
        env.step(np.zeros(4))


def test_named_rewards_pickle(toy):
    env = TrackingEnv(toy, reward="success", reward_kwargs={"threshold": 0.3})
    twin = pickle.loads(pickle.dumps(env))
    assert twin.reward_fn == env.reward_fn and twin.reward_fn.threshold == 0.3
    for name in ("iou_3d", "iou_bev", "neg_center_error", "iou_delta", "success"):
        fn = make_reward(name)
        assert pickle.loads(pickle.dumps(fn)) == fn


# --------------------------------------------------------------------------- unseen warning


def test_training_split_with_unseen_categories_warns(toy):
    train = dataclasses.replace(toy, split="train")
    with pytest.warns(UserWarning, match="unseen categories \\['Car'\\] of setting 'kitti-1'"):
        TrackingEnv(train, setting="kitti-1")
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        TrackingEnv(train, setting="kitti-1", categories=["Pedestrian", "Van", "Cyclist"])
        TrackingEnv(toy, setting="kitti-1")  # split test: evaluation sees the unseen ones
        TrackingEnv(train)  # no setting: nothing is unseen
    with pytest.warns(UserWarning, match="\\['Car'\\]"):
        env = TrackingEnv(train, setting="kitti-1", categories=["Car", "Van"])
    with warnings.catch_warnings():  # once: resets do not warn again
        warnings.simplefilter("error")
        env.reset(seed=0)
        env.reset()


# --------------------------------------------------------------------------- checkers, vectors


def test_checkers_accept_clipped_episodes(toy):
    from gymnasium.utils.env_checker import check_env
    from stable_baselines3.common.env_checker import check_env as sb3_check_env

    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        check_env(TrackingEnv(toy, start_frame="random", max_steps=2, reward="iou_delta"))
        env = gym.wrappers.RescaleAction(
            TrackingEnv(toy, sampling="random", max_steps=3, reward="success"), -1.0, 1.0
        )
        sb3_check_env(env, warn=True)


def test_vector_env_autoresets_after_truncation(toy):
    make = functools.partial(TrackingEnv, toy, max_steps=2, episode_seed=1)
    vec = gym.vector.SyncVectorEnv([make] * 2)
    try:
        vec.reset(seed=0)
        truncs = []
        for _ in range(6):
            _, _, term, trunc, _ = vec.step(np.zeros((2, 4), np.float32))
            truncs.append(trunc.copy())
        # two steps, truncation, the autoreset step, two steps, truncation, ...
        assert [bool(t[0]) for t in truncs] == [False, True, False, False, True, False]
    finally:
        vec.close()


def test_pickle_mid_clip_continues_identically(toy):
    env = TrackingEnv(toy, episode_seed=3)
    env.reset(options={"tracklet": 1, "start_frame": 2, "max_steps": 4})
    env.step(np.array([0.2, 0.1, 0.0, 0.05]))
    twin = pickle.loads(pickle.dumps(env))
    for _ in range(3):
        a = env.step(np.array([0.1, 0.0, 0.0, 0.0]))
        b = twin.step(np.array([0.1, 0.0, 0.0, 0.0]))
        assert_obs_equal(a[0], b[0])
        assert a[1:4] == b[1:4]
    assert a[3] and b[3]  # truncated
