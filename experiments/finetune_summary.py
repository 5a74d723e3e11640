"""A ``pointtrack finetune`` run's training summary, from its ``log.jsonl``.

Wall time, steps/s, and the first and last eight updates' rollout IoU, episode reward and
``group_reward_std`` (``--algo group`` only), with the mean and largest approx_kl. ::

    python experiments/finetune_summary.py runs19/gpt-grp-1 runs19/gpt-grp-2
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np


def summary(run: Path, window: int = 8) -> str:
    """One line describing the run's training log."""
    lines = (run / "log.jsonl").read_text().splitlines()
    rows = [r for r in map(json.loads, lines) if r.get("kind") == "train"]
    if not rows:
        raise SystemExit(f"{run / 'log.jsonl'}: no training rows")

    def first_last(key: str) -> str:
        values = np.array([r.get(key, np.nan) for r in rows], dtype=float)
        if np.isnan(values).all():
            return "n/a"
        return f"{np.nanmean(values[:window]):.3f} / {np.nanmean(values[-window:]):.3f}"

    kl = np.array([r["approx_kl"] for r in rows])
    last = rows[-1]
    return (
        f"{run}: {last['step']} steps, {last['wall_s']:.0f} s, "
        f"{last['step'] / last['wall_s']:.1f} steps/s; first / last {window} updates: rollout IoU "
        f"{first_last('iou')}, episode reward {first_last('ep_reward')}, group_reward_std "
        f"{first_last('group_reward_std')}; approx_kl mean {kl.mean():.3f} (max {kl.max():.2f})"
    )


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("runs", nargs="+", type=Path, help="pointtrack finetune --out directories")
    for run in parser.parse_args().runs:
        print(summary(run))


if __name__ == "__main__":
    main()
