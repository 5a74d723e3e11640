"""Env and ``VecEnv`` wrappers of RL fine-tuning, and the residual variant.

* :func:`wrap_env` / :func:`make_vec_env`: the tracking env in :class:`TrackerPolicy`'s
  ``[-1, 1]`` action units, ``K`` sub-envs stepped together (one batch-``K`` forward a step).
* :class:`SelfCriticalReward`: the reward of the policy's mean action as each step's baseline.
* The residual variant (``pointtrack finetune --algo residual``): :class:`ResidualTrackingEnv`
  (the frozen tracker acts, a small policy learns a residual on :func:`features`) and
  :class:`ResidualTracker` (the result, saved as ``residual.safetensors``; ``pointtrack eval``
  loads it through :func:`training.loading.load_tracker`).
"""

from __future__ import annotations

import json
from collections.abc import Callable
from pathlib import Path
from typing import Any

import gymnasium as gym
import numpy as np
from gymnasium import spaces
from stable_baselines3.common.policies import ActorCriticPolicy
from stable_baselines3.common.vec_env import DummyVecEnv, VecEnv, VecEnvWrapper, VecMonitor

from trackers.registry import read_safetensors, tracker_from_metadata, tracker_metadata
from training.residual_file import RESIDUAL_FORMAT
from training.rl.policy import TrackerPolicy
from training.rundir import atomic_save_safetensors

__all__ = [
    "FEATURE_DIM",
    "RESIDUAL_FORMAT",
    "ResidualTracker",
    "ResidualTrackingEnv",
    "SelfCriticalReward",
    "features",
    "make_vec_env",
    "residual_policy",
    "wrap_env",
]

RESIDUAL_VERSION = "1"


def wrap_env(env: gym.Env, clip_length: int) -> gym.Env:
    """``env`` with :class:`TrackerPolicy`'s action units (``RescaleAction`` to [-1, 1]) and,
    for ``clip_length > 0``, episodes of at most that many steps (``TimeLimit``)."""
    # a TimeLimit for envs that do not clip themselves; on one that does (max_steps) it ends
    # the episode at the same step
    if clip_length > 0:
        env = gym.wrappers.TimeLimit(env, max_episode_steps=clip_length)
    one = np.ones(4, dtype=np.float32)
    return gym.wrappers.RescaleAction(env, -one, one)


def make_vec_env(make_env: Callable[[], gym.Env], num_envs: int, clip_length: int):
    """``VecMonitor(DummyVecEnv)`` of ``num_envs`` wrapped envs (``RescaleAction`` to [-1, 1],
    ``TimeLimit`` clips): the policy acts on one batch of ``num_envs`` per step."""
    return VecMonitor(
        DummyVecEnv([lambda: wrap_env(make_env(), clip_length) for _ in range(num_envs)])
    )


class SelfCriticalReward(VecEnvWrapper):
    """Each sub-env's reward minus the reward of the policy's *mean* action at the same state:
    ``r(s, a) - r(s, mu(s))``, the self-critical baseline of Rennie et al., "Self-critical
    Sequence Training for Image Captioning" (CVPR 2017), here for one-step returns.

    Why: with a small exploration noise the reward's variance between states (a lost target
    against a tracked one) dwarfs its variance between the actions tried at one state, and a
    learned critic that cannot predict a tracker's IoU from its points leaves that variance in
    the advantage. The mean action's own reward is an exact per-state baseline (the env
    computes it without stepping, :meth:`envs.tracking_env.TrackingEnv.reward_for_action`),
    so the advantage keeps only the effect of the exploration. It is unbiased for one-step
    returns only: use it with ``gamma=0`` (each step's reward is then its return; PPO's critic
    learns a value near 0).

    ``venv``: the ``RescaleAction(env, -1, 1)`` sub-envs of :class:`TrackerPolicy`; ``policy``
    (settable later, as SB3 builds it after the env): the policy whose last forward chose the
    actions (:attr:`TrackerPolicy.last_mean`). Each step's ``info["baseline_reward"]`` records
    the baseline.
    """

    def __init__(self, venv: VecEnv, policy: TrackerPolicy | None = None) -> None:
        super().__init__(venv)
        self.policy = policy
        self._baseline = np.zeros(self.num_envs)

    def reset(self) -> Any:
        return self.venv.reset()

    def step_async(self, actions: np.ndarray) -> None:
        mean = None if self.policy is None else self.policy.last_mean
        if mean is None or mean.shape != (self.num_envs, 4):
            raise RuntimeError(
                "SelfCriticalReward: step() needs the policy's forward on this step's "
                "observations first (PPO's rollouts do that; set wrapper.policy = model.policy)"
            )
        self.policy.last_mean = None  # one baseline per forward
        env_units = (mean * self.policy.max_action.to(mean.dtype)).cpu().numpy()
        self._baseline = np.array(
            [
                self.venv.env_method("reward_for_action", env_units[i], indices=i)[0]
                for i in range(self.num_envs)
            ]
        )
        self.venv.step_async(actions)

    def step_wait(self) -> Any:
        obs, rewards, dones, infos = self.venv.step_wait()
        for info, baseline in zip(infos, self._baseline, strict=True):
            info["baseline_reward"] = float(baseline)
        return obs, (rewards - self._baseline).astype(rewards.dtype), dones, infos


# --------------------------------------------------------------------------- residual variant

FEATURE_DIM = 4 + 4 + 3 + 3 * 4
DEFAULT_SCALE = (0.5, 0.5, 0.2, 0.2)
RESIDUAL_NET_ARCH = (64, 64)


def features(obs: dict[str, np.ndarray], base: np.ndarray) -> np.ndarray:
    """The residual policy's observation ``(23,)``: the base action, the last motion, the target
    size, and for radii 0.5 / 1 / 2 m around the proposed centre the log point count and the
    mean offset of the search points."""
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


def residual_policy(log_std_init: float) -> ActorCriticPolicy:
    """The residual variant's Gaussian MLP policy on :func:`features` (untrained)."""
    return ActorCriticPolicy(
        spaces.Box(-np.inf, np.inf, (FEATURE_DIM,), np.float32),
        spaces.Box(-1.0, 1.0, (4,), np.float32),
        lambda _: 0.0,
        net_arch=list(RESIDUAL_NET_ARCH),
        log_std_init=log_std_init,
    )


class ResidualTracker:
    """A fine-tuned tracker: the frozen base tracker plus the PPO residual (deterministic).

    Saved as one ``residual.safetensors`` (the residual policy's and the base tracker's
    tensors, config as JSON metadata); :meth:`load` reads only that file — an SB3 ``ppo.zip``
    is refused, never unpickled.
    """

    def __init__(
        self,
        base: Any,
        policy: Any,
        scale=DEFAULT_SCALE,
        name: str = "finetuned",
        log_std_init: float = -2.0,
    ) -> None:
        self.base = base
        self.policy = policy
        self.scale = np.asarray(scale, dtype=np.float32)
        self.name = name
        self.log_std_init = float(log_std_init)
        #: the base tracker's env options (it acts on the same observations)
        self.env_options = dict(getattr(base, "env_options", None) or {})

    def save(self, path: str | Path) -> Path:
        """Write ``path`` (safetensors, atomic)."""
        path = Path(path)
        tensors = {
            f"policy.{k}": v.detach().cpu().contiguous()
            for k, v in self.policy.state_dict().items()
        }
        tensors.update(
            {f"base.{k}": v.detach().cpu().contiguous() for k, v in self.base.state_dict().items()}
        )
        meta = {
            "format": RESIDUAL_FORMAT,
            "version": RESIDUAL_VERSION,
            "base_tracker": self.base.name,
            "scale": json.dumps([float(s) for s in self.scale]),
            "name": self.name,
            "log_std_init": json.dumps(self.log_std_init),
        }
        # as trackers.save: the config, and env_options / inference where not the defaults
        base_meta = tracker_metadata(self.base)
        meta.update(base_config=base_meta.pop("config"), **base_meta)
        return atomic_save_safetensors(path, tensors, meta)

    @classmethod
    def load(cls, path: str | Path) -> ResidualTracker:
        """From ``residual.safetensors`` or a run directory holding it (no unpickling)."""
        path = Path(path)
        if path.is_dir():
            if not (path / "residual.safetensors").is_file() and (path / "ppo.zip").exists():
                raise ValueError(
                    f"{path} holds an SB3 ppo.zip (older pointtrack): refused, "
                    f"because loading it unpickles (and can run code); re-run "
                    f"`pointtrack finetune --algo residual`"
                )
            path = path / "residual.safetensors"
        if path.suffix == ".zip":
            raise ValueError(
                f"{path}: SB3 zips are refused (loading one unpickles); pass the "
                f"run's residual.safetensors"
            )
        if not path.is_file():
            raise FileNotFoundError(f"no residual checkpoint at {path}")
        meta, state = read_safetensors(path, "residual checkpoint")
        if meta.get("format") != RESIDUAL_FORMAT:
            raise ValueError(
                f"{path} is not a pointtrack residual checkpoint (format={meta.get('format')!r})"
            )
        base_meta = {**meta, "config": meta["base_config"]}  # older files: inference inside
        base = tracker_from_metadata(meta["base_tracker"], base_meta, path)
        base.load_state_dict(
            {k[5:]: v for k, v in state.items() if k.startswith("base.")}, strict=True
        )
        log_std = float(json.loads(meta["log_std_init"]))
        policy = residual_policy(log_std)
        policy.load_state_dict(
            {k[7:]: v for k, v in state.items() if k.startswith("policy.")}, strict=True
        )
        policy.set_training_mode(False)
        return cls(
            base.eval(), policy, json.loads(meta["scale"]), name=meta["name"], log_std_init=log_std
        )

    def act(self, obs: dict[str, np.ndarray]) -> np.ndarray:
        """One observation -> ``(4,)``; a batch -> ``(B, 4)``."""
        single = np.asarray(obs["search"]).ndim == 2
        base = np.asarray(self.base.act(obs), dtype=np.float32)
        if single:
            feats = features(obs, base)[None]
        else:
            feats = np.stack(
                [features({k: v[i] for k, v in obs.items()}, base[i]) for i in range(len(base))]
            )
        r, _ = self.policy.predict(feats, deterministic=True)
        action = base + self.scale * np.clip(r, -1, 1)
        return action[0] if single else action
