"""Optional packages: import one, or fail with a single line naming the ``pip install`` command.

The extras are declared in ``pyproject.toml`` (``video``, ``viewer``, ``tensorboard``, ``docs``);
a feature that needs one imports it through :func:`require` at the moment it is used.
"""

from __future__ import annotations

import importlib
from types import ModuleType

__all__ = ["MissingExtraError", "require"]


class MissingExtraError(ImportError):
    """An optional package is not installed; the message names the extra that brings it."""


def require(module: str, extra: str, purpose: str) -> ModuleType:
    """Import ``module`` or raise :class:`MissingExtraError` naming ``extra``.

    Args:
        module: the import name, e.g. ``"imageio"``.
        extra: the pointtrack extra that installs it, e.g. ``"video"``.
        purpose: what needs it, for the message (e.g. ``"writing videos"``).
    """
    try:
        return importlib.import_module(module)
    except ImportError as exc:
        raise MissingExtraError(
            f'{purpose} needs the optional package {module!r}: pip install "pointtrack[{extra}]"'
        ) from exc
