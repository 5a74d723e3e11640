"""Pose maths of the nuScenes layout: quaternions, global -> LiDAR boxes, and the rigid maps
between the LiDAR frames of one scene's key frames (the ``"scene"`` frame of
:class:`~envs.data.nuscenes.NuScenesTracking`).

Conventions (the devkit's): a ``calibrated_sensor`` maps LiDAR -> vehicle body, an ``ego_pose``
body -> global, quaternions are ``(w, x, y, z)``; a point ``p`` of the LiDAR frame is
``R_ego (R_cs p + t_cs) + t_ego`` in the global frame.
"""

from __future__ import annotations

import numpy as np

from envs.geometry import wrap_yaw

__all__ = [
    "global_to_lidar_boxes",
    "lidar_to_global",
    "lidar_to_reference",
    "quaternion_to_matrix",
]


def quaternion_to_matrix(q: np.ndarray) -> np.ndarray:
    """Rotation matrices of quaternions ``(..., 4)`` in nuScenes order ``(w, x, y, z)``.

    The quaternions are normalised first (as pyquaternion does); returns ``(..., 3, 3)``
    float64. A zero quaternion gives NaNs (callers check the norms and name the record).
    """
    q = np.asarray(q, dtype=np.float64)
    q = q / np.linalg.norm(q, axis=-1, keepdims=True)
    w, x, y, z = q[..., 0], q[..., 1], q[..., 2], q[..., 3]
    out = np.empty(q.shape[:-1] + (3, 3))
    out[..., 0, 0] = 1 - 2 * (y * y + z * z)
    out[..., 0, 1] = 2 * (x * y - w * z)
    out[..., 0, 2] = 2 * (x * z + w * y)
    out[..., 1, 0] = 2 * (x * y + w * z)
    out[..., 1, 1] = 1 - 2 * (x * x + z * z)
    out[..., 1, 2] = 2 * (y * z - w * x)
    out[..., 2, 0] = 2 * (x * z - w * y)
    out[..., 2, 1] = 2 * (y * z + w * x)
    out[..., 2, 2] = 1 - 2 * (x * x + y * y)
    return out


def global_to_lidar_boxes(
    translation: np.ndarray,
    size_wlh: np.ndarray,
    rotation: np.ndarray,
    ego_t: np.ndarray,
    ego_q: np.ndarray,
    cs_t: np.ndarray,
    cs_q: np.ndarray,
) -> np.ndarray:
    """Global nuScenes boxes -> LiDAR-frame boxes, vectorised over ``N`` annotations.

    Args:
        translation: ``(N, 3)`` global box centres, metres.
        size_wlh: ``(N, 3)`` sizes in nuScenes order ``(w, l, h)``, metres.
        rotation: ``(N, 4)`` global box quaternions ``(w, x, y, z)``.
        ego_t: ``(N, 3)`` ego position (body -> global) at each box's key frame, metres.
        ego_q: ``(N, 4)`` ego rotation (body -> global) at that frame, ``(w, x, y, z)``.
        cs_t: ``(N, 3)`` sensor calibration translation (LiDAR -> body) of that frame, metres.
        cs_q: ``(N, 4)`` sensor calibration rotation (LiDAR -> body), ``(w, x, y, z)``.

    Returns:
        ``(N, 7)`` float64 ``(x, y, z, l, w, h, yaw)`` in the LiDAR frame, yaw in ``[-pi, pi)``.
    """
    r_ego = quaternion_to_matrix(ego_q)
    r_cs = quaternion_to_matrix(cs_q)
    r_box = quaternion_to_matrix(rotation)
    d = np.asarray(translation, np.float64) - ego_t
    in_ego = np.einsum("nji,nj->ni", r_ego, d) - cs_t  # R_ego^T d - t_cs
    centre = np.einsum("nji,nj->ni", r_cs, in_ego)  # R_cs^T (...)
    # Heading (first column) of R_cs^T R_ego^T R_box.
    heading = np.einsum("nji,nj->ni", r_cs, np.einsum("nji,nj->ni", r_ego, r_box[:, :, 0]))
    size = np.asarray(size_wlh, np.float64)
    out = np.empty((len(centre), 7))
    out[:, :3] = centre
    out[:, 3] = size[:, 1]
    out[:, 4] = size[:, 0]
    out[:, 5] = size[:, 2]
    out[:, 6] = wrap_yaw(np.arctan2(heading[:, 1], heading[:, 0]))
    return out


def lidar_to_global(
    ego_t: np.ndarray, ego_q: np.ndarray, cs_t: np.ndarray, cs_q: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """The rigid maps LiDAR -> global of ``T`` key frames: ``(T, 3, 3)`` rotations ``R`` and
    ``(T, 3)`` translations ``t`` (metres) with ``p_global = R p + t``. Arguments as in
    :func:`global_to_lidar_boxes`, one row per key frame."""
    r_ego = quaternion_to_matrix(ego_q)
    rotation = r_ego @ quaternion_to_matrix(cs_q)
    translation = np.einsum("nij,nj->ni", r_ego, np.asarray(cs_t, np.float64)) + ego_t
    return rotation, translation


def lidar_to_reference(
    ego_t: np.ndarray, ego_q: np.ndarray, cs_t: np.ndarray, cs_q: np.ndarray, reference: int = 0
) -> np.ndarray:
    """``(T, 3, 4)`` float64 maps ``[R | t]`` from each key frame's LiDAR frame to the LiDAR
    frame of key frame ``reference`` (``p_ref = R p + t``, metres): ego motion removed, the
    reference sensor at the origin. Arguments as in :func:`lidar_to_global`."""
    rotation, translation = lidar_to_global(ego_t, ego_q, cs_t, cs_q)
    r_ref, t_ref = rotation[reference], translation[reference]
    out = np.empty((len(rotation), 3, 4))
    out[:, :, :3] = r_ref.T @ rotation
    out[:, :, 3] = (translation - t_ref) @ r_ref  # R_ref^T (t - t_ref), row vectors
    return out
