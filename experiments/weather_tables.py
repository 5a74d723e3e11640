"""Combine several `pointtrack eval --weather` results into one robustness table and one plot.

Each `pointtrack eval --weather ... --out DIR` run writes ``DIR/weather_<tracker>/weather.json``;
this script puts several of them side by side (Tables III-IV layout of the benchmark paper),
adds a summary per tracker (clean Success of the observed / unseen groups and the mean
degradation rate DR of each group over fog, rain and snow) and draws Success against level.

    PYTHONPATH=$PWD python experiments/weather_tables.py \
        p2b-kitti1-u=runs/weather/p2b/weather_p2b-kitti1-u/weather.json \
        drct=runs/weather/drct/weather_drct/weather.json \
        --table docs/weather_table.txt --plot docs/weather_success_all.png --groups mean unseen
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path
from typing import Any

import numpy as np

from training.robustness import format_weather_table, plot_success_vs_level


def load_result(item: str) -> dict[str, Any]:
    """``LABEL=PATH`` or ``PATH`` of a ``weather.json``; the label replaces the tracker name."""
    label, sep, path = item.partition("=")
    if not sep:
        label, path = "", item
    result = json.loads(Path(path).read_text())
    if label:
        result["tracker"] = label
    return result


def summary(result: dict[str, Any], groups: tuple[str, ...] = ("observed", "unseen", "mean")):
    """Per group: clean Success and the mean DR (Success) over the weather kinds of the run."""
    rows = {}
    for group in groups:
        entries = [result["robustness"][kind].get(group) for kind in result["kinds"]]
        entries = [e for e in entries if e is not None]
        if not entries:
            continue
        rows[group] = {
            "clean_success": entries[0]["clean"][0],
            "mean_dr_success": float(np.mean([e["DR"][0] for e in entries])),
            "dr_success": {k: e["DR"][0] for k, e in zip(result["kinds"], entries, strict=True)},
        }
    return rows


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("results", nargs="+", help="LABEL=PATH/weather.json or PATH")
    parser.add_argument("--table", help="also write the table to this file")
    parser.add_argument("--plot", help="write Success against level to this PNG")
    parser.add_argument("--groups", nargs="*", default=["mean", "unseen"], help="plot lines")
    args = parser.parse_args(argv)
    results = [load_result(item) for item in args.results]
    lines = [format_weather_table(results), "", "Summary (Success, percent; DR as a fraction):"]
    for r in results:
        cells = [
            f"{g} clean {v['clean_success']:.2f} mean DR {v['mean_dr_success']:.3f}"
            for g, v in summary(r).items()
        ]
        lines.append(f"  {r['tracker']}: " + "; ".join(cells))
    text = "\n".join(lines)
    print(text)
    if args.table:
        Path(args.table).write_text(text + "\n")
    if args.plot:
        plot_success_vs_level(results, args.plot, groups=args.groups)


if __name__ == "__main__":
    main()
