"""TrackingEnv under vector envs and stable-baselines3 (smoke tests)."""

from __future__ import annotations

import functools
import warnings

import gymnasium as gym
import numpy as np
import pytest

from envs.tracking_env import TrackingEnv, make_toy_dataset


@pytest.fixture(scope="module")
def toy():
    return make_toy_dataset(num_frames=[6, 7, 5, 6], seed=1, num_clutter=2000)


def _steps(vec, n=12):
    obs, infos = vec.reset(seed=0)
    assert obs["search"].shape == (vec.num_envs, 1024, 3)
    ends = 0
    for _ in range(n):
        obs, rew, term, trunc, infos = vec.step(np.zeros((vec.num_envs, 4), np.float32))
        assert rew.shape == (vec.num_envs,)
        ends += int(term.sum())
    assert ends > 0
    return obs


def test_sync_vector_env(toy):
    vec = gym.vector.SyncVectorEnv([functools.partial(TrackingEnv, toy)] * 2)
    _steps(vec)
    vec.close()


def test_async_vector_env_default_context(toy):
    vec = gym.vector.AsyncVectorEnv([functools.partial(TrackingEnv, toy)] * 2)
    try:
        a = _steps(vec)
    finally:
        vec.close()
    sync = gym.vector.SyncVectorEnv([functools.partial(TrackingEnv, toy)] * 2)
    b = _steps(sync)
    for k in a:
        np.testing.assert_array_equal(a[k], b[k])


def test_set_tracklet_order_per_sub_env(toy):
    vec = gym.vector.SyncVectorEnv([functools.partial(TrackingEnv, toy)] * 2)
    vec.set_attr("tracklet_order", [[3, 1], [2]])
    _, infos = vec.reset(seed=0)
    ids = [t.tracklet_id for t in toy.tracklets]
    assert list(infos["tracklet"]) == [ids[3], ids[2]]


@pytest.mark.slow
def test_async_vector_env_forkserver(toy):
    vec = gym.vector.AsyncVectorEnv([functools.partial(TrackingEnv, toy)] * 2, context="forkserver")
    try:
        _steps(vec)
    finally:
        vec.close()


def test_sb3_ppo_smoke(toy):
    from gymnasium.wrappers import RescaleAction
    from stable_baselines3 import PPO
    from stable_baselines3.common.vec_env import DummyVecEnv

    def make():
        return RescaleAction(TrackingEnv(toy), np.full(4, -1, np.float32), np.ones(4, np.float32))

    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        model = PPO(
            "MultiInputPolicy",
            DummyVecEnv([make]),
            n_steps=64,
            batch_size=32,
            n_epochs=1,
            seed=0,
            device="cpu",
            policy_kwargs={"net_arch": [16]},
        )
        model.learn(total_timesteps=128)
    obs = make().reset(seed=0)[0]
    action, _ = model.predict(obs, deterministic=True)
    assert action.shape == (4,)


@pytest.mark.slow
def test_sb3_subproc_vec_env_forkserver(toy):
    from gymnasium.wrappers import RescaleAction
    from stable_baselines3.common.vec_env import SubprocVecEnv

    def make():
        return RescaleAction(TrackingEnv(toy), np.full(4, -1, np.float32), np.ones(4, np.float32))

    vec = SubprocVecEnv([make, make], start_method="forkserver")
    try:
        vec.seed(0)
        obs = vec.reset()
        assert obs["search"].shape == (2, 1024, 3)
        for _ in range(8):
            obs, rew, done, infos = vec.step(np.zeros((2, 4), np.float32))
    finally:
        vec.close()
