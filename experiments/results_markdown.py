"""docs/results.md's tables from ``pointtrack eval --eval-seeds ... --out DIR`` reports.

Each cell is ``Success [90 % interval] / Precision`` (percent; the interval is the report's
tracklet bootstrap of Success, the numbers the mean over its eval seeds); one column per group
(observed, unseen) and per observed category, and the per-seed Success of the unseen group.

    python experiments/results_markdown.py runs/results-intervals/kitti-1
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path
from typing import Any


def cell(entry: dict[str, Any]) -> str:
    lo, hi = entry["success_interval"]
    return f"{entry['success']:.1f} [{lo:.1f}, {hi:.1f}] / {entry['precision']:.1f}"


def table(reports: dict[str, dict[str, Any]]) -> str:
    """The markdown table of ``{tracker: report}``: the groups, then each observed category (the
    unseen one is the unseen group), in the first report's order."""
    first = next(iter(reports.values()))
    cats = [c for c in first["categories"] if c not in _unseen(first)]
    head = ["tracker", "observed", "unseen", "unseen Success per eval seed", *cats]
    lines = ["| " + " | ".join(head) + " |", "|" + " --- |" * len(head)]
    for name, rep in reports.items():
        seeds = " / ".join(f"{v:.1f}" for v in rep["unseen"].get("success_seeds", []))
        row = [f"`{name}`", cell(rep["observed"]), cell(rep["unseen"]), seeds]
        row += [cell(rep["categories"][c]) for c in cats]
        lines.append("| " + " | ".join(row) + " |")
    return "\n".join(lines)


def _unseen(report: dict[str, Any]) -> set[str]:
    return {r["category"] for r in report["per_tracklet"] if not r["observed"]}


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("out", type=Path, help="a pointtrack eval --out directory")
    args = parser.parse_args(argv)
    path = args.out / "report.json"
    try:
        reports = json.loads(path.read_text())
    except (OSError, ValueError) as exc:
        raise SystemExit(f"{path}: cannot read an eval report ({exc})") from None
    print(table(reports))
    return 0


if __name__ == "__main__":
    sys.exit(main())
