"""Question 1 of docs/table4.md's "The search region at 2 Hz": is the region a lever?

Reads one ``pointtrack select`` ranking (``selection.json``) that holds, as trained, the new
runs ``NEW/p2b-none-sK/best.pt`` and the pilot's ``PILOT/p2b-none-sK/best.pt`` for training seeds
K = 0, 1, 2, and prints each pair's pooled observed Success on the never-trained worlds, the mean
paired difference (new minus pilot) with its 90 % t-interval over the seeds, the verdict of the
protocol, and the ranking's first five rows.

    python experiments/search_lever.py SELECTION.json NEW_ROOT PILOT_ROOT
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

from training.intervals import paired_t_interval

SEEDS = (0, 1, 2)


def paired(scores: dict[str, float], new: Path, pilot: Path) -> list[tuple[float, float]]:
    """``(new, pilot)`` Success per seed, from ``scores`` (candidate path -> Success)."""
    resolved = {str(Path(c).resolve()): s for c, s in scores.items()}
    pairs = []
    for seed in SEEDS:
        keys = [str((root / f"p2b-none-s{seed}" / "best.pt").resolve()) for root in (new, pilot)]
        missing = [k for k in keys if k not in resolved]
        if missing:
            raise SystemExit(f"the ranking lacks {', '.join(missing)}")
        pairs.append((resolved[keys[0]], resolved[keys[1]]))
    return pairs


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("selection", type=Path)
    parser.add_argument("new", type=Path, help="the search-region runs' root")
    parser.add_argument("pilot", type=Path, help="the pilot's runs' root, same setting")
    args = parser.parse_args(argv)
    ranking = json.loads(args.selection.read_text())["ranking"]
    pairs = paired({row["candidate"]: row["success"] for row in ranking}, args.new, args.pilot)
    for seed, (ours, theirs) in zip(SEEDS, pairs, strict=True):
        print(f"seed {seed}: search region {ours:.1f}, pilot {theirs:.1f}")
    mean, half = paired_t_interval([a - b for a, b in pairs])
    lo, hi = mean - half, mean + half
    verdict = "the region is a lever" if lo > 0 else "not a lever at this budget"
    print(f"new - pilot: {mean:+.1f} [{lo:+.1f}, {hi:+.1f}] (90 %, t, 2 df): {verdict}")
    for row in ranking[:5]:
        print(f"  {row['success']:5.1f}  {row['candidate']}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
