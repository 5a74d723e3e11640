"""DRCT and the -RD control on MBPTrack (training.drct): the memory batch's randomisation, the
DGCNN backbone tap, the contrast over the search region and the memory frames, training through
the CLI and exports without the auxiliary branch."""

from __future__ import annotations

import numpy as np
import pytest
import torch
from test_mbptrack import TINY
from test_pretrain_support import fake_tracklets

import trackers
from envs.weather import DomainRandomization
from training.config import ConfigError, config_from_dict
from training.drct import (
    DRCT,
    DomainRandomizedTraining,
    DRCTConfig,
    local_geometric_contrast,
    point_backbone,
    randomize_batch,
    sample_contrast,
    tap_backbone,
)
from training.memory_samples import MemorySamples
from training.samples import split_batch

pytestmark = pytest.mark.usefixtures("one_torch_thread")

ALWAYS = DomainRandomization(p_skip=0.0, p_step=1.0, max_noise_ratio=0.3, jitter_m=0.0)


def tiny_mbptrack(seed: int = 0):
    torch.manual_seed(seed)
    return trackers.make("mbptrack", **TINY)


def memory_batch():
    """Four real memory samples (training.memory_samples): the first at frame 1, so its older
    memory slot is empty."""
    data = MemorySamples(fake_tracklets(2, frames=4), candidates_per_frame=1, seed=0)
    sample = torch.utils.data.default_collate([data[i] for i in (0, 1, 2, 4)])
    batch, targets, _ = split_batch(sample, "cpu", data.batch_keys, data.target_keys)
    assert batch["memory_boxes"][0, 0, 4] == 0 and not batch["memory"][0, 0].any()
    assert bool((batch["memory_boxes"][1:, :, 4] == 1).all())
    return batch, targets


def test_randomised_memory_batch_keeps_shapes_masks_and_seeds():
    batch, targets = memory_batch()
    rb, rt = randomize_batch(batch, targets, np.random.default_rng(0), ALWAYS)
    assert set(rb) == set(batch) and set(rt) == set(targets)
    for key in batch:
        assert rb[key].shape == batch[key].shape and rb[key].dtype == batch[key].dtype
    for key in ("size", "memory_boxes"):
        assert torch.equal(rb[key], batch[key])
    assert torch.equal(rt["box"], targets["box"])
    assert not rb["memory"][0, 0].any()  # the empty slot stays empty
    assert not torch.equal(rb["memory"], batch["memory"])
    assert not torch.equal(rb["search"], batch["search"])

    def follows(old_pts, old_vals, new_pts, new_vals):
        """An original point keeps its value (no jitter here); an added noise point is 0."""
        lookup = {tuple(p): v for p, v in zip(old_pts, old_vals, strict=True)}
        is_orig = np.array([tuple(p) in lookup for p in new_pts])
        want = np.array([lookup.get(tuple(p), 0.0) for p in new_pts])
        np.testing.assert_array_equal(new_vals, want)
        assert (~is_orig).any()  # noise points were added
        assert not new_vals[~is_orig].any()

    for b in range(4):
        s_old, s_new = batch["search"][b].numpy(), rb["search"][b].numpy()
        follows(s_old, targets["search_labels"][b].numpy(), s_new, rt["search_labels"][b].numpy())
        for j in range(2):
            if not batch["memory"][b, j].any():
                continue
            old, new = batch["memory"][b, j].numpy(), rb["memory"][b, j].numpy()
            follows(old[:, :3], old[:, 3], new[:, :3], new[:, 3])
    # seeded: the same generator, the same bytes; another seed, other draws
    again = randomize_batch(batch, targets, np.random.default_rng(0), ALWAYS)
    for key in ("search", "memory"):
        assert rb[key].numpy().tobytes() == again[0][key].numpy().tobytes()
    assert rt["search_labels"].numpy().tobytes() == again[1]["search_labels"].numpy().tobytes()
    other = randomize_batch(batch, targets, np.random.default_rng(1), ALWAYS)
    assert not torch.equal(other[0]["memory"], rb["memory"])


def test_memory_records_average_the_frames_with_points():
    """Hand check of sample_contrast: one record per sample (search) and one of two memory
    frames per sample, where sample 0's first frame is an empty slot (all-zero seeds)."""
    g = torch.Generator().manual_seed(0)
    b, m, s, d = 2, 2, 6, 4

    def cloud(f):
        return torch.randn(f, s, 3, generator=g), torch.randn(f, s, d, generator=g)

    search_p, search_a, mem_p, mem_a = cloud(b), cloud(b), cloud(b * m), cloud(b * m)
    mem_a[0][0] = 0.0  # sample 0, slot 0: no points
    mem_p[0][0] = 0.0
    got = sample_contrast([search_p, mem_p], [search_a, mem_a], b, 0.7, 3)

    def one(p, a):
        return local_geometric_contrast(a[0], a[1], p[0], p[1], 0.7, 3)

    c_search, c_mem = one(search_p, search_a), one(mem_p, mem_a).view(b, m)
    want = torch.stack([(c_search[0] + c_mem[0, 1]) / 2, (c_search[1] + c_mem[1].mean()) / 2])
    torch.testing.assert_close(got, want)
    # a sample with no memory frame at all: the search region alone
    mem_a[0][1] = 0.0
    mem_p[0][1] = 0.0
    alone = sample_contrast([search_p, mem_p], [search_a, mem_a], b, 0.7, 3)
    torch.testing.assert_close(alone[0], c_search[0])
    with pytest.raises(RuntimeError, match="3 clouds for 2 samples"):
        sample_contrast([cloud(3)], [cloud(3)], b, 0.7, 3)


def test_tap_reads_the_dgcnn_backbone_and_applies_the_ffn_once():
    model = tiny_mbptrack()
    drct = DRCT(model)
    assert point_backbone(model) == (model.backbone, "forward")
    assert drct.ffn.fc1.in_features == TINY["feat_dim"]
    torch.nn.init.normal_(drct.ffn.fc2.weight, std=0.1)  # a non-identity FFN
    batch, _ = memory_batch()

    def records(net, transform=None):  # a training forward with the same sampling orders
        net.train()
        net.generator.manual_seed(3)
        with tap_backbone(net, transform) as tapped, torch.no_grad():
            net(batch)
        return tapped

    p, a = records(model), records(drct.aux, drct.ffn)
    assert [x.shape[0] for x, _ in p] == [4, 8]  # the search regions, then 4 x 2 memory frames
    for (px, pf), (ax, af) in zip(p, a, strict=True):
        torch.testing.assert_close(px, ax)
        with torch.no_grad():
            torch.testing.assert_close(af, drct.ffn(pf))
    assert "forward" not in vars(model.backbone)  # restored
    assert set(model.state_dict()) == set(tiny_mbptrack().state_dict())


@pytest.mark.parametrize("variant", ["asymmetric", "siamese"])
def test_drct_losses_are_finite_and_train_both_branches(variant):
    model = tiny_mbptrack()
    drct = DRCT(model, DRCTConfig(variant=variant, seed=1, randomization=ALWAYS))
    batch, targets = memory_batch()
    model.train()
    _, losses = drct.forward_losses(model, model, batch, targets, step=0)
    assert set(losses) >= {"total", "track", "aux_track", "contrast", "mask", "bbox"}
    for key in ("total", "track", "aux_track", "contrast"):
        assert losses[key].shape == (4,) and bool(torch.isfinite(losses[key]).all()), key
    assert bool((losses["contrast"] > 0).all())
    torch.testing.assert_close(
        losses["total"], losses["track"] + losses["aux_track"] + 0.01 * losses["contrast"]
    )
    losses["total"].mean().backward()
    assert any(p.grad is not None and p.grad.abs().sum() > 0 for p in model.loc.parameters())
    if variant == "asymmetric":
        assert drct.ffn.fc2.weight.grad.abs().sum() > 0
        assert any(p.grad is not None and p.grad.abs().sum() > 0 for p in drct.aux.parameters())
    else:
        assert drct.aux is None and drct.ffn is None and not list(drct.parameters())


@pytest.mark.parametrize("variant", ["asymmetric", "siamese"])
def test_contrast_vanishes_when_both_branches_see_the_same_clouds(variant):
    """Without randomisation, in eval (hash orders, fixed BatchNorm statistics), both branches
    encode the same clouds the same way (the asymmetric FFN starts as the identity). With
    neighbourhoods that cover every seed (a ball of 1 km, as many neighbours as the 128 seeds of
    a 1024-point cloud) both sides of Eq. 5 are the max over all seeds: the contrast is its
    epsilon floor. With randomisation it is not."""
    model = tiny_mbptrack()
    batch, targets = memory_batch()
    model.eval()
    whole = {"variant": variant, "radius_m": 1e3, "neighbours": 128}
    drct = DRCT(model, DRCTConfig(**whole, randomization=DomainRandomization(p_skip=1.0)))
    for net in {model, drct.aux} - {None}:  # one batched backbone call per cloud kind
        net.fast_eval = net.batch_invariant = False
    with torch.no_grad():
        _, same = drct.forward_losses(model, model, batch, targets, step=0)
        drct.config = DRCTConfig(**whole, randomization=ALWAYS)
        _, moved = drct.forward_losses(model, model, batch, targets, step=0)
    assert float(same["contrast"].max()) < 1e-5
    torch.testing.assert_close(same["aux_track"], same["track"])
    assert bool((moved["contrast"] > 1e-3).all())


def test_rd_control_trains_on_randomised_memory_samples():
    model = tiny_mbptrack()
    batch, targets = memory_batch()
    model.train()
    state = model.generator.get_state()
    plain = model.loss(model(batch), targets)["total"]
    model.generator.set_state(state)
    _, losses = DomainRandomizedTraining(ALWAYS, seed=2).forward_losses(
        model, model, batch, targets, step=0
    )
    assert losses["total"].shape == (4,) and bool(torch.isfinite(losses["total"]).all())
    assert not torch.allclose(losses["total"], plain)
    model.generator.set_state(state)
    _, same = DomainRandomizedTraining(DomainRandomization(p_skip=1.0), seed=2).forward_losses(
        model, model, batch, targets, step=0
    )
    torch.testing.assert_close(same["total"], plain)


def test_config_accepts_mbptrack_and_refuses_m2track():
    for key in ("drct", "domain_randomize"):
        assert getattr(config_from_dict({"tracker": "mbptrack", key: True}), key)
        with pytest.raises(ConfigError, match=f"{key}.*or mbptrack, not 'm2track'"):
            config_from_dict({"tracker": "m2track", key: True})


@pytest.mark.parametrize("flags", [["--drct"], ["--domain-randomize"]])
def test_cli_trains_mbptrack_and_exports_the_primary_alone(tmp_path, flags):
    from safetensors import safe_open

    from training.cli import main

    out, path = tmp_path / "run", tmp_path / "mbptrack.safetensors"
    argv = [
        "train",
        "--tracker",
        "mbptrack",
        "--model-size",
        "slim",
        *flags,
        "--setting",
        "kitti-1",
        "--dataset",
        "synthetic",
        "--preset",
        "tiny",
        "--epochs",
        "1",
        "--iters-per-epoch",
        "1",
        "--batch-size",
        "2",
        "--val-max-tracklets",
        "1",
        "--val-max-frames",
        "4",
        "--no-progress",
        "--out",
        str(out),
        "--export",
        str(path),
    ]
    assert main(argv) == 0
    assert (out / "best.pt").exists()
    ckpt = torch.load(out / "best.pt", weights_only=True)
    plain_keys = set(
        trackers.make("mbptrack", **trackers.size_config("mbptrack", "slim")).state_dict()
    )
    assert set(ckpt["model"]) == plain_keys
    if flags == ["--drct"]:
        assert any(k.startswith("aux.") for k in ckpt["drct"])
        assert any(k.startswith("ffn.") for k in ckpt["drct"])
    else:
        assert not ckpt["drct"]
    loaded = trackers.load(str(path))
    assert type(loaded).__name__ == "MBPTrack" and set(loaded.state_dict()) == plain_keys
    with safe_open(str(path), "pt") as f:
        names = list(f.keys())
    # the primary's tensors alone (MBPTrack's own transformer has "ffn" layers: names, not
    # substrings, are compared)
    assert set(names) == plain_keys
