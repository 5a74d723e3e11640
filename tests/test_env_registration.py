"""The registered Gymnasium ids: idempotent registration, JSON specs, make / make_vec."""

from __future__ import annotations

import json

import gymnasium as gym
import numpy as np
import pytest

import envs
from envs.tracking_env import TrackingEnv, make_toy_dataset


@pytest.fixture(scope="module")
def kitti_root(tmp_path_factory):
    ds = make_toy_dataset(num_frames=[6, 7, 5, 6], seed=2, num_clutter=2000)
    return ds.write_kitti(tmp_path_factory.mktemp("toy-kitti"), scene="0019")


def test_registration_idempotent():
    envs.register_envs()
    envs.register_envs()
    for env_id in envs.ENV_IDS:
        spec = gym.spec(env_id)
        json.loads(spec.to_json())


def test_make_kitti(kitti_root):
    env = gym.make("pointtrack/KITTI-v1", root=kitti_root, setting="kitti-1")
    assert json.loads(env.spec.to_json())["kwargs"]["root"] == kitti_root
    assert isinstance(env.unwrapped, TrackingEnv)
    obs, info = env.reset(seed=0)
    assert info["tracklet"] == "0019/0" and info["observed"] is False  # Car is unseen in kitti-1
    obs, r, term, trunc, info = env.step(np.zeros(4, np.float32))
    assert 0.0 <= r <= 1.0
    env = gym.make(
        "pointtrack/KITTI-v1", root=kitti_root, categories=["Van"], template_mode="first"
    )
    assert [t.category for t in env.unwrapped.tracklets] == ["Van"]


def test_make_kitti_needs_root():
    with pytest.raises(ValueError, match="root"):
        gym.make("pointtrack/KITTI-v1")


def test_make_vec_async_module_qualified(kitti_root):
    vec = gym.make_vec(
        "envs:pointtrack/KITTI-v1",
        num_envs=2,
        vectorization_mode="async",
        root=kitti_root,
        split="test",
    )
    try:
        obs, _ = vec.reset(seed=0)
        assert obs["template"].shape == (2, 512, 3)
        vec.step(np.zeros((2, 4), np.float32))
    finally:
        vec.close()


def test_make_synthetic_tiny():
    env = gym.make(
        "pointtrack/Synthetic-v1",
        preset="tiny",
        split="test",
        setting="kitti-1",
        render_mode="rgb_array",
    )
    json.loads(env.spec.to_json())
    import warnings

    from gymnasium.utils.env_checker import check_env

    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        check_env(env.unwrapped)
    obs, info = env.reset(seed=0)
    assert env.observation_space.contains(obs)
    done = False
    while not done:
        obs, r, term, trunc, info = env.step(np.zeros(4, np.float32))
        done = term or trunc
