"""Spinning LiDAR sensor models (beam layout, range, noise) for the synthetic world.

A sensor is a grid of rays: ``n_beams`` fixed elevations times ``n_columns`` azimuth columns
evenly spaced over 360 degrees. Ray ``(b, c)`` has flat index ``b * n_columns + c``. Directions are
unit vectors in the sensor (LiDAR) frame: x forward, y left, z up.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field, replace

import numpy as np

__all__ = ["SENSORS", "SensorModel", "get_sensor"]


@dataclass(frozen=True)
class SensorModel:
    """A spinning multi-beam LiDAR.

    Attributes:
        name: ``"hdl64"`` or ``"hdl32"``.
        elevations_deg: ``(n_beams,)`` beam elevations in degrees, descending (top beam first).
        n_columns: azimuth columns per revolution (azimuth step = 360 / n_columns degrees).
        max_range: metres; returns beyond it are dropped.
        min_range: metres; returns nearer than it are dropped (the sensor's own blind zone).
        height: metres of the sensor above the ground under the ego vehicle.
        range_noise: standard deviation of the Gaussian range noise, metres.
        dropout: probability that any return is lost (before reflectivity-dependent losses).
    """

    name: str
    elevations_deg: tuple[float, ...]
    n_columns: int
    max_range: float
    min_range: float
    height: float
    range_noise: float
    dropout: float
    _dirs: np.ndarray | None = field(default=None, repr=False, compare=False)

    @property
    def n_beams(self) -> int:
        return len(self.elevations_deg)

    @property
    def n_rays(self) -> int:
        return self.n_beams * self.n_columns

    @property
    def azimuth_step(self) -> float:
        """Radians between neighbouring columns."""
        return 2.0 * math.pi / self.n_columns

    def column_azimuths(self) -> np.ndarray:
        """``(n_columns,)`` float64 azimuths in radians, ``-pi + (c + 0.5) * step``."""
        return -math.pi + (np.arange(self.n_columns) + 0.5) * self.azimuth_step

    def ray_directions(self) -> np.ndarray:
        """``(n_beams * n_columns, 3)`` float32 unit directions, beam-major (cached)."""
        if self._dirs is None:
            el = np.deg2rad(np.asarray(self.elevations_deg, dtype=np.float64))[:, None]
            az = self.column_azimuths()[None, :]
            d = np.stack(
                [np.cos(el) * np.cos(az), np.cos(el) * np.sin(az), np.sin(el) + 0.0 * az], -1
            )
            object.__setattr__(self, "_dirs", np.ascontiguousarray(d.reshape(-1, 3), np.float32))
        return self._dirs

    def subsampled(self, column_factor: int) -> SensorModel:
        """The same sensor with every ``column_factor``-th azimuth column (a sparser, faster
        scan; used by the ``tiny`` preset)."""
        if column_factor < 1:
            raise ValueError(f"column_factor must be >= 1, got {column_factor}")
        return replace(self, n_columns=self.n_columns // column_factor, _dirs=None)


def _hdl64_elevations() -> tuple[float, ...]:
    # Velodyne HDL-64E (KITTI): an upper block of 32 lasers from +2.0 to about -8.3 degrees at
    # ~1/3 degree spacing and a lower block of 32 from about -8.8 to -24.9 at ~1/2 degree.
    upper = np.linspace(2.0, -8.33, 32)
    lower = np.linspace(-8.83, -24.9, 32)
    return tuple(float(v) for v in np.concatenate([upper, lower]))


def _hdl32_elevations() -> tuple[float, ...]:
    # Velodyne HDL-32E (nuScenes): 32 lasers evenly from +10.67 to -30.67 degrees (1.33 deg).
    return tuple(float(v) for v in np.linspace(10.67, -30.67, 32))


SENSORS: dict[str, SensorModel] = {
    # KITTI: ~0.17 deg azimuth at 10 Hz -> 2048 columns, 131k rays, ~120k returns in a city.
    "hdl64": SensorModel(
        name="hdl64",
        elevations_deg=_hdl64_elevations(),
        n_columns=2048,
        max_range=120.0,
        min_range=2.5,
        height=1.73,
        range_noise=0.02,
        dropout=0.02,
    ),
    # nuScenes: HDL-32E at 20 Hz, ~0.33 deg azimuth -> 1088 columns, ~35k rays; 70 m useful range.
    "hdl32": SensorModel(
        name="hdl32",
        elevations_deg=_hdl32_elevations(),
        n_columns=1088,
        max_range=70.0,
        min_range=2.0,
        height=1.84,
        range_noise=0.02,
        dropout=0.03,
    ),
}


def get_sensor(name: str) -> SensorModel:
    """The sensor called ``name``; a ``ValueError`` lists the valid names otherwise."""
    if name not in SENSORS:
        raise ValueError(f"unknown sensor {name!r}; valid sensors: {', '.join(SENSORS)}")
    return SENSORS[name]
