"""Supervised training samples (training.samples)."""

from __future__ import annotations

import numpy as np
import pytest
import torch
from test_pretrain_support import fake_tracklets
from torch.utils.data import DataLoader, Subset

from envs.geometry import box_to_world, points_in_box, rotation_z, world_to_box, wrap_yaw
from envs.observation import crop_box_frame
from training.samples import TrackingSamples, crop_near


@pytest.fixture(scope="module")
def data():
    return TrackingSamples(fake_tracklets(n=3, frames=6), candidates_per_frame=3, seed=5)


def _reference_box(gt: np.ndarray, search_box: np.ndarray) -> np.ndarray:
    """Recover the (perturbed) reference box from the GT and the GT expressed in it."""
    yaw = wrap_yaw(gt[6] - search_box[6])
    centre = gt[:3] - rotation_z(yaw) @ search_box[:3]
    return np.array([*centre, *gt[3:6], yaw])


def test_shapes_and_keys(data):
    s = data[0]
    assert len(data) == 3 * 5 * 3
    shapes = {
        "template": (512, 3),
        "search": (1024, 3),
        "size": (3,),
        "motion": (4,),
        "search_box": (7,),
        "search_labels": (1024,),
        "template_centers": (512, 3),
        "template_labels": (512,),
    }
    for k, shape in shapes.items():
        assert tuple(s[k].shape) == shape, k
        assert s[k].dtype == torch.float32
        assert torch.isfinite(s[k]).all()


def test_labels_consistent_with_geometry(data):
    errs = []
    for index in range(0, len(data), 4):
        s = {k: v.numpy() for k, v in data[index].items()}
        k, t, cand = data.locate(index)
        tr = data.tracklets[k]
        gt = tr.boxes[t]
        ref = _reference_box(gt, s["search_box"])
        errs.append(ref[:2] - gt[:2])
        world = box_to_world(s["search"].astype(np.float64), ref)
        lab = s["search_labels"] > 0.5
        assert lab.any()
        # labelled points lie in the exact GT box, the others outside it
        assert points_in_box(world[lab], gt).all()
        assert not points_in_box(world[~lab], gt).any()
        # vote targets (centre - point) lead every target point to the GT centre
        votes = s["search"][lab] + (s["search_box"][:3] - s["search"][lab])
        assert np.allclose(box_to_world(votes.astype(np.float64), ref), gt[:3], atol=1e-4)
        # target points fill the box, so their mean is near its centre
        assert np.linalg.norm(world[lab].mean(0) - gt[:3]) < 0.35 * gt[3:6].max()
        # template: first half around the origin, second half around the recorded centre
        tl = s["template_labels"] > 0.5
        half = 256
        assert np.allclose(s["template_centers"][:half], 0)
        first = s["template"][:half][tl[:half]]
        assert (np.abs(first) <= gt[3:6] / 2 + 1e-4).all()
        second = s["template"][half:][tl[half:]]
        c2 = s["template_centers"][half]
        assert np.linalg.norm(second.mean(0) - c2) < 0.35 * gt[3:6].max()
        if cand == 0:  # unjittered previous box: the target centre is the origin
            assert np.allclose(c2, 0, atol=1e-5)
        else:
            assert np.abs(c2[:2]).max() <= 0.3 * np.sqrt(2) + 1e-5
        assert np.allclose(s["size"], tr.boxes[0][3:6])
        if t == 1:
            assert np.allclose(s["motion"], 0)
    errs = np.array(errs)
    assert errs.std() > 0.3  # the search region is perturbed (sigma 1 m)


def test_crop_near_equals_whole_scan_crop():
    tr = fake_tracklets(n=1)[0]
    pts = tr.points(2)
    for scale, off in ((1.25, 0.0), (1.25, 2.0)):
        box = tr.boxes[2] + np.array([0.3, -0.2, 0, 0, 0, 0, 0.1])
        assert np.array_equal(crop_near(pts, box, scale, off), crop_box_frame(pts, box, scale, off))


def test_deterministic_across_worker_counts_and_epochs(data):
    idx = list(range(0, len(data), 5))

    def collect(workers):
        loader = DataLoader(Subset(data, idx), batch_size=3, num_workers=workers)
        return [b for b in loader]

    a, b = collect(0), collect(2)
    for x, y in zip(a, b, strict=True):
        for k in x:
            assert torch.equal(x[k], y[k]), k
    again = data[idx[1]]
    data.set_epoch(1)
    try:
        other = data[idx[1]]
    finally:
        data.set_epoch(0)
    assert torch.equal(again["search"], data[idx[1]]["search"])
    assert not torch.equal(again["search"], other["search"])


def test_no_tracklets_is_an_error():
    with pytest.raises(ValueError, match="no tracklets"):
        TrackingSamples([])


def test_size_jitter_is_an_exact_stretch_of_the_scene():
    base = fake_tracklets(n=3, frames=6)
    data = TrackingSamples(base, candidates_per_frame=2, seed=3, size_jitter=0.3)
    stretches = []
    for index in range(0, len(data), 3):
        s = {k: v.numpy().astype(np.float64) for k, v in data[index].items()}
        k, t, _ = data.locate(index)
        tr = data.tracklets[k]
        gt = tr.boxes[t]
        stretch = s["search_box"][3:6] / gt[3:6]
        stretches.append(stretch)
        assert ((stretch >= 0.7 - 1e-6) & (stretch <= 1.3 + 1e-6)).all()
        # one stretch per sample: the template's size input and the search box agree
        assert np.allclose(s["size"], tr.boxes[0][3:6] * stretch, rtol=1e-5)
        ref = _reference_box(np.array([*gt[:3], *s["search_box"][3:6], gt[6]]), s["search_box"])
        world = box_to_world(s["search"], ref)
        real = s["search_labels"] > 0.5
        # undo the stretch in the GT box frame: every point is a point of the real scan ...
        undone = box_to_world((world_to_box(world[real], gt) / stretch).astype(np.float64), gt)
        scan = tr.points(t).astype(np.float64)
        nearest = np.abs(undone[:, None, :] - scan[None]).max(-1).min(1)
        assert nearest.max() < 1e-4
        # ... and the labelled ones are exactly the real target's points
        assert points_in_box(undone, gt).all()
    stretches = np.array(stretches)
    assert stretches.std(0).min() > 0.1  # independent per sample and per axis


def test_size_jitter_is_deterministic_and_off_by_default():
    tracklets = fake_tracklets(n=2, frames=5)
    a = TrackingSamples(tracklets, seed=1, size_jitter=0.3)
    b = TrackingSamples(tracklets, seed=1, size_jitter=0.3)
    off = TrackingSamples(tracklets, seed=1)
    plain = TrackingSamples(tracklets, seed=1, size_jitter=0.0)
    for index in (0, 7, 13):
        for k, v in a[index].items():
            assert torch.equal(v, b[index][k]), k
            assert torch.equal(off[index][k], plain[index][k]), k
        assert not torch.equal(a[index]["search_box"], off[index]["search_box"])


@pytest.mark.parametrize("bad", [-0.1, 1.0, 1.5])
def test_size_jitter_out_of_range_is_an_error(bad):
    with pytest.raises(ValueError, match="size_jitter"):
        TrackingSamples(fake_tracklets(n=1), size_jitter=bad)


def test_load_tracklets_refuses_a_world_lacking_an_observed_category():
    from envs.data import Setting
    from training.samples import load_tracklets

    # the tiny world has Pedestrians but no Tram: training would silently be another setting
    setting = Setting("cell", ("Pedestrian", "Tram"), ("Car",))
    with pytest.raises(ValueError, match=r"no tracklets of observed Tram \(of Pedestrian, Tram\)"):
        load_tracklets("synthetic", "train", setting=setting, preset="tiny")
    tracklets, _, _ = load_tracklets("synthetic", "train", setting="kitti-1", preset="tiny")
    assert {tr.category for tr in tracklets} == {"Pedestrian", "Van", "Cyclist"}


@pytest.mark.parametrize(
    ("dataset", "setting", "supported"),
    [
        ("synthetic", "nuscenes-1", "kitti-1, kitti-2"),
        ("nuscenes", "kitti-2", "nuscenes-1, nuscenes-2"),
    ],
)
def test_a_setting_of_the_other_layout_is_refused_before_any_data(
    dataset, setting, supported, tmp_path, capsys
):
    from envs.tracking_env import make_tracking_env
    from training.cli import main
    from training.config import ConfigError, TrainConfig
    from training.samples import load_tracklets

    message = f"{setting!r} is not one of a .*; it supports {supported}"
    with pytest.raises(ValueError, match=message):
        load_tracklets(dataset, "train", setting=setting, preset="does-not-exist")
    with pytest.raises(ConfigError, match=f"setting='{setting}'.*supports {supported}"):
        TrainConfig(dataset=dataset, setting=setting).validate()
    with pytest.raises(ValueError, match=message):  # the env factory: eval, select, render, RL
        make_tracking_env(dataset, setting=setting, preset="does-not-exist")
    world = ["--dataset", dataset, "--preset", "does-not-exist", "--setting", setting]
    out = tmp_path / "out"
    for command in (["eval", "--tracker"], ["select"]):
        assert main([*command, "previous_box", *world, "--no-progress", "--out", str(out)]) == 2
        err = capsys.readouterr().err
        assert err.count("\n") == 1 and f"it supports {supported}" in err, err
    assert not out.exists()
