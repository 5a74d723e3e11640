"""The nuScenes reader's ``"scene"`` frame (ego motion removed): boxes and points against 4x4
matrices on the hand-built tables, consistency with the ``"lidar"`` frame on a synthetic world,
the weather on scene-frame data (applied in each scan's own LiDAR frame), and the refusals of
the frame on other datasets."""

from __future__ import annotations

import numpy as np
import pytest
from test_nuscenes import (
    CALIB,
    EGO,
    INSTANCES,
    VERSION,
    axis_angle_matrix,
    homogeneous,
    write_tables,
)

from envs.data import NuScenesTracking
from envs.data.nuscenes import NuScenesScans
from envs.data.nuscenes_poses import lidar_to_global, lidar_to_reference


def pose(frame: int) -> np.ndarray:
    """LiDAR -> global of a hand-built key frame, ``T_ego T_cs``."""
    t_ego = homogeneous(axis_angle_matrix(EGO[frame][0], EGO[frame][1]), EGO[frame][2])
    return t_ego @ homogeneous(axis_angle_matrix(CALIB[0], CALIB[1]), CALIB[2])


def test_scene_frame_boxes_and_points_exact(tmp_path):
    write_tables(tmp_path)
    lidar = NuScenesTracking(tmp_path, VERSION, "val")
    scene = NuScenesTracking(tmp_path, VERSION, "val", frame="scene")
    assert scene.frame == "scene" and "frame='scene'" in repr(scene)
    to_first = np.linalg.inv(pose(0))
    for tr, tr_lidar, (_, size, frames) in zip(
        scene.tracklets, lidar.tracklets, INSTANCES, strict=False
    ):
        for t, k in enumerate(tr.frames):
            axis, angle, centre = frames[int(k)]
            m = to_first @ homogeneous(axis_angle_matrix(axis, angle), centre)
            np.testing.assert_allclose(tr.boxes[t, :3], m[:3, 3], atol=1e-9)
            np.testing.assert_allclose(tr.boxes[t, 3:6], [size[1], size[0], size[2]])
            dyaw = (tr.boxes[t, 6] - np.arctan2(m[1, 0], m[0, 0]) + np.pi) % (2 * np.pi) - np.pi
            assert abs(dyaw) < 1e-9
            # The scan: each point of key frame k mapped into frame 0 (float32 storage).
            own = tr_lidar.points(t).astype(np.float64)
            want = (to_first @ pose(int(k)) @ np.c_[own, np.ones(len(own))].T).T[:, :3]
            np.testing.assert_allclose(tr.points(t), want, atol=1e-4)
            np.testing.assert_array_equal(
                tr.points_with_intensity(t)[:, 3], tr_lidar.points_with_intensity(t)[:, 3]
            )
        # Key frame 0 is the reference: both frames agree there.
        np.testing.assert_allclose(tr.boxes[0], tr_lidar.boxes[0], atol=1e-9)


def test_lidar_to_reference_identity_and_composition():
    rng = np.random.default_rng(0)
    q = rng.normal(size=(4, 4))
    ego_t, cs_t = rng.normal(size=(4, 3)) * 100, rng.normal(size=(4, 3))
    cs_q = rng.normal(size=(4, 4))
    maps = lidar_to_reference(ego_t, q, cs_t, cs_q, reference=2)
    np.testing.assert_allclose(maps[2], np.c_[np.eye(3), np.zeros(3)], atol=1e-9)
    rotation, translation = lidar_to_global(ego_t, q, cs_t, cs_q)
    p = rng.normal(size=3) * 10
    for k, m in enumerate(maps):  # frame k -> global -> frame 2, as one rigid map
        np.testing.assert_allclose(m[:, :3] @ m[:, :3].T, np.eye(3), atol=1e-12)
        want = rotation[2].T @ (rotation[k] @ p + translation[k] - translation[2])
        np.testing.assert_allclose(m[:, :3] @ p + m[:, 3], want, atol=1e-9)


def test_frame_refusals(tmp_path):
    from envs.tracking_env import make_tracking_env
    from training.config import ConfigError, TrainConfig
    from training.samples import load_tracklets

    write_tables(tmp_path)
    with pytest.raises(ValueError, match="frame 'global' is not one of"):
        NuScenesTracking(tmp_path, VERSION, "val", frame="global")
    with pytest.raises(ValueError, match=r"to_reference has shape \(2, 3, 4\), expected \(3"):
        NuScenesScans(tmp_path, "s", ["a", "b", "c"], np.zeros((2, 3, 4)))
    with pytest.raises(ValueError, match="applies to the nuscenes source"):
        make_tracking_env("kitti", root=tmp_path, frame="scene")
    with pytest.raises(ValueError, match="dataset nuscenes only"):
        load_tracklets("synthetic", "train", setting="kitti-1", nuscenes_frame="scene")
    with pytest.raises(ConfigError, match="nuscenes_frame='scene': applies to dataset=nuscenes"):
        TrainConfig(nuscenes_frame="scene").validate()
    with pytest.raises(ConfigError, match="nuscenes_frame='up'"):
        TrainConfig(dataset="nuscenes", setting="nuscenes-1", nuscenes_frame="up").validate()


def _near_sensor(points, tracklet_id, frame):
    """A range-dependent scan transform, as the weather is: the points within 30 m of the sensor
    (the origin), and one point 1 m ahead of it."""
    kept = points[np.linalg.norm(points[:, :3], axis=1) < 30.0]
    return np.r_[kept, [[1.0, 0.0, 0.0, 0.5]]].astype(np.float32)


def test_a_scan_transform_on_scene_frame_data_acts_in_each_scans_lidar_frame(tmp_path):
    """The weather on nuScenes' scene frame: each scan is transformed in its own LiDAR frame,
    where the sensor sits at the origin, then mapped into the scene frame (docs/nuscenes.md)."""
    from envs.scan_cache import TrackletScans
    from envs.tracking_env import make_tracking_env

    write_tables(tmp_path)
    lidar = NuScenesTracking(tmp_path, VERSION, "val")
    scene = NuScenesTracking(tmp_path, VERSION, "val", frame="scene")
    to_first = np.linalg.inv(pose(0))
    for tr, tr_lidar in zip(scene.tracklets, lidar.tracklets, strict=True):
        assert tr_lidar.sensor_poses is None and tr.sensor_poses.shape == (len(tr), 3, 4)
        served = TrackletScans(tr, _near_sensor, None, 1.0)
        own = TrackletScans(tr_lidar, _near_sensor, None, 1.0)
        for t, k in enumerate(tr.frames):
            want = own.scan(t).astype(np.float64)
            want[:, :3] = (to_first @ pose(int(k)) @ np.c_[want[:, :3], np.ones(len(want))].T).T[
                :, :3
            ]
            got = served.scan(t)
            assert got.dtype == np.float32 and got.shape == want.shape
            np.testing.assert_allclose(got, want, atol=1e-4)
            # the added point sits 1 m ahead of this key frame's sensor, not of the first's
            sensor = (to_first @ pose(int(k)))[:3]
            np.testing.assert_allclose(got[-1, :3], sensor @ [1.0, 0.0, 0.0, 1.0], atol=1e-4)
    make_tracking_env(scene).set_scan_transform(_near_sensor)  # accepted, as in the LiDAR frame


def test_scene_frame_on_synthetic_world_keeps_points_in_boxes(world_nus):
    """Same tracklets in both frames; each box holds the same points of its scan."""
    from envs.geometry import points_in_box

    lidar = NuScenesTracking(world_nus, "v1.0-mini", "all")
    scene = NuScenesTracking(world_nus, "v1.0-mini", "all", frame="scene")
    assert [t.tracklet_id for t in lidar.tracklets] == [t.tracklet_id for t in scene.tracklets]
    moved = 0.0
    for a, b in list(zip(lidar.tracklets, scene.tracklets, strict=True))[:12]:
        for t in range(min(len(a), 4)):
            n_a = points_in_box(a.points(t), a.boxes[t]).sum()
            n_b = points_in_box(b.points(t), b.boxes[t]).sum()
            assert abs(int(n_a) - int(n_b)) <= 1, (a.tracklet_id, t, n_a, n_b)
        moved = max(moved, float(np.abs(a.boxes[1:, :2] - b.boxes[1:, :2]).max(initial=0)))
    assert moved > 1.0  # the ego moves: the frames differ after key frame 0


@pytest.fixture(scope="module")
def world_nus(tmp_path_factory):
    from envs.synthetic.nuscenes_layout import generate_nuscenes_world

    return generate_nuscenes_world(tmp_path_factory.mktemp("nus") / "w", "tiny", progress=False)


def test_a_training_run_records_its_nuscenes_frame():
    from training.config import TrainConfig
    from training.provenance import train_provenance

    config = TrainConfig(dataset="nuscenes", setting="nuscenes-1", nuscenes_frame="scene")
    record = train_provenance(config.to_dict(), None, 2, commit="abc")
    assert record.nuscenes_frame == "scene"
    assert train_provenance({"dataset": "synthetic"}, None, 1, commit="abc").nuscenes_frame == (
        "lidar"
    )


def test_the_train_cli_passes_the_frame_and_refuses_it_off_nuscenes():
    import argparse

    from training.commands.train import add_arguments, build_config
    from training.config import ConfigError

    parser = argparse.ArgumentParser()
    add_arguments(parser)
    nus = ["--dataset", "nuscenes", "--setting", "nuscenes-1", "--nuscenes-frame", "scene"]
    assert build_config(parser.parse_args(nus)).nuscenes_frame == "scene"
    with pytest.raises(ConfigError, match="nuscenes_frame='scene': applies to dataset=nuscenes"):
        build_config(parser.parse_args(["--nuscenes-frame", "scene"]))
