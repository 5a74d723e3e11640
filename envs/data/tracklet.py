"""The tracklet data model: one target instance over consecutive frames."""

from __future__ import annotations

from collections import OrderedDict
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field

import numpy as np

ScanLoader = Callable[[int], np.ndarray]
"""Loads the whole scan of one frame of a scene: frame index -> ``(N, 4)`` float32 (x, y, z,
intensity) in that frame's LiDAR frame. Must be picklable (a module-level callable or a small
object), so environments stay cheap to send to subprocesses."""


class ScanCache:
    """A small LRU cache of whole scans, keyed by frame index, shared by a scene's tracklets."""

    def __init__(self, loader: ScanLoader, capacity: int = 8) -> None:
        self.loader = loader
        self.capacity = capacity
        self._scans: OrderedDict[int, np.ndarray] = OrderedDict()

    def __call__(self, frame: int) -> np.ndarray:
        scan = self._scans.get(frame)
        if scan is None:
            scan = self.loader(frame)
            self._scans[frame] = scan
            if len(self._scans) > self.capacity:
                self._scans.popitem(last=False)
        else:
            self._scans.move_to_end(frame)
        return scan

    def __getstate__(self) -> dict:
        return {"loader": self.loader, "capacity": self.capacity}

    def __setstate__(self, state: dict) -> None:
        self.__init__(state["loader"], state["capacity"])


@dataclass(eq=False)
class Tracklet:
    """One target over consecutive frames of one scene.

    Attributes:
        tracklet_id: unique name, ``"<scene>/<track_id>"``.
        scene: scene (sequence) name, e.g. ``"0019"``.
        track_id: the target's track id in the scene.
        category: e.g. ``"Car"``.
        frames: ``(T,)`` int frame indices in the scene, increasing.
        boxes: ``(T, 7)`` float64 boxes, each in its own frame's LiDAR frame (or in the
            frame of ``sensor_poses``).
        scans: loader of whole scans by frame index (see :data:`ScanLoader`).
        sensor_poses: ``None`` when each frame is served in its own LiDAR frame, else ``(T, 3,
            4)`` rigid maps ``[R | t]`` from each frame's LiDAR frame into the one its points
            and boxes are served in (nuScenes' ``frame="scene"``): where the sensor was, for
            transforms that model range from it (the weather).
    """

    tracklet_id: str
    scene: str
    track_id: int
    category: str
    frames: np.ndarray
    boxes: np.ndarray
    scans: ScanLoader = field(repr=False)
    sensor_poses: np.ndarray | None = field(default=None, repr=False)

    def __len__(self) -> int:
        return len(self.frames)

    def points(self, t: int) -> np.ndarray:
        """Whole scan of the tracklet's ``t``-th frame, xyz ``(N, 3)`` float32."""
        return self.scans(int(self.frames[t]))[:, :3]

    def points_with_intensity(self, t: int) -> np.ndarray:
        """Whole scan of the tracklet's ``t``-th frame, ``(N, 4)`` float32 (x, y, z, intensity)."""
        return self.scans(int(self.frames[t]))


def check_categories(
    categories: str | Sequence[str] | None, valid: Sequence[str], dataset: str
) -> tuple[str, ...] | None:
    """A category filter (one name, several, or ``None`` for all) as a tuple, or a
    ``ValueError`` naming the unknown ones and the ``valid`` names of ``dataset``."""
    if categories is None:
        return None
    if isinstance(categories, str):
        categories = (categories,)
    out = tuple(categories)
    unknown = [c for c in out if c not in valid]
    if unknown:
        raise ValueError(
            f"unknown {dataset} categor{'y' if len(unknown) == 1 else 'ies'} {unknown}; "
            f"valid: {', '.join(valid)}"
        )
    return out
