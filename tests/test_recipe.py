"""Training recipe v2 (issue 24): each recipe field's effect on the samples, v1's byte-identity
with the old samples, pooled losses against a hand computation, config validation."""

from __future__ import annotations

import dataclasses
import json
import math
import sys
import warnings
from pathlib import Path

import numpy as np
import pytest
import torch
import torch.nn.functional as F
from test_pretrain_support import FakeScans, TinyTracker, fake_tracklets

import trackers
from envs.data import Tracklet
from envs.geometry import boxes_in_frame, points_in_box, wrap_yaw
from envs.observation import crop_box_frame
from envs.tracking_env import TrackingEnv
from training import config, samples
from training.checkpoint import CheckpointError, check_resumable
from training.config import RECIPES, ConfigError, TrainConfig, config_from_dict
from training.losses import loss_counts, pooled, pooled_objective
from training.pretrain import SAMPLE_RECIPE_KEYS, default_model_factory
from training.samples import TrackingSamples

sys.path.insert(0, str(Path(__file__).resolve().parent / "data"))
import record_samples_v1  # noqa: E402


def _samples(recipe: str = "v1", **overrides) -> TrackingSamples:
    cfg = config_from_dict({"recipe": recipe, **overrides})
    values = cfg.recipe_values()
    kwargs = {k: values[k] for k in SAMPLE_RECIPE_KEYS}
    return TrackingSamples(
        fake_tracklets(n=3, frames=6),
        candidates_per_frame=4,
        seed=3,
        search_enlargement=cfg.search_enlargement(),
        **kwargs,
    )


def _offset(sample) -> tuple[np.ndarray, float]:
    """The search offset ``(dx, dy)`` in the GT box frame and ``dyaw`` (ref = GT + offset)
    recovered from the GT expressed in the reference frame (``search_box``)."""
    sb = sample["search_box"].numpy().astype(np.float64)
    dyaw = -float(sb[6])
    c, s = math.cos(dyaw), math.sin(dyaw)
    d = -np.array([c * sb[0] - s * sb[1], s * sb[0] + c * sb[1]])
    return d, dyaw


# ---------------------------------------------------------------- v1 byte-identical


def test_recipe_v1_samples_are_byte_identical_to_the_recorded_old_samples():
    """tests/data/samples_v1.json was recorded from training.samples before recipe v2."""
    recorded = json.loads((Path(__file__).parent / "data" / "samples_v1.json").read_text())
    v1 = {k: RECIPES["v1"][k] for k in SAMPLE_RECIPE_KEYS}
    for name, (kwargs, epochs) in record_samples_v1.CASES.items():
        data = record_samples_v1.build({**kwargs, **v1})
        for epoch in epochs:
            data.set_epoch(epoch)
            hashes = [record_samples_v1.sample_hash(data[i]) for i in range(len(data))]
            assert hashes == recorded[f"{name}/e{epoch}"], (name, epoch)


def test_v1_config_resolves_to_the_old_values():
    cfg = config_from_dict({"recipe": "v1", "tracker": "bat"})
    assert cfg.recipe_values() == RECIPES["v1"]
    assert cfg.env_kwargs() == {
        "template_mode": "first_and_previous",
        "search_enlargement": (1.25, 2.0),
    }
    assert "sampling" not in cfg.make_kwargs().get("backbone", {})


# ---------------------------------------------------------------- each field


def test_zero_offset_candidate_gives_candidate_zero_the_exact_ground_truth():
    on, off = _samples("v1", zero_offset_candidate=True), _samples("v1")
    exact = []
    for i in range(len(on)):
        _, t, cand = on.locate(i)
        sb = on[i]["search_box"].numpy()
        exact.append(np.allclose(sb[[0, 1, 2, 6]], 0.0, atol=1e-6))
        assert exact[-1] == (cand == 0)
        assert not np.allclose(off[i]["search_box"].numpy()[[0, 1, 6]], 0.0, atol=1e-6)
    assert np.mean(exact) == pytest.approx(1 / on.candidates)


def test_zero_offset_needs_several_candidates_as_in_open3dsot():
    data = TrackingSamples(
        fake_tracklets(n=2, frames=4), candidates_per_frame=1, zero_offset_candidate=True
    )
    assert not np.allclose(data[0]["search_box"].numpy()[[0, 1, 6]], 0.0, atol=1e-6)


def test_frame0_samples_add_frame_zero_with_previous_equal_to_current():
    off, on = _samples("v1"), _samples("v1", frame0_samples=True, zero_offset_candidate=True)
    n_tracklets = len(on.tracklets)
    assert len(on) == len(off) + n_tracklets * on.candidates
    assert on.locate(0) == (0, 0, 0) and off.locate(0) == (0, 1, 0)
    frames = {on.locate(i)[1] for i in range(len(on))}
    assert frames == set(range(6))
    s = on[0]  # tracklet 0, frame 0, candidate 0: every crop from frame 0, unperturbed
    tr = on.tracklets[0]
    box0 = tr.boxes[0]
    first = crop_box_frame(tr.points(0), box0, 1.25)
    assert len(first) <= 256  # all points kept in order, then duplicates
    tmpl = s["template"].numpy()
    assert np.array_equal(tmpl[: len(first)], first)
    assert np.array_equal(tmpl[256 : 256 + len(first)], first)  # previous = frame 0, exact box
    assert np.allclose(s["search_box"].numpy(), [0, 0, 0, *box0[3:6], 0], atol=1e-6)
    assert np.array_equal(s["motion"].numpy(), np.zeros(4, np.float32))


def _sparse_first_frame(tracklets, keep: int = 60):
    """The tracklets with frame 0's scan cut to its first ``keep`` (target) points."""
    out = []
    for tr in tracklets:
        base = tr.scans

        def scans(frame, base=base):
            points = base(frame)
            return points[:keep] if frame == 0 else points

        out.append(dataclasses.replace(tr, scans=scans))
    return out


def test_template_union_draws_from_first_and_previous_crops_merged():
    data = TrackingSamples(
        _sparse_first_frame(fake_tracklets(n=3, frames=6)),
        candidates_per_frame=3,
        seed=2,
        template_union=True,
    )
    shares = []
    for i in range(len(data)):
        k, t, cand = data.locate(i)
        tr = data.tracklets[k]
        s = {key: v.numpy() for key, v in data[i].items()}
        first = crop_box_frame(tr.points(0), tr.boxes[0], 1.25)
        prev_gt = crop_box_frame(tr.points(t - 1), tr.boxes[t - 1], 1.25)
        assert len(first) + len(prev_gt) <= 512
        # every union point once, in order (first crop, then previous), then duplicates
        assert np.array_equal(s["template"][: len(first)], first)
        if cand == 0:  # the previous box is exact: the whole union is known
            union = np.concatenate([first, prev_gt])
            assert np.array_equal(s["template"][: len(union)], union)
            own = np.array([0, 0, 0, *tr.boxes[0][3:6], 0.0])  # fake boxes keep their size
            assert np.array_equal(s["template_labels"] > 0.5, points_in_box(s["template"], own))
            continue
        centres = s["template_centers"]
        from_first = np.all(centres == 0.0, axis=1)  # the first crop's centre is its origin
        assert from_first[: len(first)].all() and not from_first[len(first)].any()
        own0 = np.array([0, 0, 0, *tr.boxes[0][3:6], 0.0])
        assert np.array_equal(
            s["template_labels"][from_first] > 0.5, points_in_box(s["template"][from_first], own0)
        )
        n_prev = len(np.unique(s["template"][~from_first], axis=0))  # the jittered crop's size
        shares.append((from_first.mean(), len(first) / (len(first) + n_prev)))
    got, expected = np.array(shares).T
    # the first crop's share of the template is its share of the union (up to the binomial
    # noise of the ~300 duplicates), not a fixed half
    assert np.abs(got - expected).max() < 0.07
    assert expected.min() < 0.3 and got.min() < 0.35  # far from half where frame 0 is sparse


def test_min_crop_points_replaces_samples_with_too_few_points():
    good = fake_tracklets(n=2, frames=5)
    boxes = np.array(good[0].boxes)
    # a tracklet whose target is nearly empty (5 points per frame) and far from any background
    sparse = Tracklet(
        "9999/9",
        "9999",
        9,
        "Pedestrian",
        np.arange(5),
        boxes,
        FakeScans(boxes, 9, n_target=5, n_background=0),
    )
    kwargs = {"candidates_per_frame": 2, "seed": 1}
    keep = TrackingSamples([sparse, *good], **kwargs)
    redraw = TrackingSamples([sparse, *good], min_crop_points=21, **kwargs)
    n_sparse = (len(sparse) - 1) * 2
    for i in range(len(keep)):
        kept, new = keep[i], redraw[i]
        assert int(new["index"]) == i
        if i < n_sparse:  # too few points: replaced by a sample of another tracklet
            assert int((kept["search"].abs().sum(1) > 0).sum()) <= 1024
            assert not torch.equal(new["template"], kept["template"])
            assert float(new["search_labels"].sum()) >= 21
        else:  # enough points: the very same sample
            for key in kept:
                assert torch.equal(kept[key], new[key]), (i, key)
    again = TrackingSamples([sparse, *good], min_crop_points=21, **kwargs)
    assert all(torch.equal(again[i]["search"], redraw[i]["search"]) for i in range(n_sparse))


def test_min_crop_points_gives_up_with_a_clear_error():
    boxes = np.array(fake_tracklets(n=1, frames=3)[0].boxes)
    sparse = Tracklet(
        "9999/9",
        "9999",
        9,
        "Pedestrian",
        np.arange(3),
        boxes,
        FakeScans(boxes, 9, n_target=5, n_background=0),
    )
    data = TrackingSamples([sparse], min_crop_points=21)
    with pytest.raises(ValueError, match=r"sample 0 .*min_crop_points"):
        data[0]


def test_limit_box_redraws_large_offsets_in_the_box_frame():
    def offsets(data):
        rows = []
        for epoch in range(4):
            data.set_epoch(epoch)
            for i in range(len(data)):
                k, t, _ = data.locate(i)
                d, _ = _offset(data[i])
                rows.append((*d, data.tracklets[k].boxes[t][4]))
        return np.array(rows)

    on, off = offsets(_samples("v1", limit_box=True)), offsets(_samples("v1"))
    for rows, limited in ((on, True), (off, False)):
        dx, dy, width = rows.T
        beyond_x = dx > np.maximum(width, 1.0) + 1e-4
        beyond_y = dy > np.maximum(np.minimum(width, 2.0), 1.0) + 1e-4
        assert (beyond_x.any() or beyond_y.any()) != limited
    # one-sided, as in Open3DSOT: large negative offsets stay
    assert (on[:, 0] < -np.maximum(on[:, 2], 1.0)).any()


def test_search_enlargement_crops_gpt_search_regions_by_four_metres():
    v2 = _samples("v2", tracker="gpt")
    assert (v2.search_scale, v2.search_offset_m) == (1.0, 4.0)
    v2_p2b = _samples("v2", tracker="p2b")
    assert (v2_p2b.search_scale, v2_p2b.search_offset_m) == (1.25, 2.0)
    cfg = config_from_dict({"tracker": "gpt", "recipe": "v2"})
    assert cfg.env_kwargs()["search_enlargement"] == (1.0, 4.0)
    data = TrackingSamples(
        fake_tracklets(n=1, frames=3),
        candidates_per_frame=2,
        zero_offset_candidate=True,
        search_enlargement=(1.0, 4.0),
    )
    tr = data.tracklets[0]
    crop = crop_box_frame(tr.points(1), tr.boxes[1], 1.0, 4.0)
    assert len(crop) <= 1024
    assert np.array_equal(data[0]["search"].numpy()[: len(crop)], crop)


# ---------------------------------------------------------------- the env agrees


def _sorted_rows(a: np.ndarray) -> np.ndarray:
    """The rows of ``a`` in lexicographic order (the env's crops come in a canonical order)."""
    return a[np.lexsort(a.T[::-1])]


def test_env_merged_template_is_the_union_of_first_and_previous_crops():
    tracklets = fake_tracklets(n=1, frames=4)
    tr = tracklets[0]

    class Data:
        pass

    data = Data()
    data.tracklets = tracklets
    env = TrackingEnv(data, template_mode="first_and_previous_merged", episode_seed=0)
    obs, _ = env.reset()
    first = crop_box_frame(tr.points(0), tr.boxes[0], 1.25)
    union = np.concatenate([first, first])  # first step: previous = first
    assert len(union) <= 512
    assert np.array_equal(_sorted_rows(obs["template"][: len(union)]), _sorted_rows(union))
    # step with the exact ground-truth offset: the previous crop is the GT crop of frame 1
    from envs.geometry import offset_between

    obs, *_ = env.step(offset_between(tr.boxes[0], tr.boxes[1]).astype(np.float32))
    prev = crop_box_frame(tr.points(1), tr.boxes[1], 1.25)
    union = np.concatenate([first, prev])
    assert len(union) <= 512
    assert np.allclose(_sorted_rows(obs["template"][: len(union)]), _sorted_rows(union), atol=1e-5)


def test_env_search_enlargement_matches_the_samples_crop_and_is_validated():
    tracklets = fake_tracklets(n=1, frames=3)

    class Data:
        pass

    data = Data()
    data.tracklets = tracklets
    env = TrackingEnv(data, reference="current_gt", search_enlargement=(1.0, 4.0), episode_seed=0)
    obs, _ = env.reset()
    tr = tracklets[0]
    crop = crop_box_frame(tr.points(1), tr.boxes[1], 1.0, 4.0)
    assert len(crop) <= 1024
    assert np.array_equal(_sorted_rows(obs["search"][: len(crop)]), _sorted_rows(crop))
    with pytest.raises(ValueError, match="search_enlargement"):
        TrackingEnv(data, search_enlargement=(0.0, 2.0))


# ---------------------------------------------------------------- pooled losses


def _fake_outputs(b: int = 3, m: int = 16, p: int = 8, seed: int = 0):
    g = torch.Generator().manual_seed(seed)
    search_box = torch.zeros(b, 7)
    search_box[:, :3] = torch.randn(b, 3, generator=g) * 0.2
    search_box[:, 3:6] = 1.0
    search_box[:, 6] = torch.randn(b, generator=g) * 0.1
    labels = (torch.rand(b, 64, generator=g) < 0.4).float()
    labels[2, :] = 0.0  # a sample without target points
    outputs = {
        "seed_idx": torch.randint(0, 64, (b, m), generator=g),
        "seed_logits": torch.randn(b, m, generator=g),
        "votes": torch.randn(b, m, 3, generator=g),
        # proposal centres at 0.1-1 m from the GT centre: positives, ignored and negatives
        "proposal_centers": search_box[:, None, :3] + torch.rand(b, p, 3, generator=g) * 0.6,
        "scores": torch.randn(b, p, generator=g),
        "box_raw": torch.randn(b, p, 4, generator=g),
    }
    return outputs, {"search_box": search_box, "search_labels": labels}


def _hand_pooled(outputs, targets, w, weights_k):
    """Open3DSOT's batch-pooled loss, with sample weights, computed element by element."""
    sb = targets["search_box"]
    b, m = outputs["seed_logits"].shape
    terms = {k: [0.0, 0.0] for k in ("vote", "seed", "objectness", "box")}
    for i in range(b):
        lab = targets["search_labels"][i][outputs["seed_idx"][i]]
        for j in range(m):
            bce = F.binary_cross_entropy_with_logits(outputs["seed_logits"][i, j], lab[j])
            terms["seed"][0] += w[i] * float(bce)
            terms["seed"][1] += w[i]
            if lab[j] > 0:
                vote = F.smooth_l1_loss(outputs["votes"][i, j], sb[i, :3])
                terms["vote"][0] += w[i] * float(vote)
                terms["vote"][1] += w[i]
        target = torch.cat([sb[i, :3], sb[i, 6:7] * 180.0 / math.pi])
        for q in range(outputs["scores"].shape[1]):
            d = float(torch.linalg.norm(outputs["proposal_centers"][i, q] - sb[i, :3]))
            pos = d < 0.3
            if pos or d > 0.6:
                obj = F.binary_cross_entropy_with_logits(
                    outputs["scores"][i, q], torch.tensor(float(pos)), pos_weight=torch.tensor(2.0)
                )
                terms["objectness"][0] += w[i] * float(obj)
                terms["objectness"][1] += w[i]
            if pos:
                box = F.smooth_l1_loss(outputs["box_raw"][i, q], target)
                terms["box"][0] += w[i] * float(box)
                terms["box"][1] += w[i]
    pooled_terms = {k: (n / d if d > 0 else 0.0) for k, (n, d) in terms.items()}
    return sum(weights_k[k] * v for k, v in pooled_terms.items()), pooled_terms


@pytest.mark.parametrize("w", [None, [0.5, 0.3, 0.2], [0.0, 1.0, 0.0]])
def test_pooled_objective_matches_a_hand_computation(w):
    model = trackers.make("p2b", **trackers.size_config("p2b", "slim"))
    outputs, targets = _fake_outputs()
    losses = model.loss(outputs, targets)
    weights = None if w is None else torch.tensor(w)
    got = float(pooled_objective(model, losses, outputs, targets, weights))
    hand, parts = _hand_pooled(outputs, targets, w or [1.0, 1.0, 1.0], model.config.loss_weights)
    assert parts["box"] > 0 and parts["vote"] > 0  # every term is exercised
    assert got == pytest.approx(hand, rel=1e-4)
    # ... and differs from the per-sample mean, which weighs every sample alike
    if w is None:
        assert float(losses["total"].mean()) != pytest.approx(got, rel=1e-3)


def test_pooled_of_uniform_counts_is_the_weighted_mean_and_empty_is_zero():
    loss = torch.tensor([1.0, 2.0, 4.0])
    assert float(pooled(loss, torch.ones(3))) == pytest.approx(7 / 3)
    assert float(pooled(loss, torch.ones(3), torch.tensor([0.5, 0.5, 0.0]))) == pytest.approx(1.5)
    assert float(pooled(loss, torch.tensor([0.0, 2.0, 2.0]))) == pytest.approx(3.0)
    assert float(pooled(loss, torch.zeros(3))) == 0.0
    tiny = TinyTracker()
    total = torch.tensor([1.0, 3.0])
    got = pooled_objective(tiny, {"total": total}, {}, {}, torch.tensor([0.75, 0.25]))
    assert float(got) == pytest.approx(1.5)


def test_loss_counts_cover_bat_and_gpt_terms():
    for name, extra in (("bat", "box_cloud"), ("gpt", "template_vote")):
        model = trackers.make(name, **trackers.size_config(name, "slim"))
        outputs, targets = _fake_outputs()
        outputs["template_votes"] = torch.zeros(3, 32, 3)
        counts = loss_counts(model, outputs, targets)
        assert extra in counts and set(model.config.loss_weights) <= set(counts)
        assert torch.equal(counts["vote"], counts["box_cloud"])


# ---------------------------------------------------------------- optimiser, init, BAT FPS


def test_kaiming_init_and_torch_default_init():
    torch.manual_seed(0)
    with pytest.warns(UserWarning, match="init='kaiming'.*--set init=default"):
        v2 = default_model_factory(config_from_dict({"model_size": "slim", "recipe": "v2"}))
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # the papers' widths, or torch's init: no warning
        default_model_factory(config_from_dict({"model_size": "default", "recipe": "v2"}))
        default_model_factory(
            config_from_dict({"model_size": "slim", "recipe": "v2", "init": "default"})
        )
    torch.manual_seed(0)
    v1 = default_model_factory(config_from_dict({"model_size": "slim", "recipe": "v1"}))
    lin2 = next(m for m in v2.modules() if isinstance(m, torch.nn.Linear))
    lin1 = next(m for m in v1.modules() if isinstance(m, torch.nn.Linear))
    fan_in = lin2.weight.shape[1]
    assert float(lin2.weight.detach().std()) == pytest.approx(math.sqrt(2 / fan_in), rel=0.15)
    # torch's default: uniform within 1 / sqrt(fan_in)
    assert float(lin1.weight.detach().abs().max()) <= 1 / math.sqrt(fan_in) + 1e-6
    assert float(lin2.weight.detach().abs().max()) > 1 / math.sqrt(fan_in)
    assert all(
        float(m.bias.detach().abs().max()) == 0.0
        for m in v2.modules()
        if isinstance(m, torch.nn.Linear) and m.bias is not None
    )


def test_adam_settings_follow_the_recipe(tmp_path):
    from training.pretrain import Trainer

    base = {"model_size": "slim", "batch_size": 4, "out": str(tmp_path / "r"), "progress": False}
    for recipe, betas, eps in (("v1", (0.9, 0.999), 1e-8), ("v2", (0.5, 0.999), 1e-6)):
        cfg = config_from_dict({**base, "recipe": recipe})
        trainer = Trainer(
            cfg,
            model_factory=lambda c: TinyTracker(),
            train_data=TrackingSamples(fake_tracklets(n=2, frames=4)),
            val_fn=False,
        )
        group = trainer.base_opt.param_groups[0]
        assert tuple(group["betas"]) == betas and group["eps"] == eps
        assert trainer.pooled == (recipe == "v2")
        trainer.close()
    cfg = config_from_dict({**base, "recipe": "v2", "adam_beta1": 0.7})
    assert cfg.recipe_value("adam_beta1") == 0.7 and cfg.recipe_value("adam_eps") == 1e-6


def test_bat_fps_backbone_handles_clouds_with_few_distinct_points():
    cfg = config_from_dict({"tracker": "bat", "model_size": "slim", "recipe": "v2"})
    assert cfg.make_kwargs()["backbone"]["sampling"] == "fps"
    assert (
        config_from_dict({"tracker": "p2b"}).make_kwargs().get("backbone", {}).get("sampling")
        is None
    )
    model = trackers.make("bat", **cfg.make_kwargs()).train()
    g = torch.Generator().manual_seed(0)
    distinct = torch.randn(2, 5, 3, generator=g)
    template = distinct[:, torch.randint(0, 5, (512,), generator=g)]
    search = torch.randn(2, 1024, 3, generator=g)
    batch = {
        "template": template,
        "search": search,
        "size": torch.ones(2, 3),
        "motion": torch.zeros(2, 4),
    }
    out = model(batch)
    assert torch.isfinite(out["proposals"]).all()


# ---------------------------------------------------------------- bad values, resume


@pytest.mark.parametrize(
    "key, value, message",
    [
        ("recipe", "v3", "recipe='v3': must be one of v1, v2"),
        ("loss_reduction", "mean", "loss_reduction='mean'"),
        ("init", "xavier", "init='xavier'"),
        ("min_crop_points", -1, "min_crop_points=-1"),
        ("adam_beta1", 1.0, "adam_beta1=1.0"),
        ("adam_eps", 0.0, "adam_eps=0.0"),
        ("template_union", "yes", "template_union='yes': must be true or false"),
    ],
)
def test_bad_recipe_values_stop_before_training_naming_them(key, value, message):
    with pytest.raises(ConfigError, match=message.replace("(", r"\(").replace(")", r"\)")):
        config_from_dict({key: value})


def test_set_reads_exponent_numbers_without_a_dot():
    """``--set adam_eps=1e-8``: YAML 1.1 reads ``1e-8`` as a string; it is the number."""
    from training.config import parse_value

    cfg = config_from_dict({"adam_eps": parse_value("1e-8"), "lr": parse_value("3e-4")})
    assert cfg.adam_eps == 1e-8 and cfg.lr == 3e-4 and type(cfg.adam_eps) is float
    with pytest.raises(ConfigError, match="adam_eps='tiny': must be a number"):
        config_from_dict({"adam_eps": parse_value("tiny")})


def test_unknown_recipe_and_bad_field_are_both_named():
    with pytest.raises(ConfigError) as err:
        config_from_dict({"recipe": "v0", "init": "zeros"})
    assert "recipe='v0'" in str(err.value) and "init='zeros'" in str(err.value)


def test_checkpoints_from_before_the_recipe_resume_only_as_v1():
    old = dataclasses.asdict(TrainConfig())
    del old["recipe"]
    for key in RECIPES["v2"]:
        old.pop(key)
    ckpt = {"tracker": "p2b", "config": old}
    check_resumable(ckpt, config_from_dict({"recipe": "v1"}), "old/last.pt")
    with pytest.raises(CheckpointError, match="recipe: checkpoint 'v1' vs now 'v2'"):
        check_resumable(ckpt, config_from_dict({"recipe": "v2"}), "old/last.pt")


def test_yaw_of_recovered_offset_is_wrapped():
    # _offset's convention check: a sample with zero offset recovers zeros
    data = TrackingSamples(
        fake_tracklets(n=1, frames=3), candidates_per_frame=2, zero_offset_candidate=True
    )
    d, dyaw = _offset(data[0])
    assert np.allclose(d, 0.0, atol=1e-5) and abs(wrap_yaw(dyaw)) < 1e-6


def test_checkpoint_trackers_are_rebuilt_with_their_recipe():
    from training.config import checkpoint_tracker_kwargs

    v2 = dataclasses.asdict(
        config_from_dict({"tracker": "bat", "model_size": "slim", "recipe": "v2"})
    )
    assert checkpoint_tracker_kwargs(v2)["backbone"]["sampling"] == "fps"
    old = {k: v for k, v in v2.items() if k != "recipe" and k not in RECIPES["v2"]}
    assert "sampling" not in checkpoint_tracker_kwargs(old)["backbone"]  # a v1 run
    assert checkpoint_tracker_kwargs({**old, "future_key": 1}) == checkpoint_tracker_kwargs(old)


# ---------------------------------------------------------------- the search region


def test_search_center_previous_keeps_the_targets_move_in_the_sample():
    kwargs = dict(candidates_per_frame=2, zero_offset_candidate=True, seed=1)
    tracklets = fake_tracklets(n=2, frames=5)
    current = TrackingSamples(tracklets, **kwargs)
    previous = TrackingSamples(tracklets, search_center="previous", **kwargs)
    for i in range(len(previous)):
        k, t, cand = previous.locate(i)
        if cand:
            continue
        boxes = tracklets[k].boxes
        # candidate 0's crop is cut around the exact previous box: the GT sits at the move
        expected = boxes_in_frame(boxes[t], boxes[t - 1])
        np.testing.assert_allclose(previous[i]["search_box"].numpy(), expected, atol=1e-5)
        assert np.linalg.norm(expected[:2]) > 0.3  # the fake targets move 0.41 m a frame
        np.testing.assert_allclose(current[i]["search_box"].numpy()[[0, 1, 6]], 0.0, atol=1e-6)
    with pytest.raises(ValueError, match="search_center"):
        TrackingSamples(tracklets, search_center="next")
    assert samples.SEARCH_CENTERS == config.SEARCH_CENTERS  # the config's copy (no torch there)


def test_search_region_flags_reach_the_samples_and_the_tracker_file_options():
    cfg = config_from_dict({"search_offset_m": 4.0, "search_center": "previous"})
    assert cfg.search_enlargement() == (1.25, 4.0)
    assert cfg.env_options()["search_enlargement"] == (1.25, 4.0)
    assert config_from_dict(
        {"tracker": "gpt", "recipe": "v2", "search_scale": 1.5}
    ).search_enlargement() == (1.5, 4.0)
    for bad, key in (
        ({"search_offset_m": -1.0}, "search_offset_m"),
        ({"search_scale": 0.0}, "search_scale"),
        ({"search_center": "next"}, "search_center"),
        ({"tracker": "m2track", "search_offset_m": 3.0}, "search_offset_m"),
        ({"tracker": "mbptrack", "search_center": "previous"}, "search_center"),
    ):
        with pytest.raises(ConfigError, match=key):
            config_from_dict(bad)
