"""GroupPPO: PPO's clipped update on several sampled actions per visited state (one-step
rewards), for :class:`training.rl.policy.TrackerPolicy`, and its rollout buffer
:class:`GroupRollout`.

At every visited state it scores ``group_size`` sampled actions with the env's reward (without
stepping) and takes each one's advantage against the group's mean reward, the group-relative
baseline of GRPO (Shao et al., "DeepSeekMath: Pushing the Limits of Mathematical Reasoning in
Open Language Models", 2024), without its division by the group's standard deviation (Liu et
al., "Understanding R1-Zero-Like Training: A Critical Perspective", 2025). The algorithm reads
the policy only through its distribution API (``mean_and_value``, ``gaussian``,
``action_std``, ``max_action``).
"""

from __future__ import annotations

import functools
from typing import Any

import numpy as np
import torch
from stable_baselines3 import PPO
from stable_baselines3.common.callbacks import BaseCallback
from stable_baselines3.common.utils import obs_as_tensor
from stable_baselines3.common.vec_env import VecEnv
from torch import nn

from training.rl.features import StageFeatures
from training.rl.policy import TrackerPolicy

__all__ = ["GroupPPO", "GroupRollout"]


class GroupRollout:
    """What :class:`GroupPPO` collects for one update: for each of the ``S = T * M`` visited
    states (``T`` steps of ``M`` sub-envs) its observation, ``K`` sampled actions ``actions
    (S, K, 4)`` in ``[-1, 1]`` units, their ``log_probs (S, K)`` under the policy that sampled
    them, their ``rewards (S, K)`` and the group-centred ``advantages (S, K)`` (each reward minus
    its state's mean over the ``K``)."""

    def __init__(self) -> None:
        self.reset()

    def reset(self) -> None:
        self._steps: list[tuple[dict[str, np.ndarray], np.ndarray, np.ndarray, np.ndarray]] = []
        self.observations: dict[str, np.ndarray] = {}
        self.actions = self.log_probs = self.rewards = self.advantages = np.zeros((0, 0))
        #: the policy's frozen stages' outputs for the S states (None: not cached)
        self.features: StageFeatures | None = None

    def add(
        self,
        obs: dict[str, np.ndarray],
        actions: np.ndarray,
        log_probs: np.ndarray,
        rewards: np.ndarray,
    ) -> None:
        """One step of the ``M`` sub-envs: ``obs`` (dict of ``(M, ...)``), ``actions (M, K, 4)``,
        ``log_probs (M, K)``, ``rewards (M, K)``."""
        self._steps.append(({k: np.array(v) for k, v in obs.items()}, actions, log_probs, rewards))

    def finish(self) -> None:
        """Stack the steps into the ``(S, ...)`` arrays and compute the advantages."""
        obs = [step[0] for step in self._steps]
        self.observations = {k: np.concatenate([o[k] for o in obs]) for k in obs[0]}
        self.actions, self.log_probs, self.rewards = (
            np.concatenate([step[i] for step in self._steps]) for i in (1, 2, 3)
        )
        self.advantages = self.rewards - self.rewards.mean(axis=1, keepdims=True)
        self._steps = []

    @property
    def size(self) -> int:
        return len(self.rewards)


class GroupPPO(PPO):
    """PPO's clipped update on ``group_size`` sampled actions per visited state, for one-step
    rewards, with :class:`TrackerPolicy`.

    Rollout: at each step the policy's mean ``mu(s)`` (one batch-``M`` tracker forward) and
    ``K = group_size`` actions sampled from ``N(mu(s), std)``; the env scores each without
    stepping (:meth:`envs.tracking_env.TrackingEnv.reward_for_action`) and then steps with the
    mean action, so the visited states are the deployed (deterministic) tracker's own. Update:
    each sample's advantage is its reward minus its state's mean over the ``K`` (divided by the
    minibatch's standard deviation when ``normalize_advantage``), in PPO's clipped surrogate
    with the usual ``target_kl`` early stop and gradient clipping; no critic, no value loss.

    Why: with a small exploration noise a state's reward differs between the sampled actions
    far less than between states (docs/notes/rl-runs.md: the learned critic explained ~0 of
    it), and one sample per state leaves the self-critical baseline (:class:`SelfCriticalReward`)
    one difference per forward. ``K`` samples cost ``K`` box IoUs and no extra tracker forward, so
    each forward yields ``K`` advantages. The objective is each frame's expected reward at the
    states the tracker visits (``gamma`` is not used; nor are the critic and ``gae_lambda``).

    ``cache_features`` (default on): the policy's frozen leading stages (the backbone, and the
    fusion under ``train_parts="head"``) keep their rollout outputs, and the update epochs reuse
    them instead of running those stages again (:mod:`training.rl.features`; the same update
    to float rounding).
    """

    def __init__(
        self,
        policy: Any,
        env: Any,
        *,
        group_size: int = 8,
        cache_features: bool = True,
        **kwargs: Any,
    ) -> None:
        if int(group_size) < 2:
            raise ValueError(f"group_size must be >= 2 (a group needs a mean), got {group_size}")
        self.group_size = int(group_size)
        self.cache_features = bool(cache_features)
        super().__init__(policy, env, **kwargs)

    def _setup_model(self) -> None:
        super()._setup_model()
        if not isinstance(self.policy, TrackerPolicy):
            raise TypeError(f"GroupPPO needs TrackerPolicy, got {type(self.policy).__name__}")
        self.rollout_buffer = GroupRollout()  # type: ignore[assignment]

    def _group_rewards(self, env: VecEnv, actions: np.ndarray) -> np.ndarray:
        """``(M, K)`` rewards of ``actions (M, K, 4)`` ([-1, 1] units) at the current states."""
        env_units = np.clip(actions, -1.0, 1.0) * self.policy.max_action.cpu().numpy()
        return np.array(
            [
                [env.env_method("reward_for_action", a, indices=i)[0] for a in env_units[i]]
                for i in range(env.num_envs)
            ]
        )

    def collect_rollouts(
        self,
        env: VecEnv,
        callback: BaseCallback,
        rollout_buffer: Any,
        n_rollout_steps: int,
    ) -> bool:
        assert self._last_obs is not None, "No previous observation was provided"
        self.policy.set_training_mode(False)
        rollout_buffer.reset()
        callback.on_rollout_start()
        with self.policy.frozen_stages.recording() as features:
            if not self._rollout_steps(env, callback, rollout_buffer, n_rollout_steps):
                return False
        rollout_buffer.finish()
        rollout_buffer.features = features[0] if self.cache_features else None
        callback.update_locals(locals())
        callback.on_rollout_end()
        return True

    def _rollout_steps(
        self, env: VecEnv, callback: BaseCallback, rollout_buffer: GroupRollout, n_steps: int
    ) -> bool:
        """``n_steps`` steps of the ``M`` sub-envs into ``rollout_buffer``; False when the
        callback stops the run."""
        for _ in range(n_steps):
            with torch.no_grad():
                obs_tensor = obs_as_tensor(self._last_obs, self.device)
                mean, _ = self.policy.mean_and_value(obs_tensor, value=False)
                dist = self.policy.gaussian(mean[:, None])  # (M, 1, 4)
                noise = torch.randn((env.num_envs, self.group_size, 4), device=mean.device)
                samples = dist.loc + dist.scale * noise
                log_probs = dist.log_prob(samples)
            samples_np = samples.cpu().numpy()
            rewards = self._group_rewards(env, samples_np)
            new_obs, _, dones, infos = env.step(np.clip(mean.cpu().numpy(), -1.0, 1.0))
            self.num_timesteps += env.num_envs
            callback.update_locals(locals())
            if not callback.on_step():
                return False
            self._update_info_buffer(infos, dones)
            rollout_buffer.add(self._last_obs, samples_np, log_probs.sum(-1).cpu().numpy(), rewards)
            self._last_obs = new_obs
            self._last_episode_starts = dones
        return True

    def train(self) -> None:
        self.policy.set_training_mode(True)
        self._update_learning_rate(self.policy.optimizer)
        clip_range = self.clip_range(self._current_progress_remaining)  # type: ignore[operator]
        buf: GroupRollout = self.rollout_buffer  # type: ignore[assignment]
        as_tensor = functools.partial(torch.as_tensor, device=self.device)
        observations = {k: as_tensor(v) for k, v in buf.observations.items()}
        actions, old_log_probs, advantages = (
            as_tensor(a, dtype=torch.float32) for a in (buf.actions, buf.log_probs, buf.advantages)
        )
        pg_losses, clip_fractions, approx_kls = [], [], []
        loss = torch.zeros(())
        continue_training = True
        for _ in range(self.n_epochs):
            for idx in torch.randperm(buf.size).split(self.batch_size):
                mean, _ = self.policy.mean_and_value(
                    {k: v[idx] for k, v in observations.items()},
                    value=False,
                    features=None if buf.features is None else buf.features.select(idx),
                )
                dist = self.policy.gaussian(mean[:, None])
                log_prob = dist.log_prob(actions[idx]).sum(-1)  # (b, K)
                adv = advantages[idx]
                if self.normalize_advantage and adv.numel() > 1:
                    adv = adv / (adv.std() + 1e-8)
                log_ratio = log_prob - old_log_probs[idx]
                ratio = torch.exp(log_ratio)
                policy_loss = -torch.min(
                    adv * ratio, adv * torch.clamp(ratio, 1 - clip_range, 1 + clip_range)
                ).mean()
                loss = policy_loss - self.ent_coef * dist.entropy().sum(-1).mean()
                with torch.no_grad():
                    approx_kl = float(torch.mean(torch.exp(log_ratio) - 1 - log_ratio))
                approx_kls.append(approx_kl)
                pg_losses.append(policy_loss.item())
                clip_fractions.append(float(torch.mean((ratio - 1).abs().gt(clip_range).float())))
                if self.target_kl is not None and approx_kl > 1.5 * self.target_kl:
                    continue_training = False
                    break
                self.policy.optimizer.zero_grad()
                loss.backward()
                nn.utils.clip_grad_norm_(self.policy.parameters(), self.max_grad_norm)
                self.policy.optimizer.step()
            self._n_updates += 1
            if not continue_training:
                break
        self.logger.record("train/policy_gradient_loss", float(np.mean(pg_losses)))
        self.logger.record("train/approx_kl", float(np.mean(approx_kls)))
        self.logger.record("train/clip_fraction", float(np.mean(clip_fractions)))
        self.logger.record("train/loss", loss.item())
        self.logger.record("train/std", self.policy.action_std.mean().item())
        # how much the K samples of one state differ: the signal the update works with
        self.logger.record("train/group_reward_std", float(buf.rewards.std(axis=1).mean()))
        self.logger.record("train/n_updates", self._n_updates, exclude="tensorboard")
        self.logger.record("train/clip_range", clip_range)
