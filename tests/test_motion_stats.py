"""envs.data.motion: ego-relative motion statistics of KITTI-layout label files."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from envs.data.kitti import write_labels
from envs.data.motion import compare, label_motion, track_samples, wasserstein_1


def _row(frame: int, track: int, kind: str, x: float, z: float, ry: float) -> list:
    return [frame, track, kind, 0, 0, 0.0, 0, 0, 10, 10, 1.5, 1.6, 4.0, x, 1.0, z, ry]


def test_track_samples_by_hand() -> None:
    frames = np.array([0, 1, 2, 4, 5])
    xz = np.array([[0.0, 0.0], [0.3, 0.4], [0.9, 1.2], [5.0, 5.0], [5.0, 5.0]])
    yaw = np.array([3.1, -3.1, -3.0, 0.0, 0.5])
    disp, accel, yaw_rate = track_samples(frames, xz, yaw)
    # pairs (0,1), (1,2), (4,5); (2,4) skips a frame
    np.testing.assert_allclose(disp, [0.5, 1.0, 0.0])
    # one triple (0,1,2): second difference (0.3, 0.4) -> 0.5 m / 0.01 s^2
    np.testing.assert_allclose(accel, [50.0])
    # 3.1 -> -3.1 wraps to +0.0832 rad
    np.testing.assert_allclose(yaw_rate, [(2 * np.pi - 6.2) / 0.1, 1.0, 5.0], rtol=1e-9)


def test_label_motion_pools_tracks_per_category(tmp_path: Path) -> None:
    rows = [_row(t, 0, "Car", 1.0 * t, 10.0, 0.0) for t in range(4)]
    rows += [_row(t, 1, "Pedestrian", 2.0, 0.1 * t, 0.0) for t in range(3)]
    rows += [_row(0, -1, "DontCare", -1, -1, -10)]
    path = tmp_path / "0000.txt"
    write_labels(path, rows)
    motion = label_motion([path])
    np.testing.assert_allclose(motion["Car"].displacement_m, [1.0, 1.0, 1.0])
    np.testing.assert_allclose(motion["Pedestrian"].displacement_m, [0.1, 0.1], rtol=1e-6)
    assert motion["Car"].tracks == 1 and motion["Van"].tracks == 0
    assert motion["Car"].still_share() == 0.0
    summary = motion["Car"].summary()
    assert summary["displacement_m_median"] == pytest.approx(1.0)
    rows_cmp = compare(motion, motion)
    assert all(r.get("w1", 0.0) == 0.0 for r in rows_cmp if r["category"] == "Car")


def test_wasserstein_of_a_shift() -> None:
    a = np.random.default_rng(0).normal(size=5000)
    assert wasserstein_1(a, a + 0.5) == pytest.approx(0.5, abs=1e-9)
    assert np.isnan(wasserstein_1(a, np.zeros(0)))


def test_real_kitti_displacement_as_measured(shared_labels: Path) -> None:
    """All 21 real label files: the issue's measured Car / Pedestrian medians and p90s."""
    motion = label_motion(sorted((shared_labels / "label_02").glob("*.txt")))
    car, ped = motion["Car"].summary(), motion["Pedestrian"].summary()
    assert car["displacement_m_median"] == pytest.approx(0.71, abs=0.005)
    assert car["displacement_m_p90"] == pytest.approx(1.36, abs=0.005)
    assert ped["displacement_m_median"] == pytest.approx(0.15, abs=0.01)
    assert ped["displacement_m_p90"] == pytest.approx(0.62, abs=0.01)
