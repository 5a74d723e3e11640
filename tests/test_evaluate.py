"""training.evaluate: OPE reports from the env, vector batching, outputs, CLI; baselines."""

from __future__ import annotations

import functools
import json

import gymnasium as gym
import numpy as np
import pytest

from envs.geometry import center_distance, iou_3d
from envs.tracking_env import TrackingEnv, make_toy_dataset
from trackers.baselines import ConstantVelocity, PreviousBox
from training.evaluate import evaluate, format_table, plot_curves, save_report, split_tracklets


@pytest.fixture(scope="module")
def toy():
    return make_toy_dataset(num_frames=[6, 9, 5, 7], seed=4, num_clutter=1500)


def _hand_auc(values, thresholds, above):
    curve = np.array([np.mean(values >= t) if above else np.mean(values <= t) for t in thresholds])
    width = thresholds[1] - thresholds[0]
    return float(np.sum((curve[1:] + curve[:-1]) * 0.5 * width) * 100 / thresholds[-1])


def test_report_equals_hand_computed(toy):
    env = TrackingEnv(toy, setting="kitti-1")
    report = evaluate(PreviousBox(), env)
    # previous box: every prediction is frame 0's box
    per_cat: dict[str, tuple[list, list]] = {}
    for tr in toy.tracklets:
        ious = [1.0] + [float(iou_3d(tr.boxes[0], b)) for b in tr.boxes[1:]]
        errs = [0.0] + [float(center_distance(tr.boxes[0], b)) for b in tr.boxes[1:]]
        per_cat.setdefault(tr.category, ([], []))
        per_cat[tr.category][0].extend(ious)
        per_cat[tr.category][1].extend(errs)
    thr_iou, thr_m = np.linspace(0, 1, 21), np.linspace(0, 2, 21)
    for cat, (ious, errs) in per_cat.items():
        entry = report["categories"][cat]
        assert entry["frames"] == len(ious) and entry["tracklets"] == 1
        assert entry["observed"] == (cat != "Car")
        assert entry["success"] == pytest.approx(_hand_auc(np.array(ious), thr_iou, True))
        assert entry["precision"] == pytest.approx(_hand_auc(np.array(errs), thr_m, False))
    all_ious = np.concatenate([np.array(v[0]) for v in per_cat.values()])
    assert report["mean"]["success"] == pytest.approx(_hand_auc(all_ious, thr_iou, True))
    assert report["mean"]["frames"] == sum(len(t) for t in toy.tracklets) == report["frames"]
    unseen = np.array(per_cat["Car"][0])
    assert report["unseen"]["success"] == pytest.approx(_hand_auc(unseen, thr_iou, True))
    assert report["tracklets"] == 4 and report["tracker_fps"] > 0
    assert report["env"]["setting"] == "kitti-1"


def test_vector_env_matches_single(toy):
    # a policy that ignores the points, so the sub-envs' own seeds do not matter
    single = evaluate(ConstantVelocity(init="zero"), TrackingEnv(toy))
    for n in (2, 3, 6):
        vec = gym.vector.SyncVectorEnv([functools.partial(TrackingEnv, toy)] * n)
        rep = evaluate(ConstantVelocity(init="zero"), vec)
        assert rep["categories"] == single["categories"]
        assert rep["mean"] == single["mean"]
    rep = evaluate(ConstantVelocity(init="zero"), TrackingEnv(toy), num_envs=3)
    assert rep["categories"] == single["categories"] and rep["env"]["num_envs"] == 3
    sub = evaluate(PreviousBox(), TrackingEnv(toy), tracklets=[1, 3])
    assert sub["tracklets"] == 2


class _CentroidTracker:
    """Moves the box to the centroid of the search points: its result depends on the resampling."""

    name = "centroid"

    def act(self, obs):
        search = np.asarray(obs["search"], dtype=np.float64)
        rows = search.reshape(-1, *search.shape[-2:])
        actions = np.zeros((len(rows), 4))
        for i, pts in enumerate(rows):  # row by row: no batch-size-dependent summation order
            actions[i, :3] = 0.5 * pts.mean(axis=0)
        return actions[0] if search.ndim == 2 else actions


def _by_tracklet(report):
    return {r["tracklet"]: (r["success"], r["precision"]) for r in report["per_tracklet"]}


def test_results_per_tracklet_do_not_depend_on_layout(toy):
    """Each episode's resampling is seeded by (seed, tracklet id): the same tracklet scores the
    same alone, in another order, in a category subset or on any number of sub-envs."""
    env = TrackingEnv(toy, setting="kitti-1")
    full = _by_tracklet(evaluate(_CentroidTracker(), env, seed=5))
    assert len(full) == 4 and env.episode_seed is None  # evaluate restores the env's value
    for n in (2, 3, 4):
        assert _by_tracklet(evaluate(_CentroidTracker(), env, seed=5, num_envs=n)) == full
    vec = gym.vector.SyncVectorEnv([functools.partial(TrackingEnv, toy, setting="kitti-1")] * 2)
    vec.set_attr("episode_seed", 11)
    assert _by_tracklet(evaluate(_CentroidTracker(), vec, seed=5)) == full
    assert vec.get_attr("episode_seed") == (11, 11)
    backwards = _by_tracklet(evaluate(_CentroidTracker(), env, seed=5, tracklets=[3, 1]))
    assert backwards == {k: full[k] for k in backwards} and len(backwards) == 2
    cars = TrackingEnv(toy, setting="kitti-1", categories=["Car"])
    only = _by_tracklet(evaluate(_CentroidTracker(), cars, seed=5))
    assert only == {k: full[k] for k in only} and len(only) == 1
    other = _by_tracklet(evaluate(_CentroidTracker(), env, seed=6))
    assert other != full  # the seed does reach the resampling


def test_split_tracklets_balanced():
    orders = split_tracklets([10, 2, 8, 3, 7], 2)
    assert sorted(i for o in orders for i in o) == [0, 1, 2, 3, 4]
    loads = [sum([10, 2, 8, 3, 7][i] - 1 for i in o) for o in orders]
    assert abs(loads[0] - loads[1]) <= 3
    assert split_tracklets([4], 3)[1:] == [[], []]


def test_outputs(toy, tmp_path):
    reports = {
        "previous_box": evaluate(PreviousBox(), TrackingEnv(toy, setting="kitti-1")),
        "constant_velocity": evaluate(ConstantVelocity(), TrackingEnv(toy, setting="kitti-1")),
    }
    table = format_table(reports)
    assert "previous_box" in table and "Car*" in table and "unseen" in table
    path = save_report(reports, tmp_path / "r.json")
    loaded = json.loads(path.read_text())
    assert loaded["previous_box"]["categories"]["Car"]["observed"] is False
    no_unseen = evaluate(PreviousBox(), TrackingEnv(toy))
    assert (
        json.loads(save_report(no_unseen, tmp_path / "n.json").read_text())["unseen"]["success"]
        is None
    )
    paths = plot_curves(reports, tmp_path)
    assert [p.name for p in paths] == ["success.png", "precision.png"]
    assert all(p.stat().st_size > 1000 for p in paths)
    # drawn in two forked processes: the same files
    forked = plot_curves(reports, tmp_path / "forked", workers=2)
    assert [p.read_bytes() for p in forked] == [p.read_bytes() for p in paths]


def test_baselines_single_and_batch():
    import torch

    obs = {
        "template": np.zeros((512, 3), np.float32),
        "search": np.zeros((1024, 3), np.float32),
        "size": np.ones(3, np.float32),
        "motion": np.array([1, 2, 3, 0.1], np.float32),
    }
    assert PreviousBox().act(obs).shape == (4,)
    np.testing.assert_array_equal(ConstantVelocity().act(obs), obs["motion"])
    batch = {k: np.stack([v, v, v]) for k, v in obs.items()}
    assert PreviousBox().act(batch).shape == (3, 4)
    out = ConstantVelocity().act({k: torch.as_tensor(v) for k, v in batch.items()})
    assert isinstance(out, np.ndarray) and out.shape == (3, 4)
    with pytest.raises(KeyError, match="motion"):
        PreviousBox().act({"search": obs["search"]})
    with pytest.raises(ValueError, match="init"):
        ConstantVelocity(init="bogus")


def test_constant_velocity_init_modes():
    """Zero motion: ``init="zero"`` keeps the box, ``init="points"`` estimates a shift from the
    points (here a flat target moving along x); non-zero motion is repeated either way."""
    search = np.zeros((1024, 3), np.float32)
    template = np.zeros((512, 3), np.float32)
    rng = np.random.default_rng(0)
    surface = np.column_stack(
        [rng.uniform(-2, 2, 600), rng.uniform(-0.9, 0.9, 600), rng.uniform(-0.4, 0.7, 600)]
    ).astype(np.float32)
    template[:256] = surface[:256]
    search[:600] = surface + np.array([0.6, 0.0, 0.0], np.float32)  # moved 0.6 m forward
    obs = {
        "template": template,
        "search": search,
        "size": np.array([4, 1.8, 1.5], np.float32),
        "motion": np.zeros(4, np.float32),
    }
    np.testing.assert_array_equal(ConstantVelocity().act(obs), 0)
    est = ConstantVelocity(init="points").act(obs)
    assert 0.3 < est[0] < 0.8 and abs(est[1]) < 0.1 and est[2] == 0 and est[3] == 0
    batch = ConstantVelocity(init="points").act({k: np.stack([v, v]) for k, v in obs.items()})
    np.testing.assert_allclose(batch[0], est)
    obs["motion"][:] = [0.5, 0.1, 0.0, 0.02]
    np.testing.assert_array_equal(ConstantVelocity(init="points").act(obs), obs["motion"])


def test_demo_balanced_subset():
    from training.commands.demo import balanced_subset

    cats = ["Car", "Car", "Car", "Van", "Pedestrian", "Pedestrian"]
    lengths = [10, 10, 10, 5, 4, 4]
    assert balanced_subset(cats, lengths, 19) == [0, 3, 4]
    assert balanced_subset(cats, lengths, 20) == [0, 1, 3, 4]
    assert balanced_subset(cats, lengths, 1000) == list(range(6))


def test_cli_demo_tiny(tmp_path, capsys):
    from training.cli import main

    rc = main(
        [
            "demo",
            "--preset",
            "tiny",
            "--out",
            str(tmp_path),
            "--no-progress",
            "--tracker",
            "previous_box",
            "constant_velocity:points",
            "no-such-tracker",
        ]
    )
    assert rc == 0
    text = capsys.readouterr().out
    assert "skipping no-such-tracker" in text and "constant_velocity:points" in text
    report = json.loads((tmp_path / "report.json").read_text())
    assert set(report) == {"previous_box", "constant_velocity:points"}
    assert report["previous_box"]["unseen"]["frames"] > 0  # Car is unseen in kitti-1
