"""Write a training run's validated weights (or a tracker file's) as tracker files with other
still-target tests (and dead zones).

``RUN/best.pt`` (or a tracker file, or a shipped name) with ``hold_chamfer_m`` set to each given
value and, with ``--min-motions``, ``min_motion_m`` to each of those (every pair; inference
only: the weights and every other setting are those of the source), as
``OUT/RUN-hHOLD.safetensors`` (``OUT/RUN-hHOLD-mMIN.safetensors`` with a dead zone; a file's
stem or a shipped name for ``RUN``), for ``pointtrack select`` to rank beside the source itself
(docs/table4.md, "Still-target test", "Budget pilot"; docs/mbptrack.md, "Still-target test").
Existing files are kept (a rerun after a kill redoes only what is missing).

    python experiments/hold_variants.py RUN [RUN ...] --holds 0.15 0.3 0.6 --out DIR
    python experiments/hold_variants.py RUN --holds 0 2.5 --min-motions 0.5 1 --out DIR \
        [--prefix budget-]
    python experiments/hold_variants.py mbptrack-kitti1-u --holds 0.15 0.2 --out DIR
"""

from __future__ import annotations

import argparse
import dataclasses
import sys
from collections.abc import Sequence
from pathlib import Path

import trackers
from training.loading import load_tracker


def write_variants(
    run: Path,
    holds: Sequence[float],
    out: Path,
    min_motions: Sequence[float] = (0.0,),
    prefix: str = "",
) -> list[Path]:
    """The files of ``run``'s ``best.pt`` (``run`` a folder; else ``run`` is loaded as it is: a
    tracker file or a shipped name) with each hold in ``holds`` and each dead zone in
    ``min_motions`` (metres; 0: none), named ``PREFIX NAME-h...`` (``NAME``: the folder's name,
    the file's stem); returns their paths, holds outer."""
    source, name = (run / "best.pt", run.name) if run.is_dir() else (run, run.stem)
    paths = []
    tracker = None
    for hold in holds:
        for min_motion in min_motions:
            dead_zone = f"-m{min_motion:g}" if min_motion > 0 else ""
            path = out / f"{prefix}{name}-h{hold:g}{dead_zone}.safetensors"
            paths.append(path)
            if path.is_file():
                continue
            tracker = tracker or load_tracker(str(source))
            tracker.inference = dataclasses.replace(
                tracker.inference, hold_chamfer_m=hold, min_motion_m=min_motion
            )
            trackers.save(tracker, path)
    return paths


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument(
        "runs",
        nargs="+",
        type=Path,
        help="training run folders (RUN/best.pt), tracker files or shipped names",
    )
    parser.add_argument("--holds", nargs="+", type=float, required=True, help="metres, >= 0")
    parser.add_argument(
        "--min-motions", nargs="+", type=float, default=[0.0], help="dead zones, metres, >= 0"
    )
    parser.add_argument("--out", type=Path, required=True)
    parser.add_argument(
        "--prefix",
        default="",
        help="put before each file's name: runs of the same name in other roots stay apart "
        "(a test reading is filed under the selected file's name)",
    )
    args = parser.parse_args(argv)
    if any(v < 0 for v in (*args.holds, *args.min_motions)):
        parser.error(f"--holds {args.holds} and --min-motions {args.min_motions} must be >= 0")
    if 0 in args.holds and 0 in args.min_motions:
        parser.error("hold 0 with min-motion 0 is the run itself (rank its best.pt instead)")
    args.out.mkdir(parents=True, exist_ok=True)
    for run in args.runs:
        if run.is_dir() and not (run / "best.pt").is_file():
            parser.error(f"{run}: no best.pt (training not finished?)")
        for path in write_variants(run, args.holds, args.out, args.min_motions, args.prefix):
            print(path)
    return 0


if __name__ == "__main__":
    sys.exit(main())
