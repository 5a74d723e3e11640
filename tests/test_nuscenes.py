"""The nuScenes layout: the native table reader against hand-built tables (exact boxes through
non-trivial ego and sensor poses, computed independently with 4x4 matrices), bad input, the
split lists, the synthetic world written in nuScenes layout read back, and the env on it."""

from __future__ import annotations

import json
import math
import shutil
import warnings

import numpy as np
import pytest

from envs.data import NuScenesTracking, get_setting
from envs.data.kitti import NonFinitePointsWarning
from envs.data.nuscenes import CATEGORY_MAP, SOT_SPLITS, split_scenes

VERSION = "v1.0-test-tables"


# --------------------------------------------------------------------------- hand-built tables


def axis_angle_matrix(axis, angle: float) -> np.ndarray:
    """Rodrigues' formula (independent of the reader's quaternion maths)."""
    k = np.asarray(axis, float) / np.linalg.norm(axis)
    kx = np.array([[0, -k[2], k[1]], [k[2], 0, -k[0]], [-k[1], k[0], 0]])
    return np.eye(3) + math.sin(angle) * kx + (1 - math.cos(angle)) * kx @ kx


def axis_angle_quaternion(axis, angle: float) -> list[float]:
    k = np.asarray(axis, float) / np.linalg.norm(axis)
    return [math.cos(angle / 2), *(math.sin(angle / 2) * k)]


def homogeneous(rot: np.ndarray, trans) -> np.ndarray:
    m = np.eye(4)
    m[:3, :3] = rot
    m[:3, 3] = trans
    return m


# Poses as (axis, angle, translation): ego poses per key frame, one sensor calibration.
EGO = [
    ((0.1, -0.05, 1.0), 0.7, (410.0, 1203.5, 0.3)),
    ((0.0, 0.1, 1.0), 0.9, (414.2, 1206.1, 0.35)),
    ((-0.1, 0.0, 1.0), 1.2, (417.9, 1209.8, 0.2)),
]
CALIB = ((0.02, -0.03, -1.0), math.pi / 2, (0.94, 0.01, 1.84))
# Instances: (category, size (w, l, h), {frame: (axis, angle, centre)}); frame 1 of the car is a
# gap. The barrier is not a tracking category and must not be loaded.
INSTANCES = [
    (
        "vehicle.car",
        (1.8, 4.5, 1.6),
        {
            0: ((0, 0, 1), 0.3, (420.0, 1210.0, 1.0)),
            2: ((0.05, 0, 1), 0.5, (424.0, 1213.0, 1.1)),
        },
    ),
    (
        "human.pedestrian.police_officer",
        (0.6, 0.7, 1.8),
        {
            0: ((0, 0, 1), -2.8, (408.0, 1215.0, 0.9)),
            1: ((0, 0, 1), -2.9, (408.5, 1215.4, 0.9)),
            2: ((0, 0, 1), 3.1, (409.0, 1215.9, 0.9)),
        },
    ),
    ("movable_object.barrier", (0.5, 2.0, 1.0), {0: ((0, 0, 1), 0.0, (415.0, 1200.0, 0.5))}),
]


def expected_box(frame: int, axis, angle: float, centre, size_wlh) -> np.ndarray:
    """The box in the LiDAR frame via explicit 4x4 matrices: inv(T_cs) inv(T_ego) T_box."""
    t_ego = homogeneous(axis_angle_matrix(EGO[frame][0], EGO[frame][1]), EGO[frame][2])
    t_cs = homogeneous(axis_angle_matrix(CALIB[0], CALIB[1]), CALIB[2])
    t_box = homogeneous(axis_angle_matrix(axis, angle), centre)
    m = np.linalg.inv(t_cs) @ np.linalg.inv(t_ego) @ t_box
    yaw = math.atan2(m[1, 0], m[0, 0])
    w, length, h = size_wlh
    return np.array([*m[:3, 3], length, w, h, yaw])


def write_tables(root, n_points: int = 50) -> dict:
    """Write the hand-built dataset under ``root``; returns the tables."""
    tok = iter(f"{i:032x}" for i in range(1, 10_000))
    sensor = {"token": next(tok), "channel": "LIDAR_TOP", "modality": "lidar"}
    cam = {"token": next(tok), "channel": "CAM_FRONT", "modality": "camera"}
    cs = {
        "token": next(tok),
        "sensor_token": sensor["token"],
        "translation": list(CALIB[2]),
        "rotation": axis_angle_quaternion(CALIB[0], CALIB[1]),
        "camera_intrinsic": [],
    }
    cs_cam = {
        "token": next(tok),
        "sensor_token": cam["token"],
        "translation": [0, 0, 0],
        "rotation": [1, 0, 0, 0],
        "camera_intrinsic": [],
    }
    log = {
        "token": next(tok),
        "logfile": "l",
        "vehicle": "v",
        "date_captured": "d",
        "location": "x",
    }
    scene = {
        "token": next(tok),
        "log_token": log["token"],
        "name": "scene-0003",
        "nbr_samples": 3,
        "description": "",
    }
    other_scene = {
        "token": next(tok),
        "log_token": log["token"],
        "name": "scene-0001",
        "nbr_samples": 0,
        "first_sample_token": "",
        "last_sample_token": "",
        "description": "",
    }
    samples, sds, poses = [], [], []
    rng = np.random.default_rng(0)
    for k, (axis, angle, trans) in enumerate(EGO):
        s = {"token": next(tok), "timestamp": 1000 + k, "scene_token": scene["token"]}
        pose = {
            "token": next(tok),
            "timestamp": 1000 + k,
            "translation": list(trans),
            "rotation": axis_angle_quaternion(axis, angle),
        }
        name = f"samples/LIDAR_TOP/f{k}.pcd.bin"
        sd = {
            "token": next(tok),
            "sample_token": s["token"],
            "ego_pose_token": pose["token"],
            "calibrated_sensor_token": cs["token"],
            "is_key_frame": True,
            "filename": name,
            "timestamp": 1000 + k,
            "fileformat": "pcd",
        }
        # A camera key frame of the same sample must be ignored.
        sd_cam = {
            "token": next(tok),
            "sample_token": s["token"],
            "ego_pose_token": pose["token"],
            "calibrated_sensor_token": cs_cam["token"],
            "is_key_frame": True,
            "filename": f"samples/CAM_FRONT/f{k}.jpg",
            "timestamp": 1000 + k,
        }
        samples.append(s)
        sds += [sd_cam, sd]
        poses.append(pose)
        pts = rng.normal(size=(n_points, 5)).astype("<f4")
        pts[:, 3] = rng.uniform(0, 255, n_points)
        (root / "samples" / "LIDAR_TOP").mkdir(parents=True, exist_ok=True)
        pts.tofile(root / name)
    for i, s in enumerate(samples):
        s["prev"] = samples[i - 1]["token"] if i else ""
        s["next"] = samples[i + 1]["token"] if i + 1 < len(samples) else ""
    scene["first_sample_token"] = samples[0]["token"]
    scene["last_sample_token"] = samples[-1]["token"]
    categories, instances, anns = [], [], []
    for name, size, frames in INSTANCES:
        cat = {"token": next(tok), "name": name, "description": ""}
        inst = {"token": next(tok), "category_token": cat["token"], "nbr_annotations": len(frames)}
        chain = []
        for k, (axis, angle, centre) in frames.items():
            chain.append(
                {
                    "token": next(tok),
                    "sample_token": samples[k]["token"],
                    "instance_token": inst["token"],
                    "translation": list(centre),
                    "size": list(size),
                    "rotation": axis_angle_quaternion(axis, angle),
                    "num_lidar_pts": 5,
                    "num_radar_pts": 0,
                    "attribute_tokens": [],
                    "visibility_token": "4",
                }
            )
        for i, a in enumerate(chain):
            a["prev"] = chain[i - 1]["token"] if i else ""
            a["next"] = chain[i + 1]["token"] if i + 1 < len(chain) else ""
        inst["first_annotation_token"] = chain[0]["token"]
        inst["last_annotation_token"] = chain[-1]["token"]
        categories.append(cat)
        instances.append(inst)
        anns += chain[::-1]  # file order must not matter
    tables = {
        "category": categories,
        "instance": instances,
        "sensor": [cam, sensor],
        "calibrated_sensor": [cs_cam, cs],
        "ego_pose": poses,
        "log": [log],
        "scene": [other_scene, scene],
        "sample": samples[::-1],
        "sample_data": sds,
        "sample_annotation": anns,
    }
    (root / VERSION).mkdir(parents=True, exist_ok=True)
    for name, records in tables.items():
        (root / VERSION / f"{name}.json").write_text(json.dumps(records))
    return tables


def rewrite(root, table: str, records) -> None:
    (root / VERSION / f"{table}.json").write_text(json.dumps(records))


@pytest.fixture
def hand(tmp_path):
    return tmp_path, write_tables(tmp_path)


def test_hand_built_boxes_exact_through_ego_and_sensor_poses(hand):
    root, tables = hand
    data = NuScenesTracking(root, VERSION, "val")
    assert data.scenes == ["scene-0003"]
    assert [tr.category for tr in data.tracklets] == ["Car", "Pedestrian"]
    assert [tr.tracklet_id for tr in data.tracklets] == ["scene-0003/0", "scene-0003/1"]
    car, ped = data.tracklets
    np.testing.assert_array_equal(car.frames, [0, 2])  # the gap is kept
    np.testing.assert_array_equal(ped.frames, [0, 1, 2])
    for tr, (_, size, frames) in zip(data.tracklets, INSTANCES, strict=False):
        want = np.array([expected_box(k, *frames[k], size) for k in tr.frames])
        np.testing.assert_allclose(tr.boxes[:, :6], want[:, :6], atol=1e-9)
        dyaw = (tr.boxes[:, 6] - want[:, 6] + np.pi) % (2 * np.pi) - np.pi
        np.testing.assert_allclose(dyaw, 0.0, atol=1e-9)
        assert np.all((tr.boxes[:, 6] >= -np.pi) & (tr.boxes[:, 6] < np.pi))
    np.testing.assert_allclose(car.boxes[0, 3:6], [4.5, 1.8, 1.6])  # (w, l, h) -> (l, w, h)
    assert data.instance_tokens == [tables["instance"][0]["token"], tables["instance"][1]["token"]]
    # Points: lazily read, xyz and intensity / 255, shared cache per scene.
    raw = np.fromfile(root / "samples/LIDAR_TOP/f2.pcd.bin", dtype="<f4").reshape(-1, 5)
    np.testing.assert_array_equal(car.points(1), raw[:, :3])
    np.testing.assert_allclose(car.points_with_intensity(1)[:, 3], raw[:, 3] / 255, rtol=1e-6)
    assert car.scans is ped.scans


def test_hand_built_categories_and_splits(hand):
    root, _ = hand
    assert [t.category for t in NuScenesTracking(root, VERSION, "val", "Pedestrian").tracklets] == [
        "Pedestrian"
    ]
    assert len(NuScenesTracking(root, VERSION, "all", ["Truck", "Car"])) == 1
    assert len(NuScenesTracking(root, VERSION, "train")) == 0  # scene-0001: no samples
    with pytest.raises(ValueError, match="split 'test' names none of the 2 scenes"):
        NuScenesTracking(root, VERSION, "test")
    with pytest.raises(
        ValueError,
        match=r"unknown nuScenes split 'sot'; valid splits: train, "
        r"val, test, mini_train, mini_val, train_detect, train_track, all",
    ):
        NuScenesTracking(root, VERSION, "sot")
    with pytest.raises(
        ValueError,
        match=r"unknown nuScenes category \['Van'\]; valid: Bicycle, "
        r"Bus, Car, Motorcycle, Pedestrian, Trailer, Truck",
    ):
        NuScenesTracking(root, VERSION, "val", "Van")
    with pytest.raises(
        ValueError,
        match="unknown setting 'nuscenes-3'; valid: kitti-1, kitti-2, nuscenes-1, nuscenes-2",
    ):
        get_setting("nuscenes-3")


def test_bad_tables_name_file_or_token(hand):
    root, tables = hand
    with pytest.raises(
        FileNotFoundError,
        match=r"no version folder .*v1.0-trainval; found: "
        f"{VERSION}$",
    ):
        NuScenesTracking(root, "v1.0-trainval", "val")
    (root / "v1.0-mini").mkdir()
    with pytest.raises(FileNotFoundError, match=f"found: v1.0-mini, {VERSION}$"):
        NuScenesTracking(root, "v1.0-trainval", "val")
    with pytest.raises(FileNotFoundError, match="found: none"):
        NuScenesTracking(root / "samples", "v1.0-trainval", "val")
    anns = tables["sample_annotation"]
    bad = [dict(anns[0], sample_token="f" * 32), *anns[1:]]
    rewrite(root, "sample_annotation", bad)
    with pytest.raises(
        KeyError,
        match=f"sample_annotation '{anns[0]['token']}' refers to "
        f"sample token '{'f' * 32}', which is not in .*sample.json",
    ):
        NuScenesTracking(root, VERSION, "val")
    bad = [dict(anns[0], rotation=[0, 0, 0, 0]), *anns[1:]]
    rewrite(root, "sample_annotation", bad)
    with pytest.raises(ValueError, match=f"record '{anns[0]['token']}' has a zero"):
        NuScenesTracking(root, VERSION, "val")
    bad = [dict(anns[0], size=[1.0, 2.0]), *anns[1:]]
    rewrite(root, "sample_annotation", bad)
    with pytest.raises(ValueError, match=f"record '{anns[0]['token']}' field 'size' must be 3"):
        NuScenesTracking(root, VERSION, "val")
    rewrite(root, "sample_annotation", anns)
    inst = tables["instance"]
    rewrite(root, "instance", [dict(inst[0], category_token="c" * 32), *inst[1:]])
    with pytest.raises(KeyError, match=f"instance '{inst[0]['token']}' refers to category"):
        NuScenesTracking(root, VERSION, "val")
    rewrite(root, "instance", inst)
    (root / VERSION / "ego_pose.json").unlink()
    with pytest.raises(FileNotFoundError, match=r"table .*ego_pose.json is missing"):
        NuScenesTracking(root, VERSION, "val")


def test_bad_scans_name_file_and_frame(hand):
    root, _ = hand
    car = NuScenesTracking(root, VERSION, "val", "Car").tracklets[0]
    path = root / "samples/LIDAR_TOP/f2.pcd.bin"
    data = path.read_bytes()
    path.write_bytes(data[:-4])
    with pytest.raises(
        ValueError,
        match=r"scene scene-0003 key frame 2: .*f2.pcd.bin: size "
        r"\d+ bytes is not a multiple of 20",
    ):
        car.points(1)
    path.unlink()
    with pytest.raises(
        FileNotFoundError,
        match=r"scene scene-0003 key frame 2: .*f2.pcd.bin "
        "not found",
    ):
        car.points(1)
    pts = np.ones((3, 5), "<f4")
    pts[1, 0] = np.nan
    pts.tofile(path)
    with pytest.warns(NonFinitePointsWarning, match="dropped 1 non-finite"):
        assert car.points(1).shape == (2, 3)


# --------------------------------------------------------------------------- split lists


def test_official_split_lists():
    train, val, test = split_scenes("train"), split_scenes("val"), split_scenes("test")
    assert (len(train), len(val), len(test)) == (700, 150, 150)
    assert len(set(train) | set(val) | set(test)) == 1000
    assert set(train) == set(split_scenes("train_detect")) | set(split_scenes("train_track"))
    assert not set(split_scenes("train_detect")) & set(split_scenes("train_track"))
    assert split_scenes("mini_val") == ("scene-0103", "scene-0916")
    assert val[:3] == ("scene-0003", "scene-0012", "scene-0013")
    assert test[0] == "scene-0077" and "scene-0001" in train
    assert set(split_scenes("mini_val")) <= set(val)
    assert split_scenes("all") is None
    assert SOT_SPLITS == {
        "train": "train_track",
        "val": "train_detect",
        "test": "val",
        "all": "all",
    }


def test_category_map_targets_are_setting_names():
    for name in ("nuscenes-1", "nuscenes-2"):
        assert set(get_setting(name).categories) <= set(CATEGORY_MAP.values())
    assert get_setting("nuscenes-1").unseen == ("Car",)
    assert get_setting("nuscenes-2").observed == ("Car", "Truck", "Bicycle")


# --------------------------------------------------------------------------- synthetic world


@pytest.fixture(scope="module")
def world(tmp_path_factory):
    from envs.synthetic.nuscenes_layout import generate_nuscenes_world

    return generate_nuscenes_world(tmp_path_factory.mktemp("nus") / "w", "tiny", progress=False)


def test_synthetic_round_trip_boxes_and_points(world):
    from envs.geometry import points_in_box
    from envs.synthetic import get_preset, get_sensor
    from envs.synthetic.nuscenes_layout import (
        KEYFRAME_EVERY,
        expected_lidar_boxes,
        scene_name,
    )
    from envs.synthetic.world import generated_scenes

    data = NuScenesTracking(world, "v1.0-mini", "all")
    manifest = json.loads((world / "manifest.json").read_text())
    stats = manifest["scene_stats"]
    assert sum(s["annotations"] for s in stats.values()) == sum(len(t) for t in data.tracklets)
    anns = {
        a["token"]: a for a in json.loads((world / "v1.0-mini/sample_annotation.json").read_text())
    }
    sensor = get_sensor("hdl32")
    scenes = {scene_name(sid): s for sid, s in generated_scenes(get_preset("tiny"), 0, sensor)}
    assert set(data.scenes) == set(scenes)
    checked = 0
    for tr, tokens in zip(data.tracklets, data.annotation_tokens, strict=True):
        scene = scenes[tr.scene]
        agents = set()
        for t, (k, box) in enumerate(zip(tr.frames, tr.boxes, strict=True)):
            want = expected_lidar_boxes(scene, sensor, int(k) * KEYFRAME_EVERY)
            a = int(np.argmin(np.linalg.norm(want[:, :3] - box[:3], axis=1)))
            agents.add(a)
            np.testing.assert_allclose(box[:6], want[a, :6], atol=1e-5)
            assert abs((box[6] - want[a, 6] + np.pi) % (2 * np.pi) - np.pi) < 1e-5
            n_own = anns[tokens[t]]["num_lidar_pts"]
            # Every own return lies in the box up to the range noise (sigma 2 cm).
            inside = points_in_box(tr.points(t), box, offset_m=0.1).sum()
            assert n_own >= 3 and inside >= n_own, (tr.tracklet_id, t, n_own, inside)
            checked += 1
        assert len(agents) == 1  # one instance = one simulated agent
    assert checked > 100
    # The world is 360-degree annotated: objects behind the ego (LiDAR y < 0) too.
    assert any((tr.boxes[:, 1] < 0).any() for tr in data.tracklets)


def test_synthetic_world_tables_and_splits(world):
    tables = {p.stem: json.loads(p.read_text()) for p in (world / "v1.0-mini").glob("*.json")}
    assert len(tables) == 13
    cs = tables["calibrated_sensor"][0]
    assert cs["rotation"] != [1, 0, 0, 0] and cs["translation"] != [0, 0, 0]
    poses = np.array([p["translation"] for p in tables["ego_pose"]])
    assert np.linalg.norm(np.diff(poses[:5], axis=0), axis=1).max() > 0.5  # the ego moves
    stamps = [s["timestamp"] for s in tables["sample"]]
    assert np.diff(stamps[:5]).tolist() == [500_000] * 4  # 2 Hz key frames
    assert {s["name"] for s in tables["scene"]} == {"scene-0004", "scene-0001", "scene-0003"}
    assert NuScenesTracking(world, "v1.0-mini", SOT_SPLITS["train"]).scenes == ["scene-0004"]
    assert NuScenesTracking(world, "v1.0-mini", SOT_SPLITS["val"]).scenes == ["scene-0001"]
    assert NuScenesTracking(world, "v1.0-mini", "val").scenes == ["scene-0003"]
    cats = {t.category for t in NuScenesTracking(world, "v1.0-mini", "all").tracklets}
    assert {"Car", "Pedestrian", "Truck", "Bicycle"} <= cats


def test_generate_reuses_and_refuses(world, tmp_path):
    from envs.synthetic.nuscenes_layout import generate_nuscenes_world

    stamp = (world / "manifest.json").stat().st_mtime_ns
    assert generate_nuscenes_world(world, "tiny", progress=False) == world
    assert (world / "manifest.json").stat().st_mtime_ns == stamp
    other = tmp_path / "other"
    other.mkdir()
    (other / "x").write_text("x")
    with pytest.raises(FileExistsError, match="is not this nuScenes-layout world"):
        generate_nuscenes_world(other, "tiny", progress=False)
    with pytest.raises(ValueError, match="version must be a folder name"):
        generate_nuscenes_world(tmp_path / "v", "tiny", version="../x", progress=False)


def test_env_on_nuscenes_layout_checks_and_oracle(world):
    import gymnasium as gym
    from gymnasium.utils.env_checker import check_env
    from gymnasium.wrappers import RescaleAction
    from stable_baselines3.common.env_checker import check_env as sb3_check_env

    from envs.geometry import offset_between

    env = gym.make(
        "pointtrack/NuScenes-v1",
        root=str(world),
        version="v1.0-mini",
        split="all",
        setting="nuscenes-1",
    )
    u = env.unwrapped
    assert {tr.category for tr in u.tracklets} <= set(get_setting("nuscenes-1").categories)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        check_env(u)
        sb3_check_env(RescaleAction(u, -1.0, 1.0))
    for i in range(u.num_tracklets):
        u.reset(options={"tracklet": i})
        while True:
            action = offset_between(u.reference_box, u.current_tracklet.boxes[u.current_frame])
            _, _, term, trunc, info = u.step(action.astype(np.float32))
            assert info["iou"] == pytest.approx(1.0) and info["center_error"] < 1e-6
            if term or trunc:
                break
    env.close()


def test_env_needs_root_or_preset():
    import gymnasium as gym

    with pytest.raises(ValueError, match="needs root=<nuScenes dataroot>"):
        gym.make("pointtrack/NuScenes-v1")


# --------------------------------------------------------------------------- devkit


def test_devkit_agrees(world, tmp_path):
    """Every annotation's LIDAR_TOP box and every instance's count agree with the nuScenes devkit
    to 1e-4. Runs when the devkit is importable here, or with $NUSCENES_DEVKIT_PYTHON (the
    python of the venv that ``scripts/check_nuscenes_devkit.sh`` builds); skips otherwise."""
    import importlib.util
    import os
    import subprocess
    import sys
    from pathlib import Path

    scripts = Path(__file__).resolve().parents[1] / "scripts"
    python = os.environ.get("NUSCENES_DEVKIT_PYTHON")
    if python is None:
        if importlib.util.find_spec("nuscenes") is None:
            pytest.skip("nuscenes-devkit not importable and $NUSCENES_DEVKIT_PYTHON not set")
        python = sys.executable
    if shutil.which(python) is None and not Path(python).is_file():
        pytest.skip(f"$NUSCENES_DEVKIT_PYTHON={python} not found")
    out = tmp_path / "devkit.json"
    subprocess.run(
        [python, str(scripts / "nuscenes_devkit_dump.py"), str(world), "v1.0-mini", str(out)],
        check=True,
        capture_output=True,
    )
    spec = importlib.util.spec_from_file_location("compare", scripts / "nuscenes_devkit_compare.py")
    compare = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(compare)
    report = compare.compare(str(world), "v1.0-mini", json.loads(out.read_text()), tol=1e-4)
    assert report["errors"] == []
    assert report["annotations"] > 100 and report["max_centre_size_err"] < 1e-4


# --------------------------------------------------------------------------- CLI and training


def test_cli_generate_and_eval_nuscenes(world, tmp_path, capsys):
    from training.cli import main

    out = tmp_path / "g"
    assert (
        main(
            [
                "generate",
                "--layout",
                "nuscenes",
                "--preset",
                "tiny",
                "--out",
                str(out),
                "--version",
                "v1.0-custom",
                "--no-progress",
            ]
        )
        == 0
    )
    assert "nuScenes-layout world written to" in capsys.readouterr().out
    assert (out / "v1.0-custom" / "sample_annotation.json").is_file()
    manifest = json.loads((out / "manifest.json").read_text())
    assert manifest["sensor"] == "hdl32" and manifest["layout"]["version"] == "v1.0-custom"
    # Same seed, same bytes as the fixture's world (version folder aside).
    for name in ("sample_annotation", "ego_pose", "scene"):
        assert (out / "v1.0-custom" / f"{name}.json").read_bytes() == (
            world / "v1.0-mini" / f"{name}.json"
        ).read_bytes()
    assert (
        main(
            ["generate", "--preset", "tiny", "--out", str(tmp_path / "k"), "--version", "v1.0-mini"]
        )
        == 2
    )
    assert "--version applies to --layout nuscenes" in capsys.readouterr().err

    report_dir = tmp_path / "eval"
    assert (
        main(
            [
                "eval",
                "--dataset",
                "nuscenes",
                "--root",
                str(world),
                "--version",
                "v1.0-mini",
                "--split",
                "test",
                "--tracker",
                "previous_box",
                "--no-progress",
                "--out",
                str(report_dir),
            ]
        )
        == 0
    )
    report = json.loads((report_dir / "report.json").read_text())["previous_box"]
    frames = sum(
        len(t)
        for t in NuScenesTracking(
            world, "v1.0-mini", "val", get_setting("nuscenes-1").categories
        ).tracklets
        if len(t) >= 2
    )
    assert report["observed"]["frames"] + report["unseen"]["frames"] == frames


def test_training_loads_nuscenes_roles(world):
    from training.config import TrainConfig
    from training.samples import load_tracklets

    tracklets, setting, root = load_tracklets(
        "nuscenes", "train", setting="nuscenes-2", data_root=str(world), version="v1.0-mini"
    )
    assert {t.scene for t in tracklets} == {"scene-0004"}  # train_track
    assert {t.category for t in tracklets} <= set(setting.observed)
    val, _, _ = load_tracklets(
        "nuscenes", "val", setting="nuscenes-2", data_root=str(world), version="v1.0-mini"
    )
    assert {t.scene for t in val} == {"scene-0001"}  # train_detect, never the test split
    TrainConfig(dataset="nuscenes", setting="nuscenes-1").validate()


def test_selection_on_nuscenes_layout_worlds():
    from training.selection import SelectionConfig, ValPart, score_candidates

    with pytest.raises(ValueError, match="dataset must be 'synthetic' or 'nuscenes'"):
        SelectionConfig(dataset="kitti")
    config = SelectionConfig(
        setting="nuscenes-1",
        preset="tiny",
        sensor="hdl32",
        parts=(ValPart(1, "test"),),
        num_envs=1,
        dataset="nuscenes",
    )
    rows = score_candidates(["previous_box"], config)
    from envs.synthetic.nuscenes_layout import ensure_nuscenes_world

    data = NuScenesTracking(
        ensure_nuscenes_world("tiny", "hdl32", 1),
        "v1.0-mini",
        "val",
        get_setting("nuscenes-1").observed,
    )
    assert rows[0]["frames"] == sum(len(t) for t in data.tracklets if len(t) >= 2)
