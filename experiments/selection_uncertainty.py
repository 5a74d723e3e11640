"""The ranking uncertainty of a finished ``pointtrack select --out DIR``, from its cached reports.

A selection made before ``pointtrack select`` printed the paired bootstrap (session 17) kept every
per-tracklet score under ``DIR/parts``; this rebuilds its rows from them, in the ranking's order,
and prints the table a new ``pointtrack select`` prints. Nothing is evaluated again. ::

    python experiments/selection_uncertainty.py runs16/sel-gptscb
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

from training.selection import format_ranking, observed_tracklet_scores, ranking_uncertainty


def rows_from_selection_dir(directory: Path) -> list[dict]:
    """``selection.json``'s ranking, each row with the per-tracklet scores of its reports."""
    ranking = json.loads((directory / "selection.json").read_text())["ranking"]
    rows = {r["candidate"]: r | {"per_tracklet": {}} for r in ranking}
    for path in sorted((directory / "parts").rglob("*.json")):
        report = json.loads(path.read_text())
        key = report["selection_key"]
        row = rows.get(key["candidate"])
        # a cache can hold reports of other files under the same name (a shipped checkpoint
        # replaced since): the row's own is the one with the part score the ranking shows
        if row is None or report["observed"]["success"] != row["parts"][key["part"]]["success"]:
            continue
        row["per_tracklet"].update(observed_tracklet_scores(report, key["part"]))
    return list(rows.values())


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("directory", type=Path, help="a pointtrack select --out directory")
    parser.add_argument("--resamples", type=int, default=2000)
    parser.add_argument("--seed", type=int, default=0)
    args = parser.parse_args()
    rows = rows_from_selection_dir(args.directory)
    print(format_ranking(rows, ranking_uncertainty(rows, resamples=args.resamples, seed=args.seed)))


if __name__ == "__main__":
    main()
