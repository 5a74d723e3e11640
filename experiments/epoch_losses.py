"""Per-epoch mean training losses (and val Success where validated) of ``pointtrack train`` runs,
side by side, from their ``log.jsonl``. Runs of the same seed and data see the same samples, so
their rows are paired: e.g. a model at two widths. ::

    python experiments/epoch_losses.py runs21/abl-bat-v1-s0 runs22/bat-kitti1-default-u \\
        --epochs 6 --keys total vote objectness box
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path


def epoch_rows(run: Path) -> dict[int, dict]:
    """``epoch -> the run's "epoch" log row`` (mean losses, samples/s, val_success if run)."""
    log = run / "log.jsonl"
    if not log.is_file():
        raise SystemExit(f"{log}: no such file (is {run} a pointtrack train run?)")
    rows = [r for r in map(json.loads, log.read_text().splitlines()) if r.get("kind") == "epoch"]
    if not rows:
        raise SystemExit(f"{log}: no finished epoch yet")
    return {int(r["epoch"]): r for r in rows}


def table(runs: list[Path], keys: list[str], epochs: int | None) -> str:
    """A Markdown table: one row per epoch, for each run its ``keys`` and val Success."""
    logs = [epoch_rows(run) for run in runs]
    last = max(max(log) for log in logs)
    header = ["epoch"] + [f"{run.name}: {key}" for run in runs for key in [*keys, "val"]]
    lines = ["| " + " | ".join(header) + " |", "|" + " --- |" * len(header)]
    for epoch in range(1, min(last, epochs or last) + 1):
        cells = [str(epoch)]
        for log in logs:
            row = log.get(epoch, {})
            cells += [f"{row[key]:.3f}" if key in row else "" for key in keys]
            cells.append(f"{row['val_success']:.1f}" if "val_success" in row else "")
        lines.append("| " + " | ".join(cells) + " |")
    return "\n".join(lines)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("runs", nargs="+", type=Path, help="run directories (--out of train)")
    parser.add_argument("--keys", nargs="+", default=["total"], help="loss terms to show")
    parser.add_argument("--epochs", type=int, default=None, help="the first N epochs only")
    args = parser.parse_args()
    print(table(args.runs, args.keys, args.epochs))


if __name__ == "__main__":
    main()
