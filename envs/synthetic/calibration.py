"""The camera-LiDAR calibration written with every generated scene (and read by label-driven
replay when a scene has no calibration file of its own)."""

from __future__ import annotations

import numpy as np

from envs.data.kitti import Calibration

__all__ = ["KITTI_LIKE_CALIBRATION"]

# A KITTI-like calibration (the 2011_09_26 rig: velodyne ~0.27 m behind and 0.08 m above the
# left camera, rectification of camera 0), used for every generated scene.
KITTI_LIKE_CALIBRATION = Calibration(
    r0_rect=np.array(
        [
            [9.999239e-01, 9.837760e-03, -7.445048e-03],
            [-9.869795e-03, 9.999421e-01, -4.278459e-03],
            [7.402527e-03, 4.351614e-03, 9.999631e-01],
        ]
    ),
    tr_velo_to_cam=np.array(
        [
            [7.533745e-03, -9.999714e-01, -6.166020e-04, -4.069766e-03],
            [1.480249e-02, 7.280733e-04, -9.998902e-01, -7.631618e-02],
            [9.998621e-01, 7.523790e-03, 1.480755e-02, -2.717806e-01],
        ]
    ),
    p0=np.array([[721.5377, 0.0, 609.5593, 0.0], [0.0, 721.5377, 172.854, 0.0], [0, 0, 1.0, 0]]),
    p1=np.array(
        [[721.5377, 0.0, 609.5593, -387.5744], [0.0, 721.5377, 172.854, 0.0], [0, 0, 1.0, 0]]
    ),
    p2=np.array(
        [
            [721.5377, 0.0, 609.5593, 44.85728],
            [0.0, 721.5377, 172.854, 0.2163791],
            [0.0, 0.0, 1.0, 0.002745884],
        ]
    ),
    p3=np.array(
        [
            [721.5377, 0.0, 609.5593, -339.5242],
            [0.0, 721.5377, 172.854, 2.199936],
            [0.0, 0.0, 1.0, 0.002729905],
        ]
    ),
    tr_imu_to_velo=np.array(
        [
            [9.999976e-01, 7.553071e-04, -2.035826e-03, -8.086759e-01],
            [-7.854027e-04, 9.998898e-01, -1.482298e-02, 3.195559e-01],
            [2.024406e-03, 1.482454e-02, 9.998881e-01, -7.997231e-01],
        ]
    ),
)
