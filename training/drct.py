"""DRCT: dual-branch training with domain randomisation and local geometric contrast, after Zhao,
Liu, Tian and Han, *Robust Single Object Tracking in LiDAR Point Clouds under Adverse Weather
Conditions* (Sec. V) — our own implementation for P2B, BAT and GPT.

* **Primary branch**: the tracker being trained, on the clean sample. It is the only branch kept:
  checkpoints' ``model`` and every export hold its weights alone.
* **Auxiliary branch**: sees the domain-randomised sample (Algorithm 1,
  :func:`envs.weather.domain_randomize`: noise points, dropped points, jitter; applied to the
  template's two halves and to the search region separately, per sample, and resampled back to
  the fixed sizes; labels follow their points, added noise points are background). It runs the
  whole tracker (backbone -> fusion -> head) and is trained by the tracking loss on that sample.

  - ``variant="asymmetric"`` (DRCT): a copy of the primary tracker at the start of training, with
    an extra feed-forward network (FFN) after its backbone.
  - ``variant="siamese"`` (the Fig. 7 ablation): the primary tracker itself (shared parameters),
    no FFN.

* **Local geometric contrast** (Eq. 4-5): the key points ``C`` are the auxiliary backbone's
  down-sampled points (its seeds). For each ``C_i`` the auxiliary feature ``F~_i`` is the max
  pool of the auxiliary seed features over the ball query of ``C_i`` among the auxiliary seeds
  (radius ``radius_m``, at most ``neighbours`` hits, Eq. 4); the primary feature ``F~_i`` is the
  max pool of the primary seed features over the ``neighbours`` nearest primary seeds of ``C_i``
  (the paper's text: "K nearest neighbor features centered on C"). The loss is
  ``mean_i ||F~aux_i - F~_i||`` (Euclidean norm, not squared, Eq. 5), per sample, averaged over
  the template and the search region. The auxiliary side is detached by default
  (``detach_aux``): knowledge flows from the auxiliary branch to the primary one.
* **Objective** per sample: ``L_track(primary) + aux_weight * L_track(aux) +
  contrast_weight * L_contrast``; both branches train jointly (one optimizer). The per-sample
  total plugs into the trainer's weighting (``-W`` sample weights, SAM) unchanged.

The paper leaves the loss weight, the neighbourhood size, the FFN and the randomisation
amounts open; our choices (config fields of :class:`training.config.TrainConfig`, documented in
docs/weather.md) are the defaults of :class:`DRCTConfig`.

The backbone features are read through the tracker's ``backbone`` attribute (a
:class:`trackers.backbone.Backbone`): for the duration of one forward, :func:`tap_backbone`
wraps that instance's public ``forward_many`` (which ``Backbone.forward`` delegates to), records
its ``(xyz, features)`` per cloud and, on the auxiliary branch, applies the FFN to the features
it returns. Nothing is changed on the module outside that window, so state dicts and exports are
untouched.
"""

from __future__ import annotations

import contextlib
import copy
from collections.abc import Callable, Iterator, Mapping
from dataclasses import dataclass, field

import numpy as np
import torch
from torch import nn

from envs.weather.randomization import DomainRandomization
from trackers import ops
from trackers.backbone import Backbone

__all__ = [
    "DRCT",
    "DRCT_VARIANTS",
    "DRCTConfig",
    "DomainRandomizedTraining",
    "FeedForward",
    "local_geometric_contrast",
    "randomize_batch",
    "tap_backbone",
]

DRCT_VARIANTS: tuple[str, ...] = ("asymmetric", "siamese")
_NORM_EPS = 1e-12  # inside the square root: a finite gradient where both features coincide


@dataclass(frozen=True)
class DRCTConfig:
    """DRCT hyper-parameters (see the module docstring; ``docs/weather.md`` for the choices)."""

    variant: str = "asymmetric"
    contrast_weight: float = 0.01
    aux_weight: float = 1.0
    radius_m: float = 0.7
    neighbours: int = 8
    detach_aux: bool = True
    ffn_ratio: float = 2.0
    randomization: DomainRandomization = field(default_factory=DomainRandomization)
    seed: int = 0

    def __post_init__(self) -> None:
        if self.variant not in DRCT_VARIANTS:
            raise ValueError(
                f"unknown DRCT variant {self.variant!r}; valid variants: {', '.join(DRCT_VARIANTS)}"
            )
        if not self.contrast_weight >= 0 or not self.aux_weight >= 0:
            raise ValueError(
                f"DRCT loss weights must be >= 0; got contrast_weight="
                f"{self.contrast_weight}, aux_weight={self.aux_weight}"
            )
        if not self.radius_m > 0:
            raise ValueError(f"DRCT radius_m must be > 0; got {self.radius_m}")
        if self.neighbours < 1:
            raise ValueError(f"DRCT neighbours must be >= 1; got {self.neighbours}")
        if not self.ffn_ratio > 0:
            raise ValueError(f"DRCT ffn_ratio must be > 0; got {self.ffn_ratio}")


# --------------------------------------------------------------------------- randomisation


def _randomize_cloud(
    points: np.ndarray, rng: np.random.Generator, dr: DomainRandomization
) -> np.ndarray:
    """Algorithm 1 on one cloud ``(N, 3)`` resampled back to ``N`` points -> the source index
    ``(N,)`` of every output point in ``points`` (``-1``: an added noise point) and the points.

    An all-zero cloud (an empty crop) is left as it is. Fewer points than ``N`` are padded by
    repeating random ones (as the env pads small crops), more are subsampled without
    replacement."""
    n = len(points)
    if n == 0 or not points.any():
        return np.arange(n), points
    out, src = dr.randomize_with_source(points, rng)
    m = len(out)
    if m == n:  # also the skipped case (Algorithm 1's p_skip): the sample exactly as it was
        return src, out
    if m > n:
        pick = np.sort(rng.choice(m, size=n, replace=False))
    else:
        pick = np.concatenate([np.arange(m), rng.integers(0, m, size=n - m)])
    return src[pick], out[pick]


def randomize_batch(
    batch: Mapping[str, torch.Tensor],
    targets: Mapping[str, torch.Tensor],
    rng: np.random.Generator,
    dr: DomainRandomization,
) -> tuple[dict[str, torch.Tensor], dict[str, torch.Tensor]]:
    """Domain-randomised copies of a training batch and its targets.

    ``batch["template"] (B, 512, 3)`` (two halves: the first and the previous frame's crop, each
    in its own box frame) and ``batch["search"] (B, 1024, 3)`` are randomised per sample and
    per cloud; ``search_labels``, ``template_labels`` and ``template_centers`` follow their points
    (a noise point is background; a half's centre is shared by its points). ``size``,
    ``motion`` and ``search_box`` are unchanged. One Python step per (sample, cloud), numpy
    inside."""
    device = batch["template"].device
    template = batch["template"].detach().cpu().numpy()
    search = batch["search"].detach().cpu().numpy()
    half = template.shape[1] // 2
    out_t, out_s = np.empty_like(template), np.empty_like(search)
    t_labels = targets.get("template_labels")
    t_centres = targets.get("template_centers")
    s_labels = targets["search_labels"].detach().cpu().numpy()
    tl = None if t_labels is None else t_labels.detach().cpu().numpy()
    tc = None if t_centres is None else t_centres.detach().cpu().numpy()
    new_tl = None if tl is None else np.empty_like(tl)
    new_tc = None if tc is None else np.empty_like(tc)
    new_sl = np.empty_like(s_labels)
    for b in range(template.shape[0]):
        for lo, hi in ((0, half), (half, template.shape[1])):
            src, pts = _randomize_cloud(template[b, lo:hi], rng, dr)
            out_t[b, lo:hi] = pts
            real = src >= 0
            if new_tl is not None:
                new_tl[b, lo:hi] = np.where(real, tl[b, lo:hi][np.maximum(src, 0)], 0.0)
            if new_tc is not None:  # every point of a half has that half's centre
                new_tc[b, lo:hi] = tc[b, lo]
        src, pts = _randomize_cloud(search[b], rng, dr)
        out_s[b] = pts
        new_sl[b] = np.where(src >= 0, s_labels[b][np.maximum(src, 0)], 0.0)
    new_batch = dict(batch)
    new_batch["template"] = torch.from_numpy(out_t).to(device)
    new_batch["search"] = torch.from_numpy(out_s).to(device)
    new_targets = dict(targets)
    new_targets["search_labels"] = torch.from_numpy(new_sl).to(device)
    if new_tl is not None:
        new_targets["template_labels"] = torch.from_numpy(new_tl).to(device)
    if new_tc is not None:
        new_targets["template_centers"] = torch.from_numpy(new_tc).to(device)
    return new_batch, new_targets


# --------------------------------------------------------------------------- the contrast


def local_geometric_contrast(
    key_xyz: torch.Tensor,
    aux_feat: torch.Tensor,
    primary_xyz: torch.Tensor,
    primary_feat: torch.Tensor,
    radius_m: float,
    neighbours: int,
) -> torch.Tensor:
    """Eq. 4-5 per sample -> ``(B,)``.

    ``key_xyz (B, M, 3)`` the auxiliary branch's down-sampled points (the key points ``C``) and
    ``aux_feat (B, M, D)`` their features; ``primary_xyz (B, M', 3)``, ``primary_feat (B, M', D)``
    the primary branch's. ``F~aux_i`` = max over the ball query (``radius_m``, at most
    ``neighbours`` hits; ``C_i`` itself is always one) of ``C_i`` in ``key_xyz``; ``F~_i`` = max
    over the ``neighbours`` nearest points of ``C_i`` in ``primary_xyz``; the result is
    ``mean_i ||F~aux_i - F~_i||``."""
    idx_aux = ops.ball_query(radius_m, neighbours, key_xyz, key_xyz)  # (B, M, K)
    aux_local = ops.group(aux_feat, idx_aux).amax(dim=2)
    k = min(neighbours, primary_xyz.shape[1])
    with torch.no_grad():
        _, idx_p = ops.knn(k, key_xyz, primary_xyz)
    primary_local = ops.group(primary_feat, idx_p).amax(dim=2)
    diff = aux_local - primary_local
    return torch.sqrt((diff * diff).sum(-1) + _NORM_EPS).mean(-1)


class FeedForward(nn.Module):
    """The auxiliary branch's extra FFN: ``f + W2 relu(W1 f)`` per point, ``(B, M, D)`` ->
    ``(B, M, D)``, hidden width ``ratio * D``. ``W2`` starts at zero, so the auxiliary branch
    starts as an exact copy of the primary (a fine-tuning run does not begin by forgetting)."""

    def __init__(self, channels: int, ratio: float = 2.0) -> None:
        super().__init__()
        hidden = max(1, int(round(ratio * channels)))
        self.fc1 = nn.Linear(channels, hidden)
        self.fc2 = nn.Linear(hidden, channels)
        nn.init.zeros_(self.fc2.weight)
        nn.init.zeros_(self.fc2.bias)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return x + self.fc2(torch.relu(self.fc1(x)))


@contextlib.contextmanager
def tap_backbone(
    tracker: nn.Module, transform: Callable[[torch.Tensor], torch.Tensor] | None = None
) -> Iterator[list[tuple[torch.Tensor, torch.Tensor]]]:
    """Record ``(xyz (B, M, 3), features (B, M, D))`` of every cloud that ``tracker.backbone``
    encodes inside the block (template first, then search, for the trackers here), applying
    ``transform`` to the features the backbone returns. Restores the backbone on exit."""
    backbone = _backbone_of(tracker)
    records: list[tuple[torch.Tensor, torch.Tensor]] = []
    original = backbone.forward_many
    depth = [0]

    def forward_many(clouds, orders):
        depth[0] += 1
        try:
            outs = original(clouds, orders)
        finally:
            depth[0] -= 1
        if depth[0]:  # the backbone calling itself (one cloud at a time in training): the
            return outs  # outermost call records and transforms, once per cloud
        if transform is not None:
            outs = [(xyz, transform(feat), idx) for xyz, feat, idx in outs]
        records.extend((xyz, feat) for xyz, feat, _ in outs)
        return outs

    backbone.forward_many = forward_many  # instance attribute: shadows the method, not saved
    try:
        yield records
    finally:
        del backbone.forward_many


def _backbone_of(tracker: nn.Module):
    backbone = getattr(tracker, "backbone", None)
    if not isinstance(backbone, Backbone) or not callable(getattr(tracker, "loss", None)):
        raise ValueError(
            f"DRCT needs a learned tracker with a PointNet++ backbone and a loss (p2b, bat, gpt); "
            f"got {type(tracker).__name__}"
        )
    return backbone


# --------------------------------------------------------------------------- training hooks


class DRCT(nn.Module):
    """The auxiliary branch and the DRCT objective. Its parameters (``state_dict``) are the
    auxiliary branch's only: the copied tracker and the FFN (asymmetric), nothing (siamese)."""

    def __init__(self, tracker: nn.Module, config: DRCTConfig | None = None) -> None:
        super().__init__()
        self.config = config or DRCTConfig()
        channels = _backbone_of(tracker).out_channels
        self.aux: nn.Module | None = None
        self.ffn: FeedForward | None = None
        if self.config.variant == "asymmetric":
            self.aux = copy.deepcopy(tracker)
            self.ffn = FeedForward(channels, self.config.ffn_ratio)

    def forward_losses(
        self,
        net: Callable[[Mapping[str, torch.Tensor]], dict[str, torch.Tensor]],
        model: nn.Module,
        batch: Mapping[str, torch.Tensor],
        targets: Mapping[str, torch.Tensor],
        step: int,
    ) -> tuple[dict[str, torch.Tensor], dict[str, torch.Tensor]]:
        """One training forward of both branches -> the primary's outputs and per-sample
        ``(B,)`` losses: the primary's terms, ``track`` (its total), ``aux_track``, ``contrast``
        and the DRCT ``total``. ``net`` is ``model`` or its DDP wrapper; ``step`` seeds the
        randomisation (``[seed, step]``), so a resumed run draws the same samples."""
        cfg = self.config
        rng = np.random.default_rng([cfg.seed, int(step), 0xD12C7])
        aux_batch, aux_targets = randomize_batch(batch, targets, rng, cfg.randomization)
        with tap_backbone(model) as primary:
            outputs = net(batch)
        losses = model.loss(outputs, targets)
        aux = model if self.aux is None else self.aux
        aux.train(model.training)
        gen = getattr(aux, "generator", None)
        if self.aux is not None and isinstance(gen, torch.Generator):
            gen.manual_seed(int(rng.integers(2**62)))  # the copy's own sampling stream
        with tap_backbone(aux, self.ffn) as auxiliary:
            aux_out = aux(aux_batch)
        aux_losses = aux.loss(aux_out, aux_targets)
        if not primary or len(primary) != len(auxiliary):
            raise RuntimeError(
                f"DRCT recorded {len(primary)} primary and {len(auxiliary)} auxiliary backbone "
                "outputs; the tracker must encode its clouds through tracker.backbone"
            )
        terms = []
        for (p_xyz, p_feat), (a_xyz, a_feat) in zip(primary, auxiliary, strict=True):
            if cfg.detach_aux:
                a_xyz, a_feat = a_xyz.detach(), a_feat.detach()
            terms.append(
                local_geometric_contrast(a_xyz, a_feat, p_xyz, p_feat, cfg.radius_m, cfg.neighbours)
            )
        contrast = torch.stack(terms).mean(0)
        total = (
            losses["total"] + cfg.aux_weight * aux_losses["total"] + cfg.contrast_weight * contrast
        )
        return outputs, {
            **losses,
            "total": total,
            "track": losses["total"],
            "aux_track": aux_losses["total"],
            "contrast": contrast,
        }


class DomainRandomizedTraining(nn.Module):
    """The ``-RD`` control: plain training of one branch on domain-randomised samples (the same
    randomisation and seeding as DRCT's auxiliary branch). No parameters."""

    def __init__(self, randomization: DomainRandomization | None = None, seed: int = 0) -> None:
        super().__init__()
        self.randomization = randomization or DomainRandomization()
        self.seed = int(seed)

    def forward_losses(self, net, model, batch, targets, step):
        """Randomise the batch, then the tracker's forward and per-sample losses."""
        rng = np.random.default_rng([self.seed, int(step), 0xD12C7])
        batch, targets = randomize_batch(batch, targets, rng, self.randomization)
        outputs = net(batch)
        return outputs, model.loss(outputs, targets)


def build_hook(cfg, model: nn.Module) -> DRCT | DomainRandomizedTraining | None:
    """The training hook a :class:`training.config.TrainConfig` asks for (``drct`` /
    ``domain_randomize``), or ``None`` for plain training."""
    dr = DomainRandomization(
        p_skip=cfg.dr_p_skip,
        p_step=cfg.dr_p_step,
        max_noise_ratio=cfg.dr_max_noise_ratio,
        max_drop_ratio=cfg.dr_max_drop_ratio,
        jitter_m=cfg.dr_jitter_m,
    )
    if cfg.drct:
        return DRCT(
            model,
            DRCTConfig(
                variant=cfg.drct_variant,
                contrast_weight=cfg.drct_contrast_weight,
                aux_weight=cfg.drct_aux_weight,
                radius_m=cfg.drct_radius_m,
                neighbours=cfg.drct_neighbours,
                detach_aux=cfg.drct_detach_aux,
                ffn_ratio=cfg.drct_ffn_ratio,
                randomization=dr,
                seed=cfg.seed,
            ),
        )
    if cfg.domain_randomize:
        return DomainRandomizedTraining(dr, seed=cfg.seed)
    return None
