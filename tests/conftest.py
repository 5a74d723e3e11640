"""Shared test set-up: a private world cache so tests never touch the user's cache."""

from __future__ import annotations

import os
import tempfile
from pathlib import Path

import pytest

# Set before any test module imports envs, so every cache lookup in this run lands here.
os.environ.setdefault("POINTTRACK_CACHE", tempfile.mkdtemp(prefix="pointtrack-test-cache-"))

SHARED_LABELS = Path(__file__).resolve().parents[1].parent / "shared" / "kitti-tracking-labels"


@pytest.fixture(scope="session")
def shared_labels() -> Path:
    """The real KITTI tracking labels of ../shared, or skip when they are absent."""
    if not (SHARED_LABELS / "label_02").is_dir():
        pytest.skip(f"real KITTI labels not found at {SHARED_LABELS}")
    return SHARED_LABELS
