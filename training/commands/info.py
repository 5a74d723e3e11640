"""`pointtrack info`: what a checkpoint is and what it was trained and chosen on.

Example::

    pointtrack info p2b-kitti1-u runs/a/best.pt

Prints the tracker, its SHA-256 and its provenance (``trackers.provenance``): the data (dataset,
world, setting, categories, splits), how much (samples, steps), the selections that chose it, its
parent checkpoint, the commit and the config; ``unknown`` where the file does not say.
"""

from __future__ import annotations

import argparse


def add_arguments(parser: argparse.ArgumentParser) -> None:
    """Declare this command's flags."""
    parser.add_argument(
        "files",
        nargs="+",
        metavar="FILE",
        help="tracker files, shipped checkpoint names or training checkpoints (RUN/best.pt)",
    )
    parser.add_argument("--json", action="store_true", help="print the provenance as JSON")


def run(args: argparse.Namespace) -> int:
    import json

    from trackers.registry import find_checkpoint
    from training.checkpoint import parent_entry
    from training.loading import load_tracker

    for spec in args.files:
        path = find_checkpoint(spec)
        if path is None:
            raise SystemExit(f"no checkpoint file or shipped checkpoint named {spec!r}")
        tracker = load_tracker(spec)  # validates the file (digest, weights, config)
        entry = parent_entry(spec)
        if args.json:
            print(
                json.dumps(
                    {"file": str(path), "sha256": entry["sha256"]}
                    | {
                        "tracker": tracker.name,
                        "provenance": entry["provenance"].to_dict(),
                    },
                    sort_keys=True,
                )
            )
            continue
        print(f"file: {path}\ntracker: {tracker.name}\nsha256: {entry['sha256']}")
        print(entry["provenance"].format())
        categories = entry["provenance"].trained_categories()  # the whole lineage
        print(
            "categories trained on, every stage: "
            + ("unknown" if categories is None else ", ".join(categories))
        )
    return 0
