"""The synthetic LiDAR world: procedural street scenes seen by a simulated spinning LiDAR,
written in the KITTI tracking layout (the project's embedded default dataset).

Entry points:

* :func:`ensure_world` — the root of a world, generated once into the cache and reused.
* :func:`generate_world` — generate a world into a directory (``pointtrack generate``).
* :func:`verify_world` — check a world's files against the sizes and SHA-256 digests of its
  manifest (``pointtrack generate --verify DIR``).
* :data:`PRESETS` (``tiny``, ``small``, ``default``), :data:`KITTI_MOTION_PRESETS` (``tiny-km``,
  ``small-km``, ``default-km``: the motion fitted to KITTI, :mod:`envs.synthetic.kitti_motion`)
  and :data:`SENSORS` (``hdl64``, ``hdl32``).

Read a world with ``envs.data.KittiTracking(root, split, categories)``.
"""

from envs.synthetic.calibration import KITTI_LIKE_CALIBRATION
from envs.synthetic.objects import CATEGORIES, SIZE_STATS
from envs.synthetic.presets import KITTI_MOTION_PRESETS, PRESETS, Preset, get_preset
from envs.synthetic.sensor import SENSORS, SensorModel, get_sensor
from envs.synthetic.world import (
    GENERATOR_VERSION,
    clean_stale_temps,
    default_cache_dir,
    ensure_world,
    generate_world,
    verify_world,
)

__all__ = [
    "CATEGORIES",
    "GENERATOR_VERSION",
    "KITTI_LIKE_CALIBRATION",
    "KITTI_MOTION_PRESETS",
    "PRESETS",
    "SENSORS",
    "SIZE_STATS",
    "Preset",
    "SensorModel",
    "clean_stale_temps",
    "default_cache_dir",
    "ensure_world",
    "generate_world",
    "get_preset",
    "get_sensor",
    "verify_world",
]
