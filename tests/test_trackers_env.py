"""Trackers acting in the real environment (the env's in-memory toy dataset)."""

from __future__ import annotations

import numpy as np
import pytest
import torch

import trackers
from envs import tracking_env

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


@pytest.mark.parametrize("name", ["p2b-kitti1-u", "bat-kitti1-u", "gpt-kitti1-u", "p2b"])
def test_eval_fast_paths_equal_the_plain_path_on_env_observations(name, env):
    """Env observations (padded templates, sparse neighbourhoods): the eval fast paths (ragged
    and de-duplicated groups, P2B's knot interpolation) give the plain path's outputs."""
    from test_trackers import assert_outputs_close, reference_outputs

    torch.manual_seed(0)
    model = trackers.load(name).eval()
    observations = []
    obs, _ = env.reset(seed=1)
    terminated = False
    while not terminated:
        observations.append(obs)
        obs, _, terminated, _, _ = env.step(model.act(obs))
    batch = {
        k: torch.as_tensor(np.stack([o[k] for o in observations])).float()
        for k in ("template", "search", "size", "motion")
    }
    with torch.no_grad():
        out = model(batch)
    assert_outputs_close(out, reference_outputs(model, batch))
