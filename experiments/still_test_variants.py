"""Diagnostic: `pointtrack select` with a variant of the still-target test patched in, to see
which of its conditions keeps the nuScenes files below `previous_box` (docs/table4.md, "Budget
pilot"). Not a library option and nothing is selected or shipped from it.

Variants (``trackers.decision._still``, replaced in this process and the forked workers):
``sparse`` holds where the crops have too few points to decide (the library decides nothing
there, so the network acts); ``previous`` tests the reference box's crop against the previous
crop only (the library also requires the first crop); ``previous+sparse`` both. ::

    python experiments/still_test_variants.py sparse RUN/hold/FILE.safetensors previous_box \\
        --setting nuscenes-1 --dataset nuscenes --preset default-km --sensor hdl32 \\
        --nuscenes-frame scene --train-world 0 --no-progress --out DIR
"""

from __future__ import annotations

import sys

import torch

import trackers.decision as decision
from training.cli import main as cli_main

VARIANTS = ("sparse", "previous", "previous+sparse")
LIBRARY_STILL = decision._still


def _still_variant(variant: str):
    """The still-target test of ``variant`` (see the module doc), same signature as the
    library's ``_still(scene, hold_m)``."""

    def still(scene: decision.Scene, hold_m: float) -> torch.Tensor:
        points, _ = scene.points
        if "sparse" in variant and len(points) and not bool(decision._reference_crop(scene)[2]):
            return torch.ones((), dtype=torch.bool, device=points.device)
        if "previous" not in variant:
            return LIBRARY_STILL(scene, hold_m)
        first, arrays = scene.first, scene.arrays  # the re-ranking reads them after: put back
        scene.__dict__["first"] = scene.previous  # the cached slot the torch path reads
        scene.__dict__["arrays"] = None  # the compiled path reads the crops' arrays instead
        try:
            return LIBRARY_STILL(scene, hold_m)
        finally:
            scene.__dict__["first"], scene.__dict__["arrays"] = first, arrays

    return still


def main(argv: list[str]) -> int:
    if not argv or argv[0] not in VARIANTS:
        raise SystemExit(f"usage: still_test_variants.py {{{','.join(VARIANTS)}}} SELECT-ARGS...")
    decision._still = _still_variant(argv[0])
    return cli_main(["select", *argv[1:]])


if __name__ == "__main__":
    raise SystemExit(main(sys.argv[1:]))
