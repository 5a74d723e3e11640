"""The dataset layer: tracklets, the KITTI and nuScenes loaders, class-agnostic settings."""

from envs.data.kitti import KittiTracking
from envs.data.nuscenes import NuScenesTracking
from envs.data.settings import (
    SETTINGS,
    Setting,
    check_setting_layout,
    class_specific,
    get_setting,
)
from envs.data.tracklet import ScanCache, Tracklet

__all__ = [
    "SETTINGS",
    "KittiTracking",
    "NuScenesTracking",
    "ScanCache",
    "Setting",
    "Tracklet",
    "check_setting_layout",
    "class_specific",
    "get_setting",
]
