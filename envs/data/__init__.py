"""The dataset layer: tracklets, the KITTI tracking loader, class-agnostic settings."""

from envs.data.kitti import KittiTracking
from envs.data.settings import SETTINGS, Setting, class_specific, get_setting
from envs.data.tracklet import ScanCache, Tracklet

__all__ = [
    "SETTINGS",
    "KittiTracking",
    "ScanCache",
    "Setting",
    "Tracklet",
    "class_specific",
    "get_setting",
]
