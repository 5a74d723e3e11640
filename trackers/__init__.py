"""Trackers: P2B, BAT, GPT (torch) and the non-learned baselines, behind one interface.

``make(name, **config)`` builds a tracker, ``save(tracker, path)`` / ``load(name_or_path)`` move
weights and config through safetensors (or a ``torch.load(weights_only=True)``-safe file);
``register`` adds a tracker class under a name, ``available()`` lists the names
(docs/trackers.md: how to add a tracker).
"""

from __future__ import annotations

from trackers.registry import (
    available,
    load,
    make,
    register,
    save,
    size_config,
    tracker_class,
    unregister,
)

# the built-in trackers register themselves on import, in this order (available()'s)
# isort: off
from trackers import p2b, bat, gpt, m2track, mbptrack, baselines  # noqa: E402, F401
# isort: on

__all__ = [
    "available",
    "load",
    "make",
    "register",
    "save",
    "size_config",
    "tracker_class",
    "unregister",
]
