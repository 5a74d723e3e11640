"""Tracker base classes: :class:`Tracker` (any learned tracker) and :class:`MatchingTracker`
(backbone -> fusion -> voting head: P2B, BAT, GPT).

:class:`Tracker` contract (what ``make`` / ``save`` / ``load``, the trainer and the env rely on):

* a config dataclass ``config_class`` (a subclass of :class:`TrackerConfig`) built from keywords,
  JSON-serialisable (``trackers.config.config_to_dict``): ``save`` writes it next to the
  ``state_dict``, ``load`` rebuilds the tracker from it and loads the weights strictly;
* ``sizes``: named config presets (``"default"``: the papers' widths; ``"slim"``: reduced widths
  for CPU training), the ``--model-size`` choices of ``pointtrack train``;
* ``forward(batch, generator=None) -> dict``: ``batch`` holds ``template (B, 512, 3)``,
  ``search (B, 1024, 3)``, ``size (B, 3)``, ``motion (B, 4)`` float tensors (template points in
  their own box frame, search points in the reference-box frame); outputs at least
  ``proposals (B, P, 4)`` = ``(dx, dy, dz, dyaw)`` in the search frame (metres, radians) and
  ``scores (B, P)`` (logits, higher is better), every output with leading dimension ``B``;
  subclasses implement :meth:`Tracker.forward_batch`, and in eval mode ``forward`` runs it one
  sample at a time (:attr:`Tracker.batch_invariant`);
* ``loss(outputs, targets) -> dict`` of per-sample ``(B,)`` terms and ``total`` (weighted sum);
* :meth:`Tracker.features`: the ``(B, M, D)`` features the decorrelation weighting (-W) pools;
* ``act(obs) -> np.ndarray``: one observation -> ``(4,)``, a batch -> ``(B, 4)`` (``(0, 4)`` for
  an empty batch); the action :func:`trackers.decision.decide` takes under ``tracker.inference``
  (an :class:`~trackers.decision.InferenceConfig`: the still-target test and the re-ranking, off
  by default: the best-scored proposal), clipped to ``self.max_action`` (default the env's
  ``a_max = (5, 5, 3, pi)``); no move for an all-zero (empty) template or search; eval-mode
  ``inference_mode`` forwards (the module's train/eval mode is restored afterwards). It is built
  from hooks a tracker of another kind overrides (M2-Track does): :meth:`Tracker.prepare`,
  :meth:`Tracker.best_action`, :meth:`Tracker.empty_observations`; RL fine-tuning
  (:mod:`training.rl`) also reads :meth:`Tracker.summary_features` and ``train_parts``.

:class:`MatchingTracker` outputs ``Z (B, M_S, D)`` the fused search features, ``proposals``,
``scores``, ``votes (B, M_S, 3)``, ``vote_features``, ``seed_logits (B, M_S)``, ``seed_xyz``,
``seed_idx (B, M_S)`` (indices into ``search``), ``template_seed_xyz``, ``template_seed_idx
(B, M_T)``, ``proposal_centers``, ``box_raw``, plus tracker extras. Subclasses implement
``build_fusion(in_channels) -> (module, out_channels)`` and ``fuse`` (and optionally
``extra_losses``).

Sampling: in training mode the backbone keeps a random prefix of each cloud (a permutation from
``generator``, default the module's own ``self.generator`` seeded by ``config.sampling_seed``); in
eval mode a :func:`trackers.ops.hash_order` keyed by ``config.sampling_seed`` - deterministic, and
the outputs do not depend on the order of the input points.

Eval env: ``tracker.env_options`` names the ``TrackingEnv`` options (template composition,
search region) the tracker was trained with and must be evaluated with; ``{}`` means the env's
defaults. ``trackers.save`` records them, ``trackers.load`` restores them, and the eval paths
build their envs with them (``training.evaluate.env_options_for``).

Eval paths: ``tracker.fast_eval`` (default ``True``) selects the exact speed-ups (folded
BatchNorm, ragged groups, P2B's knot interpolation) over the plain path (the training
computation with BatchNorm running statistics); both are the same function to float rounding.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass, field
from typing import Any, ClassVar

import numpy as np
import torch
from torch import nn

from envs.spec import DEFAULT_MAX_ACTION, OBS_SHAPES
from trackers import decision, ops
from trackers.backbone import Backbone, BackboneConfig
from trackers.config import config_from_dict, config_to_dict
from trackers.decision import INFERENCE_FIELDS, InferenceConfig
from trackers.head import HeadConfig, VotingHead, head_losses
from trackers.layers import set_fast_eval

__all__ = [
    "DEFAULT_MAX_ACTION",
    "OBS_SHAPES",
    "SLIM_BACKBONE",
    "MatchingConfig",
    "MatchingTracker",
    "Tracker",
    "TrackerConfig",
    "prepare_observation",
]


#: The slim backbone of the shipped checkpoints (the ``"slim"`` size of P2B, BAT and GPT): about
#: 6x cheaper per training step than the papers' widths, same architecture and inputs; ragged
#: training (BatchNorm statistics over real ball-query hits only) saves another ~30 % on CPU.
SLIM_BACKBONE: dict[str, Any] = {
    "channels": [[32, 32, 64], [64, 64, 128], [128, 128, 128]],
    "out_channels": 128,
    "neighbours": 16,
    "ragged_train": True,
}


@dataclass
class TrackerConfig:
    """Hyper-parameters every learned tracker has: the eval sampling seed and loss weights
    (terms not given keep the tracker's ``default_loss_weights``)."""

    sampling_seed: int = 0
    loss_weights: dict[str, float] = field(default_factory=dict)

    def __post_init__(self) -> None:
        self.loss_weights = {str(k): float(v) for k, v in self.loss_weights.items()}


@dataclass
class MatchingConfig(TrackerConfig):
    """Hyper-parameters of a matching tracker's backbone and voting head (how it decides on
    their outputs is ``tracker.inference``: :mod:`trackers.decision`)."""

    backbone: BackboneConfig = field(default_factory=BackboneConfig)
    head: HeadConfig = field(default_factory=HeadConfig)


def prepare_observation(
    obs: Any, device: torch.device | str = "cpu"
) -> tuple[dict[str, torch.Tensor], bool]:
    """Validate one observation or a batch -> (float32 tensors ``(B, ...)`` on ``device``,
    ``single``). Raises ``KeyError``/``TypeError``/``ValueError`` naming the key and the expected
    shape or dtype.
    """
    if not isinstance(obs, Mapping):
        raise TypeError(
            f"observation must be a dict with keys {list(OBS_SHAPES)}, got {type(obs).__name__}"
        )
    missing = [k for k in OBS_SHAPES if k not in obs]
    if missing:
        raise KeyError(f"observation is missing key(s) {missing}; expected {_expected()}")
    out: dict[str, torch.Tensor] = {}
    single: bool | None = None
    batch: int | None = None
    for key, shape in OBS_SHAPES.items():
        value = obs[key]
        if isinstance(value, torch.Tensor):
            if not value.is_floating_point():
                raise TypeError(
                    f"observation[{key!r}] has dtype {value.dtype}; expected a float "
                    f"tensor (float32) of shape {shape} or (B, *{shape})"
                )
            checked = tensor = value.detach().to(dtype=torch.float32)
        else:
            arr = np.asarray(value)
            if arr.dtype.kind != "f":
                raise TypeError(
                    f"observation[{key!r}] has dtype {arr.dtype}; expected float32 "
                    f"of shape {shape} or (B, *{shape})"
                )
            # the values checked in numpy: a few microseconds, where torch's checks cost ~30 a
            # key in a batch-1 act
            if arr.dtype == np.float32:
                checked = np.ascontiguousarray(arr)
            else:  # a value beyond float32's range becomes inf, which the check below names
                with np.errstate(over="ignore"):
                    checked = np.ascontiguousarray(arr, dtype=np.float32)
            tensor = torch.from_numpy(checked)
        if tuple(tensor.shape) == shape:
            is_single = True
        elif tensor.dim() == len(shape) + 1 and tuple(tensor.shape[1:]) == shape:
            is_single = False
        else:
            raise ValueError(
                f"observation[{key!r}] has shape {tuple(tensor.shape)}; expected "
                f"{shape} or (B, *{shape})"
            )
        if single is None:
            single = is_single
        elif single != is_single:
            raise ValueError(
                f"observation[{key!r}] has shape {tuple(tensor.shape)}: mixes single "
                f"and batched entries; expected {shape} for one observation"
            )
        tensor = tensor.unsqueeze(0) if is_single else tensor
        if batch is None:
            batch = tensor.shape[0]
        elif tensor.shape[0] != batch:
            raise ValueError(
                f"observation[{key!r}] has batch size {tensor.shape[0]}, other keys have {batch}"
            )
        numpy = isinstance(checked, np.ndarray)
        if not bool(np.isfinite(checked).all() if numpy else torch.isfinite(checked).all()):
            raise ValueError(f"observation[{key!r}] contains NaN or inf values")
        if key == "size" and not bool((checked > 0).all()):  # a box needs l, w, h > 0 (metres)
            raise ValueError(
                f"observation['size'] must be > 0 (l, w, h in metres), got "
                f"{tensor[(tensor <= 0).any(dim=1)][0].tolist()}"
            )
        out[key] = tensor.to(device=device)
    return out, bool(single)


def _expected() -> str:
    return ", ".join(f"{k} {s}" for k, s in OBS_SHAPES.items())


class Tracker(nn.Module):
    """Base of the learned trackers (see the module doc for the contract).

    Subclasses set ``config_class``, ``default_loss_weights`` and ``sizes``, implement
    :meth:`forward_batch` and :meth:`loss`, and register with :func:`trackers.register`, which
    sets ``name``.
    """

    name: ClassVar[str] = "tracker"
    config_class: ClassVar[type] = TrackerConfig
    default_loss_weights: ClassVar[dict[str, float]] = {}
    #: config presets by model size: keyword overrides of the config defaults
    sizes: ClassVar[dict[str, dict[str, Any]]] = {"default": {}}
    #: the batch's point clouds ``(B, N, 3)``, checked by :meth:`forward`; the first gives ``B``
    point_keys: ClassVar[tuple[str, ...]] = ("template", "search")
    #: the env's opt-in observation keys this tracker reads (``TrackingEnv(observation_keys=)``)
    observation_keys: ClassVar[tuple[str, ...]] = ()
    #: RL fine-tuning's ``train_parts`` (:mod:`training.rl`) -> the child modules each trains;
    #: ``"all"`` (every child) is implied
    train_parts: ClassVar[dict[str, tuple[str, ...]]] = {}
    #: the :class:`~trackers.decision.InferenceConfig` fields this tracker may set away from
    #: their defaults: those of :mod:`trackers.decision`'s steps that fit its observations and
    #: outputs (all of them for a matching tracker; none by default)
    inference_fields: ClassVar[tuple[str, ...]] = ()

    def __init__(self, config: Any = None, **overrides: Any) -> None:
        super().__init__()
        if config is None:
            config = {}
        if isinstance(config, self.config_class):
            config = config_to_dict(config)
        config = {**config, **overrides}
        misplaced = sorted(set(config) & set(INFERENCE_FIELDS))
        if misplaced:
            raise ValueError(
                f"{self.name} config: {misplaced} are inference settings, not part of the "
                f"architecture: set tracker.inference = trackers.decision.InferenceConfig(...) "
                f"or pass trackers.load(..., inference=...)"
            )
        cfg = config_from_dict(self.config_class, config, where=f"{self.name} config")
        unknown = sorted(set(cfg.loss_weights) - set(self.default_loss_weights))
        if unknown:
            raise ValueError(
                f"{self.name} config: unknown loss term(s) {unknown}; valid: "
                f"{sorted(self.default_loss_weights)}"
            )
        # given weights override the paper's; terms not given keep the paper's weight
        cfg.loss_weights = {**self.default_loss_weights, **cfg.loss_weights}
        self.config = cfg
        self.generator = torch.Generator().manual_seed(int(cfg.sampling_seed))
        self.max_action = np.asarray(DEFAULT_MAX_ACTION, dtype=np.float32)
        #: eval forwards one sample at a time, so a sample's outputs do not depend on what else
        #: is in its batch (batched kernels differ in the last bit with the batch size, and the
        #: closed tracking loop amplifies that); ``False``: one batched eval forward (faster,
        #: especially on a GPU, but not batch-invariant). Training is always batched.
        self.batch_invariant = True
        self._fast_eval = True
        #: the ``TrackingEnv`` options this tracker must be evaluated with (keys in
        #: ``trackers.registry.ENV_OPTION_KEYS``; ``{}``: the env's defaults), set from the
        #: training config and carried by ``trackers.save`` / ``trackers.load``
        self.env_options: dict[str, Any] = {}
        self._inference = InferenceConfig()

    @property
    def inference(self) -> InferenceConfig:
        """How :meth:`act` (and the RL policy) decide on the network's outputs
        (:mod:`trackers.decision`); saved in the checkpoint's metadata, restored by
        ``trackers.load`` (which may override it)."""
        return self._inference

    @inference.setter
    def inference(self, config: InferenceConfig) -> None:
        if not isinstance(config, InferenceConfig):
            raise TypeError(
                f"{self.name}: tracker.inference must be a trackers.decision.InferenceConfig, "
                f"got {type(config).__name__}"
            )
        default = InferenceConfig()
        unfit = [
            f
            for f in INFERENCE_FIELDS
            if getattr(config, f) != getattr(default, f) and f not in self.inference_fields
        ]
        if unfit:
            raise ValueError(
                f"{self.name}: InferenceConfig field(s) {unfit} do not fit this tracker's "
                f"observations and outputs; it may set only {list(self.inference_fields)} "
                f"away from their defaults, got {config}"
            )
        self._inference = config

    @property
    def fast_eval(self) -> bool:
        """Eval on the fast path (the default) or on the plain path (``False``): the one switch
        for every submodule's exact speed-ups; training is unaffected."""
        return self._fast_eval

    @fast_eval.setter
    def fast_eval(self, enabled: bool) -> None:
        self._fast_eval = bool(enabled)
        for sub in self.children():
            set_fast_eval(sub, enabled)

    @property
    def device(self) -> torch.device:
        return next(self.parameters()).device

    def forward(
        self, batch: Mapping[str, torch.Tensor], generator: torch.Generator | None = None
    ) -> dict[str, torch.Tensor]:
        """:meth:`forward_batch`, one sample at a time in eval mode (:attr:`batch_invariant`)."""
        for key in self.point_keys:
            value = batch[key]
            if value.dim() != 3 or value.shape[-1] != 3:
                raise ValueError(
                    f"batch[{key!r}] has shape {tuple(value.shape)}; expected "
                    f"(B, {OBS_SHAPES.get(key, ('N',))[0]}, 3)"
                )
        b = batch[self.point_keys[0]].shape[0]
        if self.training or not self.batch_invariant or b <= 1:
            return self.forward_batch(batch, generator)
        parts = [
            self.forward_batch(
                {k: v[i : i + 1] if _batched(v, b) else v for k, v in batch.items()}, generator
            )
            for i in range(b)
        ]
        return {k: torch.cat([p[k] for p in parts]) for k in parts[0]}

    def forward_batch(
        self, batch: Mapping[str, torch.Tensor], generator: torch.Generator | None = None
    ) -> dict[str, torch.Tensor]:  # pragma: no cover - abstract
        """The batched forward (see the module doc for inputs and outputs)."""
        raise NotImplementedError

    def loss(
        self, outputs: dict[str, torch.Tensor], targets: Mapping[str, torch.Tensor]
    ) -> dict[str, torch.Tensor]:  # pragma: no cover - abstract
        """Per-sample losses ``(B,)``: the named terms and their weighted ``total``."""
        raise NotImplementedError

    def features(self, outputs: dict[str, torch.Tensor]) -> torch.Tensor:
        """The per-sample features ``(B, M, D)`` or ``(B, D)`` that the decorrelation weighting
        (-W, :mod:`training.weighting`) decorrelates; by default the fused features ``Z``."""
        if "Z" not in outputs:
            raise KeyError(
                f"{self.name}: outputs have no 'Z'; override Tracker.features to "
                f"say which output the sample weighting decorrelates"
            )
        return outputs["Z"]

    def eval_forward(self, batch: Mapping[str, torch.Tensor]) -> dict[str, torch.Tensor]:
        """One eval-mode :meth:`forward` (the module's train / eval mode is restored after)."""
        if not self.training:  # the usual case: toggling walks every submodule (~10 % of act)
            return self.forward(batch)
        was_training = self.training
        self.eval()
        try:
            return self.forward(batch)
        finally:
            self.train(was_training)

    def prepare(self, obs: Any) -> tuple[dict[str, torch.Tensor], bool]:
        """One observation or a batch (arrays or tensors) -> (the :meth:`forward` batch on this
        tracker's device, ``single``); errors name the key and the expected shape."""
        return prepare_observation(obs, self.device)

    def best_action(self, outputs: dict[str, torch.Tensor]) -> torch.Tensor:
        """The best-scored proposal ``(B, 4)`` (differentiable in the proposals)."""
        best = outputs["scores"].argmax(dim=1)
        return outputs["proposals"][torch.arange(len(best), device=best.device), best]

    def empty_observations(self, batch: Mapping[str, torch.Tensor]) -> torch.Tensor:
        """``(B,)`` True where the observation holds nothing to act on (an all-zero template or
        search): the tracker does not move there."""
        return (batch["template"] == 0).flatten(1).all(1) | (batch["search"] == 0).flatten(1).all(1)

    def summary_features(self, outputs: dict[str, torch.Tensor]) -> torch.Tensor:
        """One feature vector per sample ``(B, summary_channels)`` for heads that read the
        tracker's state (the RL critic): :meth:`features` ``(B, M, D)`` max- and mean-pooled
        over the seeds, or ``(B, D)`` features as they are."""
        z = self.features(outputs)
        return z if z.dim() == 2 else torch.cat([z.amax(dim=1), z.mean(dim=1)], dim=-1)

    @property
    def summary_channels(self) -> int:  # pragma: no cover - abstract
        """Width of :meth:`summary_features`."""
        raise NotImplementedError

    @torch.inference_mode()  # no autograd bookkeeping at all: ~6-8 % faster than no_grad
    def act(self, obs: Any) -> np.ndarray:
        """The action :func:`trackers.decision.decide` takes under :attr:`inference` (0 where
        the tracker keeps the box: the network runs only on the other observations; a
        non-finite action: 0): one observation -> ``(4,)``, a batch -> ``(B, 4)`` (an empty
        batch -> an empty ``(0, 4)`` array)."""
        batch, single = self.prepare(obs)
        b = batch[self.point_keys[0]].shape[0]
        if b == 0:
            return np.zeros((0, 4), dtype=np.float32)
        inference = self.inference
        observed = None  # what the still-target test and the re-ranking share
        if inference.hold_chamfer_m > 0 or inference.rerank_top_k > 0:
            observed = decision.scenes(self, batch)
        keep = decision.keeps_box(self, batch, inference, observed)
        moving = (~keep).nonzero()[:, 0]
        if len(moving) == b:  # every observation moves (batch-1 act, mostly): no gathers
            outputs = self.eval_forward(batch)
            action = decision.decide(self, batch, outputs, inference, keep=keep, observed=observed)
        else:
            action = torch.zeros(b, 4, device=self.device)
            if len(moving):  # the network runs only on the observations it decides
                decided = {k: v[moving] if _batched(v, b) else v for k, v in batch.items()}
                if observed is not None:
                    observed = [observed[i] for i in moving.tolist()]
                outputs = self.eval_forward(decided)
                action[moving] = decision.decide(
                    self, decided, outputs, inference, keep=keep[moving], observed=observed
                ).to(action.dtype)
        action = torch.nan_to_num(action, nan=0.0, posinf=0.0, neginf=0.0)
        result = action.cpu().numpy().astype(np.float32)
        return result[0] if single else result

    def extra_repr(self) -> str:
        return f"name={self.name!r}"


def _batched(value: Any, b: int) -> bool:
    return isinstance(value, torch.Tensor) and value.dim() > 0 and value.shape[0] == b


class MatchingTracker(Tracker):
    """Backbone -> fusion -> voting head (P2B, BAT, GPT differ only in the fusion).

    Subclasses implement :meth:`build_fusion` and :meth:`fuse` (and optionally
    :meth:`extra_losses`); the backbone and head come from ``config.backbone`` / ``config.head``.
    ``fused_channels`` is the width ``D`` of the fused search features ``Z (B, M_S, D)``.
    """

    config_class: ClassVar[type] = MatchingConfig
    inference_fields: ClassVar[tuple[str, ...]] = INFERENCE_FIELDS
    train_parts: ClassVar[dict[str, tuple[str, ...]]] = {
        "head": ("head",),
        "fusion+head": ("fusion", "head"),
    }

    def __init__(self, config: Any = None, **overrides: Any) -> None:
        super().__init__(config, **overrides)
        self.backbone = Backbone(self.config.backbone)
        self.fusion, self.fused_channels = self.build_fusion(self.backbone.out_channels)
        self.head = VotingHead(self.fused_channels, self.config.head)

    @property
    def summary_channels(self) -> int:
        """``2 D``: ``Z (B, M_S, D)`` max- and mean-pooled."""
        return 2 * self.fused_channels

    def build_fusion(
        self, in_channels: int
    ) -> tuple[nn.Module, int]:  # pragma: no cover - abstract
        """The fusion module for backbone features of ``in_channels`` and its output channels."""
        raise NotImplementedError

    def fuse(
        self,
        t_xyz: torch.Tensor,
        t_feat: torch.Tensor,
        s_xyz: torch.Tensor,
        s_feat: torch.Tensor,
        batch: dict[str, torch.Tensor],
    ) -> tuple[torch.Tensor, dict[str, torch.Tensor]]:  # pragma: no cover - abstract
        """Seeds ``(B, M_T, 3)``, ``(B, M_T, D)``, ``(B, M_S, 3)``, ``(B, M_S, D)`` -> ``Z (B,
        M_S, D')`` and extra outputs (each with leading dimension ``B``)."""
        raise NotImplementedError

    def extra_losses(
        self,
        outputs: dict[str, torch.Tensor],
        targets: dict[str, torch.Tensor],
        seed_labels: torch.Tensor,
    ) -> dict[str, torch.Tensor]:
        """Tracker-specific per-sample loss terms ``(B,)`` (none by default)."""
        return {}

    def sampling_orders(
        self, template: torch.Tensor, search: torch.Tensor, generator: torch.Generator | None
    ) -> tuple[torch.Tensor, torch.Tensor]:
        """Point orders for the backbone: random in training, hash-based in eval."""
        if self.training:
            gen = generator if generator is not None else self.generator
            return (
                ops.random_order(template.shape[0], template.shape[1], gen, template.device),
                ops.random_order(search.shape[0], search.shape[1], gen, search.device),
            )
        seed = int(self.config.sampling_seed)
        order_t, order_s = ops.hash_orders([template, search], [seed, seed + 1])
        return order_t, order_s

    def forward_batch(
        self, batch: Mapping[str, torch.Tensor], generator: torch.Generator | None = None
    ) -> dict[str, torch.Tensor]:
        template, search = batch["template"], batch["search"]
        order_t, order_s = self.sampling_orders(template, search, generator)
        (t_xyz, t_feat, t_idx), (s_xyz, s_feat, s_idx) = self.backbone.forward_many(
            [template, search], [order_t, order_s]
        )
        z, extra = self.fuse(t_xyz, t_feat, s_xyz, s_feat, dict(batch))
        out = self.head(s_xyz, z)
        out.update(
            Z=z,
            seed_xyz=s_xyz,
            seed_idx=s_idx,
            template_seed_xyz=t_xyz,
            template_seed_idx=t_idx,
            **extra,
        )
        return out

    def proposal_at(self, outputs: dict[str, torch.Tensor], index: torch.Tensor) -> torch.Tensor:
        """``outputs["proposals"]`` at ``index (B,)`` -> ``(B, 4)``, the head run again on its
        inputs for that proposal alone (:meth:`trackers.head.VotingHead.proposal_at`): a
        gradient through the head's weights for the executed proposal only."""
        return self.head.proposal_at(outputs["seed_xyz"], outputs["Z"], outputs["votes"], index)

    def loss(
        self, outputs: dict[str, torch.Tensor], targets: Mapping[str, torch.Tensor]
    ) -> dict[str, torch.Tensor]:
        """Per-sample losses ``(B,)``: the head's terms, :meth:`extra_losses` and their
        weighted ``total``."""
        if "search_box" not in targets or "search_labels" not in targets:
            raise KeyError("targets need 'search_box' (B, 7) and 'search_labels' (B, N_S)")
        seed_labels = torch.gather(targets["search_labels"].float(), 1, outputs["seed_idx"])
        terms = head_losses(outputs, targets["search_box"].float(), seed_labels, self.config.head)
        terms.update(self.extra_losses(outputs, dict(targets), seed_labels))
        weights = self.config.loss_weights
        total = sum(weights[k] * terms[k] for k in weights)
        return {"total": total, **terms}
