"""Base against candidate on ``pointtrack eval`` reports, per eval seed and on the mean.

Each report is a ``pointtrack eval --tracker BASE CANDIDATE ... --out DIR`` ``DIR/report.json``
(the first two trackers are compared). Prints observed and unseen Success / Precision, the
difference, and the tracklets the candidate won, lost and tied (by per-tracklet Success), then
the mean difference over the reports. ::

    python experiments/compare_reports.py runs19/grp3test-s{0,1,2}/report.json
"""

from __future__ import annotations

import argparse
import json
from collections.abc import Mapping
from pathlib import Path
from typing import Any

import numpy as np

GROUPS = ("observed", "unseen")


def wins_losses_ties(
    base: Mapping[str, Any], candidate: Mapping[str, Any], observed: bool
) -> tuple[int, int, int]:
    """Tracklets (with frames, of the group) where the candidate's Success is higher / lower /
    equal (within 1e-6 points: float noise of the per-tracklet pooling), matched by id."""

    def scores(report: Mapping[str, Any]) -> dict[str, float]:
        rows = report["per_tracklet"]
        return {
            t["tracklet"]: t["success"] for t in rows if t["observed"] == observed and t["frames"]
        }

    b, c = scores(base), scores(candidate)
    diff = np.array([c[k] - b[k] for k in b])
    tol = 1e-6
    return int((diff > tol).sum()), int((diff < -tol).sum()), int((np.abs(diff) <= tol).sum())


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("reports", nargs="+", type=Path, help="report.json files")
    args = parser.parse_args()
    diffs: dict[str, list[float]] = {g: [] for g in GROUPS}
    for path in args.reports:
        (base_name, base), (cand_name, cand) = list(json.loads(path.read_text()).items())[:2]
        print(f"{path}: {base_name} -> {cand_name}")
        for group in GROUPS:
            b, c = base[group], cand[group]
            won, lost, tied = wins_losses_ties(base, cand, observed=group == "observed")
            diffs[group].append(c["success"] - b["success"])
            print(
                f"  {group:8s} {b['success']:.1f} / {b['precision']:.1f} -> {c['success']:.1f} / "
                f"{c['precision']:.1f} ({diffs[group][-1]:+.1f}); "
                f"won {won}, lost {lost}, tied {tied}"
            )
    for group in GROUPS:
        print(f"mean {group} Success difference: {np.mean(diffs[group]):+.2f}")


if __name__ == "__main__":
    main()
