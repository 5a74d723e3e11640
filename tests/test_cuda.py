"""The trackers and the trainer on a CUDA device (skipped where there is none): the shipped
checkpoints act there as on the CPU, and a training run there follows the CPU run's losses.

CI has no GPU; these ran on an NVIDIA H200 (docs/performance.md, "GPU")."""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np
import pytest
import torch

import trackers

sys.path.insert(0, str(Path(__file__).resolve().parent / "data"))
from record_tracker_reference import CHECKPOINTS, KEYS, LATER  # noqa: E402

pytestmark = pytest.mark.skipif(not torch.cuda.is_available(), reason="no CUDA device")


@pytest.fixture
def exact_fp32():
    """cuDNN's TF32 convolutions round inputs to 10 mantissa bits: off, so that the CUDA and
    CPU results differ by float32 summation order only."""
    saved = torch.backends.cudnn.allow_tf32, torch.backends.cuda.matmul.allow_tf32
    torch.backends.cudnn.allow_tf32 = torch.backends.cuda.matmul.allow_tf32 = False
    yield
    torch.backends.cudnn.allow_tf32, torch.backends.cuda.matmul.allow_tf32 = saved


@pytest.mark.parametrize("name", CHECKPOINTS + LATER)
def test_shipped_checkpoint_acts_on_cuda_as_on_cpu(name, exact_fp32):
    """The recorded observations (toy batches, padded clouds, env steps, an empty template):
    the CUDA actions are the CPU reference's to 1 mm / 1 mrad, and its proposals' scores to
    1e-3, batched and one at a time."""
    with np.load(Path(__file__).parent / "data" / "tracker_reference.npz") as ref:
        obs = {k: ref[f"obs_{k}"] for k in KEYS}
        expected_act, expected_scores = ref[f"{name}/act_single"], ref[f"{name}/scores"]
    model = trackers.load(name).to("cuda")
    assert model.device.type == "cuda"
    n = len(obs["template"])
    single = np.stack([model.act({k: v[i] for k, v in obs.items()}) for i in range(n)])
    np.testing.assert_allclose(single, expected_act, atol=1e-3)
    np.testing.assert_allclose(model.act(obs), expected_act, atol=1e-3)
    with torch.no_grad():
        scores = [
            model({k: torch.from_numpy(v[i : i + 1]) for k, v in obs.items()})["scores"]
            for i in range(n)
        ]
    np.testing.assert_allclose(
        np.concatenate([s.cpu().numpy() for s in scores]), expected_scores, atol=1e-3
    )


@pytest.mark.parametrize("name", ["p2b", "bat", "gpt"])
def test_training_on_cuda_follows_the_cpu_run(name, tmp_path, exact_fp32):
    """Two epochs of the real trainer (slim widths, decorrelation weighting) from the same seed
    on both devices: the same samples and initial weights, so the per-epoch losses agree to
    float32 summation order, and the CUDA checkpoint loads on the CPU."""
    from test_pretrain_support import fake_tracklets, tiny_config

    from training.config import tracker_config
    from training.pretrain import train
    from training.samples import TrackingSamples

    def run(device: str):
        cfg = tiny_config(
            tmp_path / device,
            tracker=name,
            epochs=2,
            batch_size=2,
            iters_per_epoch=2,
            lr=1e-3,
            weighting="decorrelation",
            model_size="slim",
            device=device,
        )
        data = TrackingSamples(fake_tracklets(n=2, frames=4), candidates_per_frame=1)
        return train(
            cfg,
            train_data=data,
            val_fn=False,
            model_factory=lambda c: trackers.make(name, **tracker_config(name, "slim")),
        )

    cpu, cuda = run("cpu"), run("cuda")
    for a, b in zip(cpu.history, cuda.history, strict=True):
        assert np.isfinite(b["total"])
        assert b["total"] == pytest.approx(a["total"], rel=1e-3)
    state = torch.load(tmp_path / "cuda" / "last.pt", map_location="cpu", weights_only=True)
    model = trackers.make(name, **tracker_config(name, "slim"))
    model.load_state_dict(state["model"])
