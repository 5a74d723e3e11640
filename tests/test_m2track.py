"""M2-Track (trackers.m2track): shapes, invariances, the paper's losses, act, save / load."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch
import torch.nn.functional as F

import trackers
from envs.geometry import points_in_box
from trackers.m2track import (
    PREVIOUS_SEARCH_OPTION,
    M2Track,
    box_cloud,
    motion_cloud,
    offset_boxes,
    offset_points,
    prepare_motion_observation,
)

pytestmark = pytest.mark.usefixtures("one_torch_thread")

SLIM = trackers.size_config("m2track", "slim")
TINY = {
    "seg_channels": [8, 8, 16],
    "seg_head_channels": [16, 8],
    "point_channels": [8, 16],
    "hidden_channels": [16],
    "head_channels": [8],
}


def _clouds(b: int, n: int = 128, seed: int = 0) -> dict[str, torch.Tensor]:
    """A target (a box surface) in both frames, moved between them, among ground points."""
    g = torch.Generator().manual_seed(seed)
    size = torch.tensor([[4.0, 1.8, 1.5]]).repeat(b, 1)

    def frame(centre: torch.Tensor) -> torch.Tensor:
        target = (torch.rand(b, n // 2, 3, generator=g) - 0.5) * size[:, None] + centre[:, None]
        ground = (torch.rand(b, n - n // 2, 3, generator=g) - 0.5) * torch.tensor([9.0, 6.0, 0.1])
        ground[..., 2] -= 0.75
        return torch.cat([target, ground], dim=1)

    move = torch.cat([0.5 * torch.randn(b, 2, generator=g), torch.zeros(b, 1)], dim=1)
    return {
        "previous_search": frame(torch.zeros(b, 3)),
        "search": frame(move),
        "size": size,
        "prior_is_gt": torch.tensor([1.0, 0.0] * (b // 2) + [1.0] * (b % 2)),
    }


def _targets(batch: dict[str, torch.Tensor], seed: int = 0) -> dict[str, torch.Tensor]:
    b = batch["search"].shape[0]
    g = torch.Generator().manual_seed(seed)
    labels = torch.zeros(b, batch["search"].shape[1] + batch["previous_search"].shape[1])
    n = batch["previous_search"].shape[1]
    labels[:, : n // 2] = 1
    labels[:, n : n + batch["search"].shape[1] // 2] = 1
    box = 0.3 * torch.randn(b, 4, generator=g)
    return {
        "seg_labels": labels,
        "box": box,
        "prev_box": 0.05 * torch.randn(b, 4, generator=g),
        "motion_box": box,
        "moving": (torch.arange(b) % 2).float(),
    }


def _obs(b: int | None, seed: int = 0, channels: int = 3) -> dict[str, np.ndarray]:
    batch = _clouds(1 if b is None else b, seed=seed)
    prev = batch["previous_search"].numpy()
    if channels > 3:
        prev = np.concatenate([prev, np.ones(prev.shape[:-1] + (channels - 3,), np.float32)], -1)
    obs = {
        "search": batch["search"].numpy(),
        "previous_search": prev,
        "size": batch["size"].numpy(),
        "motion": np.zeros((len(prev), 4), np.float32),
        "template": np.zeros((len(prev), 512, 3), np.float32),
    }
    return {k: v[0] for k, v in obs.items()} if b is None else obs


def test_registered_with_sizes_and_samples():
    assert "m2track" in trackers.available("learned")
    assert trackers.tracker_class("m2track") is M2Track
    slim = trackers.make("m2track", **SLIM)
    full = trackers.make("m2track")
    assert full.config.seg_channels == [64, 64, 64, 128, 1024]  # Open3DSOT's widths
    assert full.config.point_channels == [64, 128, 256, 512]
    count = lambda m: sum(p.numel() for p in m.parameters())  # noqa: E731
    assert count(slim) < count(full) / 3
    assert M2Track.sample_recipe == "motion"
    for bad in ([8], [8, 8]):
        with pytest.raises(ValueError, match="seg_channels"):
            trackers.make("m2track", seg_channels=bad)
    with pytest.raises(ValueError, match="box_aware"):
        trackers.make("m2track", loss_weights={"box_cloud": 2.0})
    assert (
        trackers.make(
            "m2track", **TINY, box_aware=True, loss_weights={"box_cloud": 2.0}
        ).config.loss_weights["box_cloud"]
        == 2.0
    )
    with pytest.raises(ValueError, match="unknown loss term"):
        trackers.make("m2track", loss_weights={"vote": 1.0})


def test_forward_shapes_and_finite_in_train_and_eval():
    model = trackers.make("m2track", **TINY)
    batch = _clouds(3)
    for train in (True, False):
        model.train(train)
        out = model(batch)
        shapes = {
            "seg_logits": (3, 256, 2),
            "motion": (3, 4),
            "motion_logits": (3, 2),
            "prev_box": (3, 4),
            "aux_box": (3, 4),
            "box": (3, 4),
            "feature": (3, 16),
            "proposals": (3, 1, 4),
            "scores": (3, 1),
        }
        for key, shape in shapes.items():
            assert tuple(out[key].shape) == shape, key
            assert torch.isfinite(out[key]).all(), key
    assert model.features(out) is out["feature"]


def test_motion_cloud_channels_match_a_direct_computation():
    batch = _clouds(2, n=64)
    cloud = motion_cloud(
        batch["previous_search"], batch["search"], batch["size"], batch["prior_is_gt"]
    )
    assert cloud.shape == (2, 128, 5)
    for i, (low, high) in enumerate([(0.0, 1.0), (0.2, 0.8)]):  # prior_is_gt = 1, then 0
        prev = batch["previous_search"][i].numpy()
        box = np.array([0, 0, 0, *batch["size"][i].tolist(), 0.0])
        inside = points_in_box(prev, box, 1.25)
        assert inside.any() and not inside.all()
        np.testing.assert_allclose(cloud[i, :64, 4].numpy(), np.where(inside, high, low))
        assert (cloud[i, :64, 3] == 0).all() and torch.allclose(cloud[i, 64:, 3], torch.tensor(0.1))
        assert (cloud[i, 64:, 4] == 0.5).all()
        assert torch.equal(cloud[i, :64, :3], batch["previous_search"][i])


def test_box_and_point_offsets_agree():
    """Moving points with a box by an offset keeps them fixed in the box's frame."""
    g = torch.Generator().manual_seed(3)
    box = torch.randn(4, 4, generator=g)
    off = torch.randn(4, 4, generator=g)
    moved_box = offset_boxes(box, off)
    c, s = torch.cos(box[:, 3]), torch.sin(box[:, 3])
    expect_x = box[:, 0] + c * off[:, 0] - s * off[:, 1]
    assert torch.allclose(moved_box[:, 0], expect_x)
    assert torch.allclose(moved_box[:, 3], box[:, 3] + off[:, 3])
    pts = torch.randn(4, 5, 3, generator=g)
    from trackers.m2track import from_box_frame, to_box_frame

    assert torch.allclose(from_box_frame(to_box_frame(pts, box), box), pts, atol=1e-5)
    moved = offset_points(pts, off)  # points in the box frame, moved with a box at the origin
    zero = torch.zeros(4, 4)
    assert torch.allclose(to_box_frame(moved, offset_boxes(zero, off)), pts, atol=1e-5)


def test_eval_is_invariant_to_point_order_and_batching():
    model = trackers.make("m2track", **SLIM).eval()
    obs = _obs(3, seed=1)
    actions = model.act(obs)
    g = np.random.default_rng(0)
    shuffled = dict(obs)
    for key in ("search", "previous_search"):
        shuffled[key] = np.stack([row[g.permutation(len(row))] for row in obs[key]])
    np.testing.assert_allclose(model.act(shuffled), actions, atol=1e-5)
    singles = np.stack([model.act({k: v[i] for k, v in obs.items()}) for i in range(3)])
    np.testing.assert_array_equal(singles, actions)


def test_fast_and_plain_eval_paths_agree():
    model = trackers.make("m2track", **SLIM).eval()
    batch = _clouds(1, seed=4)
    # resampled crops repeat points: the fast path computes each distinct row once
    for key in ("search", "previous_search"):
        batch[key][0, 64:] = batch[key][0, :64]
    target = torch.zeros(1, 256)
    target[0, [3, 5, 200]] = 1
    is_prev = torch.arange(256)[None] < 128
    rows = model._pooled_rows(target, is_prev)
    assert rows.tolist() == [0, 3, 5, 128, 200]  # targets + the first background row per frame
    model.fast_eval = True
    with torch.no_grad():
        fast = model(batch)
    model.fast_eval = False
    with torch.no_grad():
        plain = model(batch)
    for key in ("seg_logits", "feature", "box", "aux_box"):
        torch.testing.assert_close(fast[key], plain[key], atol=2e-5, rtol=1e-4)


def test_losses_are_the_published_batch_losses_per_sample():
    model = trackers.make("m2track", **TINY).train()
    batch = _clouds(4, n=64)
    targets = _targets(batch)
    out = model(batch)
    terms = model.loss(out, targets)
    assert all(v.shape == (4,) for v in terms.values())
    seg = F.cross_entropy(
        out["seg_logits"].transpose(1, 2),
        targets["seg_labels"].long(),
        weight=torch.tensor([0.5, 2.0]),
    )
    torch.testing.assert_close(terms["seg"].mean(), seg)
    moving = targets["moving"]
    center = F.smooth_l1_loss(
        out["motion"][:, :3], targets["motion_box"][:, :3], reduction="none"
    ).mean(1)
    torch.testing.assert_close(
        terms["center_motion"].mean(), (moving * center).sum() / (moving.sum() + 1e-6)
    )
    angle = F.smooth_l1_loss(torch.sin(out["box"][:, 3]), torch.sin(targets["box"][:, 3]))
    torch.testing.assert_close(terms["angle"].mean(), angle)
    torch.testing.assert_close(
        terms["motion_state"].mean(), F.cross_entropy(out["motion_logits"], moving.long())
    )
    w = model.config.loss_weights
    assert w == {
        "seg": 0.1,
        "motion_state": 0.1,
        "center_motion": 2.0,
        "angle_motion": 10.0,
        "center_prev": 2.0,
        "angle_prev": 10.0,
        "center_aux": 2.0,
        "angle_aux": 10.0,
        "center": 2.0,
        "angle": 10.0,
    }
    torch.testing.assert_close(terms["total"], sum(w[k] * terms[k] for k in w))
    with pytest.raises(KeyError, match="moving"):
        model.loss(out, {k: v for k, v in targets.items() if k != "moving"})


def test_training_steps_lower_the_loss_on_a_tiny_batch():
    """The loss of single steps jumps (x2 between neighbours), so the last five are averaged:
    15 steps and the last loss alone passed on one CPU kind and not on another (session 26);
    at 30 steps the last five average 0.14-0.32 of the first for torch seeds 0-3 here."""
    torch.manual_seed(0)
    model = trackers.make("m2track", **SLIM).train()
    batch = _clouds(4, n=128, seed=2)
    targets = _targets(batch, seed=2)
    opt = torch.optim.Adam(model.parameters(), lr=3e-3)
    losses = []
    for _ in range(30):
        loss = model.loss(model(batch), targets)["total"].mean()
        opt.zero_grad()
        loss.backward()
        opt.step()
        losses.append(float(loss.detach()))
    assert np.mean(losses[-5:]) < 0.5 * losses[0], losses


def test_save_load_round_trip(tmp_path):
    model = trackers.make("m2track", **SLIM, sampling_seed=3)
    model.train()
    model(_clouds(4))  # moves the BatchNorm running statistics away from their init
    model.eval()
    obs = _obs(2, seed=5)
    for suffix in (".safetensors", ".pt"):
        path = trackers.save(model, tmp_path / f"m2{suffix}")
        loaded = trackers.load(path)
        assert isinstance(loaded, M2Track) and loaded.config == model.config
        np.testing.assert_array_equal(loaded.act(obs), model.act(obs))


def test_act_in_action_space_single_batched_and_empty():
    model = trackers.make("m2track", **SLIM).eval()
    single = model.act(_obs(None, channels=5))  # extra channels of previous_search are ignored
    assert single.shape == (4,) and single.dtype == np.float32
    batched = model.act(_obs(3, channels=4))
    assert batched.shape == (3, 4)
    high = np.array([5.0, 5.0, 3.0, math.pi], np.float32)
    assert (np.abs(batched) <= high).all() and (np.abs(single) <= high).all()
    empty = _obs(2)
    empty["search"][1] = 0
    empty["previous_search"][1] = 0
    acted = model.act(empty)
    assert (acted[1] == 0).all() and (acted[0] != 0).any()
    assert model.act({k: v[:0] for k, v in _obs(2).items()}).shape == (0, 4)
    assert model.training is False
    model.train()
    model.act(_obs(None))
    assert model.training  # the mode is restored


def test_first_step_is_read_from_a_zero_motion():
    obs = _obs(2)
    obs["motion"][1, 0] = 0.3
    batch, single = prepare_motion_observation(obs)
    assert not single and batch["prior_is_gt"].tolist() == [1.0, 0.0]


def test_missing_previous_search_names_the_env_option():
    model = trackers.make("m2track", **TINY)
    obs = _obs(None)
    del obs["previous_search"]
    with pytest.raises(KeyError, match="previous_search") as err:
        model.act(obs)
    assert PREVIOUS_SEARCH_OPTION in str(err.value)
    assert 'observation_keys=(..., "previous_search")' in str(err.value)
    bad = _obs(None)
    bad["previous_search"] = bad["previous_search"][:, :2]
    with pytest.raises(ValueError, match=r"previous_search.*\(N', C>=3\)"):
        model.act(bad)
    bad = _obs(2)
    bad["size"] = bad["size"][:1]
    with pytest.raises(ValueError, match="batch size 1"):
        model.act(bad)
    bad = _obs(None)
    bad["search"] = bad["search"].astype(np.float64) * np.nan
    with pytest.raises(ValueError, match="NaN"):
        model.act(bad)


def test_box_cloud_matches_the_corner_distances():
    from envs.geometry import box_to_world

    g = torch.Generator().manual_seed(7)
    pts = torch.randn(2, 6, 3, generator=g)
    boxes = torch.randn(2, 4, generator=g)
    size = torch.tensor([[4.0, 1.8, 1.5], [0.8, 0.6, 1.7]])
    got = box_cloud(pts, boxes, size)
    assert got.shape == (2, 6, 9)
    for i in range(2):
        box7 = np.array([*boxes[i, :3].tolist(), *size[i].tolist(), float(boxes[i, 3])])
        l, w, h = size[i].tolist()
        corners = np.array(
            [
                [sx * l / 2, sy * w / 2, sz * h / 2]
                for sx, sy, sz in [
                    (1, 1, 1),
                    (1, -1, 1),
                    (1, -1, -1),
                    (1, 1, -1),
                    (-1, 1, 1),
                    (-1, -1, 1),
                    (-1, -1, -1),
                    (-1, 1, -1),
                ]
            ]
        )
        keypoints = box_to_world(np.vstack([np.zeros(3), corners]), box7)
        expect = np.linalg.norm(pts[i].numpy()[:, None] - keypoints[None], axis=-1)
        np.testing.assert_allclose(got[i].numpy(), expect, atol=1e-5)


def test_box_aware_variant_trains_acts_and_round_trips(tmp_path):
    model = trackers.make("m2track", **TINY, box_aware=True)
    plain = trackers.make("m2track", **TINY)
    assert "box_cloud" in model.config.loss_weights
    assert "box_cloud" not in plain.config.loss_weights
    batch = _clouds(2, n=64)
    cloud = motion_cloud(
        batch["previous_search"],
        batch["search"],
        batch["size"],
        batch["prior_is_gt"],
        box_aware=True,
    )
    assert cloud.shape == (2, 128, 14) and (cloud[:, 64:, 5:] == 0).all()
    torch.testing.assert_close(
        cloud[:, :64, 5:], box_cloud(batch["previous_search"], torch.zeros(2, 4), batch["size"])
    )
    out = model(batch)
    assert out["box_cloud"].shape == (2, 128, 9)
    targets = {**_targets(batch), "box_cloud": torch.rand(2, 128, 9)}
    terms = model.loss(out, targets)
    torch.testing.assert_close(
        terms["box_cloud"].mean(), F.smooth_l1_loss(out["box_cloud"], targets["box_cloud"])
    )
    with pytest.raises(KeyError, match="box_cloud"):
        model.loss(out, _targets(batch))
    model.eval()
    obs = _obs(2, seed=3)
    path = trackers.save(model, tmp_path / "ba.safetensors")
    np.testing.assert_array_equal(trackers.load(path).act(obs), model.act(obs))
    model.fast_eval = False
    np.testing.assert_allclose(model.act(obs), trackers.load(path).act(obs), atol=1e-5)


def test_cli_demo_gives_m2track_the_previous_frame(tmp_path):
    """`pointtrack demo` runs the shipped M2-Track checkpoint: its env serves `previous_search`."""
    import json

    from training.cli import main

    out = tmp_path / "demo"
    argv = ["demo", "--preset", "tiny", "--out", str(out), "--no-progress", "--max-tracklets", "1"]
    assert main([*argv, "--tracker", "previous_box", "m2track-kitti1-u"]) == 0
    report = json.loads((out / "report.json").read_text())
    assert report["m2track-kitti1-u"]["frames"] == report["previous_box"]["frames"] > 0
