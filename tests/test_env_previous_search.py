"""The opt-in ``previous_search`` observation (motion-centric trackers): the previous frame's
points around the reference box, against a direct crop of the previous scan, with its time and
previous-box mask channels; checkers, vector envs and pickling with it."""

from __future__ import annotations

import functools
import pickle
import warnings

import gymnasium as gym
import numpy as np
import pytest

from envs.geometry import apply_offset
from envs.observation import (
    MASK_GT,
    MASK_PREDICTED,
    PREVIOUS_SEARCH_CHANNELS,
    PREVIOUS_TIME,
    SEARCH_OFFSET_M,
    SEARCH_SCALE,
    TEMPLATE_SCALE,
)
from envs.scan_cache import crop_canonical
from envs.tracking_env import OBSERVATION_KEYS, TrackingEnv, make_toy_dataset

KEYS = (*OBSERVATION_KEYS, "previous_search")


@pytest.fixture(scope="module")
def toy():
    return make_toy_dataset(num_frames=[8, 10, 6, 7], seed=3)


@pytest.fixture(scope="module")
def sparse():
    """Few points: every crop is below 1024 points, so resampling keeps them all in order."""
    return make_toy_dataset(num_frames=6, seed=2, num_clutter=300, target_points=150)


def check_against_direct_crop(obs, scan, ref, gt_box: bool):
    """``obs`` (1024, 5) is the resampled direct crop of ``scan`` around ``ref`` with the
    channels computed by hand."""
    direct = crop_canonical(scan, ref, SEARCH_SCALE, SEARCH_OFFSET_M)
    assert obs.shape == (1024, len(PREVIOUS_SEARCH_CHANNELS)) and obs.dtype == np.float32
    xyz = obs[:, :3]
    if len(direct) <= len(obs):  # all points in order, then duplicates of them
        np.testing.assert_array_equal(xyz[: len(direct)], direct)
    else:  # a subset without repetition
        assert len(np.unique(xyz, axis=0)) == len(obs)
    rows = {tuple(r) for r in direct}
    assert all(tuple(r) in rows for r in xyz)
    assert np.all(obs[:, 3] == PREVIOUS_TIME)
    half = np.asarray(ref[3:6], dtype=np.float64) * (0.5 * TEMPLATE_SCALE)
    inside = np.all(np.abs(xyz.astype(np.float64)) <= half, axis=1)
    outside_value, inside_value = MASK_GT if gt_box else MASK_PREDICTED
    want = np.where(inside, inside_value, outside_value).astype(np.float32)
    np.testing.assert_array_equal(obs[:, 4], want)
    return inside


@pytest.fixture(scope="module")
def dense():
    """Many points: crops above 1024 points, so resampling draws a subset."""
    return make_toy_dataset(
        num_frames=[4, 5], seed=4, num_clutter=60000, target_points=1500, categories=("Car", "Van")
    )


@pytest.mark.parametrize("fixture", ["sparse", "dense"])
def test_previous_search_is_the_direct_crop_of_the_previous_scan(fixture, request):
    data = request.getfixturevalue(fixture)
    env = TrackingEnv(data, observation_keys=KEYS)
    tr = data.tracklets[1]
    obs, info = env.reset(seed=0, options={"tracklet": 1})
    assert env.observation_space.contains(obs) and not info["empty_previous_search"]
    # first step: the reference is the given box of frame 0, the previous frame's truth
    inside = check_against_direct_crop(obs["previous_search"], tr.points(0), tr.boxes[0], True)
    assert inside.any() and not inside.all()
    action = np.array([0.3, -0.2, 0.05, 0.1])
    obs, *_, info = env.step(action)
    ref = apply_offset(tr.boxes[0], action)
    ref[3:6] = tr.boxes[0, 3:6]
    np.testing.assert_allclose(env.reference_box, ref, atol=1e-12)
    check_against_direct_crop(obs["previous_search"], tr.points(1), env.reference_box, False)
    # previous_gt: the reference box is the previous frame's truth at every step
    gt_env = TrackingEnv(data, observation_keys=KEYS, reference="previous_gt")
    gt_env.reset(seed=0, options={"tracklet": 1})
    obs = gt_env.step(np.zeros(4))[0]
    check_against_direct_crop(obs["previous_search"], tr.points(1), tr.boxes[1], True)


def test_previous_search_with_a_start_frame_and_the_cell_index(toy):
    env = TrackingEnv(toy, observation_keys=KEYS)
    tr = toy.tracklets[1]
    obs, _ = env.reset(seed=1, options={"tracklet": 1, "start_frame": 4})
    check_against_direct_crop(obs["previous_search"], tr.points(4), tr.boxes[4], True)
    far = np.array([4.0, -4.0, 0.0, 2.0])  # leaves the corridor: the whole-scan cell index
    for _ in range(3):
        obs, *_ = env.step(far)
        t = env.current_frame
        check_against_direct_crop(
            obs["previous_search"], tr.points(t - 1), env.reference_box, False
        )
    assert env.cache_stats["cell_index"] > 0


def test_default_contract_unchanged_and_bad_keys(toy):
    env = TrackingEnv(toy)
    obs, info = env.reset(seed=0)
    assert tuple(obs) == OBSERVATION_KEYS and "empty_previous_search" not in info
    assert "previous_search" not in env.observation_space.spaces
    with pytest.raises(ValueError, match="unknown: \\['previous_points'\\]"):
        TrackingEnv(toy, observation_keys=(*OBSERVATION_KEYS, "previous_points"))
    with pytest.raises(ValueError, match="must hold \\['template', 'search', 'size', 'motion'\\]"):
        TrackingEnv(toy, observation_keys=("search", "previous_search"))


def test_empty_previous_frame_gives_zeros(toy):
    tr = toy.tracklets[0]
    empty_frame = int(tr.frames[2])
    env = TrackingEnv(toy, observation_keys=KEYS, scan_transform=DropFrame(empty_frame))
    env.reset(seed=0, options={"tracklet": 0})
    env.step(np.zeros(4))
    obs, *_, info = env.step(np.zeros(4))  # observation of frame 3: previous frame 2 is empty
    assert info["empty_previous_search"] and not info["empty_search"]
    np.testing.assert_array_equal(obs["previous_search"], 0.0)


class DropFrame:
    """A picklable scan transform that empties one scene frame."""

    def __init__(self, frame: int) -> None:
        self.frame = frame

    def __call__(self, points, tracklet_id, frame):
        return points[:0] if frame == self.frame else points


def test_checkers_vectors_and_pickling_with_previous_search(toy):
    from gymnasium.utils.env_checker import check_env
    from stable_baselines3.common.env_checker import check_env as sb3_check_env

    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        check_env(TrackingEnv(toy, observation_keys=KEYS))
        sb3_check_env(
            gym.wrappers.RescaleAction(TrackingEnv(toy, observation_keys=KEYS), -1.0, 1.0),
            warn=True,
        )
    vec = gym.vector.SyncVectorEnv([functools.partial(TrackingEnv, toy, observation_keys=KEYS)] * 2)
    try:
        obs, _ = vec.reset(seed=0)
        assert obs["previous_search"].shape == (2, 1024, 5)
        obs, *_ = vec.step(np.zeros((2, 4), np.float32))
        assert obs["previous_search"].shape == (2, 1024, 5)
    finally:
        vec.close()
    env = TrackingEnv(toy, observation_keys=KEYS, episode_seed=2)
    env.reset(options={"tracklet": 1})
    env.step(np.zeros(4))
    twin = pickle.loads(pickle.dumps(env))
    a, b = env.step(np.ones(4) * 0.1)[0], twin.step(np.ones(4) * 0.1)[0]
    for key in KEYS:
        np.testing.assert_array_equal(a[key], b[key])
