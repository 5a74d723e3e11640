"""Trackers: P2B, BAT, GPT (torch) and the non-learned baselines, behind one interface.

``make(name, **config)`` builds a tracker, ``save(tracker, path)`` / ``load(name_or_path)`` move
weights and config through safetensors (or a ``torch.load(weights_only=True)``-safe file).
"""

from __future__ import annotations

from trackers.registry import available, load, make, save

__all__ = ["available", "load", "make", "save"]
