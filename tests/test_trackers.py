"""The matching trackers (P2B, BAT, GPT: every registered MatchingTracker): the forward / loss / act
contract, exact speed tricks, determinism, bad input."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

import trackers
from trackers import ops
from trackers.backbone import SetAbstraction
from trackers.base import DEFAULT_MAX_ACTION, MatchingTracker, prepare_observation
from trackers.gpt import GraphFusion
from trackers.p2b import P2BFusion
from trackers.toy import toy_batch

# every registered matching tracker (P2B, BAT, GPT; one registered later is covered too): the
# tests parametrised by NAMES check the matching contract (seeds, votes, proposals, scores)
NAMES = [
    n
    for n in trackers.available("learned")
    if issubclass(trackers.tracker_class(n), MatchingTracker)
]
# the same code paths with narrow layers (fast tests); the contract tests use the full models
TINY = {
    "backbone": {"channels": [[16, 16, 32], [32, 32, 64], [64, 64, 64]], "out_channels": 64},
    "head": {"vote_channels": 64},
    "out_channels": 64,
}
# each fusion's own narrow widths; a matching tracker not listed keeps its fusion's defaults
EXTRA = {
    "p2b": {"hidden_channels": 64},
    "bat": {"hidden_channels": 64},
    "gpt": {"node_channels": 32, "itc_channels": 32},
}


def tiny(name, **kw):
    return trackers.make(name, **{**TINY, **EXTRA.get(name, {}), **kw})


def shipped_tracker(checkpoint: str) -> str:
    """The tracker name a shipped checkpoint records (read from its metadata, not its weights)."""
    from safetensors import safe_open

    path = trackers.registry.find_checkpoint(checkpoint)
    if path.suffix != ".safetensors":
        return torch.load(path, weights_only=True)["tracker"]
    with safe_open(str(path), framework="pt") as f:
        return f.metadata()["tracker"]


# every shipped checkpoint of a matching tracker
SHIPPED = [c for c in trackers.available("checkpoint") if shipped_tracker(c) in NAMES]


pytestmark = pytest.mark.usefixtures("one_torch_thread")


def test_the_lists_come_from_the_registry():
    """NAMES and SHIPPED are read from the registry and the shipped files: they hold at least
    the trackers and files these tests were written for, and no non-matching tracker."""
    assert {"p2b", "bat", "gpt"} <= set(NAMES)
    assert "m2track" not in NAMES and "previous_box" not in NAMES
    assert {f"{n}-kitti1-{w}" for n in ("p2b", "bat", "gpt") for w in "uw"} <= set(SHIPPED)
    assert not any(c.startswith("m2track") for c in SHIPPED)


@pytest.fixture(scope="module")
def toy():
    return toy_batch(2, seed=0)


@pytest.fixture(scope="module")
def models():
    torch.manual_seed(0)
    return {name: trackers.make(name) for name in NAMES}


def _single(batch, i=0):
    return {k: v[i].numpy() for k, v in batch.items()}


@pytest.mark.parametrize("name", NAMES)
def test_forward_and_loss_contract(name, models, toy):
    model = models[name].train()
    batch, targets = toy
    out = model(batch, generator=torch.Generator().manual_seed(0))
    assert out["Z"].shape == (2, 128, 256)
    assert out["proposals"].shape == (2, 64, 4) and out["scores"].shape == (2, 64)
    assert out["votes"].shape == (2, 128, 3) and out["seed_logits"].shape == (2, 128)
    assert out["seed_idx"].shape == (2, 128) and out["template_seed_idx"].shape == (2, 64)
    # seeds are input points
    assert torch.equal(ops.gather(batch["search"], out["seed_idx"]), out["seed_xyz"])
    losses = model.loss(out, targets)
    expected = set(model.config.loss_weights) | {"total"}
    assert set(losses) == expected
    for key, value in losses.items():
        assert value.shape == (2,), key
        assert torch.isfinite(value).all(), key
    total = sum(model.config.loss_weights[k] * losses[k] for k in model.config.loss_weights)
    torch.testing.assert_close(losses["total"], total)


def test_loss_weights_follow_the_papers(models):
    assert models["p2b"].config.loss_weights == {
        "vote": 1.0,
        "seed": 0.2,
        "objectness": 1.5,
        "box": 0.2,
    }
    assert models["bat"].config.loss_weights["box_cloud"] == 1.0
    assert models["gpt"].config.loss_weights == {
        "vote": 0.9,
        "template_vote": 0.1,
        "seed": 0.2,
        "box": 0.2,
        "objectness": 1.5,
    }


@pytest.mark.parametrize("name", NAMES)
def test_gradients_reach_every_parameter(name, toy):
    torch.manual_seed(1)
    model = tiny(name).train()
    batch, targets = toy
    out = model(batch, generator=torch.Generator().manual_seed(0))
    targets = dict(targets)
    # put the ground-truth centre on a proposal centre so the box loss has positives
    box = targets["search_box"].clone()
    box[:, :3] = out["proposal_centers"][:, 0].detach()
    targets["search_box"] = box
    model.loss(out, targets)["total"].sum().backward()
    missing = [
        n for n, p in model.named_parameters() if p.grad is None or not p.grad.abs().sum() > 0
    ]
    assert not missing, missing


def test_proposal_labels_and_box_target():
    """Positive within 0.3 m, ignored in (0.3, 0.6], negative beyond; box target in degrees."""
    from trackers.head import HeadConfig, head_losses

    cfg = HeadConfig()
    centres = torch.tensor([[[0.1, 0, 0], [0.45, 0, 0], [2.0, 0, 0]]])
    gt = torch.tensor([[0.0, 0, 0, 4, 2, 1.5, math.radians(10)]])
    out = {
        "votes": torch.zeros(1, 4, 3),
        "seed_logits": torch.zeros(1, 4),
        "proposal_centers": centres,
        "scores": torch.tensor([[5.0, -50.0, -5.0]]),
        "box_raw": torch.tensor([[[0.0, 0, 0, 10.0], [9, 9, 9, 9], [9, 9, 9, 9]]]),
    }
    losses = head_losses(out, gt, torch.zeros(1, 4), cfg)
    assert losses["box"].item() == pytest.approx(0.0, abs=1e-5)  # only the positive counts
    bce = torch.nn.functional.binary_cross_entropy_with_logits
    pos = bce(torch.tensor(5.0), torch.tensor(1.0))
    neg = bce(torch.tensor(-5.0), torch.tensor(0.0))
    expected = (2.0 * pos + neg) / 2  # pos_weight 2; the ignored proposal's -50 logit is excluded
    assert losses["objectness"].item() == pytest.approx(expected.item(), rel=1e-4)


def test_size_relative_proposal_labels():
    """``positive_fraction f``: radii max(0.3, f r) / max(0.6, 2 f r), r half the xy diagonal,
    per sample; f = 0 is the fixed rule."""
    from trackers.head import HeadConfig, proposal_labels

    # a 6 x 2.5 m van (r = 3.25 m) and a 0.8 x 0.6 m pedestrian (r = 0.5 m); offsets along x
    boxes = torch.tensor([[0.0, 0, 0, 6.0, 2.5, 2, 0], [1.0, 2, 0, 0.8, 0.6, 1.7, 0.3]])
    offsets = torch.tensor([0.2, 0.5, 0.7, 1.0, 1.4])
    centres = boxes[:, None, :3] + offsets[None, :, None] * torch.tensor([1.0, 0, 0])
    fixed_pos, fixed_counted = proposal_labels(centres, boxes, HeadConfig())
    expect_pos = [1, 0, 0, 0, 0]
    expect_counted = [1, 0, 1, 1, 1]  # ignored within (0.3, 0.6]
    assert fixed_pos.tolist() == [expect_pos, expect_pos]
    assert fixed_counted.tolist() == [expect_counted, expect_counted]
    pos, counted = proposal_labels(centres, boxes, HeadConfig(positive_fraction=0.2))
    # van: 0.2 * 3.25 = 0.65 m positive, 1.3 m negative; pedestrian: 0.1 / 0.2 -> 0.3 / 0.6
    assert pos.tolist() == [[1, 1, 0, 0, 0], expect_pos]
    assert counted.tolist() == [[1, 1, 0, 0, 1], expect_counted]
    with pytest.raises(ValueError, match="positive_fraction"):
        HeadConfig(positive_fraction=-0.1)


def p2b_naive(fusion, t_xyz, t_feat, s_feat):
    """P2B's TFA as written: the explicit ``(B, M_T, M_S, 1 + 3 + D)`` concatenation."""
    cos = fusion.cosine(t_feat, s_feat)
    mt, ms = cos.shape[1], cos.shape[2]
    t = torch.cat([t_xyz, t_feat], dim=-1)[:, :, None, :].expand(-1, mt, ms, -1)
    return fusion.post(fusion.mlp(torch.cat([cos[..., None], t], dim=-1)).amax(dim=1))


def gpt_naive(fusion, t_xyz, t_feat, s_feat):
    """GPT's EdgeConv as written: explicit ``[x_T; f_T - f_S; clue]`` edge features."""
    f_t, f_s = fusion.phi(t_feat), fusion.varphi(s_feat)
    if fusion.use_itc:
        seed = torch.cat([t_xyz, t_feat], dim=-1)
        clue = fusion.itc((seed + fusion.template_vote(seed))[..., 3:])
    else:
        clue = f_t
    _, nbr = ops.knn(min(fusion.k, f_t.shape[1]), f_s, f_t)
    g_x, g_f, g_c = ops.group(t_xyz, nbr), ops.group(f_t, nbr), ops.group(clue, nbr)
    edge_in = torch.cat([g_x, g_f - f_s[:, :, None, :], g_c], dim=-1)
    return fusion.edge(edge_in).amax(dim=2)


def test_p2b_fusion_trick_equals_naive_concatenation():
    torch.manual_seed(2)
    fusion = P2BFusion(32, 48, 40)
    t_xyz, t_feat, s_feat = torch.randn(2, 16, 3), torch.randn(2, 16, 32), torch.randn(2, 24, 32)
    for mode, fast in ((True, True), (False, False), (False, True)):
        fusion.train(mode)
        fusion.fast_eval = fast
        for grad in (True, False):
            with torch.set_grad_enabled(grad):
                expected = p2b_naive(fusion, t_xyz, t_feat, s_feat)
                got = fusion(t_xyz, t_feat, s_feat)
            torch.testing.assert_close(got, expected, rtol=1e-4, atol=1e-4)


@pytest.mark.parametrize("use_itc", [True, False])
def test_gpt_edgeconv_trick_equals_naive(use_itc):
    torch.manual_seed(3)
    fusion = GraphFusion(32, 16, 16, 40, k=5, use_itc=use_itc).eval()
    t_xyz, t_feat, s_feat = torch.randn(2, 12, 3), torch.randn(2, 12, 32), torch.randn(2, 20, 32)
    torch.testing.assert_close(
        fusion(t_xyz, t_feat, s_feat)[0],
        gpt_naive(fusion, t_xyz, t_feat, s_feat),
        rtol=1e-4,
        atol=1e-4,
    )


def test_set_abstraction_decomposed_and_ragged_equal_naive():
    torch.manual_seed(4)
    sa = SetAbstraction(8, (16, 16, 24), radius=0.3, k=8)
    xyz, feats = torch.rand(2, 200, 3), torch.randn(2, 200, 8)
    # naive: explicit [p_j - c_i; f_j] grouping
    centres = xyz[:, :100]
    idx = ops.ball_query(0.3, 8, xyz, centres)
    naive_in = torch.cat([ops.group(xyz, idx) - centres[:, :, None], ops.group(feats, idx)], -1)
    for mode in (True, False):
        sa.train(mode)
        expected = sa.mlp(naive_in).amax(2)
        torch.testing.assert_close(sa(xyz, feats, 100)[1], expected, rtol=1e-4, atol=1e-4)
    sa.eval()
    sa.fast_eval = sa.mlp.fast_eval = False
    dense = sa(xyz, feats, 100)[1]
    sa.fast_eval = sa.mlp.fast_eval = True
    torch.testing.assert_close(sa(xyz, feats, 100)[1], dense, rtol=1e-5, atol=1e-5)


def out_shape_ok(out):
    return out["proposals"].shape == (2, 64, 4) and out["Z"].shape == (2, 128, 64)


@pytest.mark.parametrize("name", NAMES)
def test_eval_is_deterministic_and_order_invariant(name, toy):
    torch.manual_seed(7)
    model = tiny(name).eval()
    batch, _ = toy
    g = torch.Generator().manual_seed(5)
    perm_t, perm_s = torch.randperm(512, generator=g), torch.randperm(1024, generator=g)
    shuffled = dict(batch, template=batch["template"][:, perm_t], search=batch["search"][:, perm_s])
    with torch.no_grad():
        a, b, c = model(batch), model(batch), model(shuffled)
    assert out_shape_ok(a)
    for key in ("proposals", "scores", "Z"):
        assert torch.equal(a[key], b[key]), key
        torch.testing.assert_close(a[key], c[key], rtol=1e-4, atol=1e-4)
    np.testing.assert_allclose(model.act(batch), model.act(shuffled), rtol=1e-4, atol=1e-4)


@pytest.mark.parametrize("name", NAMES)
def test_act_single_and_batched(name, models, toy):
    model = models[name].train()  # act must switch to eval and back
    batch, _ = toy
    a_max = np.asarray(DEFAULT_MAX_ACTION, np.float32)
    single = model.act(_single(batch))
    batched = model.act({k: v.numpy() for k, v in batch.items()})
    assert model.training
    assert single.shape == (4,) and single.dtype == np.float32
    assert batched.shape == (2, 4) and np.isfinite(batched).all()
    assert (np.abs(batched) <= a_max).all()
    np.testing.assert_array_equal(single, batched[0])  # eval forwards are per sample
    torch_in = model.act(batch)  # torch tensors work too
    np.testing.assert_allclose(torch_in, batched, rtol=1e-5, atol=1e-6)
    f64 = model.act({k: v.double().numpy() for k, v in batch.items()})
    np.testing.assert_allclose(f64, batched, rtol=1e-4, atol=1e-5)


@pytest.mark.parametrize("name", NAMES)
def test_empty_template_or_search_gives_no_move(name, models, toy):
    model = models[name]
    obs = _single(toy[0])
    for key in ("template", "search"):
        empty = dict(obs, **{key: np.zeros_like(obs[key])})
        action = model.act(empty)
        assert np.isfinite(action).all()
        np.testing.assert_array_equal(action, np.zeros(4, np.float32))
    both = dict(obs, template=np.zeros_like(obs["template"]), search=np.zeros_like(obs["search"]))
    with torch.no_grad():
        out = model.eval()(prepare_observation(both)[0])
    assert all(torch.isfinite(v).all() for v in out.values() if v.is_floating_point())


def test_bad_observations_name_the_key(models, toy):
    model = models["p2b"]
    obs = _single(toy[0])
    with pytest.raises(KeyError, match="search"):
        model.act({k: v for k, v in obs.items() if k != "search"})
    with pytest.raises(ValueError, match=r"template.*\(512, 3\)"):
        model.act(dict(obs, template=obs["template"][:100]))
    with pytest.raises(ValueError, match=r"size.*\(3,\)"):
        model.act(dict(obs, size=np.ones(4, np.float32)))
    with pytest.raises(TypeError, match="search.*float"):
        model.act(dict(obs, search=obs["search"].astype(np.int32)))
    with pytest.raises(TypeError, match="motion.*float"):
        model.act(dict(obs, motion=torch.zeros(4, dtype=torch.long)))
    with pytest.raises(ValueError, match="template.*NaN"):
        bad = obs["template"].copy()
        bad[3, 1] = np.nan
        model.act(dict(obs, template=bad))
    with pytest.raises(ValueError, match="search.*NaN or inf"):  # a tensor, checked by torch
        bad = torch.from_numpy(obs["search"].copy())
        bad[0, 2] = float("inf")
        model.act(dict(obs, search=bad))
    with pytest.raises(ValueError, match="motion.*NaN or inf"):  # finite in float64, not float32
        model.act(dict(obs, motion=np.full(4, 1e39)))
    np.testing.assert_array_equal(  # float64 arrays are read as float32
        model.act({k: v.astype(np.float64) for k, v in obs.items()}), model.act(obs)
    )
    with pytest.raises(ValueError, match="mixes single and batched"):
        model.act(dict(obs, search=obs["search"][None]))
    with pytest.raises(ValueError, match="batch size"):
        batched = {k: np.stack([v, v]) for k, v in obs.items()}
        batched["size"] = np.ones((3, 3), np.float32)
        model.act(batched)
    with pytest.raises(TypeError, match="dict"):
        model.act([obs["template"]])
    with pytest.raises(ValueError, match="search"):
        model(dict(toy[0], search=toy[0]["search"][..., :2]))


def test_make_rejects_bad_config():
    with pytest.raises(ValueError, match="unknown key.*hiden_channels"):
        trackers.make("p2b", hiden_channels=12)
    with pytest.raises(ValueError, match="head.*unknown key.*radius"):
        trackers.make("bat", head={"radius": 1.0})
    with pytest.raises(ValueError, match="yaw_unit"):
        trackers.make("gpt", head={"yaw_unit": "grad"})
    with pytest.raises(ValueError, match="unknown loss term"):
        trackers.make("p2b", loss_weights={"box_cloud": 1.0})
    with pytest.raises(ValueError, match="unknown tracker"):
        trackers.make("p3b")


def test_make_accepts_nested_overrides():
    model = trackers.make(
        "p2b",
        sampling_seed=3,
        head={"num_proposals": 32},
        backbone={"channels": [[16, 16, 32], [32, 32, 64], [64, 64, 64]], "out_channels": 64},
        hidden_channels=64,
        out_channels=64,
    )
    batch, _ = toy_batch(1, seed=1)
    out = model.eval()(batch)
    assert out["proposals"].shape == (1, 32, 4) and out["Z"].shape == (1, 128, 64)


@pytest.mark.parametrize(
    "name,suffix", [("p2b", ".safetensors"), ("bat", ".pt"), ("gpt", ".safetensors")]
)
def test_save_load_round_trip(name, suffix, tmp_path, toy):
    torch.manual_seed(6)
    model = tiny(name, sampling_seed=11).train()
    model(toy[0])  # move BatchNorm running statistics away from their defaults
    model.eval()
    path = trackers.save(model, tmp_path / f"m{suffix}")
    loaded = trackers.load(path)
    assert type(loaded) is type(model) and not loaded.training
    assert loaded.config == model.config
    with torch.no_grad():
        a, b = model(toy[0]), loaded(toy[0])
    for key in ("proposals", "scores", "Z"):
        assert torch.equal(a[key], b[key]), key
    assert trackers.load(str(path), expect=name) is not None


def test_load_errors(tmp_path, toy):
    model = trackers.make("p2b")
    path = trackers.save(model, tmp_path / "p2b.safetensors")
    with pytest.raises(ValueError, match="holds a 'p2b' checkpoint, not 'bat'"):
        trackers.load(path, expect="bat")
    corrupted = tmp_path / "bad.safetensors"
    corrupted.write_bytes(path.read_bytes()[:1000])
    with pytest.raises(ValueError, match="corrupted"):
        trackers.load(corrupted)
    garbage = tmp_path / "garbage.pt"
    garbage.write_bytes(b"not a checkpoint at all")
    with pytest.raises(ValueError, match="corrupted"):
        trackers.load(garbage)
    # a pickled non-tensor object (not weights-only loadable) is refused
    import pathlib

    evil = tmp_path / "evil.pt"
    torch.save(
        {"format": "pointtrack-tracker", "state_dict": {}, "x": pathlib.PurePosixPath("x")}, evil
    )
    with pytest.raises(ValueError, match="weights-only"):
        trackers.load(evil)
    # weights that do not fit the stored config
    from safetensors.torch import load_file, save_file

    state = load_file(str(path))
    import json

    meta = {
        "format": "pointtrack-tracker",
        "version": "1",
        "tracker": "p2b",
        "config": json.dumps({"hidden_channels": 128}),
    }
    mismatch = tmp_path / "mismatch.safetensors"
    save_file(state, str(mismatch), metadata=meta)
    with pytest.raises(ValueError, match="do not match"):
        trackers.load(mismatch)
    meta["config"] = json.dumps({"not_a_field": 1})
    save_file(state, str(mismatch), metadata=meta)
    with pytest.raises(ValueError, match="not_a_field"):
        trackers.load(mismatch)
    save_file(state, str(mismatch), metadata={"format": "something-else"})
    with pytest.raises(ValueError, match="not a pointtrack tracker checkpoint"):
        trackers.load(mismatch)
    with pytest.raises(FileNotFoundError):
        trackers.load(tmp_path / "missing.safetensors")
    with pytest.raises(ValueError, match="unknown tracker or checkpoint"):
        trackers.load("p2b-no-such-checkpoint")
    with pytest.raises(TypeError):
        trackers.save(object(), tmp_path / "x.safetensors")


def test_load_by_name_gives_fresh_trackers_and_baselines():
    assert isinstance(trackers.load("gpt"), trackers.make("gpt").__class__)
    assert "p2b" in trackers.available() and "previous_box" in trackers.available()
    base = trackers.load("constant_velocity")
    motion = np.array([0.5, 0.1, 0.0, 0.02], np.float32)
    np.testing.assert_array_equal(base.act({"motion": motion}), motion)
    assert np.all(trackers.make("previous_box").act({"motion": motion}) == 0)


def test_fps_sampling_option_is_order_invariant(toy):
    torch.manual_seed(8)
    model = tiny("bat", backbone={**TINY["backbone"], "sampling": "fps"}).eval()
    batch = toy[0]
    perm = torch.randperm(1024, generator=torch.Generator().manual_seed(1))
    with torch.no_grad():
        a = model(batch)
        b = model(dict(batch, search=batch["search"][:, perm]))
    torch.testing.assert_close(a["proposals"], b["proposals"], rtol=1e-4, atol=1e-4)
    assert len(set(a["seed_idx"][0].tolist())) == 128
    with pytest.raises(ValueError, match="sampling"):
        trackers.make("p2b", backbone={"sampling": "grid"})


def test_loss_weight_overrides_merge_with_the_papers(toy):
    model = tiny("bat", loss_weights={"box_cloud": 0.0, "vote": 2.0})
    assert model.config.loss_weights == {
        "vote": 2.0,
        "seed": 0.2,
        "objectness": 1.5,
        "box": 0.2,
        "box_cloud": 0.0,
    }
    gpt = tiny("gpt", use_itc=False)
    assert "template_vote" not in gpt.config.loss_weights
    losses = gpt.loss(gpt(toy[0]), toy[1])
    assert "template_vote" not in losses and losses["total"].shape == (2,)


def test_ragged_training_option_trains(toy):
    torch.manual_seed(9)
    model = tiny("p2b", backbone={**TINY["backbone"], "ragged_train": True}).train()
    out = model(toy[0], generator=torch.Generator().manual_seed(0))
    model.loss(out, toy[1])["total"].sum().backward()
    assert all(p.grad is not None for p in model.backbone.parameters())
    sa = model.backbone.layers[0]
    xyz = toy[0]["search"][:, :256]
    ragged = sa(xyz, None, 128)[1]
    sa.ragged_train = False
    dense = sa(xyz, None, 128)[1]
    assert ragged.shape == dense.shape  # same layout; values differ only through BN statistics


def test_p2b_drops_repeated_template_seeds_exactly():
    from trackers.p2b_knots import unique_seeds

    torch.manual_seed(10)
    fusion = P2BFusion(32, 48, 40).eval()
    t_xyz, t_feat, s_feat = torch.randn(2, 16, 3), torch.randn(2, 16, 32), torch.randn(2, 24, 32)
    copies = torch.tensor([0, 1, 2, 0, 4, 5, 1, 7, 8, 9, 0, 11, 12, 13, 14, 2])
    t_xyz[0], t_feat[0] = t_xyz[0, copies], t_feat[0, copies]  # 4 repeated seeds in row 0
    u_xyz, u_feat = unique_seeds(t_xyz, t_feat)
    assert u_xyz.shape == (2, 16, 3)  # row 1 has 16 distinct seeds
    u0 = unique_seeds(t_xyz[:1], t_feat[:1])[0]
    assert u0.shape == (1, 12, 3) and torch.unique(u0[0], dim=0).shape[0] == 12
    with torch.no_grad():
        fast = fusion(t_xyz[:1], t_feat[:1], s_feat[:1])
        fusion.fast_eval = False
        torch.testing.assert_close(fast, fusion(t_xyz[:1], t_feat[:1], s_feat[:1]))
        torch.testing.assert_close(
            fast, p2b_naive(fusion, t_xyz[:1], t_feat[:1], s_feat[:1]), rtol=1e-4, atol=1e-4
        )


# ---------------------------------------------------------------- eval fast paths vs reference


def reference_outputs(model, batch):
    """The plain path of ``model`` (eval, ``fast_eval=False``): dense ball-query groups (no
    ragged groups, no skipping of copied points), BatchNorm not folded, the dense proposal
    aggregation, P2B's TFA on every pair."""
    import copy

    ref = copy.deepcopy(model).eval()
    ref.fast_eval = False
    with torch.no_grad():
        return ref(batch)


def padded_batch(batch, template_distinct=(40, 512), search_distinct=(150, 1024), seed=0):
    """Env-like observations: small clouds padded to the contract sizes with copies of their
    points (first row: sparse; second row left dense)."""
    g = torch.Generator().manual_seed(seed)
    out = {k: v.clone() for k, v in batch.items()}
    for key, distinct in (("template", template_distinct), ("search", search_distinct)):
        n_keep, n = distinct
        copies = torch.randint(0, n_keep, (n,), generator=g)
        copies[:n_keep] = torch.arange(n_keep)
        out[key][0] = out[key][0, copies[torch.randperm(n, generator=g)]]
    return out


def assert_outputs_close(out, ref, atol=1e-4):
    for key in ("proposals", "scores", "Z", "seed_logits"):
        torch.testing.assert_close(out[key], ref[key], rtol=0, atol=atol, msg=key)


@pytest.mark.parametrize("name", NAMES)
def test_eval_fast_paths_equal_the_plain_path_random_init(name, toy):
    torch.manual_seed(11)
    model = trackers.make(name).eval()
    for batch in (toy[0], padded_batch(toy[0])):
        with torch.no_grad():
            out = model(batch)
        assert_outputs_close(out, reference_outputs(model, batch))


@pytest.mark.parametrize("checkpoint", SHIPPED)
def test_eval_fast_paths_equal_the_plain_path_shipped_checkpoints(checkpoint, toy):
    """Fast vs plain on the shipped checkpoints. A heavily padded template (12 distinct points)
    gives GPT many template nodes at nearly equal feature distances, so its k-NN graph flips
    with the last bits of the (folded vs unfolded BatchNorm) features: for that row GPT's
    backbone seeds are compared, the rest of its outputs only on the dense row."""
    import copy

    model = trackers.load(checkpoint).eval()
    plain = copy.deepcopy(model)
    plain.fast_eval = False
    for padded, batch in enumerate((toy[0], padded_batch(toy[0], (12, 512), (60, 1024), seed=1))):
        with torch.no_grad():
            out = model(batch)
            ref = plain(batch)
            orders = model.sampling_orders(batch["template"], batch["search"], None)
            seeds = model.backbone.forward_many([batch["template"], batch["search"]], orders)
            ref_seeds = plain.backbone.forward_many([batch["template"], batch["search"]], orders)
        for (xyz, feat, idx), (ref_xyz, ref_feat, ref_idx) in zip(seeds, ref_seeds, strict=True):
            assert torch.equal(xyz, ref_xyz) and torch.equal(idx, ref_idx)
            torch.testing.assert_close(feat, ref_feat, rtol=0, atol=1e-4)
        rows = slice(1, 2) if padded and shipped_tracker(checkpoint) == "gpt" else slice(None)
        assert_outputs_close(
            {k: v[rows] for k, v in out.items()}, {k: v[rows] for k, v in ref.items()}
        )


def test_p2b_knot_path_equals_dense_and_naive(monkeypatch):
    """Trained-like similarity ranges (random features): many knots; both the knot path and its
    dense fallback match the explicit concatenation."""
    import trackers.p2b_knots as p2b

    torch.manual_seed(12)
    fusion = P2BFusion(32, 48, 40)
    fusion.train()
    fusion(torch.randn(2, 16, 3), torch.randn(2, 16, 32), torch.randn(2, 24, 32))  # BN stats
    fusion.eval()
    t_xyz, t_feat, s_feat = torch.randn(2, 16, 3), torch.randn(2, 16, 32), torch.randn(2, 96, 32)
    s_feat[1, :48] = s_feat[1, 48:]  # repeated search features: repeated knots
    expected = p2b_naive(fusion, t_xyz, t_feat, s_feat)
    calls = []
    knots = p2b.knots
    monkeypatch.setattr(p2b, "knots", lambda *a: calls.append(knots(*a)) or calls[-1])
    for fraction in (1.0, 0.0):  # knots always affordable / never: the dense fallback
        monkeypatch.setattr(p2b, "MAX_KNOT_FRACTION", fraction)
        with torch.no_grad():
            got = fusion(t_xyz, t_feat, s_feat)
        torch.testing.assert_close(got, expected, rtol=0, atol=1e-4)
    assert calls[0] is not None and calls[0][0].shape[-1] > 2 and calls[1] is None
    knots_t = calls[0][0]
    assert (knots_t[..., 1:] >= knots_t[..., :-1]).all()  # sorted


def test_p2b_knots_are_the_kinks_of_the_tfa_mlp():
    """Between consecutive knots the TFA MLP's last pre-activation is affine in the similarity."""
    from trackers.p2b_knots import knots, pre_activation

    torch.manual_seed(13)
    fusion = P2BFusion(8, 16, 16).eval()
    a, w = fusion.first_layer(torch.randn(1, 4, 3), torch.randn(1, 4, 8))
    lo, hi = torch.full((1, 4), -1.0), torch.ones(1, 4)
    with torch.no_grad():
        t, values = knots(fusion.mlp, a, w, lo, hi, max_knots=10_000)
        mid = (t[..., 1:] + t[..., :-1]) / 2
        dense = pre_activation(fusion.mlp, a, w, mid, 2)
    torch.testing.assert_close(dense, (values[:, :, 1:] + values[:, :, :-1]) / 2, rtol=0, atol=1e-5)


def test_folded_batchnorm_cache_follows_weight_updates(toy):
    torch.manual_seed(14)
    model = tiny("p2b").eval()
    with torch.no_grad():
        before = model(toy[0])["scores"]
        for p in model.head.proposal.parameters():
            p.mul_(1.5)
        model.head.proposal.norms[0].running_var.mul_(2.0)
        after = model(toy[0])["scores"]
    assert not torch.allclose(before, after)
    torch.testing.assert_close(after, reference_outputs(model, toy[0])["scores"], rtol=0, atol=1e-5)
    # replacing a parameter's data (what .to() does) refolds too, without a version bump
    with torch.no_grad():
        norm = model.head.proposal.norms[0]
        norm.running_mean.data = norm.running_mean.data + 0.5
        replaced = model(toy[0])["scores"]
    assert not torch.allclose(after, replaced)
    torch.testing.assert_close(
        replaced, reference_outputs(model, toy[0])["scores"], rtol=0, atol=1e-5
    )


def test_max_pool_is_amax_without_autograd_and_sends_the_gradient_to_the_first_max():
    from trackers.layers import max_pool

    x = torch.tensor(
        [[[1.0, 5.0], [3.0, 5.0], [3.0, 2.0]], [[0.0, float("nan")], [1.0, 2.0], [1.0, 2.0]]]
    )
    expected = x.max(dim=1).values
    assert torch.equal(max_pool(x, 1).nan_to_num(-1.0), expected.nan_to_num(-1.0))
    leaf = x.nan_to_num(0.0).requires_grad_()
    max_pool(leaf, 1).sum().backward()
    # ties (copies of a point) send all of it to the first maximal element, as max_pool2d does
    first = torch.tensor(
        [[[0.0, 1.0], [1.0, 0.0], [0.0, 0.0]], [[0.0, 0.0], [1.0, 1.0], [0.0, 0.0]]]
    )
    assert torch.equal(leaf.grad, first)
