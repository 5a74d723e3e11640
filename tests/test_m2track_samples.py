"""M2-Track's training samples (training.motion_samples), the previous-frame observation bridge
and one trainer epoch on the tiny synthetic world."""

from __future__ import annotations

import numpy as np
import pytest
import torch
from test_pretrain_support import fake_tracklets, tiny_config

from envs.geometry import (
    apply_offset,
    box_to_world,
    offset_between,
    points_in_box,
    rotation_z,
    world_to_box,
    wrap_yaw,
)
from envs.observation import crop_box_frame
from training.motion_samples import (
    BATCH_KEYS,
    TARGET_KEYS,
    MotionSamples,
    augment_frame,
)

pytestmark = pytest.mark.usefixtures("one_torch_thread")


def _reference(gt4: np.ndarray, label: np.ndarray, size: np.ndarray) -> np.ndarray:
    """The reference box from a box ``(x, y, z, yaw)`` in the world and the same box in it."""
    yaw = wrap_yaw(gt4[3] - label[3])
    centre = gt4[:3] - rotation_z(yaw) @ label[:3]
    return np.array([*centre, *size, yaw])


def test_samples_shapes_determinism_and_epochs():
    data = MotionSamples(fake_tracklets(n=2, frames=5), candidates_per_frame=2, seed=3)
    assert len(data) == 2 * 4 * 2
    s = data[5]
    shapes = {
        "search": (1024, 3),
        "previous_search": (1024, 3),
        "size": (3,),
        "prior_is_gt": (),
        "seg_labels": (2048,),
        "box": (4,),
        "prev_box": (4,),
        "motion_box": (4,),
        "moving": (),
        "box_cloud": (2048, 9),
    }
    assert set(shapes) == set(BATCH_KEYS) | set(TARGET_KEYS)
    for key, shape in shapes.items():
        assert tuple(s[key].shape) == shape and torch.isfinite(s[key]).all(), key
    again = data[5]
    assert all(torch.equal(s[k], again[k]) for k in shapes)
    data.set_epoch(1)
    assert not torch.equal(data[5]["search"], s["search"])
    assert data[0]["prior_is_gt"] == 1 and data[1]["prior_is_gt"] == 0


def test_unaugmented_samples_are_crops_of_the_scans_with_consistent_labels():
    data = MotionSamples(
        fake_tracklets(n=2, frames=5), candidates_per_frame=3, seed=1, augment=False
    )
    shifts = []
    for index in range(len(data)):
        s = {k: v.numpy() for k, v in data[index].items()}
        k, t, cand = data.locate(index)
        tr = data.tracklets[k]
        prev_gt, gt, size0 = tr.boxes[t - 1], tr.boxes[t], tr.boxes[0][3:6]
        ref = _reference(gt[[0, 1, 2, 6]], s["box"].astype(np.float64), size0)
        # the previous box, seen from the same reference box
        ref_from_prev = _reference(prev_gt[[0, 1, 2, 6]], s["prev_box"].astype(np.float64), size0)
        np.testing.assert_allclose(ref, ref_from_prev, atol=1e-4)
        shift = world_to_box(ref[None, :3], np.r_[prev_gt[:3], size0, prev_gt[6]])[0]
        shifts.append(np.abs(shift[:2]).max())
        assert (cand == 0) == (shifts[-1] < 1e-4)
        assert abs(wrap_yaw(ref[6] - prev_gt[6])) <= np.radians(5) + 1e-6
        # both frames: the env's crop of the scan around the reference box (a subset of rows)
        for key, frame in (("previous_search", t - 1), ("search", t)):
            crop = crop_box_frame(tr.points(frame), ref, 1.25, 2.0)
            rows = {tuple(np.round(p, 3)) for p in crop}
            assert all(tuple(np.round(p, 3)) in rows for p in s[key]), key
        # labels: inside the ground truth scaled 1.25, in each frame
        prev_box = np.r_[s["prev_box"][:3], prev_gt[3:6], s["prev_box"][3]]
        box = np.r_[s["box"][:3], gt[3:6], s["box"][3]]
        np.testing.assert_array_equal(
            s["seg_labels"][:1024] > 0, points_in_box(s["previous_search"], prev_box, 1.25)
        )
        np.testing.assert_array_equal(
            s["seg_labels"][1024:] > 0, points_in_box(s["search"], box, 1.25)
        )
        # the motion moves the previous box onto the current one
        np.testing.assert_allclose(s["motion_box"], offset_between(prev_gt, gt), atol=1e-5)
        moved = apply_offset(prev_box, s["motion_box"].astype(np.float64))
        np.testing.assert_allclose(moved[:3], box[:3], atol=1e-4)
        assert s["moving"] == float(np.linalg.norm(gt[:3] - prev_gt[:3]) > 0.15)
        # BoxCloud targets: column 0 is the distance to the frame's box centre, the largest
        # corner distance is at least half the box diagonal
        centres = np.r_[np.repeat(prev_box[None, :3], 1024, 0), np.repeat(box[None, :3], 1024, 0)]
        points = np.r_[s["previous_search"], s["search"]]
        np.testing.assert_allclose(
            s["box_cloud"][:, 0], np.linalg.norm(points - centres, axis=1), atol=1e-4
        )
        assert (s["box_cloud"][1024:, 1:].max(1) >= 0.5 * np.linalg.norm(gt[3:6]) - 1e-4).all()
    assert max(shifts) > 0.05


def test_augmentation_moves_the_box_points_rigidly_and_keeps_the_rest():
    rng = np.random.default_rng(0)
    box = np.array([3.0, -2.0, -0.5, 4.0, 1.8, 1.5, 0.7])
    local = (rng.random((300, 3)) - 0.5) * np.array([8.0, 5.0, 2.0])
    points = box_to_world(local, box).astype(np.float32)
    flips = set()
    for seed in range(12):
        new_points, new_box = augment_frame(points, box, np.random.default_rng(seed))
        inside = points_in_box(points, box, 1.25)
        np.testing.assert_array_equal(new_points[~inside], points[~inside])
        np.testing.assert_allclose(new_box[3:6], box[3:6])
        assert np.linalg.norm(world_to_box(new_box[None, :3], box)[0]) <= 0.3 * np.sqrt(3) + 1e-9
        # the points keep their place in the box up to the flips: |local coordinates| agree
        before = world_to_box(points[inside].astype(np.float64), box)
        after = world_to_box(new_points[inside].astype(np.float64), new_box)
        np.testing.assert_allclose(np.abs(after), np.abs(before), atol=1e-4)
        # a flip of x turns the box by pi, so in its new frame only y's sign can differ
        signs = np.sign(after[:, :2] * before[:, :2])
        assert (signs[:, 0] == 1).all() and len(set(signs[:, 1])) == 1
        turned = abs(wrap_yaw(new_box[6] - box[6])) > np.pi / 2
        flips.add((bool(turned), int(signs[0, 1])))
    assert len(flips) == 4  # flips of x and of y, each with and without the other


@pytest.fixture(scope="module")
def tiny_world():
    from envs.synthetic import ensure_world

    return ensure_world("tiny", "hdl64", 0)


def test_m2track_acts_on_the_env_previous_search_key(tiny_world):
    """The env's opt-in key is what ``evaluate`` asks for on M2-Track's behalf, and M2-Track
    acts on it (the key's own crop is tested against the previous scan in the env tests)."""
    import trackers
    from envs.tracking_env import make_synthetic_env
    from training.evaluate import observation_keys_for

    model = trackers.make("m2track", **trackers.size_config("m2track", "slim")).eval()
    keys = observation_keys_for([model, trackers.make("previous_box")])
    assert keys[-1] == "previous_search"
    env = make_synthetic_env(preset="tiny", seed=0, split="test", observation_keys=keys)
    obs, _ = env.reset(seed=0)
    for _ in range(3):
        action = model.act(obs)
        assert env.action_space.contains(action)
        obs, _, terminated, _, _ = env.step(action)
        if terminated:
            break


def test_trainer_runs_a_tiny_m2track_epoch_on_the_tiny_world(tmp_path, tiny_world):
    from training.pretrain import train

    cfg = tiny_config(
        tmp_path / "run",
        tracker="m2track",
        model_size="slim",
        preset="tiny",
        epochs=1,
        batch_size=2,
        iters_per_epoch=2,
        candidates_per_frame=2,
        val_max_tracklets=1,
        val_max_frames=3,
        weighting="decorrelation",
        lr=1e-3,
    )
    result = train(cfg)
    assert result.epochs_done == 1 and result.steps == 2
    record = result.history[-1]
    assert np.isfinite(record["total"]) and 0 <= record["val_success"] <= 100
    assert "ess" in record
