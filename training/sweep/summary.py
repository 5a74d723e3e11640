"""What a finished trial measured, read from the files its command wrote, and the sweep's
summary table: mean +- sd over the seeds of each group of trials (the trials whose overrides
differ only in the spec's ``seed_key``), as CSV and Markdown.

Metrics per command (Success / Precision in percent, OPE as ``envs.metrics``):

- ``train``: ``val_success`` / ``val_precision`` of the best validated epoch (what ``best.pt``
  holds) and ``epochs``, from ``log.jsonl``;
- ``finetune``: ``val.json``'s ``success`` / ``precision`` of the fine-tuned and the base tracker;
- ``eval``: ``report.json``'s frame-weighted ``mean`` per tracker (one tracker: plain names);
- ``eval --weather``: the clean Success and, per weather kind, the mean Success over the levels
  and the degradation ``DR`` (Tables III-IV of Zhao et al.), from ``weather_*/weather.json``;
- ``select``: the first-ranked candidate's ``success`` / ``precision`` from ``selection.json``.
"""

from __future__ import annotations

import csv
import io
import json
import math
import statistics
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from training.rundir import atomic_write_text

__all__ = [
    "GroupRow",
    "format_markdown",
    "summarize",
    "trial_metrics",
    "write_summary",
]


def trial_metrics(command: str, run_dir: str | Path) -> dict[str, float]:
    """The numbers a finished trial of ``command`` wrote into ``run_dir`` (see the module
    docstring); ``OSError`` / ``ValueError`` naming the file when it is missing or torn."""
    run_dir = Path(run_dir)
    reader = {
        "train": _train,
        "finetune": _finetune,
        "eval": _eval,
        "eval --weather": _weather,
        "select": _select,
    }[command]
    return reader(run_dir)


def _json(path: Path) -> Any:
    try:
        return json.loads(path.read_text())
    except json.JSONDecodeError as exc:
        raise ValueError(f"{path} is not valid JSON: {exc}") from None


def _train(run_dir: Path) -> dict[str, float]:
    path = run_dir / "log.jsonl"
    epochs = [r for r in map(json.loads, path.read_text().splitlines()) if r.get("kind") == "epoch"]
    if not epochs:
        raise ValueError(f"{path} holds no finished epoch")
    validated = [r for r in epochs if r.get("val_success") is not None]
    out = {"epochs": float(epochs[-1]["epoch"]), "loss": float(epochs[-1]["total"])}
    if validated:
        best = max(validated, key=lambda r: r["val_success"])  # the epoch best.pt holds
        out |= {"val_success": best["val_success"], "val_precision": best["val_precision"]}
    return out


def _finetune(run_dir: Path) -> dict[str, float]:
    val = _json(run_dir / "val.json")
    return {
        f"{k}_{m}": float(val[k][m])
        for k in ("finetuned", "base")
        for m in ("success", "precision")
    }


def _eval(run_dir: Path) -> dict[str, float]:
    reports = _json(run_dir / "report.json")
    out = {}
    for name, report in reports.items():
        prefix = "" if len(reports) == 1 else f"{name}/"
        for metric in ("success", "precision"):
            out[prefix + metric] = _number(report["mean"][metric])
    return out


def _weather(run_dir: Path) -> dict[str, float]:
    files = sorted(run_dir.glob("weather_*/weather.json"))
    if not files:
        raise OSError(f"no weather_*/weather.json in {run_dir}")
    out = {}
    for path in files:
        result = _json(path)
        prefix = "" if len(files) == 1 else f"{result['tracker']}/"
        out[prefix + "clean_success"] = _number(result["clean"]["mean"]["success"])
        for kind in result["kinds"]:
            levels = result["weather"][kind].values()
            scores = [_number(r["mean"]["success"]) for r in levels]
            out[f"{prefix}{kind}_success"] = sum(scores) / len(scores)
            out[f"{prefix}{kind}_DR"] = _number(result["robustness"][kind]["mean"]["DR"][0])
    return out


def _select(run_dir: Path) -> dict[str, float]:
    best = _json(run_dir / "selection.json")["ranking"][0]
    return {"best_success": _number(best["success"]), "best_precision": _number(best["precision"])}


def _number(value: Any) -> float:
    return math.nan if value is None else float(value)


@dataclass(frozen=True)
class GroupRow:
    """One group of trials: its overrides without the seed key, the trials that finished and,
    per metric, the mean and the sample standard deviation (NaN for a single seed)."""

    group: str
    trials: int
    seeds: list[Any]
    mean: dict[str, float]
    sd: dict[str, float]


def summarize(
    finished: Sequence[Mapping[str, Any]], seed_key: str
) -> tuple[list[GroupRow], list[str]]:
    """Group finished trials (``{"overrides", "metrics"}`` records, in grid order) by their
    overrides less ``seed_key``; returns the rows in first-seen order and the metric names."""
    groups: dict[str, list[Mapping[str, Any]]] = {}
    for record in finished:
        rest = {k: v for k, v in record["overrides"].items() if k != seed_key}
        label = ", ".join(f"{k.replace('_', '-')}={v}" for k, v in rest.items()) or "all"
        groups.setdefault(label, []).append(record)
    metrics: list[str] = []
    for record in finished:
        metrics += [m for m in record["metrics"] if m not in metrics]
    rows = []
    for label, records in groups.items():
        mean, sd = {}, {}
        for m in metrics:
            values = [float(r["metrics"][m]) for r in records if m in r["metrics"]]
            values = [v for v in values if math.isfinite(v)]
            mean[m] = statistics.fmean(values) if values else math.nan
            sd[m] = statistics.stdev(values) if len(values) > 1 else math.nan
        seeds = [r["overrides"].get(seed_key) for r in records]
        rows.append(GroupRow(label, len(records), seeds, mean, sd))
    return rows, metrics


def _pm(mean: float, sd: float) -> str:
    if math.isnan(mean):
        return "-"
    return f"{mean:.2f}" if math.isnan(sd) else f"{mean:.2f} ± {sd:.2f}"


def format_markdown(rows: Sequence[GroupRow], metrics: Sequence[str], seed_key: str) -> str:
    """A Markdown table: one row per group, ``mean ± sd`` over its seeds per metric."""
    head = ["group", "trials", seed_key.replace("_", "-"), *metrics]
    lines = ["| " + " | ".join(head) + " |", "|" + "---|" * len(head)]
    for row in rows:
        cells = [row.group, str(row.trials), ",".join(map(str, row.seeds))]
        cells += [_pm(row.mean[m], row.sd[m]) for m in metrics]
        lines.append("| " + " | ".join(cells) + " |")
    return "\n".join(lines)


def _csv(rows: Sequence[GroupRow], metrics: Sequence[str]) -> str:
    buffer = io.StringIO()
    writer = csv.writer(buffer, lineterminator="\n")
    writer.writerow(["group", "trials", "seeds"] + [f"{m}_{s}" for m in metrics for s in "ms"])
    for row in rows:
        numbers = [row.mean[m] if s == "m" else row.sd[m] for m in metrics for s in "ms"]
        writer.writerow([row.group, row.trials, " ".join(map(str, row.seeds))] + numbers)
    return buffer.getvalue()


def write_summary(
    out: str | Path, rows: Sequence[GroupRow], metrics: Sequence[str], seed_key: str
) -> tuple[Path, Path]:
    """Write ``summary.csv`` (``METRIC_m`` mean, ``METRIC_s`` sd) and ``summary.md`` into
    ``out``, each atomically; returns their paths."""
    out = Path(out)
    csv_path = atomic_write_text(out / "summary.csv", _csv(rows, metrics))
    md_path = atomic_write_text(out / "summary.md", format_markdown(rows, metrics, seed_key) + "\n")
    return csv_path, md_path
