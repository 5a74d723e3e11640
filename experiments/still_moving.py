"""Where candidates win or lose against `previous_box`: a `pointtrack select` ranking's
per-tracklet Success split into the tracklets `previous_box` holds (its Success at least
``--still``: the target stands, or barely moves) and the rest, each group's frame-weighted
Success per candidate (docs/table4.md, "Budget pilot"). A diagnostic read after a selection;
it chooses nothing. ::

    python experiments/still_moving.py runs/table4-budget-nus1-scene/select/selection.json
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path


def split_scores(ranking: list[dict], still: float) -> dict[str, dict[str, float]]:
    """``group -> candidate -> frame-weighted Success`` over the groups ``"still"`` and
    ``"moving"`` (by `previous_box`'s per-tracklet Success), plus each group's tracklet and
    frame counts under ``"tracklets"`` and ``"frames"``."""
    rows = {row["candidate"]: row["per_tracklet"] for row in ranking}
    if "previous_box" not in rows:
        raise SystemExit("the ranking has no previous_box candidate to split the tracklets by")
    reference = rows["previous_box"]
    groups = {
        "still": [k for k, v in reference.items() if v["success"] >= still],
        "moving": [k for k, v in reference.items() if v["success"] < still],
    }
    out: dict[str, dict[str, float]] = {}
    for group, keys in groups.items():
        frames = sum(reference[k]["frames"] for k in keys)
        scores = {
            name: sum(per[k]["success"] * per[k]["frames"] for k in keys) / max(frames, 1)
            for name, per in rows.items()
        }
        out[group] = {**scores, "tracklets": len(keys), "frames": frames}
    return out


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("selection", type=Path, help="a pointtrack select selection.json")
    parser.add_argument("--still", type=float, default=80.0, help="previous_box Success (%%)")
    args = parser.parse_args(argv)
    ranking = json.loads(args.selection.read_text())["ranking"]
    for group, scores in split_scores(ranking, args.still).items():
        print(f"{group}: {scores['tracklets']} tracklets, {scores['frames']:.0f} frames")
        for name, value in scores.items():
            if name not in ("tracklets", "frames"):
                print(f"  {value:5.1f}  {name}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
