"""DRCT against plain and -RD fine-tunes over training seeds, from their weather-grid results.

Reads what ``experiments/drct_mbptrack.sh`` writes (``ROOT/weather/NAME/*/weather.json``, one
``pointtrack eval --weather ... --out`` per run; ``NAME`` is ``start`` or ``ARM-sSEED``) and
prints the tables of docs/mbptrack.md: per run and per arm (mean ± sd over seeds) the clean
Success, the weather-mean Success (the mean over every weather condition's Success) and the
mean DR (Success) over the weather kinds, for the ``mean`` / observed / unseen groups; then the
paired differences DRCT − plain and DRCT − RD with their 90 % t intervals, and the protocol's
verdict.

    python experiments/drct_seeds.py runs/mbptrack-drct [--arms plain rd drct] [--seeds 21 22 23]
    python experiments/drct_seeds.py runs/mbptrack-drct runs/mbptrack-drct-s21  # later roots'
                                                    # runs replace earlier ones of the same name
"""

from __future__ import annotations

import argparse
import json
import statistics
from pathlib import Path
from typing import Any

from training.intervals import paired_t_interval

GROUPS = ("mean", "observed", "unseen")
METRICS = {"clean": "clean Success", "weather": "weather-mean Success", "dr": "mean DR"}


def load_weather(folder: Path) -> dict[str, Any]:
    """The one ``weather.json`` under ``folder`` (a ``pointtrack eval --weather --out`` dir)."""
    paths = sorted(folder.glob("*/weather.json"))
    if len(paths) != 1:
        raise SystemExit(f"{folder}: expected one */weather.json, found {len(paths)}")
    try:
        return json.loads(paths[0].read_text())
    except (OSError, ValueError) as exc:
        raise SystemExit(f"{paths[0]}: cannot read a weather result ({exc})") from None


def run_metrics(result: dict[str, Any], group: str) -> dict[str, float]:
    """Clean Success, weather-mean Success (over every kind and level) and mean DR of ``group``."""
    try:
        entries = [result["robustness"][kind][group] for kind in result["kinds"]]
    except KeyError as exc:
        raise SystemExit(f"weather result of {result.get('tracker')}: no {exc} entry") from None
    levels = [level[0] for entry in entries for level in entry["levels"]]
    return {
        "clean": float(entries[0]["clean"][0]),
        "weather": float(statistics.fmean(levels)),
        "dr": float(statistics.fmean(entry["DR"][0] for entry in entries)),
    }


def fmt(metric: str, value: float) -> str:
    return f"{value:.3f}" if metric == "dr" else f"{value:.1f}"


def mean_sd(metric: str, values: list[float]) -> str:
    sd = statistics.stdev(values) if len(values) > 1 else float("nan")
    return f"{fmt(metric, statistics.fmean(values))} ± {fmt(metric, sd)}"


def diff_cell(metric: str, diffs: list[float]) -> str:
    mean, half = paired_t_interval(diffs)
    sign = "+" if mean >= 0 else ""
    if half is None:
        return f"{sign}{fmt(metric, mean)} (one pair)"
    return f"{sign}{fmt(metric, mean)} [{fmt(metric, mean - half)}, {fmt(metric, mean + half)}]"


def verdict(table: dict[str, dict[int, dict[str, float]]], seeds: list[int]) -> str:
    """The protocol's rule on the ``mean`` group: DRCT's weather-mean Success above plain's by
    more than the larger sd of the two arms, the paired interval above 0, clean within 1 point."""
    drct = [table["drct"][s]["weather"] for s in seeds]
    plain = [table["plain"][s]["weather"] for s in seeds]
    gain, half = paired_t_interval([d - p for d, p in zip(drct, plain, strict=True)])
    sd = max(statistics.stdev(drct), statistics.stdev(plain)) if len(seeds) > 1 else float("nan")
    clean = statistics.fmean(table["drct"][s]["clean"] - table["plain"][s]["clean"] for s in seeds)
    helps = half is not None and gain > sd and gain - half > 0 and abs(clean) <= 1.0
    interval = "no interval" if half is None else f"[{gain - half:+.2f}, {gain + half:+.2f}]"
    return (
        f"DRCT - plain, weather-mean Success {gain:+.2f} {interval} (paired, 90 %; larger sd "
        f"{sd:.2f}), clean {clean:+.2f}: " + ("DRCT helps" if helps else "not reproduced")
    )


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("roots", nargs="+", type=Path, metavar="ROOT")
    parser.add_argument("--arms", nargs="+", default=["plain", "rd", "drct"])
    parser.add_argument("--seeds", nargs="+", type=int, default=[21, 22, 23])
    args = parser.parse_args(argv)
    names = ["start"] + [f"{arm}-s{seed}" for arm in args.arms for seed in args.seeds]
    runs = {}
    for name in names:  # from the last root that has it; the start is optional
        found = [r / "weather" / name for r in args.roots if (r / "weather" / name).exists()]
        if found or name != "start":
            runs[name] = load_weather(found[-1] if found else args.roots[-1] / "weather" / name)
    for group in GROUPS:
        print(f"\n{group}: " + ", ".join(METRICS.values()))
        print("\n| run | " + " | ".join(METRICS.values()) + " |")
        print("| --- |" + " --- |" * len(METRICS))
        metrics = {name: run_metrics(result, group) for name, result in runs.items()}
        for name, values in metrics.items():
            print(f"| {name} | " + " | ".join(fmt(m, values[m]) for m in METRICS) + " |")
        table = {a: {s: metrics[f"{a}-s{s}"] for s in args.seeds} for a in args.arms}
        for arm in args.arms:
            cells = [mean_sd(m, [table[arm][s][m] for s in args.seeds]) for m in METRICS]
            print(f"| {arm} (mean ± sd) | " + " | ".join(cells) + " |")
        for other in [a for a in ("plain", "rd") if a in args.arms and "drct" in args.arms]:
            cells = [
                diff_cell(m, [table["drct"][s][m] - table[other][s][m] for s in args.seeds])
                for m in METRICS
            ]
            print(f"| drct − {other} (paired, 90 %) | " + " | ".join(cells) + " |")
        if group == "mean" and {"drct", "plain"} <= set(args.arms):
            print("\n" + verdict(table, args.seeds))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
