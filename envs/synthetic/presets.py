"""Named world sizes: the presets of the synthetic world (:data:`PRESETS`, the frozen ``"v1"``
motion) and their KITTI-motion versions (:data:`KITTI_MOTION_PRESETS`), looked up by
:func:`get_preset`.
"""

from __future__ import annotations

from dataclasses import dataclass

from envs.synthetic.scene_types import check_motion

__all__ = ["KITTI_MOTION_PRESETS", "PRESETS", "Preset", "get_preset"]


@dataclass(frozen=True)
class Preset:
    """A named world size.

    Attributes:
        name: preset name.
        scenes: scene numbers (the KITTI split applies: train 0–16, val 17–18, test 19–20).
        frames: ``(min, max)`` frames per scene (10 Hz), drawn per scene from the seed.
        density: traffic / people multiplier (see :class:`~envs.synthetic.scene_types.SceneConfig`).
        static_density: trees / poles multiplier.
        column_factor: keep every n-th azimuth column of the sensor (``tiny`` uses 2: half the
            horizontal resolution, so that it generates in seconds).
        motion: the motion model (:mod:`envs.synthetic.kitti_motion`): ``"v1"`` (the original) or
            ``"kitti"`` (fitted to the KITTI train labels).
    """

    name: str
    scenes: tuple[int, ...]
    frames: tuple[int, int]
    density: float
    static_density: float
    column_factor: int = 1
    motion: str = "v1"

    def __post_init__(self) -> None:
        check_motion(self.motion)


PRESETS: dict[str, Preset] = {
    # Tests: three short scenes, one per split; every category in every scene; half resolution.
    "tiny": Preset("tiny", (0, 17, 19), (24, 24), 0.5, 0.5, column_factor=2),
    # Demo: seven scenes (3 train, 2 val, 2 test), about a minute.
    "small": Preset("small", (0, 1, 2, 17, 18, 19, 20), (50, 50), 0.8, 1.0),
    # Benchmark: 21 scenes split like KITTI tracking.
    "default": Preset("default", tuple(range(21)), (60, 140), 1.0, 1.0),
}

# The same sizes with the motion fitted to KITTI's train labels ("km": KITTI motion): targets
# and ego move as in KITTI (docs/data.md, "Motion against KITTI"). A dict of their own: PRESETS
# stays the frozen v1 worlds that tests, golden episodes and shipped checkpoints name.
KITTI_MOTION_PRESETS: dict[str, Preset] = {
    "tiny-km": Preset("tiny-km", (0, 17, 19), (24, 24), 0.5, 0.5, column_factor=2, motion="kitti"),
    "small-km": Preset("small-km", (0, 1, 2, 17, 18, 19, 20), (50, 50), 0.8, 1.0, motion="kitti"),
    "default-km": Preset("default-km", tuple(range(21)), (60, 140), 1.0, 1.0, motion="kitti"),
}


def get_preset(name: str) -> Preset:
    """The preset called ``name`` (of :data:`PRESETS` or :data:`KITTI_MOTION_PRESETS`); a
    ``ValueError`` lists the valid names otherwise."""
    presets = {**PRESETS, **KITTI_MOTION_PRESETS}
    if name not in presets:
        raise ValueError(f"unknown preset {name!r}; valid presets: {', '.join(presets)}")
    return presets[name]
