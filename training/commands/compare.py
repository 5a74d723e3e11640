"""`pointtrack compare`: the tracklets where two evaluations differ most.

Example::

    pointtrack eval --tracker p2b-kitti1-u --out runs/eval-p2b
    pointtrack eval --tracker bat-kitti1-u --out runs/eval-bat
    pointtrack compare runs/eval-p2b runs/eval-bat --top 10

Reads each directory's ``report.json`` (per-tracklet Success / Precision; with several trackers
in one run, name the one with ``--tracker-a`` / ``--tracker-b``) and lists the tracklets by the
size of the Success difference, B minus A. With ``--save-boxes`` runs, each tracklet's frames are
in ``OUT/boxes/TRACKER.jsonl`` to look at (docs/evaluation.md).
"""

from __future__ import annotations

import argparse


def add_arguments(parser: argparse.ArgumentParser) -> None:
    """Declare this command's flags."""
    parser.add_argument("run_a", metavar="A", help="a pointtrack eval --out directory")
    parser.add_argument("run_b", metavar="B", help="another one, over the same tracklets")
    parser.add_argument("--tracker-a", default=None, help="the tracker of A (if it has several)")
    parser.add_argument("--tracker-b", default=None, help="the tracker of B (if it has several)")
    parser.add_argument("--top", type=int, default=15, help="rows to show (default 15)")
    parser.add_argument("--out", default=None, metavar="FILE", help="also write all rows as JSON")


def run(args: argparse.Namespace) -> int:
    from training.boxes import compare_runs, format_comparison

    if args.top < 1:
        raise SystemExit(f"pointtrack compare: --top must be >= 1, got {args.top}")
    comparison = compare_runs(
        args.run_a, args.run_b, tracker_a=args.tracker_a, tracker_b=args.tracker_b
    )
    print(format_comparison(comparison, args.top))
    if args.out:
        from training.reporting import save_report

        print(f"wrote {save_report(comparison, args.out)}")
    return 0
