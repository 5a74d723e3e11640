"""Multi-frame training samples for memory-network trackers (MBPTrack: Xu et al., "MBPTrack:
Improving 3D Point Cloud Tracking with Memory Networks and Box Priors", ICCV 2023).

One sample is ``(tracklet, frame t >= 1, candidate c)``: the current frame ``t`` and the memory
of the :data:`TRAIN_MEMORY_FRAMES` frames before it (the reference trains with a memory of 2),
built by the env's own memory code (:class:`envs.memory.FrameMemory`), so what a tracker trains
on is what the env serves:

* **the agent's boxes**, simulated: each frame's box is its ground truth with frame 0's size,
  moved by ``U(-0.3, 0.3)`` m along each of its axes and turned by ``U(-5, 5)`` degrees (the
  reference's sample augmentation of the previous box), except frame 0's, which is the given box
  (exact, as in every episode);
* **memory** ``(M, 1024, 4)`` / **memory_boxes** ``(M, 5)``: each memory frame's search region
  (cropped around the agent's box for the frame before it, or frame 0 around the given box), with
  the target mask of the agent's box for the frame; frames before 0 leave empty slots, as at an
  episode's start;
* **reference box**: the agent's box for frame ``t - 1`` (the env's default: the last
  prediction); **search** ``(1024, 3)``: frame ``t`` cropped around it, in its frame; **size**
  ``(3,)``: frame 0's ``l, w, h``.

Targets: ``search_labels (1024,)`` search points inside frame ``t``'s ground-truth box scaled
1.25; ``box (4,)`` that box's ``x, y, z, yaw`` in the reference frame.

Candidate 0 of a frame leaves the agent's box for frame ``t - 1`` unperturbed (the reference box
is the previous ground truth). A sample whose search crop holds fewer than :data:`MIN_SEARCH_POINTS`
points is replaced by another index drawn from its own generator
(:class:`training.motion_samples.RedrawnSamples`; the reference redraws such samples), so
samples stay deterministic in ``(seed, epoch, index)``. Not here: the reference's
time reversal and non-consecutive frames (its ``max_frame_dis`` is 1, so frames are nearly
consecutive there too).
"""

from __future__ import annotations

import math
from collections.abc import Sequence

import numpy as np
import torch

from envs.geometry import box_to_world, boxes_in_frame, points_in_box
from envs.memory import FrameMemory
from envs.observation import resample_into
from envs.spec import SEARCH_OFFSET_M, SEARCH_SCALE, SEARCH_SIZE, check_memory_frames
from training.motion_samples import RedrawnSamples
from training.samples import crop_near

__all__ = ["BATCH_KEYS", "TARGET_KEYS", "TRAIN_MEMORY_FRAMES", "MemorySamples"]

BATCH_KEYS = ("search", "size", "memory", "memory_boxes")
TARGET_KEYS = ("search_labels", "box")
TRAIN_MEMORY_FRAMES = 2
BOX_SHIFT_M = 0.3
BOX_TURN_RAD = math.radians(5.0)
LABEL_SCALE = 1.25
MIN_SEARCH_POINTS = 5


def _agent_box(gt: np.ndarray, size: np.ndarray, rng: np.random.Generator) -> np.ndarray:
    """``gt (7,)`` with ``size (3,)``, moved by ``U(-0.3, 0.3)`` m per axis in its own frame and
    turned by ``U(-5, 5)`` degrees: a simulated prediction ``(7,)``."""
    box = np.r_[gt[:3], size, gt[6]].astype(np.float64)
    shift = rng.uniform(-BOX_SHIFT_M, BOX_SHIFT_M, 3)
    box[:3] = box_to_world(shift[None, :], box)[0]
    box[6] = (box[6] + rng.uniform(-BOX_TURN_RAD, BOX_TURN_RAD) + math.pi) % (2 * math.pi) - math.pi
    return box


class MemorySamples(RedrawnSamples):
    """A ``Dataset`` of memory-tracker training samples (see the module docstring).

    Args:
        tracklets: the tracklets to sample from (already restricted to the trained categories).
        candidates_per_frame: samples per frame (candidate 0: the newest memory box unperturbed).
        seed: base seed; with the epoch and the index it determines every random draw.
        memory_frames: memory slots per sample (the reference trains with 2).
        search_enlargement: ``(scale, offset_m)`` of the search and memory crops.
    """

    batch_keys = BATCH_KEYS
    target_keys = TARGET_KEYS

    def __init__(
        self,
        tracklets: Sequence,
        *,
        candidates_per_frame: int = 4,
        seed: int = 0,
        memory_frames: int = TRAIN_MEMORY_FRAMES,
        search_enlargement: tuple[float, float] = (SEARCH_SCALE, SEARCH_OFFSET_M),
    ) -> None:
        self._set_tracklets(tracklets, candidates_per_frame, seed)
        self.memory_frames = check_memory_frames(memory_frames)
        self.search_enlargement = (float(search_enlargement[0]), float(search_enlargement[1]))
        self._index_frames(1)

    def _build(
        self, index: int, rng: np.random.Generator, last: bool
    ) -> dict[str, torch.Tensor] | None:
        k, t, cand = self.locate(index)
        tr = self.tracklets[k]
        boxes = np.asarray(tr.boxes, dtype=np.float64)
        size = boxes[0, 3:6]
        scale, offset_m = self.search_enlargement
        memory = FrameMemory(self.memory_frames)
        agent = {}  # frame -> the simulated agent's box for it
        for f in range(max(0, t - self.memory_frames - 1), t):
            exact = f == 0 or (f == t - 1 and cand == 0)
            gt = np.r_[boxes[f, :3], size, boxes[f, 6]]
            agent[f] = gt if exact else _agent_box(boxes[f], size, rng)
        for f in range(max(0, t - self.memory_frames), t):
            crop_box = agent[max(f - 1, 0)]  # frame f's search region, or frame 0's given box
            xyz = np.empty((SEARCH_SIZE, 3), np.float32)
            (count,) = resample_into(
                [crop_near(tr.points(f), crop_box, scale, offset_m)], [xyz], rng
            )
            memory.add(xyz, count, crop_box, agent[f])
        ref = agent[t - 1]
        crop = crop_near(tr.points(t), ref, scale, offset_m)
        if not last and len(crop) < MIN_SEARCH_POINTS:
            return None
        search = np.empty((SEARCH_SIZE, 3), np.float32)
        (count,) = resample_into([crop], [search], rng)
        gt = boxes_in_frame(boxes[t], ref)
        labels = points_in_box(search, gt, LABEL_SCALE) & (count > 0)
        observed = memory.observe(ref)
        return {
            "search": torch.from_numpy(search),
            "size": torch.as_tensor(size, dtype=torch.float32),
            "memory": torch.from_numpy(observed["memory"]),
            "memory_boxes": torch.from_numpy(observed["memory_boxes"]),
            "search_labels": torch.from_numpy(labels.astype(np.float32)),
            "box": torch.tensor([gt[0], gt[1], gt[2], gt[6]], dtype=torch.float32),
        }
