"""RL fine-tuning of a pretrained tracker with stable-baselines3 PPO — a minimal, working version.

Design (kept deliberately simple; DESIGN.md's ``training.finetune``):

* **Residual policy.** The pretrained tracker stays frozen and proposes
  ``a_base = tracker.act(obs)`` at every step. PPO learns a residual: the executed action is
  ``a_base + scale * r`` with ``r in [-1, 1]^4`` from a small Gaussian MLP policy. The policy's
  mean starts near 0 (PPO's orthogonal init with a small output gain) and its log-std is learned
  (initialised at ``log_std_init``), so at the start the agent *is* the pretrained tracker plus
  small exploration noise — "the pretrained tracker's act as the deterministic mean plus a
  learned log-std".
* **What PPO sees.** Not the raw 1536 points, but a compact vector: the base action, the last
  motion, the target size, and simple statistics of the search points around the proposed centre
  (counts within 0.5 / 1 / 2 m and their mean offset) — cheap and enough to learn corrections
  such as damping implausible jumps. See :class:`ResidualTrackingEnv`.
* **Reward** is the env's (3D IoU of the moved box with the ground truth), per step.

:func:`finetune` trains and saves ``ppo.zip`` + ``finetune.json``;
:class:`ResidualTracker` (``act(obs)``) replays the result so ``training.evaluate.evaluate`` and
``pointtrack eval`` can score it like any tracker.
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import gymnasium as gym
import numpy as np
from gymnasium import spaces

__all__ = ["ResidualTracker", "ResidualTrackingEnv", "features", "finetune"]

FEATURE_DIM = 4 + 4 + 3 + 3 * 4
DEFAULT_SCALE = (0.5, 0.5, 0.2, 0.2)


def features(obs: dict[str, np.ndarray], base: np.ndarray) -> np.ndarray:
    """The compact PPO observation of one env observation and the tracker's base action."""
    search = np.asarray(obs["search"], dtype=np.float32)
    d = np.linalg.norm(search[:, :2] - base[None, :2], axis=1)
    nonzero = np.any(search != 0, axis=1)
    parts = [base, obs["motion"], obs["size"]]
    for radius in (0.5, 1.0, 2.0):
        near = (d <= radius) & nonzero
        count = near.sum()
        mean = (search[near, :3].mean(0) - base[:3]) if count else np.zeros(3, np.float32)
        parts.append(np.array([np.log1p(count)], np.float32))
        parts.append(mean.astype(np.float32))
    return np.concatenate([np.asarray(p, np.float32).ravel() for p in parts]).astype(np.float32)


class ResidualTrackingEnv(gym.Wrapper):
    """Wraps a :class:`~envs.tracking_env.TrackingEnv`: actions are residuals in ``[-1, 1]^4``
    added (times ``scale``) to the frozen tracker's action; observations are :func:`features`."""

    def __init__(self, env: gym.Env, tracker: Any, scale=DEFAULT_SCALE) -> None:
        super().__init__(env)
        self.tracker = tracker
        self.scale = np.asarray(scale, dtype=np.float32)
        self.action_space = spaces.Box(-1.0, 1.0, (4,), np.float32)
        self.observation_space = spaces.Box(-np.inf, np.inf, (FEATURE_DIM,), np.float32)
        self._base = np.zeros(4, np.float32)

    def _encode(self, obs: dict[str, np.ndarray]) -> np.ndarray:
        self._base = np.asarray(self.tracker.act(obs), dtype=np.float32)
        return features(obs, self._base)

    def reset(self, *, seed=None, options=None):
        obs, info = self.env.reset(seed=seed, options=options)
        return self._encode(obs), info

    def step(self, action):
        r = np.clip(np.asarray(action, dtype=np.float32), -1.0, 1.0)
        full = self._base + self.scale * r
        low, high = self.env.action_space.low, self.env.action_space.high
        obs, reward, terminated, truncated, info = self.env.step(np.clip(full, low, high))
        return self._encode(obs), reward, terminated, truncated, info


class ResidualTracker:
    """A fine-tuned tracker: the frozen base tracker plus the PPO residual (deterministic)."""

    def __init__(self, base: Any, model: Any, scale=DEFAULT_SCALE, name: str = "finetuned") -> None:
        self.base = base
        self.model = model
        self.scale = np.asarray(scale, dtype=np.float32)
        self.name = name

    @classmethod
    def load(cls, run_dir: str | Path) -> ResidualTracker:
        from stable_baselines3 import PPO

        import trackers

        run_dir = Path(run_dir)
        meta = json.loads((run_dir / "finetune.json").read_text())
        base = trackers.load(meta["tracker"])
        model = PPO.load(str(run_dir / "ppo.zip"), device="cpu")
        return cls(base, model, meta["scale"], name=f"{meta['tracker']}-ft")

    def act(self, obs: dict[str, np.ndarray]) -> np.ndarray:
        single = np.asarray(obs["search"]).ndim == 2
        base = np.asarray(self.base.act(obs), dtype=np.float32)
        if single:
            r, _ = self.model.predict(features(obs, base), deterministic=True)
            return base + self.scale * np.clip(r, -1, 1)
        feats = np.stack([features({k: v[i] for k, v in obs.items()}, base[i])
                          for i in range(len(base))])
        r, _ = self.model.predict(feats, deterministic=True)
        return base + self.scale * np.clip(r, -1, 1)


def finetune(
    tracker_name: str,
    make_env,
    *,
    total_timesteps: int = 4096,
    out: str | Path = "runs/finetune",
    seed: int = 0,
    scale=DEFAULT_SCALE,
    n_steps: int = 256,
    log_std_init: float = -2.0,
    learning_rate: float = 3e-4,
    verbose: int = 0,
) -> ResidualTracker:
    """PPO on the residual env; ``make_env()`` builds a fresh (random-sampling) TrackingEnv."""
    import torch
    from stable_baselines3 import PPO

    import trackers

    base = trackers.load(tracker_name)
    if isinstance(base, torch.nn.Module):
        base.eval()
        for p in base.parameters():
            p.requires_grad_(False)
    env = ResidualTrackingEnv(make_env(), base, scale)
    model = PPO(
        "MlpPolicy", env, n_steps=n_steps, batch_size=min(64, n_steps), seed=seed,
        learning_rate=learning_rate, verbose=verbose, device="cpu",
        policy_kwargs={"net_arch": [64, 64], "log_std_init": log_std_init},
    )
    model.learn(total_timesteps=total_timesteps)
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    model.save(str(out / "ppo.zip"))
    (out / "finetune.json").write_text(json.dumps(
        {"tracker": tracker_name, "scale": [float(s) for s in scale], "seed": seed,
         "total_timesteps": total_timesteps, "n_steps": n_steps, "log_std_init": log_std_init},
        indent=2))
    return ResidualTracker(base, model, scale, name=f"{tracker_name}-ft")
