"""Stand-ins for the trainer tests: a tiny tracker with the trackers' forward/loss interface and
small synthetic tracklets (no dependence on the synthetic world), and one helper that runs the
real trainer on a real tracker over them.

Also runnable under ``torchrun`` (the DDP test launches it): ``python -m torch.distributed.run
--nproc_per_node 2 tests/test_pretrain_support.py OUT WEIGHTING``.
"""

from __future__ import annotations

import sys

import numpy as np
import pytest
import torch
from torch import nn

from envs.data import Tracklet
from envs.geometry import box_to_world


class FakeScans:
    """Whole scans of one fake scene: target points inside each frame's box plus background."""

    def __init__(self, boxes: np.ndarray, seed: int, n_target: int = 150, n_background: int = 300):
        self.boxes = np.asarray(boxes, dtype=np.float64)
        self.seed = seed
        self.n_target = n_target
        self.n_background = n_background

    def __call__(self, frame: int) -> np.ndarray:
        rng = np.random.default_rng([self.seed, int(frame)])
        box = self.boxes[frame]
        local = rng.uniform(-0.45, 0.45, (self.n_target, 3)) * box[3:6]
        target = box_to_world(local, box)
        ring = rng.uniform(-12, 12, (self.n_background, 3))
        ring[:, 2] = rng.uniform(-1.5, 0.5, self.n_background)
        far = np.abs(ring[:, 0] - box[0]) + np.abs(ring[:, 1] - box[1]) > 4.0
        pts = np.concatenate([target, ring[far]])
        inten = rng.uniform(0, 1, (len(pts), 1))
        return np.concatenate([pts, inten], 1).astype(np.float32)


def fake_tracklets(n: int = 3, frames: int = 8, seed: int = 0, category: str = "Pedestrian"):
    out = []
    for k in range(n):
        rng = np.random.default_rng([seed, k])
        t = np.arange(frames)
        x = rng.uniform(-5, 5) + 0.4 * t
        y = rng.uniform(-5, 5) + 0.1 * t
        yaw = rng.uniform(-1, 1) + 0.02 * t
        size = np.array([rng.uniform(0.6, 4.0), rng.uniform(0.5, 1.8), rng.uniform(1.2, 2.0)])
        boxes = np.stack(
            [x, y, np.full(frames, -0.5), *[np.full(frames, s) for s in size], yaw], axis=1
        )
        out.append(
            Tracklet(f"{k:04d}/{k}", f"{k:04d}", k, category, t.copy(), boxes, FakeScans(boxes, k))
        )
    return out


class TinyTracker(nn.Module):
    """The trackers' interface in miniature: ``forward(batch)`` with ``Z``, ``proposals``,
    ``scores``; ``loss(outputs, targets)`` with a per-sample ``total``."""

    def __init__(self, dim: int = 16, nan_at_step: int | None = None) -> None:
        super().__init__()
        self.point = nn.Sequential(nn.Linear(3, dim), nn.ReLU(), nn.Linear(dim, dim), nn.ReLU())
        self.tmpl = nn.Linear(3, dim)
        self.cls = nn.Linear(dim, 1)
        self.head = nn.Linear(2 * dim, 4)
        self.nan_at_step = nan_at_step
        self.calls = 0

    def forward(self, batch: dict[str, torch.Tensor]) -> dict[str, torch.Tensor]:
        t = self.tmpl(batch["template"]).amax(dim=1)
        f = self.point(batch["search"]) + t[:, None]
        logits = self.cls(f).squeeze(-1)
        off = self.head(torch.cat([f.amax(dim=1), t], dim=-1))
        proposals = off[:, None].expand(-1, 64, -1)
        return {
            "Z": f,
            "point_logits": logits,
            "proposals": proposals,
            "scores": torch.zeros(off.shape[0], 64),
        }

    def loss(self, outputs, targets):
        self.calls += 1
        cls = nn.functional.binary_cross_entropy_with_logits(
            outputs["point_logits"], targets["search_labels"], reduction="none"
        ).mean(1)
        gt = torch.cat([targets["search_box"][:, :3], targets["search_box"][:, 6:7]], 1)
        reg = nn.functional.smooth_l1_loss(outputs["proposals"][:, 0], gt, reduction="none").mean(1)
        total = cls + reg
        if self.nan_at_step is not None and self.calls > self.nan_at_step:
            total = total.clone()
            total[1] = float("nan")
        return {"total": total, "cls": cls, "reg": reg}

    def act(self, obs):
        raise NotImplementedError


def small_dataset(seed: int = 0):
    from training.samples import TrackingSamples

    return TrackingSamples(
        fake_tracklets(), candidates_per_frame=2, seed=seed, template_size=32, search_size=64
    )


def tiny_config(out, **kw):
    from training.config import TrainConfig

    base = dict(
        tracker="p2b",
        out=str(out),
        epochs=2,
        batch_size=4,
        iters_per_epoch=4,
        lr=1e-2,
        progress=False,
        num_threads=1,
    )
    base.update(kw)
    return TrainConfig(**base).validate()


def train_slim_tracker(out, name: str = "p2b", *, resume: bool = False, **config):
    """The real trainer on tracker ``name`` at slim widths with decorrelation weighting, batch 2,
    over two fake tracklets of 4 frames; ``config`` overrides :func:`tiny_config`'s keys."""
    import trackers
    from training.config import tracker_config
    from training.pretrain import train
    from training.samples import TrackingSamples

    cfg = tiny_config(
        out, tracker=name, batch_size=2, weighting="decorrelation", model_size="slim", **config
    )
    data = TrackingSamples(fake_tracklets(n=2, frames=4), candidates_per_frame=1)
    return train(
        cfg,
        resume=resume,
        train_data=data,
        val_fn=False,
        model_factory=lambda c: trackers.make(name, **tracker_config(name, "slim")),
    )


if __name__ == "__main__":  # the DDP run of test_pretrain_ddp
    from training.pretrain import train

    out, weighting = sys.argv[1], sys.argv[2]
    cfg = tiny_config(out, weighting=weighting, epochs=1, iters_per_epoch=3)
    train(cfg, model_factory=lambda c: TinyTracker(), train_data=small_dataset(), val_fn=False)


_FAULTS_OF_40_MIB_BLOCKS = """
import resource, sys, torch
from training.allocator import retain_freed_memory
applied = retain_freed_memory() if sys.argv[1] == "retain" else None
faults = lambda: resource.getrusage(resource.RUSAGE_SELF).ru_minflt
for _ in range(12):  # 40 MiB blocks (above glibc's largest mmap threshold, 32 MiB): the
    x = torch.ones(10 << 20)  # heap grows to a steady size first (fragmentation)
    del x
before = faults()
for _ in range(10):
    x = torch.ones(10 << 20)
    del x
print(applied, faults() - before)
"""


def test_retain_freed_memory_reuses_large_blocks_without_page_faults():
    """After ``retain_freed_memory`` freed 40 MiB blocks are reused once the heap has grown
    (no page faults); without it glibc maps and faults every one in afresh (the control, so
    the measurement can fail)."""
    import os
    import subprocess
    from pathlib import Path

    if not sys.platform.startswith("linux"):
        pytest.skip("glibc's mallopt: Linux only (elsewhere the call returns False)")
    root = str(Path(__file__).resolve().parents[1])

    def faults(mode: str) -> tuple[str, int]:
        run = subprocess.run(
            [sys.executable, "-c", _FAULTS_OF_40_MIB_BLOCKS, mode],
            capture_output=True,
            text=True,
            cwd=root,
            env={**os.environ, "PYTHONPATH": root},
        )
        assert run.returncode == 0, run.stderr
        applied, count = run.stdout.split()
        return applied, int(count)

    applied, retained = faults("retain")
    if applied == "False":
        pytest.skip("this libc has no mallopt (not glibc): retain_freed_memory is a no-op")
    _, plain = faults("plain")
    assert plain > 10 * 5000, plain  # 10,240 pages a block without it
    assert retained < 1000, retained
