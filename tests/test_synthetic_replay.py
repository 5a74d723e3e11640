"""Label-driven replay of the real KITTI tracking labels (skips without ../shared)."""

from __future__ import annotations

from collections import defaultdict

import numpy as np
import pytest

from envs.data import KittiTracking
from envs.geometry import points_in_box
from envs.synthetic import generate_world

# Published test split (scenes 19-20) frame / tracklet counts (P2B, BAT, Open3DSOT).
PUBLISHED_TEST = {
    "Car": (6424, 120),
    "Pedestrian": (6088, 62),
    "Van": (1248, 16),
    "Cyclist": (308, 8),
}


@pytest.fixture(scope="module")
def replayed(tmp_path_factory, shared_labels):
    # Scans only for the first two frames of each scene keep this fast; labels are complete.
    out = tmp_path_factory.mktemp("replay") / "world"
    return generate_world(out, "default", "hdl64", 0, shared_labels, scan_frames=2, scenes=(19, 20))


def test_replay_writes_the_source_labels_row_for_row(replayed, shared_labels):
    for scene in ("0019", "0020"):
        src = (shared_labels / "label_02" / f"{scene}.txt").read_text().splitlines()
        out = (replayed / "label_02" / f"{scene}.txt").read_text().splitlines()
        assert out == [line for line in src if line.strip()]


def test_replay_gives_the_published_test_split_counts(replayed):
    ds = KittiTracking(replayed, "test")
    frames = defaultdict(int)
    tracks = defaultdict(int)
    for tr in ds.tracklets:
        frames[tr.category] += len(tr)
        tracks[tr.category] += 1
    for cat, (n_frames, n_tracks) in PUBLISHED_TEST.items():
        assert (frames[cat], tracks[cat]) == (n_frames, n_tracks), cat


def test_replayed_objects_are_in_the_scans(replayed):
    ds = KittiTracking(replayed, "test", categories=("Car", "Pedestrian", "Van", "Cyclist"))
    near, with_points = 0, 0
    for tr in ds.tracklets:
        for t in np.flatnonzero(tr.frames < 2):
            box = tr.boxes[t]
            if np.hypot(box[0], box[1]) < 30.0:
                near += 1
                with_points += int(points_in_box(tr.points(t), box).sum() > 0)
    assert near >= 5
    # Labels include objects hidden behind others; most near ones must still be hit.
    assert with_points >= 0.7 * near
