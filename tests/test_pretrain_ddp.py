"""DDP: two CPU processes (gloo) match one process on the same global batches, on one node
(``--nproc_per_node 2``) and as two nodes of one process each (``--nnodes 2 --node-rank 0/1``,
the multi-node flags of docs/cluster.md, with the rendezvous on 127.0.0.1)."""

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


def _single_process_run(out: Path, weighting: str) -> Path:
    cfg = tiny_config(out, weighting=weighting, epochs=1, iters_per_epoch=3)
    train(cfg, model_factory=lambda c: TinyTracker(), train_data=small_dataset(), val_fn=False)
    return out


def _torchrun(flags: list[str], out: Path, weighting: str) -> subprocess.Popen:
    env = dict(os.environ, OMP_NUM_THREADS="1", PYTHONPATH=str(HERE.parent))
    command = [sys.executable, "-m", "torch.distributed.run", *flags]
    command += [str(HERE / "test_pretrain_support.py"), str(out), weighting]
    return subprocess.Popen(command, env=env, stdout=subprocess.PIPE, stderr=subprocess.PIPE)


def _finished(proc: subprocess.Popen) -> None:
    try:
        _, err = proc.communicate(timeout=300)
    finally:
        proc.kill()
    assert proc.returncode == 0, err.decode()[-3000:]


@pytest.mark.slow
@pytest.mark.parametrize("weighting", ["none", "decorrelation"])
def test_ddp_two_processes_match_single_process(tmp_path, weighting):
    single = _single_process_run(tmp_path / "single", weighting)
    ddp = tmp_path / "ddp"
    port = str(29500 + os.getpid() % 1000)
    _finished(_torchrun(["--nproc_per_node", "2", "--master_port", port], ddp, weighting))
    _assert_same_training(single, ddp)


@pytest.mark.slow
def test_two_nodes_match_single_process(tmp_path):
    """``torchrun --nnodes 2 --node-rank R`` on two "nodes" (two local launchers, one process
    each, static rendezvous on 127.0.0.1): the result of one process, written by global rank 0
    only."""
    single = _single_process_run(tmp_path / "single", "decorrelation")
    out = tmp_path / "two-nodes"
    port = str(30500 + os.getpid() % 1000)
    common = ["--nnodes", "2", "--nproc-per-node", "1", "--master-addr", "127.0.0.1"]
    common += ["--master-port", port]
    nodes = [_torchrun([*common, "--node-rank", str(r)], out, "decorrelation") for r in (0, 1)]
    for node in nodes:
        _finished(node)
    _assert_same_training(single, out)


def _assert_same_training(single: Path, ddp: Path) -> None:
    a = torch.load(single / "last.pt", weights_only=True)["model"]
    b = torch.load(ddp / "last.pt", weights_only=True)["model"]
    for k in a:
        assert torch.allclose(a[k], b[k], atol=1e-5, rtol=1e-4), k
    torch.manual_seed(0)
    init = TinyTracker().state_dict()
    moved = max(float((a[k] - init[k]).abs().max()) for k in a)
    assert moved > 1e-3  # training did change the weights
