"""Question 1 of docs/table4.md's "The search region at 2 Hz": is the region a lever?

Reads one ``pointtrack select`` ranking (``selection.json``) that holds, as trained, the new
runs ``NEW/p2b-ARM-sK/best.pt`` and the reference's ``PILOT/p2b-ARM-sK/best.pt`` for training
seeds K (default 0, 1, 2; ARM default ``none``, -U), and prints each pair's pooled observed
Success on the never-trained worlds, the mean paired difference (new minus reference) with its
90 % t-interval over the seeds and the verdict of the protocol (none from one seed), and the
ranking's first five rows.

    python experiments/search_lever.py SELECTION.json NEW_ROOT PILOT_ROOT [--seeds 0 1 2] \
        [--arm none]
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

from training.intervals import paired_t_interval


def paired(
    scores: dict[str, float], new: Path, pilot: Path, seeds: list[int], arm: str = "none"
) -> list[tuple[float, float]]:
    """``(new, pilot)`` Success per seed, from ``scores`` (candidate path -> Success)."""
    resolved = {str(Path(c).resolve()): s for c, s in scores.items()}
    pairs = []
    for seed in seeds:
        keys = [str((root / f"p2b-{arm}-s{seed}" / "best.pt").resolve()) for root in (new, pilot)]
        missing = [k for k in keys if k not in resolved]
        if missing:
            raise SystemExit(f"the ranking lacks {', '.join(missing)}")
        pairs.append((resolved[keys[0]], resolved[keys[1]]))
    return pairs


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("selection", type=Path)
    parser.add_argument("new", type=Path, help="the search-region runs' root")
    parser.add_argument("pilot", type=Path, help="the reference runs' root, same setting")
    parser.add_argument("--seeds", type=int, nargs="+", default=[0, 1, 2])
    parser.add_argument("--arm", default="none", choices=("none", "decorrelation", "sam"))
    args = parser.parse_args(argv)
    ranking = json.loads(args.selection.read_text())["ranking"]
    scores = {row["candidate"]: row["success"] for row in ranking}
    pairs = paired(scores, args.new, args.pilot, args.seeds, args.arm)
    for seed, (ours, theirs) in zip(args.seeds, pairs, strict=True):
        print(f"seed {seed}: search region {ours:.1f}, reference {theirs:.1f}")
    mean, half = paired_t_interval([a - b for a, b in pairs])
    if half is None:
        print(f"new - reference: {mean:+.1f} (one seed: no interval, no verdict)")
    else:
        lo, hi, df = mean - half, mean + half, len(pairs) - 1
        verdict = "the region is a lever" if lo > 0 else "not a lever at this budget"
        print(f"new - reference: {mean:+.1f} [{lo:+.1f}, {hi:+.1f}] (90 %, t, {df} df): {verdict}")
    for row in ranking[:5]:
        print(f"  {row['success']:5.1f}  {row['candidate']}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
