"""One pretraining loop for P2B, BAT and GPT: plain (-U), feature-decorrelation weighted (-W) and
SAM (-S).

* Optimisation: Adam (lr 1e-3), ``StepLR`` x0.2 every 12 epochs, batch 48 (GPT's constants), all in
  :class:`training.config.TrainConfig`. ``iters_per_epoch`` caps an epoch at a fresh random subset
  of the samples (chosen from ``(seed, epoch)``).
* -U minimises the mean per-sample loss; -W the weighted sum ``sum_m w_m L_m`` with the weights of
  :class:`training.weighting.FeatureDecorrelation` learned on the detached pooled fused features
  of the same forward pass (Algorithm 1 of Tian et al. (TIP 2024)); -S takes SAM steps
  (:mod:`training.sam`).
* Validation every ``val_every`` epochs: the env's OPE Success/Precision on the val split,
  through ``training.evaluate.evaluate``, on the setting's **observed** categories only (the unseen
  ones are never looked at before test). The checkpoint with the best val Success is kept.
* ``ema_decay > 0`` keeps an exponential moving average of the weights
  (:class:`training.averaging.WeightEMA`); validation, ``best.pt``'s selection and
  :func:`training.checkpoint.load_weights` (so ``--export``) then use the averaged weights.
* Checkpoints (``last.pt`` after every epoch, ``best.pt`` at the best val Success) hold the
  weights, their average (when on), optimizer, scheduler, decorrelation memory, RNG states
  (torch, numpy, python), epoch, step and config; :mod:`training.checkpoint` writes them
  atomically and reads them without running code. :func:`check_run_dir` decides, before any
  data is built, whether a run starts or resumes (a fresh run refuses a directory holding a run;
  ``resume=True`` refuses one holding nothing). ``resume=True`` continues from ``last.pt`` and
  cuts ``log.jsonl`` back to its step; every random draw depends only on ``(seed, epoch, sample
  index)`` and the torch generators (the global one and a tracker's own ``model.generator`` for
  point sampling) are reseeded at every epoch, so a resumed run ends with exactly the weights of
  an uninterrupted one (CPU). A checkpoint of another tracker or config is refused, naming the
  differing keys.
* A non-finite loss stops the run with :class:`TrainingError` naming the step and the samples;
  the last good checkpoint is left as it was.
* Data parallel: under ``torchrun --nproc_per_node N`` each process takes ``batch_size / N`` of
  every global batch (``DistributedSampler`` over the epoch's sample list), gradients are averaged
  by DDP (gloo on CPU, nccl on GPU); -W gathers the pooled features of the whole global batch so
  every process learns the same weights as a single process would. Only rank 0 validates, logs
  and writes checkpoints: one logical result.
* Logs: a tqdm bar with running losses; ``log.jsonl`` (always: the run's record); its numbers
  as scalars in ``OUT/logs`` through stable-baselines3's logger (:mod:`training.scalars`:
  ``logger="csv,json"`` by default, ``tensorboard`` with the extra); messages (resume, epoch
  lines) through :mod:`logging` (``pointtrack`` configures a handler).
"""

from __future__ import annotations

import json
import logging
import os
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import torch
from torch.utils.data import DataLoader, Subset

from training.allocator import retain_freed_memory
from training.averaging import WeightEMA
from training.checkpoint import (
    CHECKPOINT_FORMAT,
    CheckpointError,
    atomic_save,
    check_resumable,
    config_differences,
    is_training_checkpoint,
    load_weights,
    parent_entry,
    read_checkpoint,
    restore_rng_state,
    rng_state,
    tracker_from_checkpoint,
)
from training.config import TrainConfig
from training.losses import pooled_objective
from training.provenance import train_provenance
from training.rundir import atomic_write_text, remove_stale_temps, truncate_log
from training.sam import SAM
from training.samples import BATCH_KEYS, TARGET_KEYS, split_batch
from training.train_setup import (
    SAMPLE_RECIPE_KEYS,
    TrainingError,
    architecture_config,
    check_device,
    check_run_dir,
    default_model_factory,
    default_train_data,
    default_val_fn,
)
from training.weighting import FeatureDecorrelation, effective_sample_size, pool_features

log = logging.getLogger(__name__)

__all__ = [
    "SAMPLE_RECIPE_KEYS",  # re-exported from training.train_setup, with the defaults below
    "TrainResult",
    "Trainer",
    "TrainingError",
    "check_run_dir",
    "default_model_factory",
    "default_train_data",
    "default_val_fn",
    "load_weights",  # re-exported from training.checkpoint, with tracker_from_checkpoint
    "tracker_from_checkpoint",
    "train",
]


@dataclass
class TrainResult:
    out: Path
    epochs_done: int
    steps: int
    best_epoch: int | None
    best_val: dict[str, float] | None
    history: list[dict[str, Any]] = field(default_factory=list)
    wall_s: float = 0.0
    samples_per_s: float = 0.0


# --------------------------------------------------------------------------- helpers


def _epoch_seed(seed: int, epoch: int, rank: int) -> int:
    return (seed * 1_000_003 + epoch * 10_007 + rank * 101 + 17) % (2**62)


def _dist_info() -> tuple[int, int]:
    world = int(os.environ.get("WORLD_SIZE", "1"))
    rank = int(os.environ.get("RANK", "0"))
    return rank, world


def _process_device(device: str, world: int) -> torch.device:
    """Under torchrun a bare ``cuda`` is this process's GPU on its node (``LOCAL_RANK``), so
    ``--nproc-per-node N`` on a node of N GPUs (and on every node of a multi-node run, where
    ``RANK`` is global and ``LOCAL_RANK`` per node) puts one process on each."""
    if device == "cuda" and world > 1 and "LOCAL_RANK" in os.environ:
        return torch.device("cuda", int(os.environ["LOCAL_RANK"]))
    return torch.device(device)


# --------------------------------------------------------------------------- the trainer


class Trainer:
    """Holds the model, optimisation state and data of one run. Use :func:`train`."""

    def __init__(
        self,
        cfg: TrainConfig,
        *,
        model_factory: Callable[[TrainConfig], torch.nn.Module] | None = None,
        train_data: Any = None,
        val_fn: Callable[[torch.nn.Module], dict[str, float]] | None | bool = None,
    ) -> None:
        self.cfg = cfg.validate()
        self.rank, self.world = _dist_info()
        self.main = self.rank == 0
        self.device = _process_device(cfg.device, self.world)
        if cfg.num_threads:
            torch.set_num_threads(cfg.num_threads)
        if self.device.type == "cpu":  # big activations: reuse freed blocks (training.allocator)
            retain_freed_memory()
        if cfg.batch_size % self.world:
            raise TrainingError(
                f"batch_size {cfg.batch_size} is not divisible by the {self.world} processes"
            )
        self.local_batch = cfg.batch_size // self.world
        self.pg = None
        self.owns_process_group = False
        if self.world > 1:
            import torch.distributed as dist

            if not dist.is_initialized():
                backend = "nccl" if self.device.type == "cuda" else "gloo"
                if self.device.index is not None:
                    torch.cuda.set_device(self.device)  # NCCL's collectives use this GPU
                dist.init_process_group(backend)
                self.owns_process_group = True
            self.pg = dist
        torch.manual_seed(cfg.seed)  # identical initial weights on every rank
        self.model = (model_factory or default_model_factory)(cfg).to(self.device)
        # the env options it is validated with, carried by trackers.save (docs/recipe.md)
        self.model.env_options = cfg.env_options()
        if cfg.init_weights is not None:
            self._load_init_weights(cfg.init_weights)
        self.drct = None  # DRCT's auxiliary branch or the -RD randomiser (training.drct)
        if cfg.drct or cfg.domain_randomize:
            if self.world > 1:
                raise TrainingError("drct / domain_randomize train in one process only")
            from training.drct import build_hook

            self.drct = build_hook(cfg, self.model).to(self.device)
        self.ema = WeightEMA(self.model, cfg.ema_decay) if cfg.ema_decay > 0 else None
        self._averaged: torch.nn.Module | None = None  # eval copy holding the EMA weights
        self.net: torch.nn.Module = self.model
        if self.world > 1:
            from torch.nn.parallel import DistributedDataParallel

            self.net = DistributedDataParallel(self.model, find_unused_parameters=True)
        self.data = train_data if train_data is not None else default_train_data(cfg)
        # the batch / target keys of the sample recipe (the motion samples' differ)
        self._sample_keys = (
            getattr(self.data, "batch_keys", BATCH_KEYS),
            getattr(self.data, "target_keys", TARGET_KEYS),
        )
        if len(self.data) < cfg.batch_size:
            raise TrainingError(
                f"only {len(self.data)} training samples, fewer than one batch of {cfg.batch_size}"
            )
        self.base_opt = torch.optim.Adam(
            [*self.model.parameters(), *(self.drct.parameters() if self.drct else [])],
            lr=cfg.lr,
            weight_decay=cfg.weight_decay,
            betas=(cfg.recipe_value("adam_beta1"), 0.999),
            eps=cfg.recipe_value("adam_eps"),
        )
        self.pooled = cfg.recipe_value("loss_reduction") == "pooled"
        self.scheduler = torch.optim.lr_scheduler.StepLR(
            self.base_opt, step_size=cfg.lr_step_epochs, gamma=cfg.lr_gamma
        )
        self.sam = SAM(self.base_opt, rho=cfg.sam_rho) if cfg.weighting == "sam" else None
        self.decor = None
        if cfg.weighting == "decorrelation":
            self.decor = FeatureDecorrelation(
                n_functions=cfg.rff_functions,
                iterations=cfg.decor_iters,
                lr=cfg.decor_lr,
                decay_every=cfg.decor_decay_every,
                momentum=cfg.decor_momentum,
                penalty=cfg.decor_penalty,
                use_memory=cfg.decor_memory,
                memory_ratio=cfg.decor_memory_ratio,
                memory_size=cfg.batch_size,
                seed=cfg.seed,
            )
        if val_fn is None:
            val_fn = default_val_fn(cfg) if self.main else False
        self.val_fn = val_fn or None
        self.out = Path(cfg.out)
        self.epoch = 0  # epochs completed
        self.step = 0
        self.best_val: dict[str, float] | None = None
        self.best_epoch: int | None = None
        self.history: list[dict[str, Any]] = []
        self._scalars = None
        self._log = None

    def _load_init_weights(self, source: str) -> None:
        """Copy the weights of a tracker checkpoint (same tracker, same config) into the model:
        a tracker file, a shipped name, or a training checkpoint (``RUN/best.pt``: its
        validated weights, as ``pointtrack select`` scores them)."""
        from trackers.config import config_to_dict
        from trackers.registry import find_checkpoint, load_file

        path = find_checkpoint(source)
        if path is None:
            raise TrainingError(
                f"init_weights={source!r}: no such checkpoint file or shipped checkpoint name"
            )
        try:
            if is_training_checkpoint(path):
                start = tracker_from_checkpoint(path)
                if start.name != self.cfg.tracker:
                    raise ValueError(f"holds a {start.name!r} checkpoint, not {self.cfg.tracker!r}")
            else:
                start = load_file(path, expect=self.cfg.tracker)
        except (ValueError, FileNotFoundError, CheckpointError) as exc:
            raise TrainingError(f"init_weights={source!r}: {exc}") from exc
        details = config_differences(
            architecture_config(config_to_dict(start.config)),
            architecture_config(config_to_dict(self.model.config)),
            "run",
        )
        if details:
            raise TrainingError(f"init_weights={source!r} has another tracker config ({details})")
        self.model.load_state_dict(start.state_dict())

    # ------------------------------------------------------------------ checkpoints
    def state(self) -> dict[str, Any]:
        cfg_dict = self.cfg.to_dict()
        return {
            "format": CHECKPOINT_FORMAT,
            "tracker": self.cfg.tracker,
            "config": cfg_dict,
            "model": {k: v.detach().cpu().clone() for k, v in self.model.state_dict().items()},
            "optimizer": self.base_opt.state_dict(),
            "scheduler": self.scheduler.state_dict(),
            "decorrelation": self.decor.state_dict() if self.decor else {},
            "ema": self.ema.state_dict() if self.ema else {},
            "drct": self.drct.state_dict() if self.drct is not None else {},
            "rng": rng_state(),
            "epoch": self.epoch,
            "step": self.step,
            "best_val": self.best_val,
            "best_epoch": self.best_epoch,
            "history": json.dumps(self.history),
            "provenance": train_provenance(
                cfg_dict,
                getattr(self.data, "root", None),
                self.step,
                parent=parent_entry(self.cfg.init_weights) if self.cfg.init_weights else None,
            ).to_json(),
        }

    def load(self, path: Path) -> None:
        try:
            ckpt = read_checkpoint(path)
            check_resumable(ckpt, self.cfg, path)
        except CheckpointError as exc:
            raise TrainingError(str(exc)) from exc
        self.model.load_state_dict(ckpt["model"])
        self.base_opt.load_state_dict(ckpt["optimizer"])
        self.scheduler.load_state_dict(ckpt["scheduler"])
        if self.decor is not None:
            self.decor.load_state_dict(ckpt["decorrelation"])
        if self.ema is not None:
            self.ema.load_state_dict(ckpt["ema"])
        if self.drct is not None and ckpt.get("drct"):
            self.drct.load_state_dict(ckpt["drct"])
        restore_rng_state(ckpt["rng"])
        self.epoch = int(ckpt["epoch"])
        self.step = int(ckpt["step"])
        self.best_val = ckpt.get("best_val")
        self.best_epoch = ckpt.get("best_epoch")
        self.history = json.loads(ckpt.get("history") or "[]")

    def _save(self, name: str) -> None:
        if self.main:
            atomic_save(self.state(), self.out / name)

    # ------------------------------------------------------------------ logging
    def _open_logs(self) -> None:
        if not self.main:
            return
        self.out.mkdir(parents=True, exist_ok=True)
        from training.scalars import open_scalar_logger

        # rewritten from log.jsonl (already cut back to the resumed step) before it grows
        self._scalars = open_scalar_logger(
            self.out / "logs", self.cfg.logger, replay=self.out / "log.jsonl"
        )
        self._log = open(self.out / "log.jsonl", "a")  # noqa: SIM115 - closed in _close_logs

    def _write(self, record: dict[str, Any]) -> None:
        if not self.main:
            return
        if self._log is not None:
            self._log.write(json.dumps(record) + "\n")
            self._log.flush()
        if self._scalars is not None:
            from training.scalars import log_record

            log_record(self._scalars, record, record.get("step", self.step))

    def _close_logs(self) -> None:
        if self._log is not None:
            self._log.close()
            self._log = None
        if self._scalars is not None:
            self._scalars.close()
            self._scalars = None

    # ------------------------------------------------------------------ one epoch
    def _loader(self, epoch: int) -> DataLoader:
        cfg = self.cfg
        if hasattr(self.data, "set_epoch"):
            self.data.set_epoch(epoch)
        n = len(self.data)
        perm = np.random.default_rng([cfg.seed, epoch, 7]).permutation(n)
        count = n // cfg.batch_size
        if cfg.iters_per_epoch is not None:
            count = min(count, cfg.iters_per_epoch)
        subset = Subset(self.data, perm[: count * cfg.batch_size].tolist())
        sampler = None
        if self.world > 1:
            from torch.utils.data.distributed import DistributedSampler

            sampler = DistributedSampler(
                subset, num_replicas=self.world, rank=self.rank, shuffle=False, drop_last=True
            )
        return DataLoader(
            subset,
            batch_size=self.local_batch,
            sampler=sampler,
            shuffle=False,
            num_workers=cfg.num_workers,
            drop_last=True,
        )

    def _gather_features(self, z: torch.Tensor) -> torch.Tensor:
        """Pooled features of the whole global batch, in single-process order."""
        if self.world == 1:
            return z
        parts = [torch.empty_like(z) for _ in range(self.world)]
        self.pg.all_gather(parts, z.contiguous())
        # rank r's j-th sample is position r + j * world of the global batch
        return torch.stack(parts, dim=1).reshape(-1, z.shape[-1])

    def _sample_weights(self, outputs: dict[str, torch.Tensor]) -> torch.Tensor | None:
        if self.decor is None:
            return None
        # a trackers.Tracker names its decorrelated features; other models give them as "Z"
        features = getattr(self.model, "features", None)
        z = features(outputs) if callable(features) else outputs["Z"]
        z = pool_features(z.detach()).float().cpu()
        w_global = self.decor.weights(self._gather_features(z), self.step)
        local = w_global[self.rank :: self.world] if self.world > 1 else w_global
        return local.to(self.device)

    def _objective(
        self,
        losses: dict[str, torch.Tensor],
        outputs: dict[str, torch.Tensor],
        targets: dict[str, torch.Tensor],
        weights: torch.Tensor | None,
    ) -> torch.Tensor:
        if self.pooled:  # training.losses: pooled over the global batch under DDP
            reduce = self._sum_over_ranks if self.world > 1 else None
            return pooled_objective(
                self.model, losses, outputs, targets, weights, reduce, self.world
            )
        per_sample = losses["total"]
        if weights is None:
            return per_sample.mean()
        return (weights * per_sample).sum() * self.world

    def _sum_over_ranks(self, values: torch.Tensor) -> torch.Tensor:
        self.pg.all_reduce(values)
        return values

    def _check_finite(self, losses: dict[str, torch.Tensor], indices: torch.Tensor) -> None:
        total = losses["total"].detach()
        if torch.isfinite(total).all():
            return
        bad = (~torch.isfinite(total)).nonzero().flatten().tolist()
        idx = [int(indices[i]) for i in bad]
        describe = getattr(self.data, "describe", None)
        names = [describe(i) for i in idx] if describe else [f"sample {i}" for i in idx]
        terms = [k for k, v in losses.items() if not torch.isfinite(v.detach()).all()]
        raise TrainingError(
            f"non-finite loss at step {self.step} (epoch {self.epoch + 1}) in terms "
            f"{', '.join(terms)}: "
            + "; ".join(names[:10])
            + (f" and {len(names) - 10} more" if len(names) > 10 else "")
            + f". The last good checkpoint ({self.out / 'last.pt'}) is left as it was."
        )

    def _clip_gradients(self) -> None:
        """Clip the gradient norm over every parameter the optimizer steps: the tracker's and,
        with DRCT, its auxiliary branch's (one norm over both, as they train jointly)."""
        if self.cfg.grad_clip:
            params = [p for group in self.base_opt.param_groups for p in group["params"]]
            torch.nn.utils.clip_grad_norm_(params, self.cfg.grad_clip)

    def _forward_losses(
        self, batch: dict[str, torch.Tensor], targets: dict[str, torch.Tensor]
    ) -> tuple[dict[str, torch.Tensor], dict[str, torch.Tensor]]:
        """The tracker's outputs and per-sample losses; with DRCT / -RD through its hook."""
        if self.drct is not None:
            return self.drct.forward_losses(self.net, self.model, batch, targets, self.step)
        outputs = self.net(batch)
        return outputs, self.model.loss(outputs, targets)

    def train_epoch(self) -> dict[str, float]:
        cfg = self.cfg
        epoch = self.epoch  # 0-based index of the epoch being trained
        torch.manual_seed(_epoch_seed(cfg.seed, epoch, self.rank))
        gen = getattr(self.model, "generator", None)  # the trackers' own sampling generator
        if isinstance(gen, torch.Generator):
            gen.manual_seed(_epoch_seed(cfg.seed, epoch, self.rank) + 1)
        loader = self._loader(epoch)
        self.net.train()
        running: dict[str, float] = {}
        sums: dict[str, float] = {}
        n_batches = 0
        bar = None
        if self.main and cfg.progress:
            from tqdm import tqdm

            bar = tqdm(
                total=len(loader),
                desc=f"epoch {epoch + 1}/{cfg.epochs}",
                leave=False,
                dynamic_ncols=True,
            )
        t0 = time.perf_counter()
        for sample in loader:
            batch, targets, indices = split_batch(sample, self.device, *self._sample_keys)
            outputs, losses = self._forward_losses(batch, targets)
            self._check_finite(losses, indices)
            weights = self._sample_weights(outputs)
            loss = self._objective(losses, outputs, targets, weights)
            self.base_opt.zero_grad(set_to_none=True)
            loss.backward()
            if self.sam is not None:

                def closure(batch=batch, targets=targets, weights=weights):
                    out2, losses2 = self._forward_losses(batch, targets)
                    l2 = self._objective(losses2, out2, targets, weights)
                    l2.backward()
                    return l2

                self.sam.first_step(zero_grad=True)
                closure()
                self._clip_gradients()
                self.sam.second_step(zero_grad=True)
            else:
                self._clip_gradients()
                self.base_opt.step()
            if self.ema is not None:
                self.ema.update(self.model)
            self.step += 1
            n_batches += 1
            values = {k: float(v.detach().mean()) for k, v in losses.items()}
            scaled = (weights is not None and not self.pooled) or (self.pooled and self.world > 1)
            values["objective"] = float(loss.detach()) / (self.world if scaled else 1)
            if weights is not None:
                values["ess"] = effective_sample_size(weights) if self.world == 1 else float("nan")
            for k, v in values.items():
                running[k] = v if k not in running else 0.9 * running[k] + 0.1 * v
                sums[k] = sums.get(k, 0.0) + v
            if bar is not None:
                bar.set_postfix({k: f"{running[k]:.3f}" for k in list(running)[:5]})
                bar.update(1)
            if self.main and not cfg.progress and self.step % 25 == 0:
                log.info(
                    f"epoch {epoch + 1} step {self.step} "
                    + " ".join(f"{k}={running[k]:.4g}" for k in running)
                )
            if self.main and (self.step % 10 == 0):
                self._write(
                    {
                        "kind": "train",
                        "step": self.step,
                        "epoch": epoch + 1,
                        "lr": self.base_opt.param_groups[0]["lr"],
                        **values,
                    }
                )
        if bar is not None:
            bar.close()
        wall = time.perf_counter() - t0
        self.scheduler.step()
        self.epoch += 1
        mean = {k: v / max(n_batches, 1) for k, v in sums.items()}
        mean["samples_per_s"] = n_batches * cfg.batch_size / max(wall, 1e-9)
        mean["epoch_wall_s"] = wall
        return mean

    def validated_model(self) -> torch.nn.Module:
        """The model that validation sees: the weight average when ``ema_decay > 0``."""
        if self.ema is None:
            return self.model
        if self._averaged is None:
            import copy

            self._averaged = copy.deepcopy(self.model)
        return self.ema.copy_to(self._averaged)

    def validate(self) -> dict[str, float] | None:
        if self.val_fn is None:
            return None
        model = self.validated_model()
        model.eval()
        with torch.no_grad():
            result = self.val_fn(model)
        self.model.train()
        return result

    def close(self, finished: bool = True) -> None:
        """Release the process group this trainer created while the interpreter is whole: left
        to its exit, gloo's threads can race the teardown and abort a rank (SIGABRT,
        'terminate called without an active exception') after a finished run. The DDP wrapper
        goes first, because its reducer keeps the group alive past ``destroy_process_group``;
        after a finished run a barrier keeps a rank from tearing down while its peer still
        talks to it (after a failure the peers may never reach it, so there is none)."""
        if not self.owns_process_group:
            return
        import gc

        self.net = self.model
        gc.collect()
        if finished:
            self.pg.barrier()
        self.pg.destroy_process_group()
        self.pg = None
        self.owns_process_group = False

    def run(self, resume: bool = False) -> TrainResult:
        cfg = self.cfg
        if self.main:
            last = check_run_dir(self.out, resume)
        else:  # rank 0 decided the same before any rank could write
            last = self.out / "last.pt" if resume and (self.out / "last.pt").is_file() else None
        if last is not None:
            self.load(last)
            if self.main:
                dropped = truncate_log(self.out / "log.jsonl", self.step)
                log.info(
                    f"resuming {last}: {self.epoch} epochs done, step {self.step}"
                    + (
                        f" ({dropped} log records of the interrupted attempt dropped)"
                        if dropped
                        else ""
                    )
                )
        elif resume and self.main:
            # an attempt killed before its first checkpoint (check_run_dir removed its log)
            log.info(f"no checkpoint in {self.out} yet; starting its run from the beginning")
        if self.main:
            self.out.mkdir(parents=True, exist_ok=True)
            remove_stale_temps(self.out)
            atomic_write_text(self.out / "config.yaml", _yaml(cfg.to_dict()))
        self._open_logs()
        self._write(
            {
                "kind": "data",
                "step": self.step,
                "samples": len(self.data),
                "data_root": str(getattr(self.data, "root", "")),
                "world_size": self.world,
            }
        )
        t_start = time.perf_counter()
        samples = 0
        try:
            while self.epoch < cfg.epochs:
                stats = self.train_epoch()
                samples += int(round(stats["samples_per_s"] * stats["epoch_wall_s"]))
                record: dict[str, Any] = {
                    "kind": "epoch",
                    "epoch": self.epoch,
                    "step": self.step,
                    **stats,
                }
                if self.world > 1:
                    self.pg.barrier()
                val = None
                if self.main and (self.epoch % cfg.val_every == 0 or self.epoch == cfg.epochs):
                    val = self.validate()
                if val is not None:
                    record.update({f"val_{k}": v for k, v in val.items()})
                    if self.best_val is None or val["success"] > self.best_val["success"]:
                        self.best_val, self.best_epoch = dict(val), self.epoch
                        self._save("best.pt")
                self.history.append(record)
                self._write(record)
                self._save("last.pt")
                if self.main:
                    msg = " ".join(
                        f"{k}={v:.4g}"
                        for k, v in record.items()
                        if isinstance(v, float) and k != "epoch_wall_s"
                    )
                    log.info(f"epoch {self.epoch}/{cfg.epochs} {msg}")
                if self.world > 1:
                    self.pg.barrier()
        finally:
            self._close_logs()
        wall = time.perf_counter() - t_start
        return TrainResult(
            out=self.out,
            epochs_done=self.epoch,
            steps=self.step,
            best_epoch=self.best_epoch,
            best_val=self.best_val,
            history=self.history,
            wall_s=wall,
            samples_per_s=samples / max(wall, 1e-9),
        )


def _yaml(values: dict[str, Any]) -> str:
    import yaml

    return yaml.safe_dump(values, sort_keys=False)


def train(
    cfg: TrainConfig,
    *,
    resume: bool = False,
    model_factory: Callable[[TrainConfig], torch.nn.Module] | None = None,
    train_data: Any = None,
    val_fn: Callable[[torch.nn.Module], dict[str, float]] | None | bool = None,
) -> TrainResult:
    """Run (or resume) one pretraining run; see the module docstring. ``val_fn=False`` disables
    validation; the factories let tests use stand-in models and data."""
    cfg.validate()
    check_device(cfg.device)
    if int(os.environ.get("RANK", "0")) == 0:
        check_run_dir(cfg.out, resume)  # before any data is built: refusals come in a second
    trainer = Trainer(cfg, model_factory=model_factory, train_data=train_data, val_fn=val_fn)
    try:
        result = trainer.run(resume=resume)
    except BaseException:
        trainer.close(finished=False)
        raise
    trainer.close()
    return result
