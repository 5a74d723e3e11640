"""Write a training run's validated weights as tracker files with other still-target tests.

``RUN/best.pt`` with ``hold_chamfer_m`` set to each given value (inference only: the weights and
every other setting are those of the run), as ``OUT/RUN-hVALUE.safetensors``, for
``pointtrack select`` to rank beside the run itself (docs/table4.md, "Still-target test").
Existing files are kept (a rerun after a kill redoes only what is missing).

    python experiments/hold_variants.py RUN [RUN ...] --holds 0.15 0.3 0.6 --out DIR
"""

from __future__ import annotations

import argparse
import dataclasses
import sys
from pathlib import Path

import trackers
from training.loading import load_tracker


def write_variants(run: Path, holds: list[float], out: Path) -> list[Path]:
    """The files of ``run``'s ``best.pt`` with each hold in ``holds``; returns their paths."""
    paths = []
    tracker = None
    for hold in holds:
        path = out / f"{run.name}-h{hold:g}.safetensors"
        paths.append(path)
        if path.is_file():
            continue
        tracker = tracker or load_tracker(str(run / "best.pt"))
        tracker.inference = dataclasses.replace(tracker.inference, hold_chamfer_m=hold)
        trackers.save(tracker, path)
    return paths


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("runs", nargs="+", type=Path, help="training run folders (RUN/best.pt)")
    parser.add_argument("--holds", nargs="+", type=float, required=True, help="metres, > 0")
    parser.add_argument("--out", type=Path, required=True)
    args = parser.parse_args(argv)
    if any(hold <= 0 for hold in args.holds):
        parser.error(f"--holds must be > 0 (the run itself is the 0 candidate), got {args.holds}")
    args.out.mkdir(parents=True, exist_ok=True)
    for run in args.runs:
        if not (run / "best.pt").is_file():
            parser.error(f"{run}: no best.pt (training not finished?)")
        for path in write_variants(run, args.holds, args.out):
            print(path)
    return 0


if __name__ == "__main__":
    sys.exit(main())
