"""Trackers acting in the real environment (the env's in-memory toy dataset)."""

from __future__ import annotations

import numpy as np
import pytest
import torch

import trackers

tracking_env = pytest.importorskip("envs.tracking_env")


pytestmark = pytest.mark.usefixtures("one_torch_thread")


@pytest.fixture(scope="module")
def env():
    dataset = tracking_env.make_toy_dataset(num_frames=3, seed=0)
    return tracking_env.TrackingEnv(dataset)


@pytest.mark.parametrize("name", ["p2b", "bat", "gpt"])
def test_act_on_env_observations(name, env):
    torch.manual_seed(0)
    model = trackers.make(name)
    observations = []
    obs, _ = env.reset(seed=0)
    terminated = False
    while not terminated:
        action = model.act(obs)
        assert action.shape == (4,) and action.dtype == np.float32 and np.isfinite(action).all()
        assert env.action_space.contains(action), action
        observations.append(obs)
        obs, reward, terminated, truncated, info = env.step(action)
        assert not info["action_clipped"]
    batch = {k: np.stack([o[k] for o in observations]) for k in observations[0]}
    actions = model.act(batch)
    assert actions.shape == (len(observations), 4)
    assert all(env.action_space.contains(a) for a in actions)
    np.testing.assert_allclose(actions[0], model.act(observations[0]), rtol=1e-4, atol=1e-5)
