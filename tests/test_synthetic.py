"""The synthetic LiDAR world: ray caster, shapes, scenes, writer, cache and CLI."""

from __future__ import annotations

import dataclasses
import multiprocessing as mp
from collections import defaultdict
from pathlib import Path

import numpy as np
import pytest

from envs.data import KittiTracking
from envs.data.kitti import read_labels
from envs.geometry import points_in_box, world_to_box
from envs.synthetic import CATEGORIES, PRESETS, ensure_world, generate_world, get_sensor
from envs.synthetic.objects import make_object, sample_size
from envs.synthetic.raycast import CYLINDER, ELLIPSOID, Parts, box_parts, cast
from envs.synthetic.scene import SceneConfig, build_scene, render_frame
from envs.synthetic.world import KITTI_LIKE_CALIBRATION, _write_scene

SPLIT_TARGETS = ("Car", "Van", "Pedestrian", "Cyclist")


def _clean(name: str = "hdl64"):
    """A sensor without noise or dropout (exact geometry)."""
    return dataclasses.replace(get_sensor(name), range_noise=0.0, dropout=0.0, _dirs=None)


def _cast(sensor, parts: Parts, seed: int = 0):
    n = sensor.n_rays
    return cast(
        sensor,
        parts,
        np.full(n, np.inf, np.float32),
        np.zeros(n, np.float32),
        np.random.default_rng(seed),
    )


def _model_parts(category: str, box: np.ndarray, seed: int = 0, owner: int = 0) -> Parts:
    """A category's part model placed on ``box`` (sensor frame)."""
    rng = np.random.default_rng(seed)
    model = make_object(category, box[3:6], rng)
    p = model.parts_at(0.7, 1.0)
    c, s = np.cos(box[6]), np.sin(box[6])
    rot = np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])
    placed = p.transformed(rot, box[:3])
    placed.owner = np.full(len(p), owner, np.int64)
    return placed


@pytest.fixture(scope="session")
def tiny_world() -> Path:
    return ensure_world("tiny", "hdl64", 0)


# --------------------------------------------------------------------------- ray caster


def test_box_hits_lie_on_the_surface_at_the_right_range():
    sensor = _clean()
    box = np.array([10.0, 0.0, 0.0, 4.0, 2.0, 1.5, 0.0])
    res = _cast(sensor, box_parts(box[None], np.array([0.5]), np.array([0])))
    assert len(res.points) > 500
    local = world_to_box(res.points[None, :, :3], box[None])[0]
    # Every hit lies on one face: the largest normalised coordinate is 1.
    norm = np.abs(local) / (box[3:6] / 2)
    assert np.allclose(norm.max(axis=1), 1.0, atol=2e-3)
    # Seen from the origin only the face at x = 8 m is visible; the range follows the ray.
    assert np.allclose(res.points[:, 0], 8.0, atol=2e-3)
    rng = np.linalg.norm(res.points[:, :3], axis=1)
    dirs = res.points[:, :3] / rng[:, None]
    assert np.allclose(rng, 8.0 / dirs[:, 0], rtol=1e-4)
    assert res.points.dtype == np.float32
    assert (res.points[:, 3] >= 0).all() and (res.points[:, 3] <= 1).all()


def test_sphere_and_cylinder_hits_satisfy_their_equations():
    sensor = _clean()
    parts = Parts(
        np.array([ELLIPSOID, CYLINDER], np.int8),
        np.array([[8.0, 2.0, -0.5], [8.0, -2.0, -0.5]]),
        np.stack([np.eye(3), np.eye(3)]),
        np.array([[0.6, 0.6, 0.6], [0.3, 0.3, 1.0]]),
        np.array([0.4, 0.4], np.float32),
        np.array([0, 1]),
    )
    res = _cast(sensor, parts)
    sph = res.points[res.owner == 0, :3]
    cyl = res.points[res.owner == 1, :3]
    assert len(sph) > 50 and len(cyl) > 50
    assert np.allclose(np.linalg.norm(sph - [8.0, 2.0, -0.5], axis=1), 0.6, atol=2e-3)
    r = np.hypot(cyl[:, 0] - 8.0, cyl[:, 1] + 2.0)
    on_side = np.abs(cyl[:, 2] + 0.5) < 0.999
    assert np.allclose(r[on_side], 0.3, atol=2e-3)
    assert (np.abs(cyl[:, 2] + 0.5) <= 1.0 + 2e-3).all()


def test_occluded_object_gets_fewer_points():
    sensor = _clean()
    far = np.array([20.0, 0.0, -0.9, 4.0, 1.8, 1.5, 0.0])
    near = np.array([10.0, 0.5, -0.9, 1.0, 1.0, 1.6, 0.0])
    alone = _cast(sensor, _model_parts("Car", far, owner=0))
    both_parts = Parts.concat(
        [_model_parts("Car", far, owner=0), box_parts(near[None], np.array([0.5]), np.array([1]))]
    )
    both = _cast(sensor, both_parts)
    n_alone = int((alone.owner == 0).sum())
    n_both = int((both.owner == 0).sum())
    assert n_alone > 100
    assert n_both < 0.8 * n_alone
    # Nothing of the far car is seen through the near box: ranges behind it belong to the box.
    assert (both.owner == 1).sum() > 50


def test_point_count_falls_with_distance():
    sensor = get_sensor("hdl64")
    counts = []
    for dist in (8.0, 15.0, 25.0, 40.0, 60.0):
        box = np.array([dist, 0.0, -0.96, 3.9, 1.6, 1.54, 0.4])
        res = _cast(sensor, _model_parts("Car", box))
        counts.append(int(points_in_box(res.points[:, :3], box).sum()))
    assert all(a > b for a, b in zip(counts, counts[1:], strict=False)), counts
    assert counts[-1] > 0


def test_categories_have_distinct_shapes():
    """Height-to-length ratio and vertical profile of in-box points differ per category."""
    sensor = _clean()
    stats = {}
    for cat in CATEGORIES:
        ratios, profiles = [], []
        for seed in range(3):
            size = sample_size(cat, np.random.default_rng(seed))
            box = np.array([12.0, 0.0, -1.73 + size[2] / 2, *size, 0.5 * np.pi + 0.3])
            res = _cast(sensor, _model_parts(cat, box, seed))
            pts = res.points[points_in_box(res.points[:, :3], box, scale=1.01)]
            local = world_to_box(pts[None, :, :3], box[None])[0]
            ext = local.max(0) - local.min(0)
            ratios.append(ext[2] / ext[0])
            hist, _ = np.histogram(local[:, 2] / size[2] + 0.5, bins=8, range=(0, 1))
            profiles.append(hist / max(hist.sum(), 1))
        stats[cat] = (float(np.mean(ratios)), np.mean(profiles, axis=0))
    ratio = {c: v[0] for c, v in stats.items()}
    assert ratio["Pedestrian"] > 1.5 > ratio["Cyclist"] > ratio["Car"]
    assert ratio["Van"] > ratio["Car"] > ratio["Bus"]
    assert ratio["Pedestrian"] > 2 * ratio["Bicycle"]
    cats = list(CATEGORIES)
    for i, a in enumerate(cats):
        for b in cats[i + 1 :]:
            d_ratio = abs(stats[a][0] - stats[b][0]) / max(stats[a][0], stats[b][0])
            d_prof = np.abs(stats[a][1] - stats[b][1]).sum()
            assert d_ratio > 0.08 or d_prof > 0.2, (a, b, stats[a], stats[b])


def test_pedestrian_legs_swing_and_stay_in_the_box():
    model = make_object("Pedestrian", np.array([0.85, 0.65, 1.75]), np.random.default_rng(0))
    half = model.size / 2
    feet_x = []
    for phase in np.linspace(0, 2 * np.pi, 9):
        p = model.parts_at(phase, 1.0)
        # Segment end points of the limbs (local z axis of the cylinders).
        limbs = slice(len(model.parts), len(p))
        axis = p.rot[limbs, :, 2] * p.half[limbs, 2:3]
        tips = np.concatenate([p.center[limbs] + axis, p.center[limbs] - axis])
        assert (np.abs(tips) <= half + 1e-6).all()
        feet_x.append(tips[np.argmin(tips[:, 2]), 0])
    assert np.ptp(feet_x) > 0.3  # the feet move along the walking direction


# --------------------------------------------------------------------------- scenes


def test_scene_and_frames_are_deterministic(tmp_path):
    cfg = SceneConfig(n_frames=3, density=0.5, static_density=0.5)
    sensor = get_sensor("hdl64").subsampled(4)
    for out in ("a", "b"):
        scene = build_scene(5, 123, cfg)
        with _NullBar() as bar:
            _write_scene(tmp_path / out, scene, sensor, 123, KITTI_LIKE_CALIBRATION, bar)
    files_a = sorted(p.relative_to(tmp_path / "a") for p in (tmp_path / "a").rglob("*.*"))
    files_b = sorted(p.relative_to(tmp_path / "b") for p in (tmp_path / "b").rglob("*.*"))
    assert files_a == files_b and len(files_a) == 5
    for rel in files_a:
        assert (tmp_path / "a" / rel).read_bytes() == (tmp_path / "b" / rel).read_bytes()
    other = build_scene(5, 124, cfg)
    frame_a = render_frame(build_scene(5, 123, cfg), 0, sensor, np.random.default_rng(0))
    frame_c = render_frame(other, 0, sensor, np.random.default_rng(0))
    assert frame_a.points.shape != frame_c.points.shape or not np.array_equal(
        frame_a.points, frame_c.points
    )


class _NullBar:
    def __enter__(self):
        return self

    def __exit__(self, *exc):
        return False

    def update(self, n):
        pass


@pytest.mark.parametrize("seed", [1, 2, 3, 4])
def test_every_category_is_labelled_in_every_tiny_scene(seed):
    """Other seeds too: each tiny scene puts every category in the labelled view >= 2 frames."""
    from envs.synthetic.scene import (
        FOV_HALF_ANGLE,
        LABEL_RANGE,
        agent_boxes_world,
        sensor_pose,
        world_to_sensor_boxes,
    )
    from envs.synthetic.world import scene_frames

    preset = PRESETS["tiny"]
    sensor = get_sensor("hdl64")
    for scene_id in preset.scenes:
        cfg = SceneConfig(
            n_frames=scene_frames(preset, seed, scene_id),
            density=preset.density,
            static_density=preset.static_density,
        )
        scene = build_scene(scene_id, seed, cfg)
        frames_in_view = np.zeros(len(scene.agents), int)
        for t in range(scene.n_frames):
            origin, yaw = sensor_pose(scene, t, sensor)
            b = world_to_sensor_boxes(agent_boxes_world(scene, t), origin, yaw)
            az = np.arctan2(b[:, 1], b[:, 0])
            frames_in_view += (
                (np.abs(az) <= FOV_HALF_ANGLE)
                & (np.hypot(b[:, 0], b[:, 1]) <= LABEL_RANGE)
                & (b[:, 0] > 0)
            )
        best = defaultdict(int)
        for agent, k in zip(scene.agents, frames_in_view, strict=True):
            best[agent.category] = max(best[agent.category], int(k))
        assert all(best[c] >= 2 for c in CATEGORIES), (scene_id, dict(best))


def test_hdl32_is_sparser_than_hdl64():
    scene = build_scene(1, 0, SceneConfig(n_frames=2, density=0.5))
    n64 = len(render_frame(scene, 0, get_sensor("hdl64"), np.random.default_rng(0)).points)
    n32 = len(render_frame(scene, 0, get_sensor("hdl32"), np.random.default_rng(0)).points)
    assert 0.1 * n64 < n32 < 0.5 * n64
    assert n64 > 60_000  # a KITTI-like city scan has ~100k returns


def test_bad_config_values_list_the_valid_ones(tmp_path):
    with pytest.raises(ValueError, match="tiny, small, default"):
        generate_world(tmp_path / "x", preset="huge")
    with pytest.raises(ValueError, match="hdl64, hdl32"):
        generate_world(tmp_path / "x", preset="tiny", sensor="vlp16")
    with pytest.raises(ValueError, match="non-negative"):
        generate_world(tmp_path / "x", preset="tiny", seed=-1)
    with pytest.raises(ValueError, match="n_frames"):
        SceneConfig(n_frames=0)
    with pytest.raises(ValueError, match=">= 0"):
        SceneConfig(n_frames=5, density=-1.0)
    with pytest.raises(ValueError, match="valid"):
        SceneConfig(n_frames=5, required=("Tram",))
    assert not (tmp_path / "x").exists()


# --------------------------------------------------------------------------- the tiny world


def test_tiny_world_reads_with_every_target_in_every_split(tiny_world):
    assert set(PRESETS) == {"tiny", "small", "default"}
    for split in ("train", "val", "test"):
        ds = KittiTracking(tiny_world, split)
        longest: dict[str, int] = defaultdict(int)
        for tr in ds.tracklets:
            longest[tr.category] = max(longest[tr.category], len(tr))
        for cat in CATEGORIES:
            assert longest[cat] >= 2, (split, cat, dict(longest))
    # Reused, not regenerated: the same path comes back at once.
    assert ensure_world("tiny", "hdl64", 0) == tiny_world


def test_visible_labelled_boxes_contain_points(tiny_world):
    """Every labelled box with a clear line of sight (occluded == 0) within 40 m has points."""
    ds = KittiTracking(tiny_world, "all")
    occluded = {}
    for label_file in sorted((tiny_world / "label_02").glob("*.txt")):
        for row in read_labels(label_file):
            occluded[(label_file.stem, row.track_id, row.frame)] = row.occluded
    checked = 0
    for tr in ds.tracklets:
        for t in range(0, len(tr), 3):
            box = tr.boxes[t]
            if occluded[(tr.scene, tr.track_id, int(tr.frames[t]))] != 0:
                continue
            if np.hypot(box[0], box[1]) > 40.0:
                continue
            n = int(points_in_box(tr.points(t), box).sum())
            assert n > 0, (tr.tracklet_id, t, box)
            checked += 1
    assert checked > 30
    scan = ds.tracklets[0].points_with_intensity(0)
    assert scan.dtype == np.float32 and np.isfinite(scan).all()
    assert scan[:, 3].min() >= 0.0 and scan[:, 3].max() <= 1.0


def test_labelled_objects_are_seen_and_long_gaps_split_tracks(tiny_world):
    """KITTI-like labelling: a labelled box (practically) always holds LiDAR points, whatever its
    occlusion level, and no track has a gap longer than MAX_LABEL_GAP frames."""
    from envs.synthetic.world import MAX_LABEL_GAP

    ds = KittiTracking(tiny_world, "all")
    empty = total = 0
    for tr in ds.tracklets:
        assert len(tr) >= 2
        assert int(np.diff(tr.frames).max()) - 1 <= MAX_LABEL_GAP
        for t in range(0, len(tr), 2):
            total += 1
            empty += int(points_in_box(tr.points(t), tr.boxes[t]).sum() == 0)
    assert total > 100 and empty / total < 0.01, (empty, total)


def test_split_tracks_cuts_long_gaps_and_drops_glimpses():
    from envs.data.kitti import LabelRow
    from envs.synthetic.world import split_tracks

    def row(frame: int, track: int) -> LabelRow:
        return LabelRow.from_box(frame, track, "Car", np.array([1.5, 1.6, 4.0, 0, 1, 10, 0.0]))

    frames_a = [0, 1, 2, 5, 6, 20, 21, 40]  # gap of 2 kept; gap of 13 splits; 40 is a glimpse
    rows = [row(f, 7) for f in frames_a] + [row(f, 3) for f in (4, 5)]
    out = split_tracks(rows, max_gap=5, min_frames=2)
    tracks = defaultdict(list)
    for r in out:
        tracks[r.track_id].append(r.frame)
    assert dict(tracks) == {0: [4, 5], 1: [0, 1, 2, 5, 6], 2: [20, 21]}
    assert [r.frame for r in out] == sorted(r.frame for r in out)


def test_label_sizes_follow_the_category_statistics(tiny_world):
    ds = KittiTracking(tiny_world, "all")
    sizes = defaultdict(list)
    for tr in ds.tracklets:
        sizes[tr.category].append(tr.boxes[0, 3:6])
    assert np.mean([s[2] for s in sizes["Pedestrian"]]) == pytest.approx(1.76, abs=0.15)
    assert np.mean([s[0] for s in sizes["Car"]]) == pytest.approx(3.9, abs=0.5)
    assert min(s[0] for s in sizes["Bus"]) > 8.0


# --------------------------------------------------------------------------- writer and cache


def _fake_labels(root: Path) -> Path:
    """A one-scene label folder: a car driving past and a walking pedestrian, 3 frames."""
    rows = []
    for f in range(3):
        rows.append(
            f"{f} 0 Car 0 0 -1.5 500 170 600 220 1.5 1.6 3.9 {1.0 + f * 0.5:.2f} 1.7 15.0 -1.57\n"
        )
        rows.append(
            f"{f} 1 Pedestrian 0 0 -1.5 700 160 720 230 1.75 0.6 0.8 -3.0 1.7 "
            f"{10.0 + 0.13 * f:.2f} 0.0\n"
        )
        rows.append(f"{f} -1 DontCare -1 -1 -10 1 1 5 5 -1000 -1000 -1000 -10 -1 -1 -1\n")
    (root / "label_02").mkdir(parents=True)
    (root / "label_02" / "0000.txt").write_text("".join(rows))
    return root


def _generate_fake(args):
    labels, out = args
    return str(generate_world(out, "tiny", "hdl64", 3, labels))


def test_concurrent_generation_ends_with_one_complete_copy(tmp_path):
    labels = _fake_labels(tmp_path / "labels")
    out = tmp_path / "world"
    ctx = mp.get_context("fork")  # fork: no re-import, the test stays fast
    with ctx.Pool(2) as pool:
        results = pool.map(_generate_fake, [(labels, out), (labels, out)])
    assert results == [str(out), str(out)]
    assert sorted(p.name for p in tmp_path.iterdir()) == ["labels", "world"]  # no temp left
    assert (out / "manifest.json").is_file()
    assert len(list((out / "velodyne" / "0000").glob("*.bin"))) == 3


def test_killed_generation_leaves_nothing(tmp_path, monkeypatch):
    import envs.synthetic.world as world

    def boom(tmp, *args, **kwargs):
        (tmp / "velodyne").mkdir()
        raise KeyboardInterrupt

    monkeypatch.setattr(world, "_generate_into", boom)
    with pytest.raises(KeyboardInterrupt):
        generate_world(tmp_path / "w", "tiny")
    assert list(tmp_path.iterdir()) == []


def test_existing_other_world_is_not_overwritten(tmp_path):
    labels = _fake_labels(tmp_path / "labels")
    out = generate_world(tmp_path / "w", "tiny", "hdl64", 0, labels)
    assert generate_world(out, "tiny", "hdl64", 0, labels) == out  # reused
    with pytest.raises(FileExistsError):
        generate_world(out, "tiny", "hdl64", 1, labels)


def test_replay_writes_source_labels_and_objects_get_points(tmp_path):
    labels = _fake_labels(tmp_path / "labels")
    out = generate_world(tmp_path / "w", "tiny", "hdl64", 0, labels)
    assert (out / "label_02" / "0000.txt").read_text() == (
        labels / "label_02" / "0000.txt"
    ).read_text()
    ds = KittiTracking(out, "all")
    assert [(t.category, len(t)) for t in ds.tracklets] == [("Car", 3), ("Pedestrian", 3)]
    for tr in ds.tracklets:
        for t in range(len(tr)):
            assert points_in_box(tr.points(t), tr.boxes[t]).sum() > 10


def test_cli_generate_cache_is_the_world_the_envs_use(tmp_path, capsys):
    from envs.synthetic.nuscenes_layout import ensure_nuscenes_world
    from training.cli import main

    for layout, ensure in (("kitti", ensure_world), ("nuscenes", ensure_nuscenes_world)):
        args = ["generate", "--cache", "--layout", layout, "--preset", "tiny", "--no-progress"]
        assert main(args) == 0
        root = Path(capsys.readouterr().out.strip())
        assert root == ensure("tiny") and (root / "manifest.json").is_file()
    assert main(["generate", "--cache", "--preset", "tiny", "--out", str(tmp_path / "w")]) == 2
    err = capsys.readouterr().err
    assert "--cache does not take --out" in err and err.count("\n") == 1
    assert not (tmp_path / "w").exists()


def test_cli_generate(tmp_path, capsys):
    from training.cli import main

    assert main(["generate", "--out", str(tmp_path / "bad"), "--preset", "huge"]) == 2
    assert "tiny, small, default" in capsys.readouterr().err
    labels = _fake_labels(tmp_path / "labels")
    code = main(
        [
            "generate",
            "--out",
            str(tmp_path / "w"),
            "--preset",
            "tiny",
            "--from-labels",
            str(labels),
            "--preview",
            "--no-progress",
        ]
    )
    assert code == 0
    assert (tmp_path / "w" / "preview.png").stat().st_size > 10_000


def test_stale_temp_dirs_of_killed_runs_are_cleaned(tmp_path):
    """A temp dir whose lock nobody holds (its writer died) and half-deleted trash go; a temp
    dir whose writer holds its lock, or without a lock file but with a live pid, stays."""
    import os

    from envs.synthetic.world import _hold_lock, _release_lock, clean_stale_temps

    dead = tmp_path / ".w.tmp-999999999-abcd"  # lock file left, nobody holds it
    dead.mkdir()
    (tmp_path / ".w.tmp-999999999-abcd.lock").write_text("")
    no_lock_dead = tmp_path / ".w.tmp-999999998-abcd"  # no such process
    no_lock_dead.mkdir()
    no_lock_alive = tmp_path / f".w.tmp-{os.getpid()}-ef01"
    no_lock_alive.mkdir()
    held = tmp_path / f".w.tmp-{os.getpid()}-abcd"
    fd = _hold_lock(held)
    held.mkdir()
    (tmp_path / ".w.trash-1234").mkdir()
    try:
        clean_stale_temps(tmp_path)
        assert sorted(p.name for p in tmp_path.iterdir()) == sorted(
            [no_lock_alive.name, held.name, held.name + ".lock"]
        )
    finally:
        _release_lock(held, fd)
