"""Shared test set-up: a private world cache so tests never touch the user's cache."""

from __future__ import annotations

import os
import shutil
import tempfile
from pathlib import Path

import pytest
import torch

# Set before any test module imports envs, so every cache lookup in this run lands here.
_OWN_CACHE = None
if "POINTTRACK_CACHE" not in os.environ:
    _OWN_CACHE = tempfile.mkdtemp(prefix="pointtrack-test-cache-")
    os.environ["POINTTRACK_CACHE"] = _OWN_CACHE

SHARED_LABELS = Path(__file__).resolve().parents[1].parent / "shared" / "kitti-tracking-labels"


@pytest.fixture(scope="module")
def one_torch_thread():
    """Torch on one thread for a module: small models on a 2-core machine run faster without
    oversubscription."""
    before = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(before)


@pytest.fixture(scope="session")
def shared_labels() -> Path:
    """The real KITTI tracking labels of ../shared, or skip when they are absent."""
    if not (SHARED_LABELS / "label_02").is_dir():
        pytest.skip(f"real KITTI labels not found at {SHARED_LABELS}")
    return SHARED_LABELS


def pytest_sessionfinish(session: pytest.Session, exitstatus: int) -> None:
    """Remove the private cache (generated worlds are tens of MB) when this run made it."""
    if _OWN_CACHE is not None:
        shutil.rmtree(_OWN_CACHE, ignore_errors=True)
