"""DDP: two CPU processes (gloo) match one process on the same global batches."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import pytest
import torch
from test_pretrain_support import TinyTracker, small_dataset, tiny_config

from training.pretrain import train

HERE = Path(__file__).resolve().parent


@pytest.mark.slow
@pytest.mark.parametrize("weighting", ["none", "decorrelation"])
def test_ddp_two_processes_match_single_process(tmp_path, weighting):
    single = tmp_path / "single"
    cfg = tiny_config(single, weighting=weighting, epochs=1, iters_per_epoch=3)
    train(cfg, model_factory=lambda c: TinyTracker(), train_data=small_dataset(), val_fn=False)
    ddp = tmp_path / "ddp"
    env = dict(os.environ, OMP_NUM_THREADS="1", PYTHONPATH=str(HERE.parent))
    proc = subprocess.run(
        [
            sys.executable,
            "-m",
            "torch.distributed.run",
            "--nproc_per_node",
            "2",
            "--master_port",
            str(29500 + os.getpid() % 1000),
            str(HERE / "test_pretrain_support.py"),
            str(ddp),
            weighting,
        ],
        env=env,
        capture_output=True,
        text=True,
        timeout=300,
    )
    assert proc.returncode == 0, proc.stderr[-3000:]
    a = torch.load(single / "last.pt", weights_only=True)["model"]
    b = torch.load(ddp / "last.pt", weights_only=True)["model"]
    for k in a:
        assert torch.allclose(a[k], b[k], atol=1e-5, rtol=1e-4), k
    torch.manual_seed(0)
    init = TinyTracker().state_dict()
    moved = max(float((a[k] - init[k]).abs().max()) for k in a)
    assert moved > 1e-3  # training did change the weights
