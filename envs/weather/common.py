"""Shared plumbing of the weather corruptions: input checks, intensity scale, moving points
along their rays, and the sensor constants every model uses."""

from __future__ import annotations

import numpy as np

# --- sensor constants (LISA, Kilic et al. 2021, defaults for a Velodyne-like 905 nm sensor) ---
R_MAX_M = 200.0
"""Maximum range: a unit-reflectivity (0.9) target at this range is just detectable."""
P_MIN = 0.9 / R_MAX_M**2
"""Detection floor in LISA's normalised power units (reflectivity / m^2)."""
REFLECTIVITY_FLOOR = 0.05
"""Lowest reflectivity assumed for a return the sensor did report (KITTI reports 0 for many
dark but detected surfaces; reading 0 as 'no reflectivity' would make them vanish at once)."""


def check_scan(points, intensity) -> tuple[np.ndarray, np.ndarray]:
    """Validate a corruption's input -> ``(points (N,3) float32, intensity (N,) float32)``.

    Raises a ValueError naming the problem: missing intensity, wrong shapes, NaN/inf values.
    """
    if intensity is None:
        raise ValueError(
            "weather corruptions need the scan's intensity (N,) on its own scale, e.g. the 4th "
            "column of a KITTI scan; got None (pass np.full(N, 0.5) if the sensor has none)"
        )
    pts = np.asarray(points, dtype=np.float32)
    inten = np.asarray(intensity, dtype=np.float32)
    if pts.size == 0 and inten.size == 0:  # an empty scan, whatever its exact shape
        return np.zeros((0, 3), np.float32), np.zeros((0,), np.float32)
    if pts.ndim != 2 or pts.shape[1] != 3:
        raise ValueError(f"points must be (N, 3) xyz in the sensor frame, got shape {pts.shape}")
    if inten.shape != (len(pts),):
        raise ValueError(
            f"intensity must be (N,) = ({len(pts)},) matching points, got shape {inten.shape}"
        )
    if len(pts) and not (np.isfinite(pts).all() and np.isfinite(inten).all()):
        raise ValueError("points / intensity contain NaN or inf")
    if len(pts) and inten.min() < 0:
        raise ValueError(f"intensity must be >= 0, got min {float(inten.min())}")
    return pts, inten


def full_scale(intensity: np.ndarray) -> float:
    """The full scale of the scan's intensities: 1.0 for [0, 1] scans (KITTI), 255.0 for 8-bit
    scans (nuScenes, STF), else the scan's maximum. Corrupted intensities stay on this scale."""
    top = float(intensity.max()) if len(intensity) else 1.0
    if top <= 1.0:
        return 1.0
    if top <= 255.0:
        return 255.0
    return top


def move_along_rays(points: np.ndarray, ranges: np.ndarray, new_ranges: np.ndarray) -> np.ndarray:
    """Points moved along their rays from the sensor to ``new_ranges`` (float32)."""
    scale = np.divide(new_ranges, ranges, out=np.ones_like(ranges), where=ranges > 0)
    return (points * scale[:, None].astype(np.float32)).astype(np.float32, copy=False)
