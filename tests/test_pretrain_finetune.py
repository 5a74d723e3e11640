"""RL fine-tuning (training.finetune): a short PPO run on the toy env produces a tracker."""

from __future__ import annotations

import numpy as np
import pytest


@pytest.mark.slow
def test_finetune_residual_policy_runs_and_reloads(tmp_path):
    trackers = pytest.importorskip("trackers")
    from envs.tracking_env import TrackingEnv, make_toy_dataset
    from training.config import tracker_config
    from training.evaluate import evaluate
    from training.finetune import ResidualTracker, finetune

    path = tmp_path / "p2b.safetensors"
    trackers.save(trackers.make("p2b", **tracker_config("p2b", "slim")), path)
    data = make_toy_dataset(num_frames=6)
    tuned = finetune(str(path), lambda: TrackingEnv(data, sampling="random"),
                     total_timesteps=64, n_steps=32, out=tmp_path / "ft")
    obs, _ = TrackingEnv(data).reset(seed=0)
    action = tuned.act(obs)
    assert action.shape == (4,) and np.all(np.isfinite(action))
    again = ResidualTracker.load(tmp_path / "ft")
    assert np.allclose(again.act(obs), action, atol=1e-5)
    report = evaluate(tuned, TrackingEnv(data))
    assert 0.0 <= report["mean"]["success"] <= 100.0
