"""Class-agnostic settings (Table I of Tian et al. (TIP 2024)) and class-specific mode.

A :class:`Setting` names the categories a tracker is trained on (``observed``) and the ones it
meets only at test time (``unseen``). Presets: ``kitti-1``, ``kitti-2``, ``nuscenes-1``,
``nuscenes-2``; :func:`class_specific` builds the one-category mode.
"""

from __future__ import annotations

from dataclasses import dataclass

from envs.data.kitti import CATEGORIES

__all__ = [
    "LAYOUT_SETTINGS",
    "SETTINGS",
    "Setting",
    "check_setting_layout",
    "class_specific",
    "get_setting",
]


@dataclass(frozen=True)
class Setting:
    """Observed (training) and unseen (test-only) categories of one study.

    Attributes:
        name: e.g. ``"kitti-1"`` or ``"class-specific:Car"``.
        observed: categories seen in training.
        unseen: categories held out from training, tracked at test time.
    """

    name: str
    observed: tuple[str, ...]
    unseen: tuple[str, ...] = ()

    @property
    def categories(self) -> tuple[str, ...]:
        """All categories of the setting: observed then unseen."""
        return self.observed + self.unseen

    def is_observed(self, category: str) -> bool:
        """Whether ``category`` is an observed one (``ValueError`` if not in the setting)."""
        if category in self.observed:
            return True
        if category in self.unseen:
            return False
        raise ValueError(
            f"category {category!r} is not in setting {self.name!r}; "
            f"valid: {', '.join(self.categories)}"
        )


SETTINGS: dict[str, Setting] = {
    "kitti-1": Setting("kitti-1", ("Pedestrian", "Van", "Cyclist"), ("Car",)),
    "kitti-2": Setting("kitti-2", ("Car", "Van", "Cyclist"), ("Pedestrian",)),
    "nuscenes-1": Setting("nuscenes-1", ("Pedestrian", "Truck", "Bicycle"), ("Car",)),
    "nuscenes-2": Setting("nuscenes-2", ("Car", "Truck", "Bicycle"), ("Pedestrian",)),
}

#: the class-agnostic settings of each dataset layout (Table I of Tian et al.): a KITTI setting
#: names KITTI's categories (Cyclist), a nuScenes one nuScenes' (Bicycle, Truck)
LAYOUT_SETTINGS: dict[str, tuple[str, ...]] = {
    "kitti": ("kitti-1", "kitti-2"),
    "nuscenes": ("nuscenes-1", "nuscenes-2"),
}


def check_setting_layout(setting: str | Setting, layout: str) -> None:
    """Refuse a class-agnostic setting of the other layout's table: ``ValueError`` naming the
    settings a ``layout`` (``"kitti"`` or ``"nuscenes"``) world supports. Class-specific and
    custom settings pass."""
    name = setting.name if isinstance(setting, Setting) else str(setting)
    own = LAYOUT_SETTINGS[layout]
    if name not in own and any(name in names for names in LAYOUT_SETTINGS.values()):
        raise ValueError(
            f"setting {name!r} is not one of a {layout}-layout world's; it supports "
            f"{', '.join(own)} (and class-specific:<Category>)"
        )


def class_specific(category: str) -> Setting:
    """Class-specific mode: train and test on one category (``observed=(category,)``, no unseen)."""
    if category not in CATEGORIES:
        raise ValueError(f"unknown category {category!r}; valid: {', '.join(CATEGORIES)}")
    return Setting(f"class-specific:{category}", (category,), ())


def get_setting(name: str) -> Setting:
    """The preset called ``name``; ``"class-specific:<Category>"`` also works.

    Raises ``ValueError`` listing the valid names for an unknown one.
    """
    if isinstance(name, Setting):
        return name
    if name in SETTINGS:
        return SETTINGS[name]
    if isinstance(name, str) and name.startswith("class-specific:"):
        return class_specific(name.split(":", 1)[1])
    raise ValueError(
        f"unknown setting {name!r}; valid: {', '.join(SETTINGS)} or 'class-specific:<Category>'"
    )
