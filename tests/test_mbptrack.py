"""MBPTrack (trackers.mbptrack) and the env's memory keys (envs.memory): shapes, invariances,
memory of 0 / 1 / M frames, no hidden state, the reference's losses by hand, training, save /
load, bad input, the env's memory observation."""

from __future__ import annotations

import json
import math
import warnings

import numpy as np
import pytest
import torch

import trackers
from envs.geometry import boxes_in_frame, points_in_box
from envs.spec import MAX_MEMORY_FRAMES, MEMORY_KEYS, TEMPLATE_SCALE
from envs.tracking_env import OBSERVATION_KEYS, TrackingEnv, make_toy_dataset
from trackers import ops
from trackers.mbptrack import MEMORY_OPTION, MBPTrack
from trackers.mbptrack_layers import box_prior_offsets

pytestmark = pytest.mark.usefixtures("one_torch_thread")

TINY = {
    "edge_channels": [[8, 8], [16, 16], [16, 16]],
    "neighbours": 8,
    "feat_dim": 16,
    "ffn_channels": 16,
    "proposals": 8,
    "aggr_neighbours": 4,
    "dropout": 0.0,
    "memory_frames": 2,
}
KEYS = (*OBSERVATION_KEYS, *MEMORY_KEYS)


def _batch(b: int = 2, n: int = 128, m: int = 2, seed: int = 0) -> dict[str, torch.Tensor]:
    """A box-shaped target among ground points in the current frame and in ``m`` memory frames
    (each in its own box's frame, the target near the origin, mask = inside the box x1.25)."""
    g = torch.Generator().manual_seed(seed)
    size = torch.tensor([[4.0, 1.8, 1.5]]).repeat(b, 1)

    def frame(centre: torch.Tensor, lead: tuple[int, ...]) -> torch.Tensor:
        s = size.view(b, *([1] * (len(lead) - 1)), 1, 3)
        target = (torch.rand(*lead, n // 2, 3, generator=g) - 0.5) * s + centre[..., None, :]
        ground = (torch.rand(*lead, n - n // 2, 3, generator=g) - 0.5) * torch.tensor(
            [9.0, 6.0, 0.1]
        )
        ground[..., 2] -= 0.75
        return torch.cat([target, ground], dim=-2)

    move = torch.cat([0.5 * torch.randn(b, 2, generator=g), torch.zeros(b, 1)], dim=1)
    memory = frame(torch.zeros(b, m, 3), (b, m))
    inside = (memory.abs() <= size[:, None, None] * (TEMPLATE_SCALE / 2)).all(-1).float()
    boxes = torch.zeros(b, m, 5)
    boxes[..., 0] = -0.3 * torch.arange(m - 1, -1, -1)  # older frames farther behind
    boxes[..., 3] = 0.05
    boxes[..., 4] = 1.0
    return {
        "template": torch.zeros(b, 512, 3),
        "search": frame(move, (b,)),
        "size": size,
        "motion": torch.zeros(b, 4),
        "memory": torch.cat([memory, inside[..., None]], dim=-1),
        "memory_boxes": boxes,
        "_move": move,
    }


def _targets(batch: dict[str, torch.Tensor]) -> dict[str, torch.Tensor]:
    move = batch["_move"]
    rel = batch["search"] - move[:, None]
    labels = (rel.abs() <= batch["size"][:, None] * (TEMPLATE_SCALE / 2)).all(-1).float()
    return {"search_labels": labels, "box": torch.cat([move, torch.zeros(len(move), 1)], 1)}


def _inputs(batch):
    return {k: v for k, v in batch.items() if not k.startswith("_")}


def _tiny(seed: int = 0) -> MBPTrack:
    torch.manual_seed(seed)
    return trackers.make("mbptrack", **TINY)


def test_registered_with_default_and_slim_widths():
    assert "mbptrack" in trackers.available("learned")
    default = trackers.make("mbptrack")
    slim = trackers.make("mbptrack", **trackers.size_config("mbptrack", "slim"))
    n_default = sum(p.numel() for p in default.parameters())
    n_slim = sum(p.numel() for p in slim.parameters())
    assert n_slim < n_default / 3
    assert default.config.loss_weights == {
        "mask": 0.2,
        "coarse_objectness": 1.0,
        "objectness": 1.0,
        "bbox": 1.0,
        "center": 10.0,
    }
    assert default.config.memory_frames == 3 and default.config.box_grid == [3, 3, 5]
    assert MBPTrack.observation_keys == ("memory", "memory_boxes")
    assert MBPTrack.sample_recipe == "memory"


def test_light_size_is_slim_with_less_per_frame_work_and_mbptracks_alone():
    slim, light = (trackers.size_config("mbptrack", s) for s in ("slim", "light"))
    changed = {k: v for k, v in light.items() if slim.get(k) != v}
    assert changed == {"layers": 1, "box_grid": [2, 2, 3], "aggr_neighbours": 4, "neighbours": 8}
    model = trackers.make("mbptrack", **light).eval()
    out = model(_inputs(_batch(b=2, n=1024, m=3)))
    assert out["proposals"].shape == (2, 32, 4) and torch.isfinite(out["proposals"]).all()
    assert len(model.transformer) == 1 and model.loc.grid.shape == (12, 3)
    with pytest.raises(ValueError, match="'p2b' has no model size 'light'; valid: "):
        trackers.size_config("p2b", "light")


def test_box_prior_grid_is_the_shrunk_cell_centres():
    grid = box_prior_offsets(3, 3, 5)
    assert grid.shape == (45, 3)
    assert torch.allclose(grid[0], torch.tensor([-1 / 3, -1 / 3, -0.4]))
    assert torch.allclose(grid[-1], torch.tensor([1 / 3, 1 / 3, 0.4]))
    assert torch.allclose(grid.mean(0), torch.zeros(3), atol=1e-7)


@pytest.mark.parametrize("mode", ["train", "eval"])
def test_shapes_and_finite(mode):
    model = _tiny()
    model.train(mode == "train")
    out = model(_inputs(_batch(b=3, m=2)))
    s, k = 128 // 8, TINY["proposals"]
    shapes = {
        "proposals": (3, k, 4),
        "scores": (3, k),
        "mask_logits": (3, s),
        "center": (3, s, 3),
        "coarse_logits": (3, s),
        "proposal_xyz": (3, k, 3),
        "box_raw": (3, k, 5),
        "seed_idx": (3, s),
        "Z": (3, s, TINY["feat_dim"]),
        "motion": (3, 4),
    }
    assert {k: tuple(v.shape) for k, v in out.items()} == shapes
    assert all(torch.isfinite(v.float()).all() for v in out.values())
    assert torch.allclose(out["proposals"][..., 3], torch.deg2rad(out["box_raw"][..., 3]))


def test_order_invariance_of_every_point_set():
    model = _tiny().eval()
    batch = _inputs(_batch(b=1, m=2, seed=4))
    ref = model(batch)
    g = torch.Generator().manual_seed(1)
    shuffled = dict(batch)
    shuffled["search"] = batch["search"][:, torch.randperm(128, generator=g)]
    shuffled["memory"] = batch["memory"][:, :, torch.randperm(128, generator=g)]
    out = model(shuffled)
    for key in ("proposals", "scores", "mask_logits"):
        torch.testing.assert_close(out[key], ref[key], atol=1e-5, rtol=1e-5)


def test_memory_of_zero_one_and_m_frames():
    model = _tiny().eval()
    batch = _inputs(_batch(b=1, m=2, seed=5))

    def with_valid(valid, jitter_slot=None):
        b = {k: v.clone() for k, v in batch.items()}
        b["memory_boxes"][0, :, 4] = torch.tensor(valid)
        if jitter_slot is not None:
            b["memory"][0, jitter_slot, :, :3] += 0.7
            b["memory"][0, jitter_slot, :, 3] = 1 - b["memory"][0, jitter_slot, :, 3]
        return model(b)["scores"]

    # 0 frames: the current frame stands in, and no memory content matters
    none = with_valid([0.0, 0.0])
    assert torch.isfinite(none).all()
    torch.testing.assert_close(with_valid([0.0, 0.0], jitter_slot=0), none)
    torch.testing.assert_close(with_valid([0.0, 0.0], jitter_slot=1), none)
    # 1 frame: only the valid slot matters
    one = with_valid([0.0, 1.0])
    torch.testing.assert_close(with_valid([0.0, 1.0], jitter_slot=0), one)
    assert not torch.allclose(with_valid([0.0, 1.0], jitter_slot=1), one)
    assert not torch.allclose(one, none)
    # M frames: every slot matters
    both = with_valid([1.0, 1.0])
    assert not torch.allclose(with_valid([1.0, 1.0], jitter_slot=0), both)
    assert not torch.allclose(both, one)


def _act_batch(b: int = 1, m: int = 2, seed: int = 0) -> dict[str, torch.Tensor]:
    """:func:`_batch` at the env's sizes (``act`` checks them)."""
    return _batch(b=b, n=1024, m=m, seed=seed)


def _obs(batch, i: int = 0, slots: int | None = None) -> dict[str, np.ndarray]:
    obs = {k: v[i].numpy() for k, v in _inputs(batch).items()}
    if slots is not None:
        obs["memory"], obs["memory_boxes"] = obs["memory"][-slots:], obs["memory_boxes"][-slots:]
    return obs


def test_act_has_no_hidden_state():
    model = _tiny(seed=2)
    batch = _act_batch(b=2, m=2, seed=6)
    first = model.act(_obs(batch, 0))
    model.act(_obs(batch, 1))
    again = model.act(_obs(batch, 0))
    fresh = _tiny(seed=9)
    fresh.load_state_dict(model.state_dict())
    np.testing.assert_array_equal(again, first)
    np.testing.assert_array_equal(fresh.act(_obs(batch, 0)), first)
    assert first.shape == (4,) and first.dtype == np.float32
    batched = model.act({k: v.numpy() for k, v in _inputs(batch).items()})
    np.testing.assert_array_equal(batched[0], first)


def test_missing_target_repeats_the_last_motion():
    model = _tiny(seed=3)
    obs = _obs(_act_batch(b=1, m=2, seed=7))
    obs["motion"] = np.array([0.4, -0.1, 0.0, 0.02], np.float32)
    model.config.missing_threshold = 1.0  # no seed can reach it
    np.testing.assert_allclose(model.act(obs), obs["motion"])
    model.config.missing_threshold = 0.0
    assert not np.allclose(model.act(obs), obs["motion"])


def test_still_target_test_keeps_the_box_and_leaves_moving_targets_to_the_network():
    """With ``hold_chamfer_m`` the tracker keeps the box (action 0) where the search's points in
    the reference box match both template crops, and elsewhere acts as without it."""
    from trackers.decision import InferenceConfig

    model = _tiny(seed=4)
    g = torch.Generator().manual_seed(11)
    target = (torch.rand(256, 3, generator=g) - 0.5) * torch.tensor([4.0, 1.8, 1.5])
    ground = (torch.rand(768, 3, generator=g) - 0.5) * torch.tensor([9.0, 6.0, 0.1])
    ground[:, 2] -= 0.75
    obs = _obs(_act_batch(b=1, m=2, seed=8))
    obs["template"] = torch.cat([target, target]).numpy()  # first and previous crops
    still = {**obs, "search": torch.cat([target, ground]).numpy()}
    moved = {**obs, "search": torch.cat([target + torch.tensor([1.5, 0.0, 0.0]), ground]).numpy()}
    free = {k: model.act(o) for k, o in (("still", still), ("moved", moved))}
    model.inference = InferenceConfig(hold_chamfer_m=0.15)
    np.testing.assert_array_equal(model.act(still), np.zeros(4, np.float32))
    np.testing.assert_array_equal(model.act(moved), free["moved"])
    assert np.abs(free["still"]).max() > 0  # the hold, not the network, kept the box


def test_missing_memory_key_and_short_memory_are_clear_errors():
    model = _tiny()
    obs = _obs(_act_batch(b=1, m=2))
    for key in MEMORY_KEYS:
        broken = {k: v for k, v in obs.items() if k != key}
        with pytest.raises(KeyError, match=rf"{key}.*observation_keys"):
            model.act(broken)
    assert "memory_frames" in MEMORY_OPTION
    with pytest.raises(ValueError, match=r"holds 1 frame.*memory_frames=2"):
        model.act(_obs(_act_batch(b=1, m=2), slots=1))
    longer = _obs(_act_batch(b=1, m=3))  # more slots than it reads: the newest two
    np.testing.assert_array_equal(model.act(longer), model.act(_obs(_act_batch(b=1, m=3), slots=2)))
    bad = dict(obs, memory=obs["memory"][..., :3])
    with pytest.raises(ValueError, match=r"memory.*\(M, N, 4\)"):
        model.act(bad)


def _bce(logit: float, label: float, pos_weight: float = 1.0) -> float:
    p = 1 / (1 + math.exp(-logit))
    return -(pos_weight * label * math.log(p) + (1 - label) * math.log(1 - p))


def _smooth_l1(x: float) -> float:
    return 0.5 * x * x if abs(x) < 1 else abs(x) - 0.5


def test_losses_against_hand_computation():
    model = _tiny()
    # two samples, two seeds, two proposals; ground truth at (1, 0, 0), yaw pi / 6
    outputs = {
        "seed_idx": torch.tensor([[0, 2], [1, 0]]),
        "mask_logits": torch.tensor([[0.5, -1.0], [2.0, 0.0]]),
        "center": torch.tensor(
            [[[1.1, 0.0, 0.0], [3.0, 0.0, 0.0]], [[1.0, 0.5, 0.0], [1.0, 0.0, 0.2]]]
        ),
        "coarse_logits": torch.tensor([[1.0, -2.0], [0.0, 0.5]]),
        "proposal_xyz": torch.tensor(
            [[[1.2, 0.0, 0.0], [0.0, 0.0, 0.0]], [[1.0, 0.0, 0.1], [2.0, 2.0, 0.0]]]
        ),
        "box_raw": torch.tensor(
            [
                [[1.0, 0.1, 0.0, 32.0, 0.3], [0.0, 0.0, 0.0, 0.0, -1.0]],
                [[1.5, 0.0, 0.0, 30.0, 1.5], [2.0, 2.0, 0.0, 0.0, 0.2]],
            ]
        ),
    }
    targets = {
        "search_labels": torch.tensor([[1.0, 0.0, 1.0], [0.0, 1.0, 0.0]]),
        "box": torch.tensor([[1.0, 0.0, 0.0, math.pi / 6]] * 2),
    }
    terms = model.loss(outputs, targets)
    labels = [[1.0, 1.0], [1.0, 0.0]]  # search_labels at seed_idx
    mask = [
        np.mean([_bce(outputs["mask_logits"][i, j].item(), labels[i][j]) for j in (0, 1)])
        for i in (0, 1)
    ]
    np.testing.assert_allclose(terms["mask"].numpy(), mask, rtol=1e-5)
    # centre: squared error (mean over xyz) on target seeds, x B / all target seeds of the batch
    n_pos = 3
    center = [2 * (0.01 / 3 + 4.0 / 3) / n_pos, 2 * (0.25 / 3) / n_pos]
    np.testing.assert_allclose(terms["center"].numpy(), center, rtol=1e-4)
    # coarse objectness: centres within 0.3 m are positive: seeds (0,0), (1,1)
    coarse_pos = [[1.0, 0.0], [0.0, 1.0]]
    coarse = [
        np.mean(
            [_bce(outputs["coarse_logits"][i, j].item(), coarse_pos[i][j], 2.0) for j in (0, 1)]
        )
        for i in (0, 1)
    ]
    np.testing.assert_allclose(terms["coarse_objectness"].numpy(), coarse, rtol=1e-5)
    # refined objectness: proposals within 0.3 m: (0, 0) and (1, 0)
    rfn_pos = [[1.0, 0.0], [1.0, 0.0]]
    rfn = [
        np.mean([_bce(outputs["box_raw"][i, j, 4].item(), rfn_pos[i][j], 2.0) for j in (0, 1)])
        for i in (0, 1)
    ]
    np.testing.assert_allclose(terms["objectness"].numpy(), rfn, rtol=1e-5)
    # box: smooth-L1 mean over (x, y, z, yaw in degrees) on positive proposals, / 2 positives
    err0 = np.mean([_smooth_l1(v) for v in (0.0, 0.1, 0.0, 2.0)])
    err1 = np.mean([_smooth_l1(v) for v in (0.5, 0.0, 0.0, 0.0)])
    np.testing.assert_allclose(terms["bbox"].numpy(), [2 * err0 / 2, 2 * err1 / 2], rtol=1e-4)
    w = model.config.loss_weights
    total = sum(w[k] * terms[k] for k in w)
    torch.testing.assert_close(terms["total"], total)
    assert w["center"] == 10.0 and w["mask"] == 0.2
    with pytest.raises(KeyError, match="search_labels"):
        model.loss(outputs, {"box": targets["box"]})


def test_training_steps_lower_the_loss():
    torch.manual_seed(0)
    model = trackers.make("mbptrack", **{**TINY, "dropout": 0.1}).train()
    batch = _batch(b=4, m=2, seed=8)
    targets = _targets(batch)
    opt = torch.optim.Adam(model.parameters(), lr=1e-3, betas=(0.5, 0.999), eps=1e-6)
    losses = []
    gen = torch.Generator().manual_seed(0)
    for _ in range(30):
        loss = model.loss(model(_inputs(batch), gen), targets)["total"].mean()
        opt.zero_grad()
        loss.backward()
        opt.step()
        losses.append(loss.item())
    assert np.mean(losses[-5:]) < 0.8 * losses[0], losses


def test_save_load_round_trip(tmp_path):
    model = _tiny(seed=4)
    batch = _act_batch(b=1, m=2, seed=9)
    model.train()
    model(_inputs(batch))  # move the BatchNorm statistics off their defaults
    model.eval()
    path = trackers.save(model, tmp_path / "mbp.safetensors")
    loaded = trackers.load(path)
    assert isinstance(loaded, MBPTrack) and loaded.config == model.config
    np.testing.assert_array_equal(loaded.act(_obs(batch)), model.act(_obs(batch)))


@pytest.mark.parametrize("suffix", [".safetensors", ".pt"])
def test_checkpoint_carries_provenance_and_info_reads_it(tmp_path, capsys, suffix):
    from trackers.provenance import Provenance
    from training.cli import main

    prov = Provenance(written_by="train", setting="kitti-1", categories=["Car"], steps=3)
    path = trackers.save(_tiny(seed=4), tmp_path / f"mbp{suffix}", provenance=prov)
    assert trackers.load(path).provenance == prov
    again = trackers.save(trackers.load(path), tmp_path / f"again{suffix}")  # carried along
    assert trackers.load(again).provenance == prov
    assert main(["info", "--json", str(path)]) == 0
    data = json.loads(capsys.readouterr().out)
    assert data["tracker"] == "mbptrack" and data["provenance"]["setting"] == "kitti-1"
    assert data["provenance"]["categories"] == ["Car"] and data["provenance"]["steps"] == 3


# ---------------------------------------------------------------- the env's memory keys


@pytest.fixture(scope="module")
def toy():
    return make_toy_dataset(num_frames=[7, 9, 6, 6], seed=3)


def test_env_memory_keys_pass_the_checkers(toy):
    from gymnasium.utils.env_checker import check_env
    from stable_baselines3.common.env_checker import check_env as sb3_check_env

    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        check_env(TrackingEnv(toy, observation_keys=KEYS, memory_frames=2))
        sb3_check_env(TrackingEnv(toy, observation_keys=KEYS), warn=True)
    for bad in (0, MAX_MEMORY_FRAMES + 1, 2.5, True):
        with pytest.raises(ValueError, match="memory_frames"):
            TrackingEnv(toy, observation_keys=KEYS, memory_frames=bad)
    plain = TrackingEnv(toy)
    assert not set(MEMORY_KEYS) & set(plain.observation_space.spaces)


def test_env_memory_holds_the_search_regions_and_the_agents_boxes(toy):
    env = TrackingEnv(toy, observation_keys=KEYS, memory_frames=3, episode_seed=0)
    obs, info = env.reset(seed=0)
    assert env.observation_space.contains(obs)
    assert obs["memory"].shape == (3, 1024, 4) and obs["memory_boxes"].shape == (3, 5)
    # first step: frame 0 around the given box (the reference box), two empty slots
    np.testing.assert_array_equal(obs["memory_boxes"][:2], 0)
    np.testing.assert_allclose(obs["memory_boxes"][2], [0, 0, 0, 0, 1], atol=1e-6)
    assert not obs["memory"][:2].any()
    size = info["init_box"][3:6]
    inside = np.all(np.abs(obs["memory"][2, :, :3]) <= size * TEMPLATE_SCALE / 2 + 1e-6, axis=1)
    np.testing.assert_array_equal(obs["memory"][2, :, 3], inside.astype(np.float32))
    frame0 = obs["memory"][2].copy()
    preds, searches = [info["init_box"]], [None, obs["search"].copy()]
    actions = [np.array([0.3, -0.1, 0.0, 0.05]), np.array([0.1, 0.2, 0.0, -0.1])]
    for step, action in enumerate(actions):
        obs, _, _, _, step_info = env.step(action.astype(np.float32))
        assert env.observation_space.contains(obs)
        preds.append(step_info["pred_box"])
        ref = preds[-1]  # the reference box: the last prediction
        frames = list(range(step + 2))  # frames 0 .. t - 1 in the memory, oldest first
        slots = range(3 - len(frames), 3)
        assert obs["memory_boxes"][:, 4].tolist() == [0.0] * (3 - len(frames)) + [1.0] * len(frames)
        for slot, k in zip(slots, frames, strict=True):
            crop_box = preds[max(k - 1, 0)]  # frame k's search region was cropped around it
            want = boxes_in_frame(crop_box, ref)
            np.testing.assert_allclose(obs["memory_boxes"][slot, :3], want[:3], atol=1e-5)
            np.testing.assert_allclose(obs["memory_boxes"][slot, 3], want[6], atol=1e-6)
            if k == 0:
                np.testing.assert_array_equal(obs["memory"][slot], frame0)
                continue
            np.testing.assert_array_equal(obs["memory"][slot, :, :3], searches[k])
            agent = boxes_in_frame(preds[k], crop_box)  # the agent's box for frame k
            mask = points_in_box(searches[k], agent, TEMPLATE_SCALE).astype(np.float32)
            np.testing.assert_array_equal(obs["memory"][slot, :, 3], mask)
        searches.append(obs["search"].copy())


def test_mbptrack_tracks_in_the_env_and_refuses_an_env_without_memory(toy):
    model = trackers.make("mbptrack", **{**TINY, "memory_frames": 3})
    env = TrackingEnv(toy, observation_keys=KEYS, memory_frames=3)
    obs, _ = env.reset(seed=0)
    done = False
    while not done:
        action = model.act(obs)
        assert env.action_space.contains(action)
        obs, _, terminated, truncated, _ = env.step(action)
        done = terminated or truncated
    obs, _ = TrackingEnv(toy).reset(seed=0)
    with pytest.raises(KeyError, match="memory"):
        model.act(obs)
    obs, _ = TrackingEnv(toy, observation_keys=KEYS, memory_frames=2).reset(seed=0)
    with pytest.raises(ValueError, match=r"holds 2 frame.*memory_frames=3"):
        model.act(obs)


def test_fast_eval_equals_plain_and_the_seed_cache_is_exact():
    model = _tiny(seed=5)
    model.train()
    batch = _inputs(_act_batch(b=2, m=2, seed=10))
    model(batch)  # BatchNorm statistics off their defaults
    model.eval()
    with torch.no_grad():  # the cache serves no-grad eval forwards only
        fast = model(batch)
        assert len(model._seed_cache) == 6  # two samples x (search + two memory frames)
        cached = model(batch)
        model.fast_eval = False
        plain = model(batch)
        for key in ("proposals", "scores", "mask_logits"):
            torch.testing.assert_close(cached[key], fast[key], atol=0, rtol=0)
            torch.testing.assert_close(plain[key], fast[key], atol=1e-4, rtol=1e-4)
        # an optimiser step changes the backbone: the cache must not serve the old seeds
        model.fast_eval = True
        model.backbone.fc.bias.add_(0.5)
        moved = model(batch)
        model._seed_cache.clear()
        torch.testing.assert_close(model(batch)["scores"], moved["scores"], atol=0, rtol=0)
    assert not torch.allclose(moved["scores"], fast["scores"])


def test_backbone_evaluates_each_distinct_point_once():
    """The backbone's one-cloud eval path (``copies=True``) on a cloud the env would serve (a
    few distinct points repeated to fill it): the same seeds as evaluating every centre, where
    most centres are copies (checked to differ when a copy takes another centre's row)."""
    model = _tiny(seed=3)
    model.train()
    model(_inputs(_act_batch(b=2, m=2, seed=4)))  # BatchNorm statistics off their defaults
    model.eval()
    g = torch.Generator().manual_seed(0)
    distinct = torch.randn(90, 3, generator=g) * torch.tensor([1.5, 0.8, 0.4])
    cloud = distinct[torch.randint(0, 90, (256,), generator=g)][None]
    first = ops.first_copy(cloud)
    assert (first == torch.arange(256)).float().mean() < 0.4  # mostly copies
    with torch.no_grad():
        all_xyz, all_feat = model.backbone(cloud)
        xyz, feat = model.backbone(cloud, copies=True)
        no_copies = model.backbone(distinct[None], copies=True)[1]
    assert torch.equal(xyz, all_xyz)
    torch.testing.assert_close(feat, all_feat, atol=1e-6, rtol=1e-6)
    torch.testing.assert_close(no_copies, model.backbone(distinct[None])[1], atol=0, rtol=0)
    assert not torch.allclose(feat, feat.roll(1, dims=1), atol=1e-3)  # distinct rows differ


def test_memory_samples_are_deterministic_and_shaped_like_the_env(toy):
    from training.memory_samples import MemorySamples

    data = MemorySamples(toy.tracklets, candidates_per_frame=2, seed=1)
    again = MemorySamples(toy.tracklets, candidates_per_frame=2, seed=1)
    env = TrackingEnv(toy, observation_keys=KEYS, memory_frames=2)
    obs, _ = env.reset(seed=0)
    for index in (0, 1, 9, len(data) - 1):
        sample = data[index]
        assert all(torch.equal(sample[k], again[index][k]) for k in sample)
        for key in ("search", "size", *MEMORY_KEYS):
            assert tuple(sample[key].shape) == obs[key].shape, key
            assert env.observation_space[key].contains(sample[key].numpy()), key
        # the newest memory frame was cropped around the box before the reference box
        _, t, cand = data.locate(index)
        valid = sample["memory_boxes"][:, 4]
        assert valid.tolist() == ([0.0, 1.0] if t == 1 else [1.0, 1.0])
        if t == 1:  # frame 0: cropped around the given box, which is the reference box
            torch.testing.assert_close(sample["memory_boxes"][1, :4], torch.zeros(4))
        labels = sample["search_labels"].bool()
        box = sample["box"]
        rel = sample["search"] - box[:3]
        c, s = math.cos(box[3]), math.sin(box[3])
        local = torch.stack([c * rel[:, 0] + s * rel[:, 1], -s * rel[:, 0] + c * rel[:, 1]], -1)
        half = sample["size"] * TEMPLATE_SCALE / 2
        inside = (local.abs() <= half[:2] + 1e-5).all(-1) & (rel[:, 2].abs() <= half[2] + 1e-5)
        assert torch.equal(labels, inside)
    data.set_epoch(1)
    assert not torch.equal(data[1]["search"], again[1]["search"])


def test_tracker_policy_acts_like_mbptrack_and_learns(toy):
    from gymnasium.wrappers import RescaleAction
    from stable_baselines3 import PPO

    from training.rl import TrackerPolicy

    base = _tiny(seed=6).eval()
    env = RescaleAction(TrackingEnv(toy, observation_keys=KEYS), -1, 1)
    model = PPO(
        TrackerPolicy,
        env,
        policy_kwargs={"tracker": base},
        n_steps=16,
        batch_size=16,
        n_epochs=1,
        seed=0,
        device="cpu",
    )
    probe = TrackingEnv(toy, observation_keys=KEYS)
    obs, _ = probe.reset(seed=0)
    for _ in range(3):
        action, _ = model.predict(obs, deterministic=True)
        np.testing.assert_allclose(action, base.act(obs) / base.max_action, atol=1e-5)
        obs, *_ = probe.step(base.act(obs))
    model.learn(16)
    assert all(torch.isfinite(p).all() for p in model.policy.parameters())


@pytest.mark.skipif(not torch.cuda.is_available(), reason="no CUDA device")
def test_cuda_forward_matches_cpu():
    model = _tiny(seed=7).eval()
    batch = _inputs(_act_batch(b=1, m=2, seed=11))
    with torch.no_grad():
        cpu = model(batch)
        gpu = model.to("cuda")({k: v.cuda() for k, v in batch.items()})
    for key in ("proposals", "scores", "mask_logits"):
        torch.testing.assert_close(gpu[key].cpu(), cpu[key], atol=1e-4, rtol=1e-4)
    obs = _obs(_act_batch(b=1, m=2, seed=11))
    np.testing.assert_allclose(model.act(obs), model.to("cpu").act(obs), atol=1e-4)


@pytest.mark.parametrize(
    ("name", "size"),
    [
        ("mbptrack-kitti1-u", "slim"),
        ("mbptrack-kitti1-w", "slim"),
        ("mbptrack-kitti1-u-light", "light"),
    ],
)
def test_shipped_file_loads_acts_and_records_its_provenance(name, size, toy):
    """The shipped MBPTrack files (docs/mbptrack.md, "Shipped-budget runs", "A `light` size"):
    of their model size, trained on the `default` world's kitti-1 observed categories, chosen
    by `pointtrack select`; they act on an env serving the memory, the same action twice (no
    hidden state)."""
    tracker = trackers.load(name)
    assert isinstance(tracker, MBPTrack) and tracker.config.memory_frames == 3
    for key, value in trackers.size_config("mbptrack", size).items():
        assert getattr(tracker.config, key) == value, key
    provenance = tracker.provenance
    assert (provenance.preset, provenance.setting, provenance.world_seed) == (
        "default",
        "kitti-1",
        0,
    )
    assert "Car" not in provenance.categories and provenance.selection
    env = TrackingEnv(toy, observation_keys=KEYS, memory_frames=3)
    obs, _ = env.reset(seed=0)
    for _ in range(3):
        action = tracker.act(obs)
        assert np.isfinite(action).all()
        np.testing.assert_array_equal(trackers.load(name).act(obs), action)
        obs, *_ = env.step(action)
