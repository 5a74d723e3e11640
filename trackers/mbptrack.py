"""MBPTrack (Xu et al., "MBPTrack: Improving 3D Point Cloud Tracking with Memory Networks and Box
Priors", ICCV 2023): a memory of past frames with per-point target masks propagates the target
into the current frame, and a box-prior localisation network (BPLocNet) places the box.

Input (the env's opt-in ``memory`` keys, :mod:`envs.memory`; the tracker keeps no state between
calls): the current frame's ``search (B, N, 3)`` in the reference-box frame, ``size (B, 3)``,
``motion (B, 4)``, and the memory of the last ``M`` frames, ``memory (B, M, N_m, 4)`` (each
frame's points cropped around the box the agent predicted for it, in that box's frame, with a
target mask column: 1 inside the box scaled 1.25, else 0) and ``memory_boxes (B, M, 5)`` (those
boxes ``x, y, z, yaw`` in the current reference frame, and 1 for a slot that holds a frame with
points, 0 for an empty slot). Slots run oldest to newest; the tracker reads the newest
``memory_frames``.

Network (the reference code's ``mbptrack_kitti_car_cfg.yaml`` for ``"default"``):

1. DGCNN backbone (:class:`trackers.mbptrack_layers.DGCNNBackbone`) on every frame: seeds
   ``(N / 8, D)``;
2. the memory seeds moved into the current frame by their boxes; two memory transformer layers
   (:class:`~trackers.mbptrack_layers.MemoryTransformerLayer`): cross-attention from the current
   seeds to the memory seeds (values: features and embedded target masks), self-attention,
   feed-forward -> target features and mask embeddings of the current seeds;
3. BPLocNet (:class:`~trackers.mbptrack_layers.BPLocNet`): per-seed mask logit, coarse centre and
   objectness; 64 proposals by farthest-point sampling of the centres; box-prior sampling 3 x 3 x
   5 and point-to-reference aggregation; refined ``(x, y, z, yaw, score)`` per proposal.

Where this differs from the reference, and why: the reference keeps its memory as hidden state
(each layer's input features of past frames, and the masks it predicted for them); here the
memory comes from the observation, so every layer's memory features are computed from the memory
frame's backbone features, and the masks are the box priors of the agent's own boxes (exactly
the reference's first-frame mask for the given box). With no valid memory frame the current
frame is its own memory with the reference box's mask (the reference's first-frame case).

``act`` executes the best-scored proposal; where no seed's mask probability reaches
``missing_threshold`` (the target is missing) it repeats the last motion (``motion``), as the
reference does. Of :mod:`trackers.decision`'s inference settings it takes the still-target test
and the dead zone (they read only the template crops, the search and the action); not the
re-ranking, which would pick among raw proposals past the missing-target fallback.

Losses (per sample, batch means are the reference's batch losses): mask BCE
(0.2), centre MSE on target seeds (10), coarse and refined objectness BCE with positive weight 2
and 0.3 m labels (1, 1), box smooth-L1 on positive proposals with the yaw in degrees (1).
"""

from __future__ import annotations

import hashlib
import math
from collections import OrderedDict
from collections.abc import Mapping
from dataclasses import dataclass, field
from typing import Any, ClassVar

import torch
import torch.nn.functional as F

from trackers import ops
from trackers.base import Tracker, TrackerConfig, prepare_observation
from trackers.m2track import _to_tensor, from_box_frame
from trackers.mbptrack_layers import BPLocNet, DGCNNBackbone, MemoryTransformerLayer
from trackers.registry import register

__all__ = ["MEMORY_OPTION", "MBPTrack", "MBPTrackConfig", "prepare_memory_observation"]

#: How to make an env that serves the memory.
MEMORY_OPTION = (
    'TrackingEnv(..., observation_keys=(*OBSERVATION_KEYS, "memory", "memory_boxes"), '
    "memory_frames=M)"
)
#: The target mask's box scale (the reference's ``get_pcd_in_box_mask(..., scale=1.25)``).
MASK_SCALE = 1.25
#: A centre or proposal within this distance (m) of the target's centre is positive.
POSITIVE_RADIUS_M = 0.3
OBJECTNESS_POS_WEIGHT = 2.0
#: Frames whose backbone seeds the eval cache keeps (the memory and the current frame, with room
#: for a few interleaved episodes).
SEED_CACHE_FRAMES = 32


@dataclass
class MBPTrackConfig(TrackerConfig):
    """MBPTrack widths and memory (the reference configuration by default)."""

    edge_channels: list[list[int]] = field(
        default_factory=lambda: [[64, 64, 128], [128, 128, 128], [256, 256, 256]]
    )
    neighbours: int = 32
    ratios: list[int] = field(default_factory=lambda: [2, 4, 8])
    feat_dim: int = 128
    layers: int = 2
    heads: int = 1
    ffn_channels: int = 128
    dropout: float = 0.1
    proposals: int = 64
    box_grid: list[int] = field(default_factory=lambda: [3, 3, 5])
    aggr_neighbours: int = 8
    #: memory frames read at evaluation (the reference trains with 2 and evaluates with 3)
    memory_frames: int = 3
    missing_threshold: float = 0.2

    def __post_init__(self) -> None:
        super().__post_init__()
        self.edge_channels = [[int(c) for c in layer] for layer in self.edge_channels]
        self.ratios = [int(r) for r in self.ratios]
        self.box_grid = [int(n) for n in self.box_grid]
        if len(self.edge_channels) != len(self.ratios) or not all(self.edge_channels):
            raise ValueError(
                f"edge_channels {self.edge_channels} needs one non-empty width list per ratio "
                f"{self.ratios}"
            )
        ints = {
            "neighbours": self.neighbours,
            "feat_dim": self.feat_dim,
            "layers": self.layers,
            "heads": self.heads,
            "ffn_channels": self.ffn_channels,
            "proposals": self.proposals,
            "aggr_neighbours": self.aggr_neighbours,
            "memory_frames": self.memory_frames,
        }
        for key, value in [*ints.items(), *(("box_grid", v) for v in self.box_grid)]:
            if isinstance(value, bool) or not isinstance(value, int) or value < 1:
                raise ValueError(f"mbptrack config: {key} must be an integer >= 1, got {value!r}")
        if len(self.box_grid) != 3:
            raise ValueError(f"box_grid must be 3 sample counts (x, y, z), got {self.box_grid}")
        if not 0 <= self.dropout < 1 or not 0 <= self.missing_threshold <= 1:
            raise ValueError(
                f"dropout {self.dropout} must lie in [0, 1) and missing_threshold "
                f"{self.missing_threshold} in [0, 1]"
            )


def prepare_memory_observation(
    obs: Any, memory_frames: int, device: torch.device | str = "cpu"
) -> tuple[dict[str, torch.Tensor], bool]:
    """One observation or a batch -> (the :meth:`MBPTrack.forward` batch with the newest
    ``memory_frames`` slots, ``single``). A missing memory key is a ``KeyError`` naming the env
    option; a memory of fewer than ``memory_frames`` slots a ``ValueError`` naming both."""
    if isinstance(obs, Mapping):
        missing = [k for k in ("memory", "memory_boxes") if k not in obs]
        if missing:
            raise KeyError(
                f"MBPTrack needs the memory of past frames: the observation has no {missing} "
                f"(keys: {sorted(obs)}); make the env with {MEMORY_OPTION}"
            )
    batch, single = prepare_observation(obs, device)
    b = batch["search"].shape[0]
    for key, width in (("memory", 4), ("memory_boxes", 5)):
        t = _to_tensor(obs, key, device)
        t = t.unsqueeze(0) if single else t
        dims = 4 if key == "memory" else 3
        if t.dim() != dims or t.shape[0] != b or t.shape[-1] != width:
            want = "(M, N, 4)" if key == "memory" else "(M, 5)"
            raise ValueError(
                f"observation[{key!r}] has shape {tuple(obs[key].shape)}; expected {want} "
                f"(batched: (B, ...) with B = {b} as search)"
            )
        batch[key] = t
    m = batch["memory"].shape[1]
    if batch["memory_boxes"].shape[1] != m:
        raise ValueError(
            f"observation['memory_boxes'] has {batch['memory_boxes'].shape[1]} slots, "
            f"observation['memory'] {m}"
        )
    if m < memory_frames:
        raise ValueError(
            f"the observation's memory holds {m} frame(s); this mbptrack reads "
            f"memory_frames={memory_frames}: make the env with memory_frames >= {memory_frames} "
            f"({MEMORY_OPTION})"
        )
    batch["memory"] = batch["memory"][:, m - memory_frames :]
    batch["memory_boxes"] = batch["memory_boxes"][:, m - memory_frames :]
    return batch, single


@register("mbptrack")
class MBPTrack(Tracker):
    """MBPTrack: memory transformer + box-prior localisation (see the module doc)."""

    config_class = MBPTrackConfig
    default_loss_weights: ClassVar[dict[str, float]] = {
        "mask": 0.2,
        "coarse_objectness": 1.0,
        "objectness": 1.0,
        "bbox": 1.0,
        "center": 10.0,
    }
    _slim: ClassVar[dict[str, Any]] = {
        "edge_channels": [[32, 32, 64], [64, 64, 64], [64, 64, 64]],
        "neighbours": 16,
        "feat_dim": 64,
        "ffn_channels": 64,
        "proposals": 32,
    }
    sizes: ClassVar[dict[str, dict[str, Any]]] = {
        "default": {},
        "slim": _slim,
        # slim with less per-frame work (one memory layer, a 2 x 2 x 3 box prior, 4 and 8
        # neighbours): a batch-1 act at P2B's rate on CPU, where slim takes ~1.7x its time
        "light": {
            **_slim,
            "neighbours": 8,
            "layers": 1,
            "box_grid": [2, 2, 3],
            "aggr_neighbours": 4,
        },
    }
    #: the training-sample recipe (:mod:`training.memory_samples`), read by the trainer
    sample_recipe: ClassVar[str] = "memory"
    observation_keys: ClassVar[tuple[str, ...]] = ("memory", "memory_boxes")
    point_keys: ClassVar[tuple[str, ...]] = ("search",)
    inference_fields: ClassVar[tuple[str, ...]] = ("hold_chamfer_m", "min_motion_m")
    train_parts: ClassVar[dict[str, tuple[str, ...]]] = {"head": ("loc",)}
    #: DRCT's backbone tap (:func:`training.drct.tap_backbone`): the point backbone's attribute
    #: and its method that encodes one batch of clouds ``(F, N, 3)`` -> ``(xyz (F, S, 3),
    #: features (F, S, D))``; the search region (``F = B``), then the memory frames (``F = B M``,
    #: each sample's ``M`` frames consecutive) in training
    drct_backbone: ClassVar[tuple[str, str]] = ("backbone", "forward")

    def __init__(self, config: Any = None, **overrides: Any) -> None:
        super().__init__(config, **overrides)
        cfg = self.config
        d = cfg.feat_dim
        self.backbone = DGCNNBackbone(cfg.edge_channels, cfg.neighbours, cfg.ratios, d)
        self.transformer = torch.nn.ModuleList(
            MemoryTransformerLayer(d, cfg.heads, cfg.ffn_channels, cfg.dropout)
            for _ in range(cfg.layers)
        )
        self.loc = BPLocNet(d, cfg.box_grid, cfg.proposals, cfg.aggr_neighbours)
        #: frame bytes -> (backbone weight versions, seeds): :meth:`_cached_seeds`
        self._seed_cache: OrderedDict[bytes, tuple[list, tuple[torch.Tensor, ...]]] = OrderedDict()

    def _frame_seeds(
        self, clouds: torch.Tensor, generator: torch.Generator | None, stamp: list | None
    ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """Backbone seeds of frames ``clouds (F, N, 3)``: xyz ``(F, S, 3)``, features ``(F, S,
        D)``, indices into each cloud ``(F, S)``. Training: random point orders (batched). Eval:
        hash orders (order invariant); on the fast path one frame at a time through
        :meth:`_cached_seeds` (``stamp``: :meth:`_seed_stamp`, read once per forward), on the
        plain path batched."""
        if self.training:
            gen = generator if generator is not None else self.generator
            return self._seeds(clouds, ops.random_order(*clouds.shape[:2], gen, clouds.device))
        if not self.fast_eval:
            return self._seeds(clouds, ops.hash_order(clouds, int(self.config.sampling_seed)))
        parts = [self._cached_seeds(cloud[None], stamp) for cloud in clouds]
        return tuple(torch.cat(p) for p in zip(*parts, strict=True))

    def _seed_stamp(self) -> list | None:
        """The backbone weights' versions and addresses, the seed cache's check that they did
        not change; ``None`` where nothing is cached (training, the plain eval path, and under
        autograd, where cached tensors would carry no graph)."""
        if self.training or not self.fast_eval or torch.is_grad_enabled():
            return None
        return [(t._version, t.data_ptr()) for t in self._backbone_tensors]

    def _seeds(
        self, cloud: torch.Tensor, order: torch.Tensor, copies: bool = False
    ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """Backbone seeds of ``cloud (F, N, 3)`` taken in ``order (F, N)``: xyz, features,
        indices into the cloud (the seeds are the first points of the order); ``copies``: the
        backbone's one-cloud path that evaluates each distinct point once."""
        xyz, feat = self.backbone(ops.gather(cloud, order), copies=copies)
        return xyz, feat, order[:, : xyz.shape[1]]

    @property
    def _backbone_tensors(self) -> list[torch.Tensor]:
        """The backbone's parameters and buffers, read fresh (``.to`` replaces buffers) from each
        module's own dicts: a third of ``state_dict``'s cost, paid on every eval batch."""
        return [
            t
            for module in self.backbone.modules()
            for tensors in (module._parameters, module._buffers)
            for t in tensors.values()
            if t is not None
        ]

    def _cached_seeds(self, cloud: torch.Tensor, stamp: list | None) -> tuple[torch.Tensor, ...]:
        """The eval seeds of one frame ``(1, N, 3)``, from a cache keyed by the frame's bytes and
        ``stamp``, the backbone weights' versions and addresses: a frame's search region returns
        as memory in the next steps (:mod:`envs.memory`), so each frame goes through the backbone
        once. A pure speed-up: a hit returns the very tensors a miss computes (frames always run
        alone). ``stamp=None`` (under autograd: cached tensors carry no graph) computes."""
        seed = int(self.config.sampling_seed)
        if stamp is None:
            return self._seeds(cloud, ops.hash_order(cloud, seed), copies=True)
        key = hashlib.blake2b(cloud.cpu().numpy().tobytes(), digest_size=16).digest()
        hit = self._seed_cache.get(key)
        if hit is not None and hit[0] == stamp:
            self._seed_cache.move_to_end(key)
            return hit[1]
        seeds = self._seeds(cloud, ops.hash_order(cloud, seed), copies=True)
        self._seed_cache[key] = (stamp, seeds)
        if len(self._seed_cache) > SEED_CACHE_FRAMES:
            self._seed_cache.popitem(last=False)
        return seeds

    def forward_batch(
        self, batch: Mapping[str, torch.Tensor], generator: torch.Generator | None = None
    ) -> dict[str, torch.Tensor]:
        """``search (B, N, 3)``, ``size (B, 3)``, ``memory (B, M, N_m, 4)``, ``memory_boxes (B,
        M, 5)`` -> ``proposals (B, K, 4)`` ``(x, y, z, yaw)`` (m, rad, search frame), ``scores (B,
        K)`` (logits), ``mask_logits (B, S)``, ``center (B, S, 3)``, ``coarse_logits (B, S)``,
        ``proposal_xyz (B, K, 3)``, ``box_raw (B, K, 5)`` (yaw in degrees), ``seed_idx (B, S)``
        (into ``search``), ``Z (B, S, D)`` (the localisation features), ``motion (B, 4)`` (the
        batch's last motion: :meth:`best_action`'s fallback; only where the batch has one: the
        training samples of :mod:`training.memory_samples` carry none)."""
        search, size = batch["search"], batch["size"]
        memory, boxes = batch["memory"], batch["memory_boxes"]
        b, m, n_m = memory.shape[:3]
        mem_cloud = memory[..., :3].reshape(b * m, n_m, 3)
        stamp = self._seed_stamp()
        xyz, feat, idx = self._frame_seeds(search, generator, stamp)
        m_xyz, m_feat, m_idx = self._frame_seeds(mem_cloud, generator, stamp)
        s = m_xyz.shape[1]
        m_mask = torch.gather(memory[..., 3].reshape(b * m, n_m), 1, m_idx).reshape(b, m * s)
        # the memory seeds in the current frame: each frame's points sit in its box's frame
        m_box = boxes[..., :4].reshape(b * m, 4)
        m_xyz = from_box_frame(m_xyz, m_box).reshape(b, m * s, 3)
        m_feat = m_feat.reshape(b, m * s, -1)
        has_memory = boxes[..., 4] > 0.5  # (B, M)
        m_valid = has_memory.repeat_interleave(s, dim=1)
        # no frame in memory: the current frame with the reference box's mask stands in
        alone = ~has_memory.any(dim=1)
        half = size[:, None, :] * (MASK_SCALE / 2)
        own_mask = (xyz.abs() <= half).all(-1).to(xyz.dtype)
        keys_xyz = torch.cat([m_xyz, xyz], dim=1)
        keys_mask = torch.cat([m_mask, own_mask], dim=1)
        keys_valid = torch.cat([m_valid, alone[:, None].expand(-1, xyz.shape[1])], dim=1)
        x, mask_x = feat, self.transformer[0].initial_mask(feat)
        for layer in self.transformer:
            mem = torch.cat([layer.memory_features(m_feat), layer.memory_features(x)], dim=1)
            x, mask_x = layer(x, mask_x, xyz, mem, keys_xyz, keys_mask, keys_valid)
        loc = self.loc(xyz, x, mask_x, size)
        raw = loc["boxes"]
        proposals = torch.cat([raw[..., :3], torch.deg2rad(raw[..., 3:4])], dim=-1)
        out = {
            "proposals": proposals,
            "scores": raw[..., 4],
            "mask_logits": loc["mask_logits"],
            "center": loc["center"],
            "coarse_logits": loc["coarse_logits"],
            "proposal_xyz": loc["proposal_xyz"],
            "box_raw": raw,
            "seed_idx": idx,
            "Z": loc["feature"],
        }
        if "motion" in batch:
            out["motion"] = batch["motion"]
        return out

    def loss(
        self, outputs: dict[str, torch.Tensor], targets: Mapping[str, torch.Tensor]
    ) -> dict[str, torch.Tensor]:
        """Per-sample losses ``(B,)`` and their weighted ``total``. Targets: ``search_labels (B,
        N)`` (1: the search point lies in the ground-truth box scaled 1.25), ``box (B, 4)`` the
        ground truth ``(x, y, z, yaw)`` in the search frame (m, rad). Batch-normalised terms
        (centre over target seeds, box over positive proposals) carry their batch normaliser,
        so each term's batch mean is the reference's batch loss."""
        missing = [k for k in ("search_labels", "box") if k not in targets]
        if missing:
            raise KeyError(
                f"mbptrack targets are missing {missing}; expected search_labels (B, N) and "
                f"box (B, 4) (training.memory_samples)"
            )
        labels = torch.gather(targets["search_labels"].float(), 1, outputs["seed_idx"])
        gt = targets["box"].float()
        b = gt.shape[0]
        mask = F.binary_cross_entropy_with_logits(
            outputs["mask_logits"], labels, reduction="none"
        ).mean(1)
        center = outputs["center"]
        sq = (center - gt[:, None, :3]).square()
        center_term = (sq.mean(-1) * labels).sum(1) * b / (labels.sum() + 1e-6)
        pos_weight = center.new_tensor(OBJECTNESS_POS_WEIGHT)

        def objectness(points: torch.Tensor, logits: torch.Tensor) -> torch.Tensor:
            dist = torch.sqrt((points.detach() - gt[:, None, :3]).square().sum(-1) + 1e-6)
            positive = (dist < POSITIVE_RADIUS_M).to(logits.dtype)
            bce = F.binary_cross_entropy_with_logits(
                logits, positive, pos_weight=pos_weight, reduction="none"
            )
            return bce.mean(1), positive

        coarse, _ = objectness(center, outputs["coarse_logits"])
        refined, positive = objectness(outputs["proposal_xyz"], outputs["box_raw"][..., 4])
        gt_box = torch.cat([gt[:, :3], torch.rad2deg(gt[:, 3:4])], dim=-1)
        box_err = F.smooth_l1_loss(
            outputs["box_raw"][..., :4],
            gt_box[:, None].expand(-1, positive.shape[1], -1),
            reduction="none",
        ).mean(-1)
        bbox = (box_err * positive).sum(1) * b / (positive.sum() + 1e-6)
        terms = {
            "mask": mask,
            "coarse_objectness": coarse,
            "objectness": refined,
            "bbox": bbox,
            "center": center_term,
        }
        weights = self.config.loss_weights
        total = sum(weights[k] * terms[k] for k in weights)
        return {"total": total, **terms}

    def prepare(self, obs: Any) -> tuple[dict[str, torch.Tensor], bool]:
        """:func:`prepare_memory_observation` on this tracker's device."""
        return prepare_memory_observation(obs, self.config.memory_frames, self.device)

    def empty_observations(self, batch: Mapping[str, torch.Tensor]) -> torch.Tensor:
        """``(B,)`` True where the search region is empty (all zeros)."""
        return (batch["search"] == 0).flatten(1).all(1)

    def best_action(self, outputs: dict[str, torch.Tensor]) -> torch.Tensor:
        """The best-scored proposal ``(B, 4)``, its yaw wrapped to ``[-pi, pi)``; or the last
        motion ``outputs["motion"]`` where no seed's target probability reaches
        ``config.missing_threshold`` (the reference's missing target). Here, not in a
        ``choose_action`` override, so every caller of ``best_action`` (``act``, the RL policy,
        ``trackers.decision``) takes the same action."""
        best = super().best_action(outputs)
        yaw = torch.remainder(best[:, 3:] + math.pi, 2 * math.pi) - math.pi
        best = torch.cat([best[:, :3], yaw], dim=1)
        seen = outputs["mask_logits"].sigmoid().amax(dim=1) >= self.config.missing_threshold
        return torch.where(seen[:, None], best, outputs["motion"].to(best.dtype))

    @property
    def summary_channels(self) -> int:
        """``2 D``: the localisation features ``Z (B, S, D)`` max- and mean-pooled."""
        return 2 * int(self.config.feat_dim)
