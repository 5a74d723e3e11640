"""DRCT: dual-branch training with domain randomisation and local geometric contrast, after Zhao,
Liu, Tian and Han, *Robust Single Object Tracking in LiDAR Point Clouds under Adverse Weather
Conditions* (Sec. V) — our own implementation for P2B, BAT, GPT and MBPTrack (the paper builds
DRCT on MBPTrack).

* **Primary branch**: the tracker being trained, on the clean sample. It is the only branch kept:
  checkpoints' ``model`` and every export hold its weights alone.
* **Auxiliary branch**: sees the domain-randomised sample (Algorithm 1,
  :func:`envs.weather.domain_randomize`: noise points, dropped points, jitter; applied to each
  cloud the tracker reads separately, per sample, and resampled back to the fixed sizes: the
  template's two halves and the search region, or MBPTrack's search region and memory frames;
  labels and memory masks follow their points, added noise points are background;
  :func:`randomize_batch`). It runs the whole tracker (backbone -> fusion -> head, or MBPTrack's
  backbone -> memory transformer -> BPLocNet) and is trained by the tracking loss on that sample.

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
  the template and the search region (MBPTrack: the search region and the mean over the memory
  frames that hold points; :func:`sample_contrast`). The auxiliary side is detached by default
  (``detach_aux``): knowledge flows from the auxiliary branch to the primary one.
* **Objective** per sample: ``L_track(primary) + aux_weight * L_track(aux) +
  contrast_weight * L_contrast``; both branches train jointly (one optimizer). The per-sample
  total plugs into the trainer's weighting (``-W`` sample weights, SAM) unchanged.

The paper leaves the loss weight, the neighbourhood size, the FFN and the randomisation
amounts open; our choices (config fields of :class:`training.config.TrainConfig`, documented in
docs/weather.md) are the defaults of :class:`DRCTConfig`.

The backbone features are read through the tracker's point backbone (:func:`point_backbone`:
a tracker names it and the method that encodes clouds in ``drct_backbone``, as MBPTrack does
with its DGCNN backbone's ``forward``; by default a :class:`trackers.backbone.Backbone` at
``tracker.backbone``, tapped at its public ``forward_many``, which ``Backbone.forward`` delegates
to): for the duration of one forward, :func:`tap_backbone` wraps that instance's method, records
its ``(xyz, features)`` per batch of clouds and, on the auxiliary branch, applies the FFN to the
features it returns. Nothing is changed on the module outside that window, so state dicts and
exports are untouched.
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
    "point_backbone",
    "randomize_batch",
    "sample_contrast",
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


def _follow(values: np.ndarray, src: np.ndarray) -> np.ndarray:
    """Per-point ``values (N,)`` carried to the randomised points with source ``src (N',)``
    (:func:`_randomize_cloud`): an added noise point (``-1``) gets 0 (background)."""
    return np.where(src >= 0, values[np.maximum(src, 0)], 0.0).astype(values.dtype)


def _numpy(t: torch.Tensor | None) -> np.ndarray | None:
    return None if t is None else t.detach().cpu().numpy()


def randomize_batch(
    batch: Mapping[str, torch.Tensor],
    targets: Mapping[str, torch.Tensor],
    rng: np.random.Generator,
    dr: DomainRandomization,
) -> tuple[dict[str, torch.Tensor], dict[str, torch.Tensor]]:
    """Domain-randomised copies of a training batch and its targets, per sample and per cloud.

    * ``search (B, N, 3)`` (every layout): ``search_labels (B, N)`` follow their points (a noise
      point is background);
    * ``template (B, 512, 3)`` (matching trackers: two halves, the first and the previous
      frame's crop, each in its own box frame): each half separately; ``template_labels`` and
      ``template_centers`` follow their points (a half's centre is shared by its points);
    * ``memory (B, M, N_m, 4)`` (MBPTrack, :mod:`training.memory_samples`): each slot's points
      ``[..., :3]`` separately, its target-mask column ``[..., 3]`` follows them (a noise point is
      background); an empty slot (all zeros) stays empty. ``memory_boxes`` are unchanged: they
      are the agent's boxes, which weather does not move.

    ``size``, ``motion``, ``search_box`` and ``box`` are unchanged. Draws per sample: the
    template's halves, the search region, the memory slots oldest first (a matching tracker's
    stream is the one it had before memory batches were supported). One Python step per
    (sample, cloud), numpy inside."""
    device = batch["search"].device
    search = _numpy(batch["search"])
    template, memory = _numpy(batch.get("template")), _numpy(batch.get("memory"))
    s_labels = _numpy(targets["search_labels"])
    tl, tc = _numpy(targets.get("template_labels")), _numpy(targets.get("template_centers"))
    out_s, new_sl = np.empty_like(search), np.empty_like(s_labels)
    out_t = None if template is None else np.empty_like(template)
    out_m = None if memory is None else np.empty_like(memory)
    new_tl = None if tl is None else np.empty_like(tl)
    new_tc = None if tc is None else np.empty_like(tc)
    for b in range(search.shape[0]):
        if template is not None:
            half = template.shape[1] // 2
            for lo, hi in ((0, half), (half, template.shape[1])):
                src, pts = _randomize_cloud(template[b, lo:hi], rng, dr)
                out_t[b, lo:hi] = pts
                if new_tl is not None:
                    new_tl[b, lo:hi] = _follow(tl[b, lo:hi], src)
                if new_tc is not None:  # every point of a half has that half's centre
                    new_tc[b, lo:hi] = tc[b, lo]
        src, out_s[b] = _randomize_cloud(search[b], rng, dr)
        new_sl[b] = _follow(s_labels[b], src)
        for j in range(0 if memory is None else memory.shape[1]):
            src, out_m[b, j, :, :3] = _randomize_cloud(memory[b, j, :, :3], rng, dr)
            out_m[b, j, :, 3] = _follow(memory[b, j, :, 3], src)
    new_batch, new_targets = dict(batch), dict(targets)
    new_batch["search"] = torch.from_numpy(out_s).to(device)
    new_targets["search_labels"] = torch.from_numpy(new_sl).to(device)
    for store, key, value in (
        (new_batch, "template", out_t),
        (new_batch, "memory", out_m),
        (new_targets, "template_labels", new_tl),
        (new_targets, "template_centers", new_tc),
    ):
        if value is not None:
            store[key] = torch.from_numpy(value).to(device)
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
    """Record ``(xyz (F, M, 3), features (F, M, D))`` of every batch of clouds that the
    tracker's point backbone (:func:`point_backbone`) encodes inside the block (template, then
    search for the matching trackers; search, then memory frames for MBPTrack), applying
    ``transform`` to the features the backbone returns. Restores the backbone on exit."""
    module, method = point_backbone(tracker)
    records: list[tuple[torch.Tensor, torch.Tensor]] = []
    original = getattr(module, method)
    depth = [0]

    def tapped(*args, **kwargs):
        depth[0] += 1
        try:
            outs = original(*args, **kwargs)
        finally:
            depth[0] -= 1
        if depth[0]:  # the backbone calling itself (one cloud at a time in training): the
            return outs  # outermost call records and transforms, once per cloud
        many = isinstance(outs, list)  # forward_many: a list of (xyz, features, idx)
        items = outs if many else [outs]
        if transform is not None:
            items = [(out[0], transform(out[1]), *out[2:]) for out in items]
        records.extend((out[0], out[1]) for out in items)
        return items if many else items[0]

    setattr(module, method, tapped)  # instance attribute: shadows the method, not saved
    try:
        yield records
    finally:
        delattr(module, method)


def point_backbone(tracker: nn.Module) -> tuple[nn.Module, str]:
    """The module DRCT taps and the name of its method that encodes clouds.

    The protocol: a tracker with a ``loss`` names its point backbone in a class attribute
    ``drct_backbone = (attribute, method)`` (MBPTrack: ``("backbone", "forward")``); without one,
    a :class:`trackers.backbone.Backbone` at ``tracker.backbone`` is tapped at ``forward_many``
    (P2B, BAT, GPT). The method returns ``(xyz (F, M, 3), features (F, M, D), ...)`` for one
    batch of ``F = k B`` clouds (each sample's ``k`` consecutive), or a list of those; the
    module has ``out_channels`` (``D``)."""
    if callable(getattr(tracker, "loss", None)):
        spec = getattr(type(tracker), "drct_backbone", None)
        if spec is not None:
            module = getattr(tracker, spec[0], None)
            if isinstance(module, nn.Module) and callable(getattr(module, spec[1], None)):
                return module, spec[1]
        backbone = getattr(tracker, "backbone", None)
        if spec is None and isinstance(backbone, Backbone):
            return backbone, "forward_many"
    raise ValueError(
        f"DRCT needs a learned tracker with a point backbone and a loss (p2b, bat, gpt, "
        f"mbptrack); got {type(tracker).__name__}"
    )


def sample_contrast(
    primary: list[tuple[torch.Tensor, torch.Tensor]],
    auxiliary: list[tuple[torch.Tensor, torch.Tensor]],
    batch_size: int,
    radius_m: float,
    neighbours: int,
) -> torch.Tensor:
    """The per-sample contrast ``(B,)`` over the tapped records of both branches (pairs of
    ``(xyz (F, M, 3), features (F, M, D))``, in the same order): the mean over the records of
    :func:`local_geometric_contrast`. A record of ``k > 1`` clouds per sample (MBPTrack's memory
    frames, ``F = k B``) counts as the mean over that sample's clouds with points (an empty
    memory slot is padding, not a frame), and not at all where the sample has none; a record of
    one cloud per sample counts as it is (an empty search crop too, as for P2B)."""
    terms, weights = [], []
    for (p_xyz, p_feat), (a_xyz, a_feat) in zip(primary, auxiliary, strict=True):
        c = local_geometric_contrast(a_xyz, a_feat, p_xyz, p_feat, radius_m, neighbours)
        k = c.shape[0] // batch_size
        if k * batch_size != c.shape[0]:
            raise RuntimeError(
                f"DRCT tapped a backbone batch of {c.shape[0]} clouds for {batch_size} samples"
            )
        if k == 1:
            terms.append(c)
            weights.append(torch.ones_like(c))
            continue
        has = a_xyz.detach().flatten(1).ne(0).any(1).view(batch_size, k).to(c.dtype)
        n = has.sum(1)
        terms.append((c.view(batch_size, k) * has).sum(1) / n.clamp(min=1))
        weights.append((n > 0).to(c.dtype))
    w = torch.stack(weights)
    return (torch.stack(terms) * w).sum(0) / w.sum(0).clamp(min=1)


# --------------------------------------------------------------------------- training hooks


class DRCT(nn.Module):
    """The auxiliary branch and the DRCT objective. Its parameters (``state_dict``) are the
    auxiliary branch's only: the copied tracker and the FFN (asymmetric), nothing (siamese)."""

    def __init__(self, tracker: nn.Module, config: DRCTConfig | None = None) -> None:
        super().__init__()
        self.config = config or DRCTConfig()
        module, _ = point_backbone(tracker)
        channels = int(module.out_channels)
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
                "outputs; the tracker must encode its clouds through its point backbone"
            )
        if cfg.detach_aux:
            auxiliary = [(xyz.detach(), feat.detach()) for xyz, feat in auxiliary]
        contrast = sample_contrast(
            primary, auxiliary, losses["total"].shape[0], cfg.radius_m, cfg.neighbours
        )
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
