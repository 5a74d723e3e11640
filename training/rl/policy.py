"""A pretrained tracker as a stable-baselines3 policy: :class:`TrackerPolicy`.

The actor *is* the tracker. For an observation batch the tracker runs one forward (in eval
mode) and the Gaussian policy's mean is the tracker's own action, rescaled to the
``RescaleAction(env, -1, 1)`` units ``a / max_action``; a learned, state-independent log-std
(initial value ``log_std_init``, default -2: a standard deviation of 0.14 normalised units, i.e.
0.68 m on x and y with the env's default ``max_action``) gives the exploration; a value head
reads the tracker's :meth:`~trackers.base.Tracker.summary_features` (P2B, BAT, GPT: the fused
search features ``Z (B, M, D)`` max- and mean-pooled over the seeds; M2-Track: its motion
feature), or, with ``critic="separate"``, a small PointNet of its own on the search points. Any
learned tracker serves: the matching trackers and M2-Track (whose env must serve
``previous_search``). ::

    import gymnasium as gym
    from stable_baselines3 import PPO
    from training.rl import TrackerPolicy

    env = gym.wrappers.RescaleAction(my_tracking_env, -1.0, 1.0)
    model = PPO(TrackerPolicy, env, policy_kwargs={"tracker": "p2b-kitti1-u"})

Why each choice (the traps of wrapping a tracker by hand, issue 22):

* **No re-initialisation.** SB3's ``ortho_init`` overwrites every weight it reaches; the tracker
  is never passed to it (the value head keeps PyTorch's default init), so building the policy
  changes no tracker weight and, before any update, ``predict(obs, deterministic=True)`` equals
  ``tracker.act(obs) / max_action``.
* **Always eval mode.** In training mode the backbone samples points at random and BatchNorm
  uses batch statistics, so the log-probability of the same action would change between the
  rollout and the update (PPO's ratio would not start at 1). :meth:`TrackerPolicy.train` keeps
  the tracker in eval mode whatever SB3's ``set_training_mode`` asks; an eval-mode forward is
  still differentiable.
* **Action mean** ``action_mode="best"`` (default): ``trackers.decision.decide`` (the
  best-scored proposal, or the re-ranked one under ``tracker.inference``; M2-Track's final
  box; zero where the tracker keeps the box; clipped), exactly what ``tracker.act`` executes,
  so the policy starts
  as the pretrained tracker and PPO's gradient reaches the box regression of that proposal
  (votes, clustering, offsets, and through them the fusion and backbone features); the scores
  get no gradient (an argmax is piecewise constant). ``"soft"``: the softmax(scores /
  ``temperature``)-weighted mean of the proposals, which also trains the scores but starts
  *away* from ``tracker.act`` (it averages proposals on different parts of the scene), so the
  first updates must first undo that shift (M2-Track has one proposal: the same as ``"best"``
  but for the yaw's wrapping).
* **Which parts train** (``train_parts``): ``"head"`` (the proposal head; M2-Track's four
  box and motion heads), ``"fusion+head"`` (matching trackers), ``"all"`` (the tracker's
  ``train_parts`` class attribute names the modules); the value head and the log-std always
  train. The tracker's parameters get the learning rate times ``tracker_lr_scale`` (default
  0.03: 1e-5 under PPO's 3e-4), the value head and log-std the full rate, through per-group
  ``lr_scale`` in :class:`ScaledAdam` (SB3 sets one learning rate for every group; the scale
  survives it).
* The stages that do not train *and* run before the first trained one (the backbone, and the
  fusion for ``"head"``; M2-Track's segmentation and first PointNet) run under ``no_grad``: no
  gradient can pass through them to a trained stage, and the update skips their autograd graph.
  A frozen stage between trained ones (M2-Track's second PointNet) keeps its graph.
* :meth:`TrackerPolicy.freeze_actor` stops the actor's gradients (tracker and log-std) for a
  critic warm-up.
* **The distribution API** algorithms use (:class:`training.rl.group_ppo.GroupPPO` reads
  nothing else): :meth:`TrackerPolicy.mean_and_value` (the mean, one tracker forward),
  :meth:`TrackerPolicy.gaussian` (the action distribution around any mean, broadcast over
  leading dimensions), :attr:`TrackerPolicy.max_action` (the env's units) and
  :attr:`TrackerPolicy.last_mean`.
* Any SB3 actor-critic algorithm can drive it (PPO, A2C: ``optimizer_class`` is wrapped by
  :func:`lr_scaled`). Save the result with ``trackers.save(model.policy.tracker, path)`` or
  through ``pointtrack finetune`` (:mod:`training.rl.run`, safetensors): SB3's zips load by
  unpickling.
"""

from __future__ import annotations

import contextlib
import copy
import functools
import math
from typing import Any

import numpy as np
import torch
from gymnasium import spaces
from stable_baselines3.common.distributions import DiagGaussianDistribution
from stable_baselines3.common.policies import ActorCriticPolicy
from stable_baselines3.common.torch_layers import BaseFeaturesExtractor
from torch import nn

import trackers
from trackers.base import OBS_SHAPES, MatchingTracker, Tracker
from trackers.decision import (
    Scene,
    chosen_proposal,
    clip_action,
    decide,
    keeps_box,
    scenes,
)
from training.rl.features import FrozenStages, PerState, StageFeatures

__all__ = [
    "ACTION_MODES",
    "CRITICS",
    "TRAIN_PARTS",
    "ScaledAdam",
    "TrackerPolicy",
    "lr_scaled",
    "resolve_tracker",
]

TRAIN_PARTS = ("head", "fusion+head", "all")
ACTION_MODES = ("best", "soft")
CRITICS = ("fused", "separate")


class _LRScaled:
    """Mixin for a torch optimizer: a parameter group may carry ``lr_scale`` and then steps with
    ``lr * lr_scale``. SB3 writes one learning rate into every group before each update; the
    scale keeps the tracker's rate a fixed fraction of it."""

    @torch.no_grad()
    def step(self, closure: Any = None) -> Any:
        saved = [group["lr"] for group in self.param_groups]
        for group in self.param_groups:
            group["lr"] = group["lr"] * float(group.get("lr_scale", 1.0))
        try:
            return super().step(closure)
        finally:
            for group, lr in zip(self.param_groups, saved, strict=True):
                group["lr"] = lr


class ScaledAdam(_LRScaled, torch.optim.Adam):
    """Adam with per-group ``lr_scale`` (the default optimizer of :class:`TrackerPolicy`)."""


@functools.cache
def lr_scaled(optimizer_class: type[torch.optim.Optimizer]) -> type[torch.optim.Optimizer]:
    """``optimizer_class`` with per-group ``lr_scale`` (A2C asks for RMSprop, for instance)."""
    if issubclass(optimizer_class, _LRScaled):
        return optimizer_class
    return type(f"LRScaled{optimizer_class.__name__}", (_LRScaled, optimizer_class), {})


class _NoFeatures(BaseFeaturesExtractor):
    """SB3 builds a features extractor in ``__init__``; the tracker reads the observation."""

    def __init__(self, observation_space: spaces.Space) -> None:
        super().__init__(observation_space, features_dim=1)

    def forward(self, observations: Any) -> torch.Tensor:  # pragma: no cover - never called
        raise RuntimeError("TrackerPolicy reads observations through its tracker")


#: what the separate critic reads (every tracking env serves them)
_CRITIC_KEYS = ("search", "size", "motion")


class _SearchCritic(nn.Module):
    """A small PointNet value network: per-point MLP on ``search (B, N, 3)``, max-pool, then an
    MLP with ``size (B, 3)`` and ``motion (B, 4)`` -> ``(B,)``."""

    def __init__(self, width: int = 64) -> None:
        super().__init__()
        self.point = nn.Sequential(nn.Linear(3, width), nn.ReLU(), nn.Linear(width, 2 * width))
        self.out = nn.Sequential(nn.Linear(2 * width + 7, width), nn.Tanh(), nn.Linear(width, 1))

    def forward(self, obs: dict[str, torch.Tensor]) -> torch.Tensor:
        pooled = self.point(obs["search"]).amax(dim=1)
        return self.out(torch.cat([pooled, obs["size"], obs["motion"]], dim=-1)).squeeze(-1)


def _scenes(tracker: Tracker, batch: dict[str, torch.Tensor]) -> PerState:
    """The batch's :func:`trackers.decision.scenes`, one per state (a cacheable frozen call)."""
    return PerState(scenes(tracker, batch))


def resolve_tracker(tracker: Any) -> Tracker:
    """A learned tracker from a shipped name, a checkpoint path or a :class:`Tracker`; a
    ``TypeError`` for anything without weights (a baseline such as ``previous_box``)."""
    if isinstance(tracker, str | bytes) or hasattr(tracker, "__fspath__"):
        tracker = trackers.load(tracker)
    if not isinstance(tracker, Tracker):
        name = getattr(tracker, "name", type(tracker).__name__)
        raise TypeError(
            f"TrackerPolicy needs a learned tracker (P2B, BAT, GPT or M2-Track: a shipped "
            f"name such as 'p2b-kitti1-u', a checkpoint path or a Tracker); "
            f"{name!r} has no parameters to train"
        )
    return tracker


class TrackerPolicy(ActorCriticPolicy):
    """SB3 actor-critic policy whose actor is a pretrained tracker (see the module docstring).

    Keywords (``policy_kwargs``): ``tracker`` (required), ``train_parts`` (``"head"``),
    ``log_std_init`` (-2.0), ``action_mode`` (``"best"``), ``temperature`` (1.0, for
    ``"soft"``), ``critic`` (``"fused"``), ``critic_width`` (64), ``tracker_lr_scale`` (0.03),
    ``max_action`` (default: the tracker's ``max_action``, which must equal the env's: the policy
    works in ``a / max_action`` units), ``executed_gradient_only`` (True: with ``train_parts
    "head"`` on a matching tracker, the update differentiates the executed proposal's cluster
    alone, :meth:`_executed_action`; False: the whole head, the same gradient at ~3x the cost).
    The tracker is copied: the caller's object is unchanged.
    """

    def __init__(
        self,
        observation_space: spaces.Space,
        action_space: spaces.Space,
        lr_schedule: Any,
        *,
        tracker: Any,
        train_parts: str = "head",
        log_std_init: float = -2.0,
        action_mode: str = "best",
        temperature: float = 1.0,
        critic: str = "fused",
        critic_width: int = 64,
        tracker_lr_scale: float = 0.03,
        max_action: Any = None,
        optimizer_class: type[torch.optim.Optimizer] = ScaledAdam,
        optimizer_kwargs: dict[str, Any] | None = None,
        use_sde: bool = False,
        executed_gradient_only: bool = True,
    ) -> None:
        if use_sde:
            raise ValueError("TrackerPolicy does not support gSDE (use_sde=True)")
        _check_choice("train_parts", train_parts, TRAIN_PARTS)
        _check_choice("action_mode", action_mode, ACTION_MODES)
        _check_choice("critic", critic, CRITICS)
        if not (temperature > 0 and math.isfinite(temperature)):
            raise ValueError(f"temperature must be a positive number, got {temperature!r}")
        if not (tracker_lr_scale >= 0 and math.isfinite(tracker_lr_scale)):
            raise ValueError(f"tracker_lr_scale must be >= 0, got {tracker_lr_scale!r}")
        if not math.isfinite(log_std_init):
            raise ValueError(f"log_std_init must be finite, got {log_std_init!r}")
        model = copy.deepcopy(resolve_tracker(tracker)).eval()
        # one batched forward for the K sub-envs' observations (and a minibatch): the policy's
        # outputs then differ from tracker.act's one-at-a-time ones by float rounding only
        model.batch_invariant = False
        _check_spaces(observation_space, action_space, model)
        super().__init__(
            observation_space,
            action_space,
            lr_schedule,
            net_arch=[],
            ortho_init=False,
            log_std_init=log_std_init,
            features_extractor_class=_NoFeatures,
            optimizer_class=lr_scaled(optimizer_class),
            optimizer_kwargs={"eps": 1e-5} if optimizer_kwargs is None else optimizer_kwargs,
        )
        # SB3's _build (called above) built nothing; the tracker, value head and optimizer now
        self.tracker = model
        self.train_parts = train_parts
        self.action_mode = action_mode
        self.temperature = float(temperature)
        self.critic_kind = critic
        self.tracker_lr_scale = float(tracker_lr_scale)
        self.executed_gradient_only = bool(executed_gradient_only)
        a_max = model.max_action if max_action is None else max_action
        a_max = np.asarray(a_max, dtype=np.float32)
        if a_max.shape != (4,) or not np.all(a_max > 0):
            raise ValueError(f"max_action must be 4 positive numbers, got {max_action!r}")
        self.register_buffer("max_action", torch.as_tensor(a_max))
        self.log_std = nn.Parameter(torch.full((4,), float(log_std_init)))
        if critic == "fused":
            self.value_head: nn.Module = nn.Sequential(
                nn.Linear(model.summary_channels, critic_width),
                nn.Tanh(),
                nn.Linear(critic_width, 1),
            )
        else:
            self.value_head = _SearchCritic(critic_width)
        self._trainable = self._select_trainable()
        for p in self.tracker.parameters():
            p.requires_grad_(False)
        for p in self._trainable:
            p.requires_grad_(True)
        prefix = self._frozen_prefix()
        self.frozen_stages = FrozenStages(prefix)
        if isinstance(model, MatchingTracker) and model.backbone in prefix:
            # the backbone alone reads its sampling orders: cached with its outputs
            self.frozen_stages.wrap(model, "sampling_orders")
        self._actor_frozen = False
        # the mean of the last forward, (B, 4) [-1, 1] units: SelfCriticalReward reads it
        self.last_mean: torch.Tensor | None = None
        own = [*self.value_head.parameters(), self.log_std]
        self.optimizer = self.optimizer_class(
            [
                {"params": own, "lr_scale": 1.0, "name": "value+log_std"},
                {"params": self._trainable, "lr_scale": self.tracker_lr_scale, "name": "tracker"},
            ],
            lr=lr_schedule(1),
            **self.optimizer_kwargs,
        )
        self.tracker.eval()

    # ------------------------------------------------------------------ SB3 hooks
    def _build(self, lr_schedule: Any) -> None:
        """Nothing here: ``__init__`` builds the modules once the tracker can be assigned
        (SB3's own ``_build`` would add unused networks and orthogonally initialise them)."""
        self.action_dist = DiagGaussianDistribution(int(np.prod(self.action_space.shape)))

    def train(self, mode: bool = True) -> TrackerPolicy:
        """Module mode for the value head; the tracker stays in eval mode (see module doc)."""
        super().train(mode)
        if hasattr(self, "tracker"):
            self.tracker.eval()
        return self

    def _get_constructor_parameters(self) -> dict[str, Any]:
        raise NotImplementedError(
            "TrackerPolicy is not saved through SB3 (it would be pickled); "
            "use training.rl.run.finetune, which writes safetensors"
        )

    def forward(
        self, obs: Any, deterministic: bool = False
    ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        mean, values = self.mean_and_value(obs)
        self.last_mean = mean.detach()
        dist = self.action_dist.proba_distribution(mean, self.log_std)
        actions = dist.get_actions(deterministic=deterministic)
        return actions, values[:, None], dist.log_prob(actions)

    def evaluate_actions(
        self, obs: Any, actions: torch.Tensor
    ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        mean, values = self.mean_and_value(obs)
        dist = self.action_dist.proba_distribution(mean, self.log_std)
        return values[:, None], dist.log_prob(actions), dist.entropy()

    def get_distribution(self, obs: Any) -> DiagGaussianDistribution:
        mean, _ = self.mean_and_value(obs, value=False)
        return self.action_dist.proba_distribution(mean, self.log_std)

    def predict_values(self, obs: Any) -> torch.Tensor:
        return self.mean_and_value(obs)[1][:, None]

    # ------------------------------------------------------------------ the actor and critic
    def mean_and_value(
        self, obs: Any, value: bool = True, features: StageFeatures | None = None
    ) -> tuple[torch.Tensor, torch.Tensor | None]:
        """Action mean ``(B, 4)`` in ``[-1, 1]`` units and value ``(B,)`` (None unless
        ``value``) from one batched tracker forward; ``features``: the frozen stages' outputs
        for these observations, recorded in the rollout (:attr:`frozen_stages`), so that only
        the trained stages run. Raises ``FloatingPointError`` on a non-finite mean or value
        (broken weights must stop a run, not be trained on)."""
        batch, _ = self.tracker.prepare(obs)
        self.frozen_stages.start_forward(batch[self.tracker.point_keys[0]].shape[0])
        executed_only = self._executed_gradient and torch.is_grad_enabled()
        inference = self.tracker.inference
        with self.frozen_stages.replaying(features):
            with torch.no_grad() if executed_only else contextlib.nullcontext():
                out = self.tracker(batch)
            # the observation's alone, so cached from the rollout like the frozen stages: the
            # scenes (with the point sets the still-target test computed) and the test itself
            observed = None  # what the still-target test and the re-ranking share
            if inference.hold_chamfer_m > 0 or inference.rerank_top_k > 0:
                observed = list(self.frozen_stages.call(_scenes, self.tracker, batch))
            keep = self.frozen_stages.call(keeps_box, self.tracker, batch, inference, observed)
        if executed_only:
            action = self._executed_action(batch, out, keep, observed)
        else:
            soft = None  # "best": the action tracker.act executes
            if self.action_mode == "soft":
                proposals, scores = out["proposals"], out["scores"]  # (B, P, 4), (B, P)
                weights = torch.softmax(scores / self.temperature, dim=1)
                soft = (weights[..., None] * proposals).sum(dim=1)
            # tracker.act's decision: no move where it keeps the box, the clip to max_action
            action = decide(
                self.tracker,
                batch,
                out,
                inference,
                action=soft,
                max_action=self.max_action,
                keep=keep,
                observed=observed,
            )
        mean = action / self.max_action.to(action.dtype)
        if not torch.isfinite(mean).all():
            raise FloatingPointError("TrackerPolicy: the tracker's action is NaN or inf")
        if not value:
            return mean, None
        if self.critic_kind == "fused":
            # detached: the critic's loss must not move the tracker's features
            v = self.value_head(self.tracker.summary_features(out).detach()).squeeze(-1)
        else:
            device = self.max_action.device
            v = self.value_head({k: obs[k].to(device, torch.float32) for k in _CRITIC_KEYS})
        if not torch.isfinite(v).all():
            raise FloatingPointError("TrackerPolicy: the value head's output is NaN or inf")
        return mean, v

    @property
    def _executed_gradient(self) -> bool:
        """Whether the forward runs without autograd and only the executed proposal's cluster
        is evaluated again with it (:meth:`_executed_action`): the head alone trains, on a
        matching tracker's best (or re-ranked) proposal, and the actor is not frozen."""
        return (
            self.executed_gradient_only
            and self.action_mode == "best"
            and self.train_parts == "head"
            and isinstance(self.tracker, MatchingTracker)
            and not self._actor_frozen
        )

    def _executed_action(
        self,
        batch: dict[str, torch.Tensor],
        out: dict[str, torch.Tensor],
        keep: torch.Tensor,
        observed: list[Scene] | None,
    ) -> torch.Tensor:
        """:func:`trackers.decision.decide`'s action on ``out`` (a forward without autograd;
        ``keep (B,)``: the still-target test), differentiable in the head's weights through
        the executed proposal alone: the decision's choice is piecewise constant, so the other
        proposals (~98 % of the head's work per state) add nothing to the gradient. The same
        action and gradient as the full head's, to float rounding (tests/test_rl.py)."""
        tracker, inference, a_max = self.tracker, self.tracker.inference, self.max_action
        with torch.no_grad():
            index = chosen_proposal(tracker, batch, out, inference, a_max, observed)
            index = torch.where(keep, torch.full_like(index, -1), index)
        proposal = clip_action(tracker.proposal_at(out, index.clamp(min=0)), a_max)
        action = torch.where((index >= 0)[:, None], proposal, torch.zeros_like(proposal))
        return decide(
            tracker,
            batch,
            out,
            inference,
            action=action,
            max_action=a_max,
            keep=keep,
            observed=observed,
        )

    def gaussian(self, mean: torch.Tensor) -> torch.distributions.Normal:
        """The action distribution around ``mean (..., 4)`` ([-1, 1] units): independent
        normals with the learned state-independent std (broadcast to ``mean``'s shape; a
        ``(B, 1, 4)`` mean scores ``(B, K, 4)`` samples). Differentiable in ``mean`` and the
        log-std."""
        return torch.distributions.Normal(mean, torch.exp(self.log_std))

    @property
    def action_std(self) -> torch.Tensor:
        """The exploration's standard deviation ``(4,)`` in [-1, 1] units."""
        return torch.exp(self.log_std)

    # ------------------------------------------------------------------ parameter control
    def _select_trainable(self) -> list[nn.Parameter]:
        parts = {
            **self.tracker.train_parts,
            "all": tuple(name for name, _ in self.tracker.named_children()),
        }
        if self.train_parts not in parts:
            raise ValueError(
                f"train_parts={self.train_parts!r}: tracker {self.tracker.name!r} has no such "
                f"part; its parts: {list(parts)}"
            )
        params: list[nn.Parameter] = []
        for name in parts[self.train_parts]:
            params.extend(getattr(self.tracker, name).parameters())
        return params

    def _frozen_prefix(self) -> list[nn.Module]:
        """The tracker's frozen stages that come before its first trained one (children in
        registration order, which is execution order): they run under ``no_grad`` (no gradient
        could pass through them to a trained stage, and the update's forward skips their
        autograd graph; P2B's fusion then takes its fast eval path, the one the rollout takes:
        identical log-probabilities in rollout and update), and their outputs can be cached
        from the rollout for the update (:mod:`training.rl.features`)."""
        prefix = []
        for _, child in self.tracker.named_children():
            if any(p.requires_grad for p in child.parameters()):
                break
            prefix.append(child)
        return prefix

    @property
    def trainable_tracker_parameters(self) -> list[nn.Parameter]:
        """The tracker parameters ``train_parts`` selects (frozen ones never change)."""
        return list(self._trainable)

    def freeze_actor(self, frozen: bool = True) -> None:
        """Stop (or restart) gradients into the actor (trainable tracker parts and log-std):
        a critic warm-up trains the value head alone."""
        for p in [*self._trainable, self.log_std]:
            p.requires_grad_(not frozen)
        self._actor_frozen = frozen

    @property
    def actor_frozen(self) -> bool:
        return self._actor_frozen


def _check_choice(name: str, value: Any, valid: tuple[str, ...]) -> None:
    if value not in valid:
        raise ValueError(f"{name} must be one of {list(valid)}, got {value!r}")


def _check_spaces(
    observation_space: spaces.Space, action_space: spaces.Space, tracker: Tracker
) -> None:
    if not isinstance(observation_space, spaces.Dict) or any(
        k not in observation_space.spaces or observation_space[k].shape != s
        for k, s in OBS_SHAPES.items()
    ):
        raise ValueError(
            f"TrackerPolicy needs the tracking env's Dict observation space with "
            f"{ {k: s for k, s in OBS_SHAPES.items()} }, got {observation_space}"
        )
    missing = [k for k in tracker.observation_keys if k not in observation_space.spaces]
    if missing:
        raise ValueError(
            f"tracker {tracker.name!r} reads the observation key(s) {missing}, which the env "
            f"does not serve: make it with TrackingEnv(..., observation_keys=(..., "
            f"{', '.join(repr(k) for k in missing)}))"
        )
    if (
        not isinstance(action_space, spaces.Box)
        or action_space.shape != (4,)
        or not np.allclose(action_space.low, -1.0)
        or not np.allclose(action_space.high, 1.0)
    ):
        raise ValueError(
            f"TrackerPolicy needs a Box(-1, 1, (4,)) action space: wrap the env in "
            f"gymnasium.wrappers.RescaleAction(env, -1.0, 1.0); got {action_space}"
        )
