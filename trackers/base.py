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
  an empty batch); the best-scored proposal, clipped to ``self.max_action`` (default the env's
  ``a_max = (5, 5, 3, pi)``); no move for an all-zero (empty) template or search; eval-mode
  ``inference_mode`` forwards (the module's train/eval mode is restored afterwards). It is
  built from hooks a tracker of another kind overrides (M2-Track does): :meth:`Tracker.prepare`,
  :meth:`Tracker.best_action`, :meth:`Tracker.empty_observations`, :meth:`Tracker.keeps_box`
  (where the box stays and the network does not run); RL fine-tuning
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

import math
from collections.abc import Mapping
from dataclasses import dataclass, field
from typing import Any, ClassVar

import numpy as np
import torch
from torch import nn

from envs.geometry import world_to_box_torch
from envs.observation import TEMPLATE_SCALE
from trackers import ops
from trackers.backbone import Backbone, BackboneConfig
from trackers.config import config_from_dict, config_to_dict
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

#: The env's default action bound ``a_max`` (metres, metres, metres, radians).
DEFAULT_MAX_ACTION = (5.0, 5.0, 3.0, math.pi)

#: Observation keys and their per-sample shapes (``envs.observation`` sizes).
OBS_SHAPES: dict[str, tuple[int, ...]] = {
    "template": (512, 3),
    "search": (1024, 3),
    "size": (3,),
    "motion": (4,),
}

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


#: Fewest points in a crop for the still-target test to decide anything.
HOLD_MIN_POINTS = 5
#: The still-target test and the re-ranking leave out points this close above the box's bottom
#: (m): the ground.
HOLD_GROUND_CLEARANCE_M = 0.2


#: The :class:`MatchingConfig` fields that act at inference only (the weights do not depend on
#: them).
INFERENCE_ONLY_FIELDS = ("hold_chamfer_m", "rerank_top_k", "rerank_margin_m")


@dataclass
class MatchingConfig(TrackerConfig):
    """Hyper-parameters of a matching tracker's backbone and voting head, and of its
    still-target test: with ``hold_chamfer_m > 0`` the tracker keeps the reference box (action
    0) where the current points inside it (scaled 1.25) lie within ``hold_chamfer_m`` metres
    (symmetric Chamfer distance) of the template's crops (:meth:`MatchingTracker.keeps_box`):
    the target has not moved against the sensor. Not in the papers: the matching head alone
    lets a parked car's box slide along it (docs/checkpoints.md, "Holding still targets").
    0 (default) is off.

    And of its re-ranking: with ``rerank_top_k > 0`` the executed box is, of the reference box
    and the ``rerank_top_k`` best-scored proposals, the one whose crop (scaled 1.25) lies
    nearest (symmetric Chamfer distance) to the first frame's crop, a proposal counting
    ``rerank_margin_m`` farther than it is (:meth:`MatchingTracker.choose_action`): the network
    moves the box only where the move matches the target better. Not in the papers either
    (docs/checkpoints.md, "Re-ranking by the first crop"). 0 (default) is off."""

    backbone: BackboneConfig = field(default_factory=BackboneConfig)
    head: HeadConfig = field(default_factory=HeadConfig)
    hold_chamfer_m: float = 0.0
    rerank_top_k: int = 0
    rerank_margin_m: float = 0.0

    def __post_init__(self) -> None:
        super().__post_init__()
        if not (math.isfinite(self.hold_chamfer_m) and self.hold_chamfer_m >= 0):
            raise ValueError(
                f"hold_chamfer_m = {self.hold_chamfer_m!r}: expected a finite distance >= 0 "
                f"(metres; 0 turns the still-target test off)"
            )
        if isinstance(self.rerank_top_k, bool) or not (
            isinstance(self.rerank_top_k, int) and self.rerank_top_k >= 0
        ):
            raise ValueError(
                f"rerank_top_k = {self.rerank_top_k!r}: expected an integer >= 0 (proposals; "
                f"0 turns the re-ranking off)"
            )
        if not (math.isfinite(self.rerank_margin_m) and self.rerank_margin_m >= 0):
            raise ValueError(
                f"rerank_margin_m = {self.rerank_margin_m!r}: expected a finite distance >= 0 "
                f"(metres)"
            )


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
            tensor = value.detach()
        else:
            arr = np.asarray(value)
            if arr.dtype.kind != "f":
                raise TypeError(
                    f"observation[{key!r}] has dtype {arr.dtype}; expected float32 "
                    f"of shape {shape} or (B, *{shape})"
                )
            tensor = torch.from_numpy(np.ascontiguousarray(arr))
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
        tensor = tensor.to(device=device, dtype=torch.float32)
        if not torch.isfinite(tensor).all():
            raise ValueError(f"observation[{key!r}] contains NaN or inf values")
        out[key] = tensor
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

    def __init__(self, config: Any = None, **overrides: Any) -> None:
        super().__init__()
        if config is None:
            config = {}
        if isinstance(config, self.config_class):
            config = config_to_dict(config)
        config = {**config, **overrides}
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

    def keeps_box(self, batch: Mapping[str, torch.Tensor]) -> torch.Tensor:
        """``(B,)`` True where :meth:`act` keeps the reference box (action 0) without running
        the network: by default the :meth:`empty_observations`."""
        return self.empty_observations(batch)

    def choose_action(
        self, batch: Mapping[str, torch.Tensor], outputs: dict[str, torch.Tensor]
    ) -> torch.Tensor:
        """The action ``(B, 4)`` :meth:`act` executes (before clipping to ``max_action``) from
        :meth:`forward`'s ``outputs`` on ``batch``: by default :meth:`best_action`."""
        return self.best_action(outputs)

    def clip_to_max_action(self, action: torch.Tensor) -> torch.Tensor:
        """``action (..., 4)`` clipped to ``[-max_action, max_action]`` per component."""
        a_max = torch.as_tensor(self.max_action, device=action.device, dtype=action.dtype)
        return torch.maximum(torch.minimum(action, a_max), -a_max)

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
        """:meth:`choose_action` as an action, 0 where :meth:`keeps_box`: one observation ->
        ``(4,)``, a batch -> ``(B, 4)`` (an empty batch -> an empty ``(0, 4)`` array)."""
        batch, single = self.prepare(obs)
        b = batch[self.point_keys[0]].shape[0]
        if b == 0:
            return np.zeros((0, 4), dtype=np.float32)
        keep = self.keeps_box(batch)
        action = torch.zeros(b, 4, device=self.device)
        if not keep.all():  # the network runs on the observations it decides
            moving = ~keep
            decided = {k: v[moving] if _batched(v, b) else v for k, v in batch.items()}
            action[moving] = self.choose_action(decided, self.eval_forward(decided)).to(
                action.dtype
            )
        action = self.clip_to_max_action(torch.nan_to_num(action, nan=0.0, posinf=0.0, neginf=0.0))
        result = action.cpu().numpy().astype(np.float32)
        return result[0] if single else result

    def extra_repr(self) -> str:
        return f"name={self.name!r}"


def _above_ground(points: torch.Tensor, size: torch.Tensor) -> torch.Tensor:
    """``(B, N)`` bool: the points ``(B, N, 3)`` (box frame; zero rows are padding) at least
    :data:`HOLD_GROUND_CLEARANCE_M` above the bottom of the box of ``size (B, 3)``."""
    floor = -size[:, None, 2] / 2 + HOLD_GROUND_CLEARANCE_M
    return (points != 0).any(-1) & (points[..., 2] > floor)


def _crop_mask(points: torch.Tensor, size: torch.Tensor) -> torch.Tensor:
    """``(B, N)`` bool: the points ``(B, N, 3)`` of :func:`_above_ground` inside the box scaled
    :data:`TEMPLATE_SCALE` (the template's crop of them)."""
    half = size[:, None, :] * (TEMPLATE_SCALE / 2)
    return (points.abs() <= half).all(-1) & _above_ground(points, size)


def _batched(value: Any, b: int) -> bool:
    return isinstance(value, torch.Tensor) and value.dim() > 0 and value.shape[0] == b


class MatchingTracker(Tracker):
    """Backbone -> fusion -> voting head (P2B, BAT, GPT differ only in the fusion).

    Subclasses implement :meth:`build_fusion` and :meth:`fuse` (and optionally
    :meth:`extra_losses`); the backbone and head come from ``config.backbone`` / ``config.head``.
    ``fused_channels`` is the width ``D`` of the fused search features ``Z (B, M_S, D)``.
    """

    config_class: ClassVar[type] = MatchingConfig
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

    def keeps_box(self, batch: Mapping[str, torch.Tensor]) -> torch.Tensor:
        """The empty observations and, with ``config.hold_chamfer_m > 0``, the still targets
        ``(B,)`` bool: the search points inside the reference box scaled 1.25 (the template's
        crop) lie within ``hold_chamfer_m`` (:func:`trackers.ops.chamfer_distance`) of both
        template crops, the previous frame's (it has not moved) and the first frame's (the box
        is still on the target, not on background it lost it to). Points less than
        :data:`HOLD_GROUND_CLEARANCE_M` above the box's bottom are left out (ground the crops
        share whether or not the target moves), and a crop of fewer than
        :data:`HOLD_MIN_POINTS` points decides nothing."""
        keep = self.empty_observations(batch)
        if self.config.hold_chamfer_m <= 0:
            return keep
        first, previous = self.template_crops(batch["template"])  # (B, P, 3) each
        size, search = batch["size"], batch["search"]
        in_box = _crop_mask(search, size)
        still = in_box.sum(1) >= HOLD_MIN_POINTS
        for crop in (previous, first):
            mask = _above_ground(crop, size)  # the env cropped it
            distance = ops.chamfer_distance(search, in_box, crop, mask)
            still &= (distance < self.config.hold_chamfer_m) & (mask.sum(1) >= HOLD_MIN_POINTS)
        return keep | still

    def choose_action(
        self, batch: Mapping[str, torch.Tensor], outputs: dict[str, torch.Tensor]
    ) -> torch.Tensor:
        """:meth:`best_action`, or with ``config.rerank_top_k = K > 0`` the re-ranked action
        ``(B, 4)``: of the reference box (action 0) and the ``K`` best-scored proposals (each
        clipped to ``max_action``), the box whose crop (search points inside it scaled 1.25,
        above the ground as in :meth:`keeps_box`) has the smallest Chamfer distance to the first
        frame's crop, a proposal's distance counted ``rerank_margin_m`` larger. A candidate
        whose crop has fewer than :data:`HOLD_MIN_POINTS` points is out; where the first crop
        has fewer, or no candidate is left, or a proposal is not finite, :meth:`best_action`
        stands. Differentiable in the chosen proposal (not in the choice)."""
        best = self.best_action(outputs)
        k = min(self.config.rerank_top_k, outputs["scores"].shape[1])
        if k == 0:
            return best
        b = best.shape[0]
        top = outputs["scores"].topk(k, dim=1).indices  # (B, K)
        proposals = outputs["proposals"][torch.arange(b, device=top.device)[:, None], top]
        candidates = torch.cat(  # (B, 1 + K, 4): the reference box first
            [torch.zeros_like(best)[:, None], self.clip_to_max_action(proposals)], dim=1
        )
        first, _ = self.template_crops(batch["template"])
        size, search = batch["size"], batch["search"]
        zeros = torch.zeros_like(candidates[..., :3])
        boxes = torch.cat([candidates[..., :3], zeros, candidates[..., 3:]], dim=-1)  # (B, 1+K, 7)
        # the search points in each candidate box's frame, (B (1 + K), N, 3)
        in_frames = world_to_box_torch(search[:, None].detach(), boxes.detach())
        in_frames = in_frames.reshape(b * (k + 1), -1, 3)
        padding = (search == 0).all(-1).repeat_interleave(k + 1, 0)  # zero before moving
        in_box = _crop_mask(in_frames, size.repeat_interleave(k + 1, 0)) & ~padding
        first_mask = _above_ground(first, size)
        distance = ops.chamfer_distance(
            in_frames,
            in_box,
            first.repeat_interleave(k + 1, dim=0),
            first_mask.repeat_interleave(k + 1, dim=0),
        ).reshape(b, k + 1)
        distance = torch.where(
            in_box.sum(1).reshape(b, k + 1) >= HOLD_MIN_POINTS, distance, math.inf
        )
        distance[:, 1:] += self.config.rerank_margin_m
        decides = (
            (first_mask.sum(1) >= HOLD_MIN_POINTS)
            & torch.isfinite(distance).any(1)
            & torch.isfinite(proposals).all(-1).all(-1)
        )
        chosen = candidates[torch.arange(b, device=top.device), distance.argmin(1)]
        return torch.where(decides[:, None], chosen, best)

    def template_crops(self, template: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """The first and the previous frame's crops ``(B, 256, 3)`` of ``template (B, 512,
        3)``, laid out by the env's ``template_mode`` ``"first_and_previous"`` (the default; see
        :attr:`env_options`); other modes do not keep the two apart, and the still-target test
        refuses them."""
        mode = self.env_options.get("template_mode", "first_and_previous")
        if mode != "first_and_previous":
            raise ValueError(
                f"{self.name}: hold_chamfer_m needs the first and previous crops apart in the "
                f"template (template_mode 'first_and_previous'); this tracker's env runs "
                f"template_mode {mode!r}"
            )
        half = template.shape[1] // 2
        return template[:, :half], template[:, half:]

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
