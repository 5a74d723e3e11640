"""The ``"kitti"`` motion of the synthetic world (envs.synthetic.kitti_motion) and its presets."""

from __future__ import annotations

import json
from collections import defaultdict
from pathlib import Path

import numpy as np
import pytest

from envs.data.motion import label_motion
from envs.synthetic import CATEGORIES, ensure_world, generate_world, get_preset, get_sensor
from envs.synthetic.kitti_motion import KITTI_MOTION, scene_plan
from envs.synthetic.presets import Preset
from envs.synthetic.scene import SceneConfig, build_scene
from envs.synthetic.scene_types import check_motion
from envs.synthetic.world import world_identity

TRAIN_SCENES = range(0, 17)


def _labels(root: Path) -> list[Path]:
    return sorted((root / "label_02").glob("*.txt"))


def test_unknown_motion_names_the_valid_ones():
    with pytest.raises(ValueError, match="unknown motion 'fast'; valid motions: v1, kitti"):
        check_motion("fast")
    with pytest.raises(ValueError, match="v1, kitti"):
        SceneConfig(n_frames=2, motion="fast")
    with pytest.raises(ValueError, match="v1, kitti"):
        Preset("x", (0,), (2, 2), 1.0, 1.0, motion="KITTI")


def test_old_presets_keep_their_identity_fields():
    """v1 presets' manifests hold the fields they held before motion versions existed; the
    kitti-motion presets are other worlds (another identity, another cache directory)."""
    for name in ("tiny", "small", "default"):
        assert get_preset(name).motion == "v1"
        assert "motion" not in world_identity(name, "hdl64", 0)["config"]["preset"]
        km = world_identity(f"{name}-km", "hdl64", 0)
        assert km["config"]["preset"]["motion"] == "kitti"
        old = get_preset(name)
        new = get_preset(f"{name}-km")
        # Same sizes: only the motion differs.
        assert (old.scenes, old.frames, old.density, old.column_factor) == (
            new.scenes,
            new.frames,
            new.density,
            new.column_factor,
        )


def test_scene_modes_follow_the_cycle_and_the_layout_is_v1s():
    cycle = KITTI_MOTION.mode_cycle
    modes = [scene_plan("kitti", 3, k).mode for k in range(21)]
    for k in range(len(cycle), 21):
        assert modes[k] == modes[k - len(cycle)]
    assert sorted(modes[: len(cycle)]) == sorted(cycle)
    assert scene_plan("v1", 3, 0) is None
    # The kitti motion draws from its own stream: the street (road, ground) is v1's (the static
    # world's extent follows the ego's distance, so it differs).
    v1 = build_scene(4, 3, SceneConfig(n_frames=20, density=0.5, static_density=0.5))
    km = build_scene(
        4, 3, SceneConfig(n_frames=20, density=0.5, static_density=0.5, motion="kitti")
    )
    assert v1.ground.road_y == km.ground.road_y
    assert (v1.ground.slope_x, v1.ground.asphalt) == (km.ground.slope_x, km.ground.asphalt)
    standing = modes[4] == "stopped"
    assert standing == (np.ptp(km.ego[:, 0]) == 0.0)


def test_tiny_km_world_has_every_target_in_every_split():
    """As the v1 worlds: every split of the `tiny-km` world holds every category as a labelled
    target of at least 2 frames (the stopped and slow egos see them too)."""
    from envs.data import KittiTracking

    root = ensure_world("tiny-km", "hdl64", 0)
    for split in ("train", "val", "test"):
        longest: dict[str, int] = defaultdict(int)
        for tr in KittiTracking(root, split).tracklets:
            longest[tr.category] = max(longest[tr.category], len(tr))
        assert all(longest[c] >= 2 for c in CATEGORIES), (split, dict(longest))


def test_tiny_km_same_seed_same_bytes(tmp_path):
    a = generate_world(tmp_path / "a", "tiny-km", "hdl64", 0, progress=False)
    b = generate_world(tmp_path / "b", "tiny-km", "hdl64", 0, progress=False)
    files_a = json.loads((a / "manifest.json").read_text())["files"]
    files_b = json.loads((b / "manifest.json").read_text())["files"]
    assert files_a == files_b and len(files_a) > 70
    tiny = json.loads((ensure_world("tiny", "hdl64", 0) / "manifest.json").read_text())["files"]
    label = "label_02/0019.txt"
    assert files_a[label]["sha256"] != tiny[label]["sha256"]


def test_tiny_km_moves_towards_kitti(shared_labels):
    """Cheap direction check on the tiny worlds (3 scenes of 24 frames): against v1, the kitti
    motion brings the vehicles' yaw rates up from ~0 and the pedestrians' down from their
    wandering walk, towards the real train labels."""
    real = label_motion([f for f in _labels(shared_labels) if int(f.stem) in TRAIN_SCENES])
    v1 = label_motion(_labels(ensure_world("tiny", "hdl64", 0)))
    km = label_motion(_labels(ensure_world("tiny-km", "hdl64", 0)))

    def p90(motion, category):
        return motion[category].summary()["yaw_rate_radps_p90"]

    for category in ("Car", "Van"):
        assert p90(v1, category) < 0.02 < 0.05 < p90(km, category) <= 2 * p90(real, category)
    assert p90(km, "Pedestrian") < 0.5 * p90(v1, "Pedestrian")
    assert abs(p90(km, "Pedestrian") - p90(real, "Pedestrian")) < abs(
        p90(v1, "Pedestrian") - p90(real, "Pedestrian")
    )


# Statistics of the generated `small-km` world that miss the 15 % goal today, with the miss
# measured (docs/data.md, "Motion against KITTI"): a looser bound keeps them from getting worse.
KNOWN_MISSES = {("Van", "displacement_m_p90"): 0.30, ("Cyclist", "displacement_m_median"): 0.25}


@pytest.mark.slow
def test_small_km_displacement_within_15_percent_of_kitti_train(shared_labels):
    """The goal of issue 45 item 0 on the generated `small-km` world of seed 0: median and p90
    of the ego-relative displacement a frame within 15 % of the real train labels for Car, Van,
    Pedestrian and Cyclist -- met by six of the eight; Van p90 (-25 %) and the Cyclist median
    (+18 %) are held to KNOWN_MISSES. Generates the world (350 frames, ~30 s on this machine)
    unless it is cached."""
    real = label_motion([f for f in _labels(shared_labels) if int(f.stem) in TRAIN_SCENES])
    gen = label_motion(_labels(ensure_world("small-km", "hdl64", 0)))
    for category in ("Car", "Van", "Pedestrian", "Cyclist"):
        r, g = real[category].summary(), gen[category].summary()
        for stat in ("displacement_m_median", "displacement_m_p90"):
            bound = KNOWN_MISSES.get((category, stat), 0.15)
            assert abs(g[stat] / r[stat] - 1.0) <= bound, (category, stat, g[stat], r[stat])


def test_nuscenes_layout_key_frames_sample_the_same_motion(tmp_path):
    """The nuScenes-layout `tiny-km` world annotates, at its 2 Hz key frames, the agents of the
    very scenes the KITTI-layout `tiny-km` world simulates at 10 Hz (same per-second motion)."""
    from envs.data import NuScenesTracking
    from envs.synthetic import get_preset
    from envs.synthetic.nuscenes_layout import (
        KEYFRAME_EVERY,
        expected_lidar_boxes,
        generate_nuscenes_world,
        scene_name,
    )
    from envs.synthetic.world import generated_scenes

    root = generate_nuscenes_world(tmp_path / "nus", "tiny-km", progress=False)
    manifest = json.loads((root / "manifest.json").read_text())
    assert manifest["config"]["preset"]["motion"] == "kitti"
    sensor = get_sensor("hdl32").subsampled(2)
    scenes = {scene_name(sid): s for sid, s in generated_scenes(get_preset("tiny-km"), 0, sensor)}
    data = NuScenesTracking(root, "v1.0-mini", "all")
    checked = 0
    for tr in data.tracklets:
        scene = scenes[tr.scene]
        for k, box in zip(tr.frames, tr.boxes, strict=True):
            want = expected_lidar_boxes(scene, sensor, int(k) * KEYFRAME_EVERY)
            assert np.linalg.norm(want[:, :3] - box[:3], axis=1).min() < 1e-4
            checked += 1
    assert checked > 20
