"""KITTI calibration files and box conversions between the rectified camera frame and LiDAR.

A LiDAR point ``p`` maps to the rectified camera-0 frame by ``R0_rect @ (Tr_velo_to_cam[:, :3] @
p + Tr_velo_to_cam[:, 3])``; we go through both matrices (Open3DSOT drops ``R0_rect``; we don't).
Conventions of the converted boxes: :mod:`envs.data.kitti`. Errors name the file.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from envs.geometry import wrap_yaw

__all__ = [
    "BOX_CONVENTIONS",
    "Calibration",
    "camera_to_lidar_boxes",
    "camera_to_open3dsot_boxes",
    "lidar_to_camera_boxes",
    "read_calibration",
    "write_calibration",
]


# --------------------------------------------------------------------------- calibration

# Key aliases: object-benchmark style (written) first, then the raw tracking names.
_KEY_ALIASES: dict[str, tuple[str, ...]] = {
    "P0": ("P0",),
    "P1": ("P1",),
    "P2": ("P2",),
    "P3": ("P3",),
    "R0_rect": ("R0_rect", "R_rect"),
    "Tr_velo_to_cam": ("Tr_velo_to_cam", "Tr_velo_cam"),
    "Tr_imu_to_velo": ("Tr_imu_to_velo", "Tr_imu_velo"),
}


def _default_p() -> np.ndarray:
    return np.hstack([np.eye(3), np.zeros((3, 1))])


@dataclass
class Calibration:
    """One scene's calibration.

    Attributes:
        r0_rect: ``(3, 3)`` rectifying rotation of camera 0.
        tr_velo_to_cam: ``(3, 4)`` rigid transform LiDAR -> (unrectified) camera 0, metres.
        p0, p1, p2, p3: ``(3, 4)`` camera projection matrices (kept for writing; unused here).
        tr_imu_to_velo: ``(3, 4)`` IMU -> LiDAR (kept for writing; unused here).
    """

    r0_rect: np.ndarray = field(default_factory=lambda: np.eye(3))
    tr_velo_to_cam: np.ndarray = field(default_factory=_default_p)
    p0: np.ndarray = field(default_factory=_default_p)
    p1: np.ndarray = field(default_factory=_default_p)
    p2: np.ndarray = field(default_factory=_default_p)
    p3: np.ndarray = field(default_factory=_default_p)
    tr_imu_to_velo: np.ndarray = field(default_factory=_default_p)

    def __post_init__(self) -> None:
        self.r0_rect = np.asarray(self.r0_rect, dtype=np.float64).reshape(3, 3)
        for name in ("tr_velo_to_cam", "p0", "p1", "p2", "p3", "tr_imu_to_velo"):
            setattr(self, name, np.asarray(getattr(self, name), dtype=np.float64).reshape(3, 4))

    def velo_to_rect(self) -> np.ndarray:
        """``(4, 4)`` LiDAR -> rectified camera transform ``R0_rect @ Tr_velo_to_cam``."""
        r0 = np.eye(4)
        r0[:3, :3] = self.r0_rect
        tr = np.eye(4)
        tr[:3, :] = self.tr_velo_to_cam
        return r0 @ tr

    def rect_to_velo(self) -> np.ndarray:
        """``(4, 4)`` inverse of :meth:`velo_to_rect`."""
        return np.linalg.inv(self.velo_to_rect())


def _parse_calibration_line(line: str) -> tuple[str, list[str]] | None:
    line = line.strip()
    if not line:
        return None
    if ":" in line.split(maxsplit=1)[0]:
        key, _, rest = line.partition(":")
    else:
        key, _, rest = line.partition(" ")
    return key.strip(), rest.split()


def read_calibration(path: str | Path) -> Calibration:
    """Read a calibration file in either key style (``R0_rect:`` / ``Tr_velo_to_cam:`` or the
    raw tracking ``R_rect`` / ``Tr_velo_cam`` without colon).

    ``R0_rect`` and ``Tr_velo_to_cam`` are required; a missing one raises a ``KeyError`` naming
    the file and the key. Missing projection matrices default to ``[I | 0]``.
    """
    path = Path(path)
    try:
        text = path.read_text()
    except OSError as exc:
        raise FileNotFoundError(f"cannot read calibration file {path}: {exc}") from exc
    raw: dict[str, list[str]] = {}
    for lineno, line in enumerate(text.splitlines(), 1):
        parsed = _parse_calibration_line(line)
        if parsed is not None:
            raw[parsed[0]] = parsed[1] + [f"@{lineno}"]
    values: dict[str, np.ndarray] = {}
    for canonical, aliases in _KEY_ALIASES.items():
        key = next((k for k in aliases if k in raw), None)
        if key is None:
            if canonical in ("R0_rect", "Tr_velo_to_cam"):
                raise KeyError(
                    f"calibration file {path} lacks key {canonical!r} "
                    f"(also accepted: {', '.join(aliases[1:])})"
                )
            continue
        *numbers, where = raw[key]
        expected = 9 if canonical == "R0_rect" else 12
        try:
            arr = np.array([float(v) for v in numbers], dtype=np.float64)
        except ValueError as exc:
            raise ValueError(
                f"calibration file {path}, line {where[1:]}: key {key!r}: {exc}"
            ) from exc
        if arr.size != expected or not np.all(np.isfinite(arr)):
            raise ValueError(
                f"calibration file {path}, line {where[1:]}: key {key!r} needs {expected} "
                f"finite numbers, "
                f"got {arr.size}"
            )
        values[canonical] = arr
    return Calibration(
        r0_rect=values["R0_rect"].reshape(3, 3),
        tr_velo_to_cam=values["Tr_velo_to_cam"].reshape(3, 4),
        p0=values.get("P0", _default_p()),
        p1=values.get("P1", _default_p()),
        p2=values.get("P2", _default_p()),
        p3=values.get("P3", _default_p()),
        tr_imu_to_velo=values.get("Tr_imu_to_velo", _default_p()),
    )


def write_calibration(path: str | Path, calib: Calibration) -> None:
    """Write ``calib`` with the object-style keys (``P0:`` … ``R0_rect:``, ``Tr_velo_to_cam:``)."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)

    def fmt(arr: np.ndarray) -> str:
        return " ".join(f"{v:.12e}" for v in np.asarray(arr, dtype=np.float64).ravel())

    lines = [
        f"P0: {fmt(calib.p0)}",
        f"P1: {fmt(calib.p1)}",
        f"P2: {fmt(calib.p2)}",
        f"P3: {fmt(calib.p3)}",
        f"R0_rect: {fmt(calib.r0_rect)}",
        f"Tr_velo_to_cam: {fmt(calib.tr_velo_to_cam)}",
        f"Tr_imu_to_velo: {fmt(calib.tr_imu_to_velo)}",
    ]
    path.write_text("\n".join(lines) + "\n")


# --------------------------------------------------------------------------- box conversion


def camera_to_lidar_boxes(hwl_xyz_ry: np.ndarray, calib: Calibration) -> np.ndarray:
    """KITTI label boxes -> LiDAR boxes.

    Args:
        hwl_xyz_ry: ``(..., 7)`` ``[h, w, l, x, y, z, rotation_y]`` in the rectified camera frame,
            metres / radians, ``(x, y, z)`` the bottom centre.
        calib: the scene's calibration.

    Returns:
        ``(..., 7)`` float64 ``(x, y, z, l, w, h, yaw)`` in the LiDAR frame, centre = bottom
        centre lifted by ``h / 2`` along LiDAR +z, yaw wrapped to ``[-pi, pi)``.
    """
    cam = np.asarray(hwl_xyz_ry, dtype=np.float64)
    if cam.shape[-1] != 7:
        raise ValueError(
            f"camera boxes must have shape (..., 7) [h, w, l, x, y, z, ry]; got {cam.shape}"
        )
    inv = calib.rect_to_velo()
    lin, trans = inv[:3, :3], inv[:3, 3]
    h, w, length = cam[..., 0], cam[..., 1], cam[..., 2]
    bottom = cam[..., 3:6] @ lin.T + trans
    ry = cam[..., 6]
    heading_cam = np.stack([np.cos(ry), np.zeros_like(ry), -np.sin(ry)], axis=-1)
    heading = heading_cam @ lin.T
    yaw = wrap_yaw(np.arctan2(heading[..., 1], heading[..., 0]))
    out = np.empty(cam.shape, dtype=np.float64)
    out[..., 0:2] = bottom[..., 0:2]
    out[..., 2] = bottom[..., 2] + 0.5 * h
    out[..., 3] = length
    out[..., 4] = w
    out[..., 5] = h
    out[..., 6] = yaw
    return out


BOX_CONVENTIONS = ("lidar", "open3dsot")
"""``KittiTracking(box_convention=...)``: ``"lidar"`` (:func:`camera_to_lidar_boxes`, through
``R0_rect``) or ``"open3dsot"`` (:func:`camera_to_open3dsot_boxes`, Open3DSOT's boxes)."""


def camera_to_open3dsot_boxes(hwl_xyz_ry: np.ndarray, calib: Calibration) -> np.ndarray:
    """KITTI label boxes -> the LiDAR boxes Open3DSOT's KITTI loader builds
    (``coordinate_mode="velodyne"``), for comparisons with published tables.

    Open3DSOT treats the labels as if in the unrectified camera frame (no ``R0_rect``): centre
    ``= Tr_velo_to_cam^-1 (x, y - h / 2, z)``, and a yaw about LiDAR +z of ``-ry - pi / 2``
    whatever the calibration's rotation. Same layout as :func:`camera_to_lidar_boxes`:
    ``(..., 7)`` -> ``(..., 7)`` float64 ``(x, y, z, l, w, h, yaw)``, yaw wrapped to
    ``[-pi, pi)``.
    """
    cam = np.asarray(hwl_xyz_ry, dtype=np.float64)
    if cam.shape[-1] != 7:
        raise ValueError(
            f"camera boxes must have shape (..., 7) [h, w, l, x, y, z, ry]; got {cam.shape}"
        )
    velo_to_cam = np.eye(4)
    velo_to_cam[:3, :] = calib.tr_velo_to_cam
    inv = np.linalg.inv(velo_to_cam)
    centre_cam = cam[..., 3:6].copy()
    centre_cam[..., 1] -= 0.5 * cam[..., 0]
    out = np.empty(cam.shape, dtype=np.float64)
    out[..., 0:3] = centre_cam @ inv[:3, :3].T + inv[:3, 3]
    out[..., 3] = cam[..., 2]
    out[..., 4] = cam[..., 1]
    out[..., 5] = cam[..., 0]
    out[..., 6] = wrap_yaw(-cam[..., 6] - 0.5 * np.pi)
    return out


def lidar_to_camera_boxes(boxes: np.ndarray, calib: Calibration) -> np.ndarray:
    """Exact inverse of :func:`camera_to_lidar_boxes`.

    Args:
        boxes: ``(..., 7)`` LiDAR boxes ``(x, y, z, l, w, h, yaw)``.
        calib: the scene's calibration.

    Returns:
        ``(..., 7)`` float64 ``[h, w, l, x, y, z, rotation_y]`` (bottom centre, rectified camera
        frame), ``rotation_y`` wrapped to ``[-pi, pi)``. The heading is recovered exactly: among
        the LiDAR directions whose horizontal part points along ``yaw``, the one that maps into the
        camera's x-z plane is taken, and ``rotation_y`` is read from its camera image.
    """
    box = np.asarray(boxes, dtype=np.float64)
    if box.shape[-1] != 7:
        raise ValueError(f"LiDAR boxes must have shape (..., 7); got {box.shape}")
    fwd = calib.velo_to_rect()
    lin, trans = fwd[:3, :3], fwd[:3, 3]
    h = box[..., 5]
    bottom = box[..., 0:3].copy()
    bottom[..., 2] -= 0.5 * h
    bottom_cam = bottom @ lin.T + trans
    c, s = np.cos(box[..., 6]), np.sin(box[..., 6])
    # d = (c, s, 0) + beta * (0, 0, 1) with (lin @ d)_y == 0  (camera y: the axis ry turns about).
    horiz_y = lin[1, 0] * c + lin[1, 1] * s
    beta = -horiz_y / lin[1, 2]
    dx = lin[0, 0] * c + lin[0, 1] * s + lin[0, 2] * beta
    dz = lin[2, 0] * c + lin[2, 1] * s + lin[2, 2] * beta
    ry = wrap_yaw(np.arctan2(-dz, dx))
    out = np.empty(box.shape, dtype=np.float64)
    out[..., 0] = h
    out[..., 1] = box[..., 4]
    out[..., 2] = box[..., 3]
    out[..., 3:6] = bottom_cam
    out[..., 6] = ry
    return out
