"""The decision step (:mod:`trackers.decision`): the still-target test, the re-ranking and the
clip; ``decide`` and ``act`` against the actions recorded from main before the decision step
moved out of ``trackers/base.py`` (``tests/data/decisions.npz``,
``tests/data/record_decisions.py``); ``InferenceConfig``; old checkpoints' migration."""

from __future__ import annotations

import json
import math
import re
from pathlib import Path

import numpy as np
import pytest
import torch
from test_trackers import tiny

import trackers
from trackers import decision, kernels, ops
from trackers.base import prepare_observation
from trackers.decision import (
    InferenceConfig,
    choose_action,
    chosen_proposal,
    clip_action,
    decide,
    keeps_box,
    scenes,
)

pytestmark = pytest.mark.usefixtures("one_torch_thread")

DATA = Path(__file__).parent / "data" / "decisions.npz"
KEYS = ("template", "search", "size", "motion")


@pytest.fixture(scope="module")
def recorded():
    with np.load(DATA) as data:
        return {k: data[k] for k in data.files}


def _recorded_names(recorded):
    return sorted({k.split("/")[0] for k in recorded if "/" in k})


RECORDED = [
    *(f"{n}-kitti1-{w}" for n in ("p2b", "bat", "gpt") for w in "uw"),
    "p2b-kitti1-u-rl",
    "gpt-kitti1-u-rl",
    "p2b-kitti1-drct",
]


def test_the_recording_covers_every_shipped_kitti1_matching_file(recorded):
    shipped = [
        n
        for n in trackers.available("checkpoint")
        if "kitti1" in n and "rerank_top_k" in trackers.load(n).inference_fields
    ]
    assert _recorded_names(recorded) == sorted(shipped) == sorted(RECORDED)


@pytest.mark.parametrize("name", RECORDED)
def test_decide_and_act_take_the_recorded_decisions(name, recorded):
    """On the recorded observations (tiny world, each file holding, keeping the reference box,
    executing the best-scored proposal and overruling it), ``decide`` on the recorded network
    outputs gives the recorded actions bit for bit, and ``act`` (its own forward) to the
    tolerance of another CPU's rounding (``tests/test_trackers_reference.py``)."""
    model = trackers.load(name)
    assert model.inference.hold_chamfer_m > 0 and model.inference.rerank_top_k == 8
    obs = {k: recorded[f"obs_{k}"] for k in KEYS}
    want, kind = recorded[f"{name}/act"], recorded[f"{name}/kind"]
    assert set(kind.tolist()) == {0, 1, 2}  # no move, the best proposal, another one
    batch, _ = prepare_observation(obs)
    outputs = {k: torch.from_numpy(recorded[f"{name}/{k}"]) for k in ("proposals", "scores")}
    got = decide(model, batch, outputs, model.inference)
    np.testing.assert_array_equal(torch.nan_to_num(got).numpy(), want)
    held = keeps_box(model, batch, model.inference).numpy()
    assert held.any() and not want[held].any()
    single = np.stack([model.act({k: v[i] for k, v in obs.items()}) for i in range(len(want))])
    np.testing.assert_allclose(single, want, rtol=0, atol=1e-4)
    np.testing.assert_array_equal(model.act(obs), single)


@pytest.mark.parametrize("name", RECORDED)
def test_chosen_proposal_names_the_proposal_decide_executes(name, recorded):
    """``chosen_proposal`` (the RL update differentiates that proposal alone) on the recorded
    network outputs: ``-1`` exactly where the re-ranking keeps the reference box, and elsewhere
    ``decide``'s action is that proposal clipped, bit for bit (the best-scored one or another:
    every kind of decision is among the recorded ones)."""
    model = trackers.load(name)
    obs = {k: recorded[f"obs_{k}"] for k in KEYS}
    batch, _ = prepare_observation(obs)
    outputs = {k: torch.from_numpy(recorded[f"{name}/{k}"]) for k in ("proposals", "scores")}
    moving = ~keeps_box(model, batch, model.inference).numpy()
    index = chosen_proposal(model, batch, outputs, model.inference, model.max_action)
    kind = recorded[f"{name}/kind"][moving]  # 0 no move, 1 the best proposal, 2 another one
    np.testing.assert_array_equal(index.numpy()[moving] == -1, kind == 0)
    rows = torch.arange(len(index))
    executed = clip_action(outputs["proposals"][rows, index.clamp(min=0)], model.max_action)
    action = decide(model, batch, outputs, model.inference).numpy()[moving]
    np.testing.assert_array_equal(action[kind > 0], executed.numpy()[moving][kind > 0])


def test_old_checkpoints_migrate_and_act_identically(tmp_path, recorded):
    """A file in the old format (the inference fields inside the architecture config, as every
    shipped file) and the same tracker saved now (``inference`` metadata of its own) load to
    the same ``InferenceConfig`` and act the same; ``load(..., inference=)`` overrides it."""
    from safetensors.torch import save_file

    from trackers.registry import find_checkpoint, read_safetensors

    name = "bat-kitti1-u"
    meta, state = read_safetensors(find_checkpoint(name), "checkpoint")
    assert json.loads(meta["config"])["hold_chamfer_m"] == 0.2 and "inference" not in meta
    old = tmp_path / "old.safetensors"
    save_file(state, str(old), metadata=meta)
    model = trackers.load(old)
    assert model.inference == InferenceConfig(0.2, 8, 0.0)
    assert not hasattr(model.config, "hold_chamfer_m")
    new = trackers.save(model, tmp_path / "new.safetensors")
    new_meta, _ = read_safetensors(new, "checkpoint")
    assert "hold_chamfer_m" not in json.loads(new_meta["config"])
    assert json.loads(new_meta["inference"]) == model.inference.to_dict()
    obs = {k: recorded[f"obs_{k}"] for k in KEYS}
    act = trackers.load(new).act(obs)
    np.testing.assert_array_equal(act, model.act(obs))
    np.testing.assert_array_equal(act, trackers.load(name).act(obs))
    # the default inference writes no entry; both at once is refused
    plain = trackers.load(new, inference=InferenceConfig())
    assert plain.inference == InferenceConfig()
    assert "inference" not in read_safetensors(trackers.save(plain, new), "checkpoint")[0]
    both = tmp_path / "both.safetensors"
    save_file(state, str(both), metadata={**meta, "inference": new_meta["inference"]})
    with pytest.raises(ValueError, match="both.safetensors: inference settings both in the"):
        trackers.load(both)
    bad = tmp_path / "bad.safetensors"
    save_file(state, str(bad), metadata={**new_meta, "inference": '{"rerank_top_k": -1}'})
    with pytest.raises(ValueError, match="bad.safetensors: inference: InferenceConfig.rerank"):
        trackers.load(bad)
    # overrides for evaluation: a whole config, or some fields over the file's
    partial = trackers.load(name, inference={"rerank_top_k": 2})
    assert partial.inference == InferenceConfig(0.2, 2, 0.0)
    with pytest.raises(ValueError, match="inference override for bat-kitti1-u: unknown"):
        trackers.load(name, inference={"rerank_k": 2})
    with pytest.raises(ValueError, match="baseline"):
        trackers.load("previous_box", inference={"rerank_top_k": 2})


def test_decide_keeps_clips_and_takes_a_given_action():
    tracker = tiny("p2b")
    obs = _still_target_observation(0, shift_m=0.6)
    batch, _ = prepare_observation({k: np.stack([obs[k]] * 3) for k in obs})
    batch["search"][2] = 0  # an empty observation: kept
    proposals = torch.tensor([[[9.0, -9.0, 0.5, 4.0]]]).expand(3, 1, 4)
    outputs = {"proposals": proposals, "scores": torch.zeros(3, 1)}
    got = decide(tracker, batch, outputs, tracker.inference)
    np.testing.assert_array_equal(got[0].numpy(), np.float32([5, -5, 0.5, np.pi]))
    assert not got[2].any()
    given = torch.tensor([[1.0, 0, 0, 0], [float("inf"), 0, 0, 0], [1.0, 0, 0, 0]])
    got = decide(tracker, batch, outputs, tracker.inference, action=given, max_action=[0.5] * 4)
    np.testing.assert_array_equal(got[0].numpy(), np.float32([0.5, 0, 0, 0]))
    assert torch.isnan(got[1, 0]) and not got[2].any()  # non-finite: NaN, for the caller
    # the dead zone: a move shorter than min_motion_m keeps the box (its yaw too)
    dead_zone = InferenceConfig(min_motion_m=0.5)
    given = torch.tensor([[0.3, 0.39, 0.0, 0.5], [0.3, 0.4, 0.0, 0.5], [0.1, 0, 0, 0]])
    got = decide(tracker, batch, outputs, dead_zone, action=given)
    assert not got[0].any()  # |(0.3, 0.39, 0)| < 0.5
    np.testing.assert_array_equal(got[1].numpy(), np.float32([0.3, 0.4, 0.0, 0.5]))  # = 0.5
    given = torch.tensor([[math.nan, 0, 0, 0]] * 3)
    assert torch.isnan(decide(tracker, batch, outputs, dead_zone, action=given)[0, 0])
    chosen = decide(tracker, batch, outputs, dead_zone)  # the network's (9, -9) move, clipped
    np.testing.assert_array_equal(chosen[0].numpy(), np.float32([5, -5, 0.5, np.pi]))


def _still_target_observation(seed=0, shift_m=0.0):
    """A box-frame observation whose search holds the target's crop (the template's two halves:
    the same car surface, resampled) moved by ``shift_m`` along x, plus ground and clutter."""
    rng = np.random.default_rng(seed)
    size = np.array([4.0, 1.8, 1.5], np.float32)
    surface = rng.uniform(-0.5, 0.5, (60, 3)) * size * [1, 1, 0.8]  # above the ground clearance
    surface[:, 2] += 0.1
    template = np.concatenate(
        [surface[rng.integers(0, 60, 256)], surface[rng.integers(0, 60, 256)]]
    )
    ground = np.c_[rng.uniform(-4, 4, (200, 2)), np.full(200, -0.75)]  # at the box's bottom
    clutter = rng.uniform(-5, 5, (300, 3)) + [0, 0, 3]  # outside the box
    target = surface + [shift_m, 0, 0]
    cloud = np.concatenate([target, ground, clutter])
    search = cloud[rng.integers(0, len(cloud), 1024)]
    return {
        "template": template.astype(np.float32),
        "search": search.astype(np.float32),
        "size": size,
        "motion": np.zeros(4, np.float32),
    }


def test_still_target_test_keeps_the_box_only_where_the_target_stayed():
    moving_tracker = tiny("p2b")
    hold = tiny("p2b")
    hold.load_state_dict(moving_tracker.state_dict())
    hold.inference = InferenceConfig(hold_chamfer_m=0.1)
    still, moved = _still_target_observation(0), _still_target_observation(0, shift_m=0.6)
    np.testing.assert_array_equal(hold.act(still), np.zeros(4, np.float32))
    np.testing.assert_array_equal(hold.act(moved), moving_tracker.act(moved))
    batch = {k: np.stack([still[k], moved[k]]) for k in still}
    np.testing.assert_array_equal(
        hold.act(batch), np.stack([np.zeros(4), moving_tracker.act(moved)])
    )
    assert keeps_box(hold, prepare_observation(batch)[0], hold.inference).tolist() == [True, False]
    # the box lost to static background: the previous crop matches, the first crop does not
    other = _still_target_observation(1)["template"][:256]  # another object's first crop
    lost = dict(still, template=np.concatenate([other, still["template"][256:]]))
    assert not keeps_box(hold, prepare_observation(lost)[0], hold.inference).item()
    # too few points to decide
    sparse = dict(still, template=np.zeros_like(still["template"]))
    sparse["template"][:, :] = still["template"][0]
    sparse["template"][:4] = still["template"][1:5]
    assert keeps_box(hold, prepare_observation(sparse)[0], hold.inference).item() is False


def _reranked_by_hand(obs, candidates, margin_m):
    """The re-ranking's choice computed independently (float64 numpy, brute-force Chamfer):
    the index of the candidate ``(K, 4)`` whose crop lies nearest to the first crop."""
    size = obs["size"].astype(np.float64)
    floor = -size[2] / 2 + 0.2

    def above(points):
        return points[(points != 0).any(1) & (points[:, 2] > floor)]

    first = above(obs["template"][:256].astype(np.float64))
    search = obs["search"].astype(np.float64)
    search = search[(search != 0).any(1)]  # padding rows, wherever a box moves them
    distances = []
    for j, (dx, dy, dz, dyaw) in enumerate(candidates.astype(np.float64)):
        p = search - [dx, dy, dz]
        c, s = np.cos(dyaw), np.sin(dyaw)
        p = np.c_[c * p[:, 0] + s * p[:, 1], -s * p[:, 0] + c * p[:, 1], p[:, 2]]
        crop = above(p[(np.abs(p) <= size * 0.625).all(1)])
        if len(crop) < 5:
            distances.append(np.inf)
            continue
        d = np.linalg.norm(crop[:, None] - first[None], axis=-1)
        distances.append(0.5 * (d.min(1).mean() + d.min(0).mean()) + (margin_m if j else 0.0))
    return int(np.argmin(distances))


def _choose(tracker, batch, outputs, k, margin=0.0):
    inference = InferenceConfig(rerank_top_k=k, rerank_margin_m=margin)
    return choose_action(tracker, batch, outputs, inference, tracker.max_action)


def test_re_ranking_executes_the_candidate_that_matches_the_first_crop():
    tracker = tiny("p2b")
    moved = _still_target_observation(0, shift_m=0.6)
    batch, _ = prepare_observation(moved)
    # the best-scored proposal goes the wrong way; the second one follows the target
    proposals = torch.tensor([[[-2.0, 0.0, 0.0, 0.0], [0.6, 0.0, 0.0, 0.0], [0.3, 0.2, 0.0, 0.1]]])
    outputs = {"proposals": proposals, "scores": torch.tensor([[0.9, 0.5, 0.1]])}
    for k, margin, expected in ((2, 0.0, [0.6, 0, 0, 0]), (1, 0.0, [0, 0, 0, 0])):
        chosen = _choose(tracker, batch, outputs, k, margin)[0].numpy()
        candidates = np.r_[np.zeros((1, 4)), proposals[0, :k].numpy()]
        hand = candidates[_reranked_by_hand(moved, candidates, margin)]
        np.testing.assert_allclose(hand, expected, atol=1e-6)
        np.testing.assert_array_equal(chosen, np.asarray(expected, np.float32))
    assert not _choose(tracker, batch, outputs, 2, 10.0).any()  # moves never win
    # off, too few first-crop points, or a non-finite proposal: the best-scored proposal stands
    best = proposals[0, 0].numpy()
    np.testing.assert_array_equal(_choose(tracker, batch, outputs, 0)[0].numpy(), best)
    sparse = dict(moved, template=np.zeros_like(moved["template"]))
    sparse_batch, _ = prepare_observation(sparse)
    np.testing.assert_array_equal(_choose(tracker, sparse_batch, outputs, 2)[0].numpy(), best)
    broken = dict(outputs, proposals=proposals.clone())
    broken["proposals"][0, 1, 0] = float("nan")
    np.testing.assert_array_equal(_choose(tracker, batch, broken, 2)[0].numpy(), best)


def test_re_ranking_leaves_zero_padding_out_of_every_candidate_crop():
    """Zero rows pad the search; a moved candidate box moves them off the origin, where they
    must still not count as points. Here the target (a face 1.5 m ahead of the centre) moved
    0.6 m; in the true candidate's frame the padding would sit 2.1 m from the face and the
    reference box would win."""
    rng = np.random.default_rng(4)
    face = np.c_[np.full(256, 1.5), rng.uniform(-0.8, 0.8, 256), rng.uniform(-0.4, 0.6, 256)]
    search = np.zeros((1024, 3))
    search[:256] = face[rng.permutation(256)] + [0.6, 0, 0]  # 3/4 of the rows are padding
    padded = {
        "template": np.r_[face, face].astype(np.float32),
        "search": search.astype(np.float32),
        "size": np.float32([4.0, 1.8, 1.5]),
        "motion": np.zeros(4, np.float32),
    }
    tracker = tiny("p2b")
    proposals = torch.tensor([[[0.0, 0.5, 0.0, 0.0], [0.6, 0.0, 0.0, 0.0]]])
    outputs = {"proposals": proposals, "scores": torch.tensor([[0.9, 0.5]])}
    chosen = _choose(tracker, prepare_observation(padded)[0], outputs, 2)[0].numpy()
    candidates = np.r_[np.zeros((1, 4)), proposals[0].numpy()]
    np.testing.assert_array_equal(chosen, candidates[_reranked_by_hand(padded, candidates, 0.0)])
    np.testing.assert_array_equal(chosen, np.float32([0.6, 0, 0, 0]))


def test_re_ranking_agrees_with_an_independent_choice_on_network_outputs():
    tracker = trackers.load("bat-kitti1-u")  # trained: its proposals follow the moved target
    tracker.inference = InferenceConfig(rerank_top_k=4, rerank_margin_m=0.02)
    shifts = (0.0, 0.3, 0.8, 1.5)
    obs = [_still_target_observation(seed, shift_m) for seed in (0, 1) for shift_m in shifts]
    batch = {k: np.stack([o[k] for o in obs]) for k in obs[0]}
    with torch.no_grad():
        out = tracker.eval_forward(prepare_observation(batch)[0])
    top = out["scores"].topk(4, dim=1).indices
    a_max = np.asarray(tracker.max_action)
    actions, picks = tracker.act(batch), []
    for i, o in enumerate(obs):
        candidates = np.clip(
            np.r_[np.zeros((1, 4)), out["proposals"][i, top[i]].numpy()], -a_max, a_max
        )
        picks.append(_reranked_by_hand(o, candidates, 0.02))
        np.testing.assert_allclose(actions[i], candidates[picks[-1]], atol=1e-6)
    # the reference box on the still targets, and proposals other than the best-scored
    assert picks[0] == picks[4] == 0 and max(picks) >= 2
    tracker.inference = InferenceConfig()
    np.testing.assert_array_equal(
        tracker.act(batch), np.clip(tracker.best_action(out).numpy(), -a_max, a_max)
    )


def test_compiled_decision_step_equals_the_torch_ops(recorded, monkeypatch):
    """The decision step's compiled passes (``trackers.kernels.scene_kernel``,
    ``crop_distance_kernel``) against the torch ops they replace, on the recorded observations
    and 24 candidate boxes each (moved up to 1.5 m, turned up to 0.5 rad): the same point sets
    bit for bit, the same crops (which distances are finite) and the same still-target and
    re-ranking distances to float32 rounding (the kernel sums in float64, torch in float32 in
    its own order), so the same choice of candidate in every row."""
    if kernels.scene_kernel() is None:
        pytest.skip("numba is not installed (pip install 'pointtrack[fast]')")
    obs = {k: recorded[f"obs_{k}"] for k in KEYS}
    batch, _ = prepare_observation(obs)
    g = torch.Generator().manual_seed(0)
    candidates = (torch.rand(len(obs["search"]), 24, 4, generator=g) * 2 - 1) * torch.tensor(
        [1.5, 1.5, 0.3, 0.5]
    )
    candidates[:, 0] = 0  # the reference box among them
    tracker = trackers.load("p2b-kitti1-u")

    def run(compiled: bool):
        observed = scenes(tracker, batch)
        assert all((sc.arrays is not None) == compiled for sc in observed)
        sets = []
        for sc in observed:  # each set read back through its layout (its order is free)
            (points, layout), masks = sc.points, sc.crop_masks
            crops = [c[lay[m]] for (c, lay), m in zip((sc.first, sc.previous), masks, strict=True)]
            sets.append((sc.real, masks, points[layout[sc.real]], *crops))
        still = [decision.still_distances(sc) for sc in observed]
        crop = [decision._crop_distances(sc, c) for sc, c in zip(observed, candidates, strict=True)]
        return sets, still, np.stack(crop)

    compiled_sets, compiled_still, compiled_crop = run(True)
    monkeypatch.setattr(kernels, "scene_kernel", lambda: None)
    sets, still, crop = run(False)
    np.testing.assert_array_equal(np.isfinite(compiled_crop), np.isfinite(crop))
    finite = np.isfinite(crop)
    np.testing.assert_allclose(compiled_crop[finite], crop[finite], rtol=2e-6)
    rows = finite.any(1)
    np.testing.assert_array_equal(compiled_crop[rows].argmin(1), crop[rows].argmin(1))
    assert finite.mean() > 0.3 and not finite.all()  # crops with points, and without
    assert sum(d is not None for d in still) > len(still) // 2  # the test decides on most
    for c, r in zip(compiled_still, still, strict=True):
        assert (c is None) == (r is None)
        assert r is None or torch.allclose(c, r, rtol=2e-6, atol=0)
    for c, r in zip(compiled_sets, sets, strict=True):
        assert all(torch.equal(x, y) for x, y in zip(c, r, strict=True))


def test_inference_config_checks_its_fields():
    for field, bad in (
        ("hold_chamfer_m", -0.1),
        ("hold_chamfer_m", float("nan")),
        ("hold_chamfer_m", float("inf")),
        ("hold_chamfer_m", "0.1"),
        ("hold_chamfer_m", True),
        ("rerank_top_k", -1),
        ("rerank_top_k", 1.5),
        ("rerank_top_k", True),
        ("rerank_top_k", "8"),
        ("rerank_margin_m", -0.1),
        ("rerank_margin_m", float("nan")),
        ("rerank_margin_m", None),
        ("min_motion_m", -0.5),
        ("min_motion_m", float("inf")),
    ):
        with pytest.raises(ValueError, match=f"InferenceConfig.{field} = {re.escape(repr(bad))}"):
            InferenceConfig(**{field: bad})
    assert InferenceConfig(hold_chamfer_m=1, rerank_top_k=np.int64(8)).to_dict() == {
        "hold_chamfer_m": 1.0,
        "rerank_top_k": 8,
        "rerank_margin_m": 0.0,
        "min_motion_m": 0.0,
    }
    with pytest.raises(ValueError, match=r"here: unknown field\(s\) \['hold'\]"):
        InferenceConfig.from_dict({"hold": 0.1}, where="here")
    with pytest.raises(ValueError, match="here: InferenceConfig.rerank_top_k = -2"):
        InferenceConfig.from_dict({"rerank_top_k": -2}, where="here")
    with pytest.raises(ValueError, match="inference settings, not part of the architecture"):
        tiny("p2b", hold_chamfer_m=0.1)
    with pytest.raises(TypeError, match="must be a trackers.decision.InferenceConfig"):
        tiny("p2b").inference = {"hold_chamfer_m": 0.1}
    with pytest.raises(ValueError, match=r"m2track: InferenceConfig field\(s\) \['rerank_top_k'\]"):
        trackers.make("m2track").inference = InferenceConfig(rerank_top_k=2)
    with pytest.raises(ValueError, match=r"\['min_motion_m'\] do not fit.*set only \[\]"):
        trackers.make("m2track").inference = InferenceConfig(min_motion_m=1.0)
    with pytest.raises(ValueError, match=r"mbptrack: .*\['rerank_top_k'\] do not fit"):
        trackers.make("mbptrack").inference = InferenceConfig(hold_chamfer_m=0.1, rerank_top_k=2)
    tracker = tiny("bat")
    tracker.inference = InferenceConfig(hold_chamfer_m=0.1)
    tracker.env_options = {"template_mode": "first_and_previous_merged"}
    with pytest.raises(ValueError, match="template_mode 'first_and_previous_merged'"):
        tracker.act(_still_target_observation(1))


def test_distinct_points_and_chamfer_distance_on_resampled_clouds():
    """Clouds the env resampled repeat points: the distinct points read back through the
    layout give the cloud, and the Chamfer distance equals a brute force over every copy."""
    g = torch.Generator().manual_seed(2)
    base = torch.randn(2, 40, 3, generator=g)
    a = base[:, torch.randint(0, 40, (300,), generator=g)]
    b = base[:, torch.randint(0, 20, (120,), generator=g)] + 0.1
    a_mask = torch.rand(2, 300, generator=g) < 0.7
    b_mask = torch.rand(2, 120, generator=g) < 0.5
    b_mask[1] = False  # an empty set: inf
    points, layout = ops.distinct_points(a[0], a_mask[0])
    assert len(points) == len(torch.unique(a[0][a_mask[0]], dim=0))
    assert torch.equal(points[layout[a_mask[0]]], a[0][a_mask[0]])
    assert (layout[~a_mask[0]] == len(points)).all()
    got = ops.chamfer_distance(a, a_mask, b, b_mask)
    pa, pb = a[0][a_mask[0]].double(), b[0][b_mask[0]].double()
    d = torch.cdist(pa, pb)
    want = 0.5 * (d.min(1).values.mean() + d.min(0).values.mean())
    assert got[0].item() == pytest.approx(want.item(), rel=1e-5) and torch.isinf(got[1])
    assert torch.equal(ops.chamfer_distance(b, b_mask, a, a_mask), got)
