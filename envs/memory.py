"""The env's memory of past frames: the opt-in observation keys ``memory`` and ``memory_boxes``
(the input of memory-network trackers such as MBPTrack: Xu et al., "MBPTrack: Improving 3D Point
Cloud Tracking with Memory Networks and Box Priors", ICCV 2023).

The memory lives in the observation, not in a tracker's hidden state, so a policy stays a
function of its observation (docs/design.md). At frame ``t`` it holds the last ``M`` frames
``t - M .. t - 1`` of the episode (fewer at its start), as MBPTrack's memory does: each frame's
search region as the agent saw it, with the target mask of the box the agent then predicted:

* ``memory (M, N, 4)`` float32 (columns :data:`envs.spec.MEMORY_CHANNELS`): frame ``k``'s
  ``search`` observation (the same points, bit for bit, in the frame of the box it was cropped
  around: the agent's box for frame ``k - 1``), with a target-mask column: 1 inside the agent's
  box for frame ``k`` scaled 1.25 (the template crop's scale), else 0. The episode's first
  frame, which has no search region, is cropped around the given box like one (and resampled
  once) with its mask;
* ``memory_boxes (M, 5)`` float32 (columns :data:`envs.spec.MEMORY_BOX_CHANNELS`): the crop
  boxes ``x, y, z, yaw`` in the current reference-box frame (m, rad, yaw wrapped to
  ``[-pi, pi)``), and 1 where the slot holds a frame with points (0: an empty slot, or an empty
  crop).

Because a frame's memory points are its search points, a tracker can reuse what it computed on
a search region when the frame comes back as memory (MBPTrack caches its backbone seeds so).

Slots run oldest to newest and are right-aligned: the newest frame is always slot ``M - 1``;
empty slots (all zeros) come first. ``M`` is the env's ``memory_frames`` (1 to
:data:`envs.spec.MAX_MEMORY_FRAMES`). The keys, shapes and option live in :mod:`envs.spec`, the
spaces in :func:`envs.observation.observation_space`.
"""

from __future__ import annotations

import math
from collections import deque

import numpy as np

from envs.geometry import boxes_in_frame, points_in_box
from envs.observation import POINT_BOUND_M, resample_into
from envs.spec import SEARCH_SIZE, TEMPLATE_SCALE, check_memory_frames

__all__ = ["FrameMemory"]


class FrameMemory:
    """The last ``frames`` frames' crops and boxes of one episode (see the module doc)."""

    def __init__(self, frames: int) -> None:
        self.frames = check_memory_frames(frames)
        self._slots: deque[tuple[np.ndarray, np.ndarray, bool]] = deque(maxlen=self.frames)
        # the last search region served, (points, count, crop box): the next step's newest frame
        self._search: tuple[np.ndarray, int, np.ndarray] | None = None

    def clear(self) -> None:
        """Forget every frame (a new episode)."""
        self._slots.clear()
        self._search = None

    def add(self, xyz: np.ndarray, count: int, crop_box: np.ndarray, agent_box: np.ndarray) -> None:
        """Add the newest frame: its resampled points ``xyz (N, 3)`` (``count`` distinct ones
        before resampling; 0: an empty crop, zeros) in the frame of ``crop_box (7,)``, the box
        the crop was taken around, and the agent's box for that frame ``agent_box (7,)`` (world,
        float64), which the target mask is taken from."""
        points = np.zeros((len(xyz), 4), np.float32)
        if count:
            inner = boxes_in_frame(np.asarray(agent_box, np.float64), np.asarray(crop_box))
            points[:, :3] = np.clip(xyz, -POINT_BOUND_M, POINT_BOUND_M)
            points[:, 3] = points_in_box(xyz, inner, TEMPLATE_SCALE)
        self._slots.append((points, np.array(crop_box, dtype=np.float64), count > 0))

    def add_crop(self, crop: np.ndarray, box: np.ndarray, rng: np.random.Generator) -> None:
        """Add the episode's first frame: its crop ``(K, 3)`` (m) around the given box ``box
        (7,)``, which is also the agent's box for it, resampled to ``SEARCH_SIZE`` points with
        ``rng``."""
        xyz = np.empty((SEARCH_SIZE, 3), np.float32)
        (count,) = resample_into([crop], [xyz], rng)
        self.add(xyz, count, box, box)

    def step(
        self, agent_box: np.ndarray, search: np.ndarray, count: int, ref: np.ndarray
    ) -> dict[str, np.ndarray]:
        """One env step: add the search region served at the previous step (if any) with the
        agent's box for its frame ``agent_box (7,)``, keep this step's ``search (N, 3)``
        (``count`` distinct points, cropped around ``ref (7,)``) for the next step, and return
        :meth:`observe` of ``ref``."""
        if self._search is not None:
            self.add(*self._search, agent_box)
        # a copy: the caller owns ``search`` and may write to it
        self._search = (search.copy(), count, np.array(ref, dtype=np.float64))
        return self.observe(ref)

    def observe(self, ref: np.ndarray) -> dict[str, np.ndarray]:
        """The ``memory`` and ``memory_boxes`` arrays (fresh) for the reference box ``ref``."""
        memory = np.zeros((self.frames, SEARCH_SIZE, 4), np.float32)
        boxes = np.zeros((self.frames, 5), np.float32)
        first = self.frames - len(self._slots)
        for slot, (points, box, valid) in enumerate(self._slots, start=first):
            local = boxes_in_frame(box, np.asarray(ref, dtype=np.float64))
            memory[slot] = points
            boxes[slot, :3] = np.clip(local[:3], -POINT_BOUND_M, POINT_BOUND_M)
            boxes[slot, 3] = local[6]
            boxes[slot, 4] = float(valid)
        np.clip(boxes[:, 3], -math.pi, math.pi, out=boxes[:, 3])  # float32 rounding of pi
        return {"memory": memory, "memory_boxes": boxes}
