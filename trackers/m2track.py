"""M2-Track (Zheng et al., "Beyond 3D Siamese Tracking: A Motion-Centric Paradigm for 3D Single
Object Tracking in Point Clouds", CVPR 2022): segment the target in two consecutive frames and
regress its relative motion, no template matching.

Input (built inside :meth:`M2Track.forward_batch` from the observation, so the trainer and
``act`` feed the same thing): the previous frame's points ``previous_search (B, N_p, 3)`` and the
current frame's ``search (B, N_c, 3)``, both cropped around the reference box (the previous
prediction) enlarged by 1.25 plus 2 m and expressed in its frame, merged into one ``(B, N_p + N_c,
5)`` cloud of ``xyz``, a time channel (0 for the previous frame, 0.1 for the current one) and the
prior-targetness mask (previous frame: 1 inside the reference box scaled 1.25, 0 outside, or
0.8 / 0.2 when the reference box is itself a prediction rather than the ground truth; current
frame: 0.5, unknown). The reference box in its own frame is the box of ``size`` at the origin
with yaw 0, so the mask needs only ``xyz`` and ``size``.

Network (Open3DSOT's widths for ``"default"``):

1. segmentation PointNet on the merged cloud: per-point MLP ``[5, 64, 64, 64, 128, 1024]``,
   max-pool, the second layer's 64 channels concatenated with the pooled 1024, per-point MLP
   ``[1088, 512, 256, 128, 128]`` and a linear layer to 2 logits (background / target);
2. the points predicted as target (others zeroed), ``xyz`` + time, through a mini PointNet
   (per-point ``[4, 64, 128, 256, 512]``, max-pool, ``[512, 256]``) -> the motion feature
   ``(B, 256)``; three heads ``[256, 128, 128, k]``: the target motion ``(dx, dy, dz, dyaw)``
   from the previous to the current frame in the previous box's frame, a moving / static
   classification (a static target gets zero motion), and the refined previous box ``(x, y, z,
   yaw)``; the first-stage box is the refined previous box moved by the motion;
3. second stage: the previous frame's target points moved by the motion, merged with the current
   frame's, expressed in the first-stage box's frame, through a second mini PointNet (``[3, 64,
   128, 256, 512]``, ``[512, 256]``) and a head ``[256, 128, 128, 4]``: the offset of the final
   box from the first-stage box.

The final box ``(x, y, z, yaw)`` in the reference-box frame is the action (``proposals (B, 1,
4)``, ``scores (B, 1)``: one candidate). Every MLP layer is Linear -> BatchNorm -> ReLU
(:class:`trackers.layers.MLP`), heads end in a plain Linear.

Losses (Open3DSOT's M2-Track; per sample, their batch means are the published batch losses):
segmentation cross-entropy with class weights 0.5 / 2.0 (weight 0.1); motion-state
cross-entropy (0.1); smooth-L1 of the centre (weight 2) and of ``sin(yaw)`` (weight 10) for the
motion (moving samples only), the refined previous box, the first-stage box and the final box.
Targets: see :mod:`training.motion_samples`.

Box-aware enhancement (``box_aware=True``, off by default; Open3DSOT's KITTI configuration turns
it on): BAT's BoxCloud (Zheng et al., "Box-Aware Feature Enhancement for Single Object Tracking
on Point Clouds", ICCV 2021), each point's distances to the centre and the 8 corners of a box,
as 9 more input channels (previous frame: to the reference box; current frame: zeros); the
segmentation network also predicts each point's BoxCloud to its frame's ground-truth box
(smooth-L1, weight 1), and the predicted BoxCloud of the target points joins both mini
PointNets' inputs.
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import dataclass, field
from typing import Any, ClassVar

import numpy as np
import torch
import torch.nn.functional as F
from torch import nn

from trackers import ops
from trackers.base import Tracker, TrackerConfig
from trackers.layers import MLP, max_pool
from trackers.registry import register

__all__ = ["M2Track", "M2TrackConfig", "box_cloud", "motion_cloud", "prepare_motion_observation"]

#: The env option that adds the previous frame's points to the observation.
PREVIOUS_SEARCH_OPTION = 'TrackingEnv(..., observation_keys=(..., "previous_search"))'
#: Time channel of the previous and the current frame's points.
TIME_PREVIOUS, TIME_CURRENT = 0.0, 0.1
#: Prior-targetness mask: previous-frame points outside / inside the reference box scaled
#: ``MASK_SCALE``, when it is the ground truth and when it is a prediction; current frame.
MASK_GT = (0.0, 1.0)
MASK_PREDICTED = (0.2, 0.8)
MASK_CURRENT = 0.5
MASK_SCALE = 1.25
#: Segmentation cross-entropy class weights (background, target).
SEG_CLASS_WEIGHTS = (0.5, 2.0)


@dataclass
class M2TrackConfig(TrackerConfig):
    """M2-Track widths (Open3DSOT's by default)."""

    seg_channels: list[int] = field(default_factory=lambda: [64, 64, 64, 128, 1024])
    seg_head_channels: list[int] = field(default_factory=lambda: [512, 256, 128, 128])
    point_channels: list[int] = field(default_factory=lambda: [64, 128, 256, 512])
    hidden_channels: list[int] = field(default_factory=lambda: [512, 256])
    head_channels: list[int] = field(default_factory=lambda: [128, 128])
    box_aware: bool = False

    def __post_init__(self) -> None:
        super().__post_init__()
        for key in (
            "seg_channels",
            "seg_head_channels",
            "point_channels",
            "hidden_channels",
            "head_channels",
        ):
            value = [int(c) for c in getattr(self, key)]
            if not value or min(value) < 1:
                raise ValueError(
                    f"{key} must be a non-empty list of positive widths, got {getattr(self, key)!r}"
                )
            setattr(self, key, value)
        if len(self.seg_channels) < 3:
            raise ValueError(
                f"seg_channels needs at least 3 layers (the second one's features "
                f"are concatenated with the pooled last ones), got "
                f"{self.seg_channels}"
            )


class MiniPointNet(nn.Module):
    """Per-point MLP, max-pool over the points, MLP: ``(B, N, C) -> (B, D)``."""

    def __init__(self, in_channels: int, point: list[int], hidden: list[int]) -> None:
        super().__init__()
        self.point = MLP([in_channels, *point])
        self.hidden = MLP([point[-1], *hidden])

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return self.hidden(max_pool(self.point(x), 1))


class SegPointNet(nn.Module):
    """Per-point outputs ``(B, N, out)`` of a cloud ``(B, N, C)``: local (second-layer)
    features concatenated with the max-pooled global ones."""

    def __init__(
        self, in_channels: int, channels: list[int], head: list[int], out_channels: int = 2
    ) -> None:
        super().__init__()
        self.local = MLP([in_channels, *channels[:2]])
        self.glob = MLP(channels[1:])
        self.head = MLP([channels[1] + channels[-1], *head, out_channels], last_activation=False)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        local = self.local(x)
        pooled = max_pool(self.glob(local), 1)  # (B, C_g)
        # the head's first Linear on [local; pooled] = W_l local + W_g pooled: the pooled part
        # once per sample instead of once per point
        w, b = self.head.linear_params(0)
        c = local.shape[-1]
        pre = F.linear(local, w[:, :c], b) + F.linear(pooled, w[:, c:])[:, None, :]
        return self.head.forward_from(0, pre, fresh=True)


def _rot_z(yaw: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    return torch.cos(yaw), torch.sin(yaw)


def offset_boxes(ref: torch.Tensor, offset: torch.Tensor) -> torch.Tensor:
    """Boxes ``(B, 4)`` ``(x, y, z, yaw)`` moved by offsets ``(B, 4)`` in their own frame (the
    action convention): centre + R(yaw) (dx, dy, dz), yaw + dyaw (not wrapped)."""
    c, s = _rot_z(ref[:, 3])
    x = ref[:, 0] + c * offset[:, 0] - s * offset[:, 1]
    y = ref[:, 1] + s * offset[:, 0] + c * offset[:, 1]
    return torch.stack([x, y, ref[:, 2] + offset[:, 2], ref[:, 3] + offset[:, 3]], dim=-1)


def to_box_frame(points: torch.Tensor, box: torch.Tensor) -> torch.Tensor:
    """Points ``(B, N, 3)`` in the frame of boxes ``(B, 4)``."""
    c, s = _rot_z(box[:, 3])
    d = points - box[:, None, :3]
    x = c[:, None] * d[..., 0] + s[:, None] * d[..., 1]
    y = -s[:, None] * d[..., 0] + c[:, None] * d[..., 1]
    return torch.stack([x, y, d[..., 2]], dim=-1)


def from_box_frame(points: torch.Tensor, box: torch.Tensor) -> torch.Tensor:
    """Points ``(B, N, 3)`` given in the frame of boxes ``(B, 4)`` back to the outer frame."""
    c, s = _rot_z(box[:, 3])
    x = c[:, None] * points[..., 0] - s[:, None] * points[..., 1] + box[:, None, 0]
    y = s[:, None] * points[..., 0] + c[:, None] * points[..., 1] + box[:, None, 1]
    return torch.stack([x, y, points[..., 2] + box[:, None, 2]], dim=-1)


def box_cloud(points: torch.Tensor, boxes: torch.Tensor, size: torch.Tensor) -> torch.Tensor:
    """BAT's BoxCloud: distances ``(B, N, 9)`` of points ``(B, N, 3)`` to the centre and the 8
    corners of boxes ``(B, 4)`` ``(x, y, z, yaw)`` of ``size (B, 3)`` (``l, w, h``), in the
    nuScenes corner order."""
    signs = points.new_tensor(
        [
            [0, 0, 0],
            [1, 1, 1],
            [1, -1, 1],
            [1, -1, -1],
            [1, 1, -1],
            [-1, 1, 1],
            [-1, -1, 1],
            [-1, -1, -1],
            [-1, 1, -1],
        ]
    )
    keypoints = signs[None] * (0.5 * size[:, None, :])  # (B, 9, 3) in the box frame
    local = to_box_frame(points, boxes)
    return torch.linalg.vector_norm(local[:, :, None, :] - keypoints[:, None], dim=-1)


def motion_cloud(
    previous: torch.Tensor,
    current: torch.Tensor,
    size: torch.Tensor,
    prior_is_gt: torch.Tensor,
    box_aware: bool = False,
) -> torch.Tensor:
    """The merged two-frame cloud ``(B, N_p + N_c, 5)``: ``xyz``, time, prior-targetness mask
    (``box_aware``: ``(B, N_p + N_c, 14)``, plus the BoxCloud of the previous points to the
    reference box and zeros for the current ones).

    ``previous (B, N_p, 3)`` and ``current (B, N_c, 3)`` in the reference-box frame (m);
    ``size (B, 3)`` the box's ``l, w, h`` (m); ``prior_is_gt (B,)`` whether the reference box is
    the ground truth (mask 0 / 1) or a prediction (0.2 / 0.8).
    """
    half = size[:, None, :] * (0.5 * MASK_SCALE)
    inside = (previous.abs() <= half).all(dim=-1)  # the reference box: origin, yaw 0
    gt = prior_is_gt.to(previous.dtype)[:, None]
    low = gt * MASK_GT[0] + (1 - gt) * MASK_PREDICTED[0]
    high = gt * MASK_GT[1] + (1 - gt) * MASK_PREDICTED[1]
    mask_prev = torch.where(inside, high, low)
    b, n_p, n_c = previous.shape[0], previous.shape[1], current.shape[1]
    prev = torch.cat(
        [previous, previous.new_full((b, n_p, 1), TIME_PREVIOUS), mask_prev[..., None]], dim=-1
    )
    cur = torch.cat(
        [
            current,
            current.new_full((b, n_c, 1), TIME_CURRENT),
            current.new_full((b, n_c, 1), MASK_CURRENT),
        ],
        dim=-1,
    )
    if box_aware:
        reference = previous.new_zeros(b, 4)
        prev = torch.cat([prev, box_cloud(previous, reference, size)], dim=-1)
        cur = torch.cat([cur, current.new_zeros(b, n_c, 9)], dim=-1)
    return torch.cat([prev, cur], dim=1)


def _to_tensor(obs: Mapping[str, Any], key: str, device: torch.device | str) -> torch.Tensor:
    value = obs[key]
    if isinstance(value, torch.Tensor):
        if not value.is_floating_point():
            raise TypeError(f"observation[{key!r}] has dtype {value.dtype}; expected float32")
        tensor = value.detach()
    else:
        arr = np.asarray(value)
        if arr.dtype.kind != "f":
            raise TypeError(f"observation[{key!r}] has dtype {arr.dtype}; expected float32")
        tensor = torch.from_numpy(np.ascontiguousarray(arr))
    tensor = tensor.to(device=device, dtype=torch.float32)
    if not torch.isfinite(tensor).all():
        raise ValueError(f"observation[{key!r}] contains NaN or inf values")
    return tensor


def prepare_motion_observation(
    obs: Any, device: torch.device | str = "cpu"
) -> tuple[dict[str, torch.Tensor], bool]:
    """One observation or a batch -> (the :meth:`M2Track.forward` batch, ``single``).

    Reads ``search (N, 3)``, ``previous_search (N', C >= 3)`` (its first 3 columns as ``xyz``),
    ``size (3,)`` and ``motion (4,)`` (all zeros: the first step, whose reference box is the
    ground truth), each with an optional leading batch dimension. A missing ``previous_search``
    is a ``KeyError`` naming the env option that provides it.
    """
    if not isinstance(obs, Mapping):
        raise TypeError(f"observation must be a dict, got {type(obs).__name__}")
    if "previous_search" not in obs:
        raise KeyError(
            f"M2-Track needs the previous frame's points: the observation has no "
            f"'previous_search' (keys: {sorted(obs)}); make the env with "
            f"{PREVIOUS_SEARCH_OPTION}"
        )
    missing = [k for k in ("search", "size", "motion") if k not in obs]
    if missing:
        raise KeyError(
            f"observation is missing key(s) {missing}; M2-Track reads search (N, 3), "
            f"previous_search (N', C>=3), size (3,), motion (4,)"
        )
    search = _to_tensor(obs, "search", device)
    single = search.dim() == 2
    shapes = {"search": (None, 3), "previous_search": (None, None), "size": (3,), "motion": (4,)}
    out = {}
    batch = None
    for key, shape in shapes.items():
        raw = search if key == "search" else _to_tensor(obs, key, device)
        t = raw.unsqueeze(0) if single else raw
        ok = t.dim() == len(shape) + 1 and all(
            want is None or got == want for got, want in zip(t.shape[1:], shape, strict=True)
        )
        if key == "previous_search":
            ok = ok and t.shape[-1] >= 3
        if not ok:
            want = {
                "search": "(N, 3)",
                "previous_search": "(N', C>=3)",
                "size": "(3,)",
                "motion": "(4,)",
            }[key]
            raise ValueError(
                f"observation[{key!r}] has shape {tuple(raw.shape)}; expected "
                f"{want}" + (" or (B, ...) like search" if not single else " (search is unbatched)")
            )
        if batch is None:
            batch = t.shape[0]
        elif t.shape[0] != batch:
            raise ValueError(
                f"observation[{key!r}] has batch size {t.shape[0]}, search has {batch}"
            )
        out[key] = t
    return {
        "search": out["search"],
        "previous_search": out["previous_search"][..., :3],
        "size": out["size"],
        "prior_is_gt": (out["motion"] == 0).all(dim=-1).float(),
    }, single


@register("m2track")
class M2Track(Tracker):
    """M2-Track: motion-centric two-stage tracker (see the module doc)."""

    config_class = M2TrackConfig
    default_loss_weights: ClassVar[dict[str, float]] = {
        "seg": 0.1,
        "motion_state": 0.1,
        "center_motion": 2.0,
        "angle_motion": 10.0,
        "center_prev": 2.0,
        "angle_prev": 10.0,
        "center_aux": 2.0,
        "angle_aux": 10.0,
        "center": 2.0,
        "angle": 10.0,
        "box_cloud": 1.0,
    }
    sizes: ClassVar[dict[str, dict[str, Any]]] = {
        "default": {},
        "slim": {
            "seg_channels": [32, 32, 64, 128, 256],
            "seg_head_channels": [128, 64, 64, 64],
            "point_channels": [32, 64, 128, 256],
            "hidden_channels": [256, 128],
            "head_channels": [64, 64],
        },
    }
    #: the training-sample recipe (:mod:`training.motion_samples`), read by the trainer
    sample_recipe: ClassVar[str] = "motion"
    #: the observation keys ``act`` reads beyond the default contract
    observation_keys: ClassVar[tuple[str, ...]] = ("previous_search",)
    point_keys: ClassVar[tuple[str, ...]] = ("search", "previous_search")
    train_parts: ClassVar[dict[str, tuple[str, ...]]] = {
        "head": ("motion_head", "state_head", "prev_head", "box_head"),
    }

    def __init__(self, config: Any = None, **overrides: Any) -> None:
        super().__init__(config, **overrides)
        cfg = self.config
        bc = 9 if cfg.box_aware else 0
        if not cfg.box_aware:  # no BoxCloud regression: the term does not exist
            given = (config or {}) if isinstance(config, dict) else {}
            if "box_cloud" in {**given, **overrides}.get("loss_weights", {}):
                raise ValueError("m2track config: loss weight 'box_cloud' needs box_aware=True")
            cfg.loss_weights = {k: v for k, v in cfg.loss_weights.items() if k != "box_cloud"}
        self.seg = SegPointNet(5 + bc, cfg.seg_channels, cfg.seg_head_channels, 2 + bc)
        self.motion_net = MiniPointNet(4 + bc, cfg.point_channels, cfg.hidden_channels)
        d = cfg.hidden_channels[-1]
        self.motion_head = MLP([d, *cfg.head_channels, 4], last_activation=False)
        self.state_head = MLP([d, *cfg.head_channels, 2], last_activation=False)
        self.prev_head = MLP([d, *cfg.head_channels, 4], last_activation=False)
        self.box_net = MiniPointNet(3 + bc, cfg.point_channels, cfg.hidden_channels)
        self.box_head = MLP([d, *cfg.head_channels, 4], last_activation=False)

    def forward_batch(
        self, batch: Mapping[str, torch.Tensor], generator: torch.Generator | None = None
    ) -> dict[str, torch.Tensor]:
        """``search (B, N_c, 3)``, ``previous_search (B, N_p, 3)``, ``size (B, 3)``,
        ``prior_is_gt (B,)`` -> ``seg_logits (B, N_p + N_c, 2)``, ``motion (B, 4)``,
        ``motion_logits (B, 2)``, ``prev_box (B, 4)``, ``aux_box (B, 4)``, ``box (B, 4)``,
        ``feature (B, D)``, ``proposals (B, 1, 4)``, ``scores (B, 1)`` (boxes ``(x, y, z, yaw)``
        in the reference frame, the motion in the previous box's frame)."""
        previous, current = batch["previous_search"], batch["search"]
        box_aware = self.config.box_aware
        cloud = motion_cloud(previous, current, batch["size"], batch["prior_is_gt"], box_aware)
        fast = not self.training and self.fast_eval and cloud.shape[0] == 1
        inverse = None
        if fast:
            # one sample on the fast eval path: resampling repeats points, and every layer is
            # per point until a max-pool, so each distinct row is computed once (exact); the
            # time channel keeps the two frames' rows apart
            unique, inverse = ops.unique_rows(cloud[0])
            cloud = unique[None]
        is_prev = cloud[..., 3] == TIME_PREVIOUS  # (B, N)
        seg_out = self.seg(cloud)
        seg_logits = seg_out[..., :2]
        # hard assignment, as published: the target points go on, the others are zeroed
        target = (seg_logits[..., 1] > seg_logits[..., 0]).to(cloud.dtype)[..., None]
        masked = cloud[..., :4] * target
        if box_aware:  # the predicted BoxCloud of the target points joins both mini PointNets
            masked_bc = seg_out[..., 2:] * target
            masked = torch.cat([masked, masked_bc], dim=-1)
        # fast path: the zeroed (background) rows of a frame are all equal, so the max-pools
        # need only the target rows and one background row per frame (exact)
        rows = self._pooled_rows(target[..., 0], is_prev) if fast else None
        feature = self.motion_net(masked if rows is None else masked[:, rows])
        motion = self.motion_head(feature)
        motion_logits = self.state_head(feature)
        moving = (motion_logits[:, 1] > motion_logits[:, 0]).to(motion.dtype)[:, None]
        motion_used = motion * moving
        prev_box = self.prev_head(feature)
        aux_box = offset_boxes(prev_box, motion_used)
        # second stage: previous target points moved by the motion (in the previous box's
        # frame), merged with the current ones, in the first-stage box's frame
        xyz = masked[..., :3]
        moved = from_box_frame(offset_points(to_box_frame(xyz, prev_box), motion_used), prev_box)
        merged = torch.where(is_prev[..., None], moved, xyz)
        if box_aware:
            merged = torch.cat([merged, masked_bc], dim=-1)
        merged = merged if rows is None else merged[:, rows]
        merged = torch.cat([to_box_frame(merged[..., :3], aux_box), merged[..., 3:]], dim=-1)
        box = offset_boxes(aux_box, self.box_head(self.box_net(merged)))
        if inverse is not None:
            seg_out = seg_out[:, inverse]
        out = {
            "seg_logits": seg_out[..., :2],
            "motion": motion,
            "motion_logits": motion_logits,
            "prev_box": prev_box,
            "aux_box": aux_box,
            "box": box,
            "feature": feature,
            "proposals": box[:, None, :],
            "scores": box.new_zeros(box.shape[0], 1),
        }
        if box_aware:
            out["box_cloud"] = seg_out[..., 2:]
        return out

    @staticmethod
    def _pooled_rows(target: torch.Tensor, is_prev: torch.Tensor) -> torch.Tensor:
        """The indices ``(K,)`` of the target rows of ``target (1, N)`` plus the first
        background row of each frame (``is_prev (1, N)``): the background rows of a frame are
        equal in both mini PointNets' inputs."""
        keep = target[0] > 0
        for frame in (is_prev[0], ~is_prev[0]):
            background = (~keep & frame).nonzero()
            if len(background):
                keep[background[0, 0]] = True
        return keep.nonzero()[:, 0]

    def features(self, outputs: dict[str, torch.Tensor]) -> torch.Tensor:
        """The motion feature ``(B, D)`` (the first mini PointNet's output, which every
        first-stage head reads): what the decorrelation weighting (-W) decorrelates."""
        return outputs["feature"]

    def loss(
        self, outputs: dict[str, torch.Tensor], targets: Mapping[str, torch.Tensor]
    ) -> dict[str, torch.Tensor]:
        """Per-sample losses ``(B,)`` and their weighted ``total``.

        Targets: ``seg_labels (B, N_p + N_c)`` (1: target), ``box (B, 4)``, ``prev_box (B,
        4)`` (``x, y, z, yaw`` in the reference frame), ``motion_box (B, 4)`` (the current box in
        the previous box's frame), ``moving (B,)`` (1: the centre moved more than the motion
        threshold); with ``box_aware``, ``box_cloud (B, N_p + N_c, 9)`` each point's BoxCloud to
        its frame's ground-truth box. The batch-normalised terms of the paper (the
        class-weighted segmentation mean, the motion loss over moving samples) are written per
        sample with their batch normaliser, so the batch mean of each term is the published
        loss.
        """
        need = ("seg_labels", "box", "prev_box", "motion_box", "moving")
        missing = [k for k in need if k not in targets]
        if missing:
            raise KeyError(
                f"m2track targets are missing {missing}; expected {list(need)} "
                f"(training.motion_samples)"
            )
        labels = targets["seg_labels"].long()
        logits = outputs["seg_logits"]
        class_w = logits.new_tensor(SEG_CLASS_WEIGHTS)[labels]  # (B, N)
        ce = F.cross_entropy(logits.transpose(1, 2), labels, reduction="none")
        seg = (class_w * ce).sum(1) / class_w.sum(1).mean().clamp_min(1e-12)
        moving = targets["moving"].float()
        state = F.cross_entropy(outputs["motion_logits"], moving.long(), reduction="none")
        terms = {"seg": seg, "motion_state": state}
        motion_norm = moving.mean() + 1e-6
        for suffix, pred, target, weight in (
            ("motion", outputs["motion"], targets["motion_box"], moving / motion_norm),
            ("prev", outputs["prev_box"], targets["prev_box"], None),
            ("aux", outputs["aux_box"], targets["box"], None),
            ("", outputs["box"], targets["box"], None),
        ):
            target = target.float()
            center = F.smooth_l1_loss(pred[:, :3], target[:, :3], reduction="none").mean(1)
            angle = F.smooth_l1_loss(
                torch.sin(pred[:, 3]), torch.sin(target[:, 3]), reduction="none"
            )
            if weight is not None:
                center, angle = center * weight, angle * weight
            name = f"_{suffix}" if suffix else ""
            terms[f"center{name}"] = center
            terms[f"angle{name}"] = angle
        if self.config.box_aware:
            if "box_cloud" not in targets:
                raise KeyError("box_aware m2track targets need 'box_cloud' (B, N_p + N_c, 9)")
            terms["box_cloud"] = F.smooth_l1_loss(
                outputs["box_cloud"], targets["box_cloud"].float(), reduction="none"
            ).mean(dim=(1, 2))
        weights = self.config.loss_weights
        total = sum(weights[k] * terms[k] for k in weights)
        return {"total": total, **terms}

    def prepare(self, obs: Any) -> tuple[dict[str, torch.Tensor], bool]:
        """:func:`prepare_motion_observation` on this tracker's device."""
        return prepare_motion_observation(obs, self.device)

    def best_action(self, outputs: dict[str, torch.Tensor]) -> torch.Tensor:
        """The final box ``(B, 4)``, its yaw wrapped to ``[-pi, pi)`` (``act`` executes it)."""
        box = outputs["box"]
        yaw = torch.remainder(box[:, 3:] + math.pi, 2 * math.pi) - math.pi
        return torch.cat([box[:, :3], yaw], dim=1)

    def empty_observations(self, batch: Mapping[str, torch.Tensor]) -> torch.Tensor:
        """``(B,)`` True where both frames' crops are empty (all zeros)."""
        return (batch["search"] == 0).flatten(1).all(1) & (batch["previous_search"] == 0).flatten(
            1
        ).all(1)

    @property
    def summary_channels(self) -> int:
        """``D`` of the motion feature (:meth:`features`, the critic's summary as it is)."""
        return int(self.config.hidden_channels[-1])


def offset_points(points: torch.Tensor, offset: torch.Tensor) -> torch.Tensor:
    """Points ``(B, N, 3)`` in a box's frame moved with the box by ``offset (B, 4)`` (rotation
    ``dyaw`` about the box centre, then translation), in the same frame."""
    c, s = _rot_z(offset[:, 3])
    x = c[:, None] * points[..., 0] - s[:, None] * points[..., 1] + offset[:, None, 0]
    y = s[:, None] * points[..., 0] + c[:, None] * points[..., 1] + offset[:, None, 1]
    return torch.stack([x, y, points[..., 2] + offset[:, None, 2]], dim=-1)
