"""DRCT (training.drct): the local geometric contrast, the two branches, training and export."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch
from test_pretrain_support import small_dataset, tiny_config

from envs.geometry import points_in_box
from envs.weather import DomainRandomization
from training.config import ConfigError, config_from_dict, tracker_config
from training.drct import (
    DRCT,
    DomainRandomizedTraining,
    DRCTConfig,
    local_geometric_contrast,
    randomize_batch,
    tap_backbone,
)
from training.samples import split_batch


def slim_p2b(seed: int = 0):
    import trackers

    torch.manual_seed(seed)
    return trackers.make("p2b", **tracker_config("p2b", "slim"))


def a_batch(n: int = 4, seed: int = 0):
    data = small_dataset(seed)
    sample = torch.utils.data.default_collate([data[i] for i in range(n)])
    batch, targets, _ = split_batch(sample)
    return batch, targets


def test_contrast_against_a_hand_computed_case():
    key = torch.tensor([[[0.0, 0, 0], [0.5, 0, 0], [3.0, 0, 0]]])
    aux = torch.tensor([[[1.0, 0], [0.0, 2], [5.0, 5]]])
    prim_xyz = torch.tensor([[[0.0, 0, 0.1], [3.0, 0, 0], [4.0, 0, 0]]])
    prim = torch.tensor([[[0.0, 3], [1.0, 1], [2.0, -1]]])
    # ball query r = 1 among the key points: {0, 1}, {0, 1}, {2} -> max [1,2], [1,2], [5,5]
    # 2 nearest primary points: {0, 1}, {0, 1}, {1, 2} -> max [1,3], [1,3], [2,1]
    # norms of the differences: 1, 1, 5 -> mean 7/3
    got = local_geometric_contrast(key, aux, prim_xyz, prim, radius_m=1.0, neighbours=2)
    assert got.shape == (1,)
    assert float(got[0]) == pytest.approx(7.0 / 3.0, rel=1e-6)
    # a batch of two: per sample, and the same sample gives the same value
    two = local_geometric_contrast(
        key.repeat(2, 1, 1),
        torch.cat([aux, aux * 0]),
        prim_xyz.repeat(2, 1, 1),
        prim.repeat(2, 1, 1),
        1.0,
        2,
    )
    want_second = (math.sqrt(1 + 9) * 2 + math.sqrt(4 + 1)) / 3  # zero aux features
    assert two[0] == pytest.approx(7.0 / 3.0, rel=1e-6)
    assert two[1] == pytest.approx(want_second, rel=1e-6)


def test_gradients_reach_the_primary_branch_only_through_the_contrast():
    model = slim_p2b()
    drct = DRCT(model, DRCTConfig(seed=1))
    batch, targets = a_batch()
    _, losses = drct.forward_losses(model, model, batch, targets, step=0)
    assert set(losses) >= {"total", "track", "aux_track", "contrast"}
    assert losses["contrast"].shape == (4,) and bool((losses["contrast"] > 0).all())
    losses["contrast"].sum().backward()
    prim = [p.grad for p in model.backbone.parameters()]
    assert any(g is not None and g.abs().sum() > 0 for g in prim)
    # the auxiliary side is the teacher: detached, no gradient from the contrast
    assert all(p.grad is None for p in drct.parameters())
    # the full objective trains the auxiliary branch (its FFN) through its tracking loss
    model.zero_grad()
    _, losses = drct.forward_losses(model, model, batch, targets, step=0)
    losses["total"].mean().backward()
    assert drct.ffn.fc2.weight.grad.abs().sum() > 0
    assert any(p.grad is not None and p.grad.abs().sum() > 0 for p in drct.aux.head.parameters())
    total = losses["track"] + losses["aux_track"] + 0.01 * losses["contrast"]
    torch.testing.assert_close(losses["total"], total)


def test_branches_start_equal_and_the_tap_leaves_the_backbone_alone():
    model = slim_p2b()
    drct = DRCT(model)
    assert drct.aux is not model
    for (k, a), (_, b) in zip(
        drct.aux.state_dict().items(), model.state_dict().items(), strict=True
    ):
        torch.testing.assert_close(a, b, msg=k)
    # the FFN starts as the identity: on the same clean input both branches agree
    batch, _ = a_batch(2)
    model.eval()
    drct.aux.eval()
    # one batched eval forward (batch-invariant eval would run the backbone once per sample)
    model.batch_invariant = drct.aux.batch_invariant = False
    with tap_backbone(model) as p, torch.no_grad():
        model(batch)
    with tap_backbone(drct.aux, drct.ffn) as a, torch.no_grad():
        drct.aux(batch)
    assert len(p) == len(a) == 2  # template, search
    for (px, pf), (ax, af) in zip(p, a, strict=True):
        torch.testing.assert_close(px, ax)
        torch.testing.assert_close(pf, af)
    assert "forward_many" not in vars(model.backbone)  # restored
    assert set(model.state_dict()) == set(slim_p2b().state_dict())


def test_tap_records_each_cloud_once_and_applies_the_ffn_once_in_training():
    """In training the backbone encodes one cloud per (recursive) call; the tap must still see
    two clouds and transform each once."""
    model = slim_p2b()
    drct = DRCT(model)
    torch.nn.init.normal_(drct.ffn.fc2.weight, std=0.1)  # a non-identity FFN
    batch, _ = a_batch(2)
    model.train()
    drct.aux.train()
    model.generator.manual_seed(5)
    with tap_backbone(model) as p, torch.no_grad():
        model(batch)
    drct.aux.generator.manual_seed(5)
    with tap_backbone(drct.aux, drct.ffn) as a, torch.no_grad():
        drct.aux(batch)
    assert len(p) == len(a) == 2
    for (px, pf), (ax, af) in zip(p, a, strict=True):
        torch.testing.assert_close(px, ax)
        with torch.no_grad():
            torch.testing.assert_close(af, drct.ffn(pf))
        assert not torch.allclose(af, pf)


def test_siamese_variant_shares_parameters():
    model = slim_p2b()
    drct = DRCT(model, DRCTConfig(variant="siamese"))
    assert drct.aux is None and drct.ffn is None and not list(drct.parameters())
    batch, targets = a_batch()
    _, losses = drct.forward_losses(model, model, batch, targets, step=3)
    losses["total"].mean().backward()
    assert any(p.grad is not None and p.grad.abs().sum() > 0 for p in model.head.parameters())
    assert torch.isfinite(losses["total"]).all()


def test_randomized_batch_labels_follow_points():
    batch, targets = a_batch(6)
    dr = DomainRandomization(p_skip=0.0, p_step=1.0, max_noise_ratio=0.3, jitter_m=0.0)
    rb, rt = randomize_batch(batch, targets, np.random.default_rng(0), dr)
    for key in ("template", "search", "size", "motion"):
        assert rb[key].shape == batch[key].shape and rb[key].dtype == batch[key].dtype
    torch.testing.assert_close(rb["size"], batch["size"])
    assert not torch.equal(rb["search"], batch["search"])
    for b in range(6):
        search = rb["search"][b].numpy()
        labels = rt["search_labels"][b].numpy().astype(bool)
        inside = points_in_box(search, targets["search_box"][b].numpy().astype(np.float64))
        orig = {tuple(p) for p in batch["search"][b].numpy()}
        is_orig = np.array([tuple(p) in orig for p in search])
        # an original point keeps its label (= inside the box, no jitter here); noise is 0
        np.testing.assert_array_equal(labels[is_orig], inside[is_orig])
        assert not labels[~is_orig].any()
        assert (~is_orig).any()  # noise points were added
        half = rb["template"].shape[1] // 2
        c = rt["template_centers"][b].numpy()
        np.testing.assert_array_equal(c[:half], targets["template_centers"][b, :half].numpy())
        np.testing.assert_array_equal(
            c[half:], np.broadcast_to(targets["template_centers"][b, half], c[half:].shape)
        )
    again = randomize_batch(batch, targets, np.random.default_rng(0), dr)
    torch.testing.assert_close(again[0]["search"], rb["search"])
    # an empty (all-zero) crop stays empty
    empty = dict(batch)
    empty["search"] = torch.zeros_like(batch["search"])
    zt = dict(targets)
    zt["search_labels"] = torch.zeros_like(targets["search_labels"])
    eb, et = randomize_batch(empty, zt, np.random.default_rng(1), dr)
    assert not eb["search"].any() and not et["search_labels"].any()


def test_domain_randomized_control_trains_on_randomised_samples():
    model = slim_p2b()
    rd = DomainRandomizedTraining(DomainRandomization(p_skip=0.0, p_step=1.0), seed=2)
    batch, targets = a_batch()
    model.train()
    gen_state = model.generator.get_state()
    plain = model.loss(model(batch), targets)["total"]
    model.generator.set_state(gen_state)
    _, losses = rd.forward_losses(model, model, batch, targets, step=0)
    assert losses["total"].shape == (4,) and torch.isfinite(losses["total"]).all()
    assert not torch.allclose(losses["total"], plain)  # the samples were randomised
    # and with randomisation switched off it is plain training, draw for draw
    off = DomainRandomizedTraining(DomainRandomization(p_skip=1.0), seed=2)
    model.generator.set_state(gen_state)
    _, same = off.forward_losses(model, model, batch, targets, step=0)
    torch.testing.assert_close(same["total"], plain)
    assert not list(rd.parameters())


def test_train_drct_export_has_no_auxiliary_branch_and_resumes_exactly(tmp_path):
    import trackers
    from training.pretrain import load_weights, tracker_from_checkpoint, train

    def run(out, epochs, resume=False, **kw):
        cfg = tiny_config(
            out,
            epochs=epochs,
            batch_size=2,
            iters_per_epoch=2,
            model_size="slim",
            drct=True,
            weighting="decorrelation",
            **kw,
        )
        return train(cfg, resume=resume, train_data=small_dataset(), val_fn=False)

    run(tmp_path / "a", 2)
    run(tmp_path / "b", 1)
    run(tmp_path / "b", 2, resume=True)
    wa, cfg = load_weights(tmp_path / "a" / "last.pt")
    wb, _ = load_weights(tmp_path / "b" / "last.pt")
    assert cfg["drct"] is True
    for k in wa:
        torch.testing.assert_close(wa[k], wb[k], rtol=0, atol=0, msg=k)
    ckpt = torch.load(tmp_path / "a" / "last.pt", weights_only=True)
    assert any(k.startswith("aux.") for k in ckpt["drct"])
    assert any(k.startswith("ffn.") for k in ckpt["drct"])
    plain_keys = set(slim_p2b().state_dict())
    assert set(ckpt["model"]) == plain_keys
    tracker = tracker_from_checkpoint(tmp_path / "a" / "last.pt")
    path = tmp_path / "p2b-drct.safetensors"
    trackers.save(tracker, path)
    loaded = trackers.load(str(path))
    assert set(loaded.state_dict()) == plain_keys
    from safetensors import safe_open

    with safe_open(str(path), "pt") as f:
        names = list(f.keys())
    assert names and not any("aux" in n or "ffn" in n for n in names)


def test_bad_options():
    with pytest.raises(ValueError, match="asymmetric, siamese"):
        DRCTConfig(variant="twin")
    with pytest.raises(ValueError, match="neighbours"):
        DRCTConfig(neighbours=0)
    from trackers.baselines import PreviousBox

    with pytest.raises(ValueError, match="p2b, bat, gpt"):
        DRCT(PreviousBox())
    with pytest.raises(ConfigError, match="drct_variant.*asymmetric, siamese"):
        config_from_dict({"drct": True, "drct_variant": "twin"})
    with pytest.raises(ConfigError, match="domain_randomize"):
        config_from_dict({"drct": True, "domain_randomize": True})
    with pytest.raises(ConfigError, match="dr_p_skip"):
        config_from_dict({"domain_randomize": True, "dr_p_skip": 1.5})
    with pytest.raises(ConfigError, match="unknown keys: drct_foo"):
        config_from_dict({"drct_foo": 1})
    from training.cli import main

    with pytest.raises(SystemExit):  # a baseline is not a training choice
        main(["train", "--drct", "--tracker", "previous_box", "--out", "x"])
    with pytest.raises(SystemExit):
        main(["train", "--drct", "--drct-variant", "twin", "--out", "x"])


def test_cli_flags_set_the_config():
    import argparse

    from training.commands.train import add_arguments, build_config

    parser = argparse.ArgumentParser()
    add_arguments(parser)
    cfg = build_config(
        parser.parse_args(
            [
                "--drct",
                "--drct-variant",
                "siamese",
                "--weighting",
                "decorrelation",
                "--set",
                "drct_neighbours=4",
            ]
        )
    )
    assert cfg.drct and cfg.drct_variant == "siamese" and cfg.weighting == "decorrelation"
    assert cfg.drct_neighbours == 4
    assert not build_config(parser.parse_args([])).drct
    assert build_config(parser.parse_args(["--domain-randomize"])).domain_randomize


def test_drct_with_sam_and_the_rd_control_train(tmp_path):
    """--drct with --weighting sam (the SAM closure recomputes the DRCT objective on the same
    randomised batch) and the -RD control both run and move the weights."""
    from training.pretrain import load_weights, train

    start = {k: v.clone() for k, v in slim_p2b().state_dict().items()}
    for name, kw in (
        ("sam", {"drct": True, "weighting": "sam"}),
        ("rd", {"domain_randomize": True}),
    ):
        cfg = tiny_config(
            tmp_path / name, epochs=1, batch_size=2, iters_per_epoch=1, model_size="slim", **kw
        )
        result = train(
            cfg, train_data=small_dataset(), val_fn=False, model_factory=lambda c: slim_p2b()
        )
        assert result.steps == 1
        weights, _ = load_weights(tmp_path / name / "last.pt")
        moved = [
            k
            for k in start
            if start[k].is_floating_point() and not torch.equal(start[k], weights[k])
        ]
        assert moved, name
        log = (tmp_path / name / "log.jsonl").read_text()
        assert "NaN" not in log


def test_grad_clip_covers_the_auxiliary_branch(tmp_path):
    """One norm over both branches: with a vanishing clip, Adam's first step moves neither the
    primary tracker nor the auxiliary copy of it (unclipped, the copy would move by ~lr)."""
    from training.pretrain import train

    cfg = tiny_config(
        tmp_path / "run",
        epochs=1,
        batch_size=2,
        iters_per_epoch=1,
        model_size="slim",
        drct=True,
        lr=1e-2,
        grad_clip=1e-14,
    )
    train(cfg, train_data=small_dataset(), val_fn=False)
    ckpt = torch.load(tmp_path / "run" / "last.pt", weights_only=True)
    parameter_names = [name for name, _ in slim_p2b().named_parameters()]
    for name in parameter_names:
        primary, aux = ckpt["model"][name], ckpt["drct"][f"aux.{name}"]
        torch.testing.assert_close(aux, primary, rtol=0, atol=1e-6, msg=name)
