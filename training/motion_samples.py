"""Motion-centric training samples (M2-Track's recipe, Open3DSOT's ``motion_processing``) and a
bridge that adds the previous frame's points to an env's observations.

One sample is ``(tracklet, frame t >= 1, candidate c)``, a pair of consecutive frames:

* **motion augmentation** (``augment=True``, the default, as Open3DSOT trains M2-Track): in each
  of the two frames independently, the points inside the ground-truth box scaled 1.25 are moved
  with the box by a random rigid transform in the box's frame: flip of x (the box turns by pi)
  and of y, each with probability 1/2, a rotation about z of ``U(-10, 10)`` degrees, a
  translation of ``U(-0.3, 0.3)`` m per axis. The other points stay, so the relative motion of
  the two boxes, and the target's shape, change.
* **reference box**: the (augmented) previous ground truth with frame 0's size (the env's
  boxes keep frame 0's size); candidate 0 as it is, candidates ``c > 0`` shifted by
  ``U(-0.3, 0.3)`` m in x and y in its own frame and turned by ``U(-5, 5)`` degrees (the
  paper's perturbation of the previous box; at test time it is the previous prediction).
* **previous_search** / **search** (``1024`` points each): the previous / current frame cropped
  around the reference box enlarged by 1.25 plus 2 m, in its frame, resampled
  (:mod:`envs.observation`'s crop and resampling, the env's code: what the env observes).
* **prior_is_gt**: 1 for candidate 0 (the reference box is the ground truth: mask 0 / 1), else 0
  (0.2 / 0.8; see :mod:`trackers.m2track`).
* **size** ``(3,)``: frame 0's ``l, w, h``.

Targets: ``seg_labels (2048,)`` points inside the augmented ground-truth box of their frame
scaled 1.25 (previous frame first); ``box (4,)`` / ``prev_box (4,)`` the current / previous
augmented ground truth ``(x, y, z, yaw)`` in the reference frame; ``motion_box (4,)`` the current
one in the previous one's frame; ``moving ()`` 1 when their centres are more than 0.15 m apart;
``box_cloud (2048, 9)`` each point's BoxCloud (distances to the centre and corners) to its
frame's augmented ground-truth box (the box-aware variant's target).

Open3DSOT skips a pair whose previous ground-truth box holds 10 points or fewer or whose current
crop holds 20 or fewer; here such a sample is replaced by another index drawn from the sample's
own generator (at most :data:`MAX_REDRAWS` times, then kept as it is), so every sample stays
deterministic in ``(seed, epoch, index)`` like :class:`training.samples.TrackingSamples`.
"""

from __future__ import annotations

import math
from collections.abc import Sequence

import numpy as np
import torch

from envs.geometry import box_to_world, boxes_in_frame, offset_between, points_in_box, world_to_box
from envs.observation import SEARCH_OFFSET_M, SEARCH_SCALE, SEARCH_SIZE, resample_into
from trackers.m2track import box_cloud
from training.samples import FrameCandidateSamples, crop_near

__all__ = ["BATCH_KEYS", "TARGET_KEYS", "MotionSamples", "RedrawnSamples", "augment_frame"]

BATCH_KEYS = ("search", "previous_search", "size", "prior_is_gt")
TARGET_KEYS = ("seg_labels", "box", "prev_box", "motion_box", "moving", "box_cloud")

REF_SHIFT_M = 0.3
REF_TURN_RAD = math.radians(5.0)
AUG_SHIFT_M = 0.3
AUG_TURN_RAD = math.radians(10.0)
AUG_SCALE = 1.25  # the augmented points: inside the ground-truth box scaled by this
LABEL_SCALE = 1.25  # target points: inside the ground-truth box scaled by this
MOTION_THRESHOLD_M = 0.15
MIN_PREVIOUS_TARGET_POINTS = 10
MIN_SEARCH_POINTS = 20
MAX_REDRAWS = 10


def _wrap(yaw: float) -> float:
    return (yaw + math.pi) % (2 * math.pi) - math.pi


def augment_frame(
    points: np.ndarray, box: np.ndarray, rng: np.random.Generator
) -> tuple[np.ndarray, np.ndarray]:
    """Open3DSOT's motion augmentation of one frame: the points ``(N, 3)`` inside ``box`` ``(7,)``
    scaled 1.25 and the box moved by one random rigid transform in the box's frame (flip x / y,
    rotation ``U(-10, 10)`` deg, translation ``U(-0.3, 0.3)`` m) -> (points ``(N, 3)``, box
    ``(7,)``); the other points are unchanged."""
    shift = rng.uniform(-AUG_SHIFT_M, AUG_SHIFT_M, 3)
    turn = rng.uniform(-AUG_TURN_RAD, AUG_TURN_RAD)
    flip_x, flip_y = rng.random(2) < 0.5
    inside = points_in_box(points, box, AUG_SCALE)
    local = world_to_box(points[inside], box).astype(np.float64)
    if flip_x:
        local[:, 0] = -local[:, 0]
    if flip_y:
        local[:, 1] = -local[:, 1]
    c, s = math.cos(turn), math.sin(turn)
    rotated = local.copy()
    rotated[:, 0] = c * local[:, 0] - s * local[:, 1]
    rotated[:, 1] = s * local[:, 0] + c * local[:, 1]
    rotated += shift
    # the box in its own frame: turned by pi when x flips (its heading follows the points)
    yaw_local = (math.pi if flip_x else 0.0) + turn
    new_box = np.asarray(box, dtype=np.float64).copy()
    new_box[:3] = box_to_world(shift[None, :], box)[0]
    new_box[6] = _wrap(float(box[6]) + yaw_local)
    out = np.array(points, dtype=points.dtype, copy=True)
    out[inside, :3] = box_to_world(rotated, box).astype(points.dtype)
    return out, new_box


def _reach_m(box: np.ndarray) -> float:
    return math.hypot(
        0.5 * SEARCH_SCALE * box[3] + SEARCH_OFFSET_M, 0.5 * SEARCH_SCALE * box[4] + SEARCH_OFFSET_M
    )


def _near(points: np.ndarray, centre: np.ndarray, r: float) -> np.ndarray:
    keep = (np.abs(points[:, 0] - centre[0]) <= r) & (np.abs(points[:, 1] - centre[1]) <= r)
    return points[keep]


def _box4(box: np.ndarray) -> np.ndarray:
    return np.array([box[0], box[1], box[2], box[6]], dtype=np.float32)


class RedrawnSamples(FrameCandidateSamples):
    """Samples that a subclass's ``_build(index, rng, last)`` may refuse (``None``): the index is
    then replaced by another one drawn from the sample's own generator, at most
    :data:`MAX_REDRAWS` times (the last attempt must return a sample), so every sample stays
    deterministic in ``(seed, epoch, index)``."""

    def __getitem__(self, index: int) -> dict[str, torch.Tensor]:
        rng = np.random.default_rng([self.seed, self.epoch, int(index)])
        source = int(index)
        for attempt in range(MAX_REDRAWS + 1):
            sample = self._build(source, rng, last=attempt == MAX_REDRAWS)
            if sample is not None:
                sample["index"] = torch.tensor(int(index), dtype=torch.int64)
                return sample
            source = int(rng.integers(len(self)))
        raise AssertionError("unreachable: the last attempt always returns a sample")

    def _build(
        self, index: int, rng: np.random.Generator, last: bool
    ) -> dict[str, torch.Tensor] | None:  # pragma: no cover - abstract
        raise NotImplementedError


class MotionSamples(RedrawnSamples):
    """A ``Dataset`` of M2-Track training samples (see the module docstring).

    Args:
        tracklets: the tracklets to sample from (already restricted to the trained categories).
        candidates_per_frame: samples per frame (candidate 0: the unperturbed previous box).
        seed: base seed; with the epoch and the index it determines every random draw.
        augment: the motion augmentation (on in the paper's training).
        search_size: points per frame (1024, the env's search size).
    """

    batch_keys = BATCH_KEYS
    target_keys = TARGET_KEYS

    def __init__(
        self,
        tracklets: Sequence,
        *,
        candidates_per_frame: int = 4,
        seed: int = 0,
        augment: bool = True,
        search_size: int = SEARCH_SIZE,
    ) -> None:
        self._set_tracklets(tracklets, candidates_per_frame, seed)
        if search_size < 1:
            raise ValueError(f"search_size must be >= 1, got {search_size}")
        self.augment = bool(augment)
        self.search_size = int(search_size)
        self._index_frames(1)

    def _build(
        self, index: int, rng: np.random.Generator, last: bool
    ) -> dict[str, torch.Tensor] | None:
        k, t, cand = self.locate(index)
        tr = self.tracklets[k]
        boxes = np.asarray(tr.boxes, dtype=np.float64)
        prev_gt, gt, size0 = boxes[t - 1].copy(), boxes[t].copy(), boxes[0][3:6]
        prev_pts, cur_pts = tr.points(t - 1), tr.points(t)
        if (
            not last
            and int(points_in_box(_near(prev_pts, prev_gt, _reach_m(prev_gt)), prev_gt).sum())
            <= MIN_PREVIOUS_TARGET_POINTS
        ):
            return None
        # only points that can reach the crop (or the augmented boxes) are transformed
        r = _reach_m(np.r_[prev_gt[:3], size0, prev_gt[6]]) + REF_SHIFT_M + 1.0
        prev_pts = _near(prev_pts, prev_gt, r + np.hypot(*prev_gt[3:5]))
        cur_pts = _near(
            cur_pts, prev_gt, r + np.hypot(*(gt[:2] - prev_gt[:2])) + np.hypot(*gt[3:5])
        )
        if self.augment:
            prev_pts, prev_gt = augment_frame(prev_pts, prev_gt, rng)
            cur_pts, gt = augment_frame(cur_pts, gt, rng)
        ref = np.r_[prev_gt[:3], size0, prev_gt[6]]
        if cand > 0:
            shift = rng.uniform(-REF_SHIFT_M, REF_SHIFT_M, 2)
            ref[:2] = box_to_world(np.array([[shift[0], shift[1], 0.0]]), ref)[0, :2]
            ref[6] = _wrap(ref[6] + rng.uniform(-REF_TURN_RAD, REF_TURN_RAD))
        prev_crop = crop_near(prev_pts, ref, SEARCH_SCALE, SEARCH_OFFSET_M)
        cur_crop = crop_near(cur_pts, ref, SEARCH_SCALE, SEARCH_OFFSET_M)
        if not last and len(cur_crop) <= MIN_SEARCH_POINTS:
            return None
        previous = np.empty((self.search_size, 3), np.float32)
        search = np.empty((self.search_size, 3), np.float32)
        m_p, m_c = resample_into([prev_crop, cur_crop], [previous, search], rng)
        prev_box = boxes_in_frame(prev_gt, ref)
        box = boxes_in_frame(gt, ref)
        labels = np.concatenate(
            [
                points_in_box(previous, prev_box, LABEL_SCALE) & (m_p > 0),
                points_in_box(search, box, LABEL_SCALE) & (m_c > 0),
            ]
        )
        moving = float(np.linalg.norm(gt[:3] - prev_gt[:3]) > MOTION_THRESHOLD_M)
        points = torch.from_numpy(np.stack([previous, search]))
        boxes = torch.from_numpy(np.stack([_box4(prev_box), _box4(box)]))
        sizes = torch.tensor(np.stack([prev_gt[3:6], gt[3:6]]), dtype=torch.float32)
        distances = box_cloud(points, boxes, sizes).reshape(-1, 9)
        f32 = torch.float32
        return {
            "search": torch.from_numpy(search),
            "previous_search": torch.from_numpy(previous),
            "size": torch.as_tensor(size0, dtype=f32),
            "prior_is_gt": torch.tensor(1.0 if cand == 0 else 0.0),
            "seg_labels": torch.from_numpy(labels.astype(np.float32)),
            "box": torch.from_numpy(_box4(box)),
            "prev_box": torch.from_numpy(_box4(prev_box)),
            "motion_box": torch.as_tensor(offset_between(prev_gt, gt), dtype=f32),
            "moving": torch.tensor(moving),
            "box_cloud": distances,
        }
