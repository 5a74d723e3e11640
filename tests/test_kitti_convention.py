"""KittiTracking(box_convention=...): both conventions against independent conversions of real
label rows (../shared/kitti-tracking-labels; skipped when absent)."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest

from envs.data import KittiTracking


def _matrices(calib_file: Path) -> tuple[np.ndarray, np.ndarray]:
    """``R0_rect`` and ``Tr_velo_to_cam`` as 4x4 matrices, parsed by hand."""
    values = {}
    for line in calib_file.read_text().splitlines():
        key, _, rest = line.partition(":")
        if rest.strip():
            values[key.strip()] = [float(v) for v in rest.split()]
    r0 = np.eye(4)
    r0[:3, :3] = np.reshape(values["R0_rect"], (3, 3))
    tr = np.eye(4)
    tr[:3, :] = np.reshape(values["Tr_velo_to_cam"], (3, 4))
    return r0, tr


def _rows(label_file: Path, category: str, n: int) -> list[list[str]]:
    rows = [line.split() for line in label_file.read_text().splitlines()]
    return [r for r in rows if r[2] == category][:n]


def _wrap(a: float) -> float:
    return (a + math.pi) % (2 * math.pi) - math.pi


def _lidar_box(row: list[str], r0: np.ndarray, tr: np.ndarray) -> np.ndarray:
    """The physically right LiDAR box: rectified camera -> LiDAR through (R0_rect Tr)^-1; centre
    the bottom centre lifted by h/2 along LiDAR +z; yaw the LiDAR image of the camera heading."""
    h, w, length, x, y, z, ry = (float(v) for v in row[10:17])
    to_velo = np.linalg.inv(r0 @ tr)
    bottom = to_velo @ np.array([x, y, z, 1.0])
    tip = to_velo @ np.array([x + math.cos(ry), y, z - math.sin(ry), 1.0])
    heading = tip[:3] - bottom[:3]
    return np.array(
        [
            bottom[0],
            bottom[1],
            bottom[2] + h / 2,
            length,
            w,
            h,
            _wrap(math.atan2(heading[1], heading[0])),
        ]
    )


def _open3dsot_box(row: list[str], tr: np.ndarray) -> np.ndarray:
    """Open3DSOT's KITTI box (datasets/kitti.py, velodyne mode): centre Tr^-1 (x, y - h/2, z),
    size (w, l, h) with the heading along l, orientation Q(-z, ry) * Q(-z, 90 deg)."""
    h, w, length, x, y, z, ry = (float(v) for v in row[10:17])
    centre = np.linalg.solve(tr, np.array([x, y - h / 2, z, 1.0]))[:3]

    def rot_minus_z(angle: float) -> np.ndarray:  # rotation by `angle` about -z
        c, s = math.cos(-angle), math.sin(-angle)
        return np.array([[c, -s, 0], [s, c, 0], [0, 0, 1]])

    heading = rot_minus_z(ry) @ rot_minus_z(math.pi / 2) @ np.array([1.0, 0.0, 0.0])
    return np.array([*centre, length, w, h, math.atan2(heading[1], heading[0])])


def _loaded(ds: KittiTracking, scene: str, row: list[str]) -> np.ndarray:
    frame, track = int(row[0]), int(row[1])
    for tr in ds.tracklets:
        if tr.scene == scene and tr.track_id == track:
            return np.asarray(tr.boxes)[list(tr.frames).index(frame)]
    raise AssertionError(f"track {track} of scene {scene} not loaded")


CASES = [("0019", "Car"), ("0016", "Pedestrian"), ("0002", "Cyclist"), ("0020", "Van")]


@pytest.fixture(scope="module")
def both(shared_labels):
    """Both conventions' loaders of every split with the four categories."""
    cats = [c for _, c in CASES]
    return (
        KittiTracking(shared_labels, "all", cats),
        KittiTracking(shared_labels, "all", cats, box_convention="open3dsot"),
    )


@pytest.mark.parametrize("scene, category", CASES)
def test_both_conventions_against_independent_conversions(shared_labels, both, scene, category):
    r0, tr = _matrices(shared_labels / "calib" / f"{scene}.txt")
    rows = _rows(shared_labels / "label_02" / f"{scene}.txt", category, 25)
    assert rows
    lidar, o3d = both
    assert lidar.box_convention == "lidar" and o3d.box_convention == "open3dsot"
    for row in rows:
        for ds, expected in ((lidar, _lidar_box(row, r0, tr)), (o3d, _open3dsot_box(row, tr))):
            got = _loaded(ds, scene, row)
            assert np.allclose(got[:6], expected[:6], atol=1e-9), (ds.box_convention, row)
            assert abs(_wrap(got[6] - expected[6])) < 1e-9, (ds.box_convention, row)
        # the conventions differ by R0_rect: centimetres to decimetres, never zero
        diff = np.linalg.norm(_loaded(lidar, scene, row)[:3] - _loaded(o3d, scene, row)[:3])
        assert 1e-4 < diff < 1.0


def test_open3dsot_yaw_is_minus_ry_minus_half_pi(shared_labels, both):
    row = _rows(shared_labels / "label_02" / "0019.txt", "Car", 1)[0]
    o3d = both[1]
    ry = float(row[16])
    assert _loaded(o3d, "0019", row)[6] == pytest.approx(_wrap(-ry - math.pi / 2), abs=1e-12)


def test_box_convention_accepts_only_its_two_values(tmp_path):
    with pytest.raises(
        ValueError, match="box_convention must be one of lidar, open3dsot; got 'camera'"
    ):
        KittiTracking(tmp_path, "all", box_convention="camera")
