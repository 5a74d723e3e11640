"""Reports of :func:`training.evaluate.evaluate` as text, JSON and plots.

:func:`format_table` prints one row per report (``45.6 ± 2.1`` where the report carries
bootstrap intervals, :mod:`training.intervals`; an oracle reference marked in the name),
:func:`save_report` writes JSON atomically, :func:`plot_curves` draws the OPE curves.
"""

from __future__ import annotations

import json
import math
from collections.abc import Iterable, Mapping, Sequence
from pathlib import Path
from typing import Any

import numpy as np

from envs.metrics import THRESHOLDS_IOU, THRESHOLDS_M
from envs.plotting import pyplot, save_figure
from training.rundir import atomic_write_text

__all__ = [
    "category_order",
    "display_name",
    "format_table",
    "json_safe",
    "plot_curves",
    "save_report",
    "slug",
]


def slug(name: str) -> str:
    """``name`` as a file name: characters other than letters, digits, ``-_.`` become ``_``."""
    return "".join(c if c.isalnum() or c in "-_." else "_" for c in name)


def _fmt(x: float) -> str:
    return "  -  " if x is None or (isinstance(x, float) and math.isnan(x)) else f"{x:5.1f}"


def _cell(entry: Mapping[str, Any] | None) -> str:
    """``Succ / Prec`` of a table entry, each as ``45.6 ± 2.1`` when it has an interval (the
    half-width of its ``[lo, hi]``)."""
    if entry is None:
        return "-"
    parts = []
    for key in ("success", "precision"):
        text = _fmt(entry[key])
        bounds = entry.get(f"{key}_interval")
        if bounds is not None and None not in bounds:
            text += f" ± {(bounds[1] - bounds[0]) / 2:3.1f}"
        parts.append(text)
    return " / ".join(parts)


def display_name(name: str, report: Mapping[str, Any]) -> str:
    """A table's name for a report: ``name (oracle: current_gt)`` for an oracle reference."""
    oracle = report.get("oracle")
    return f"{name} (oracle: {oracle})" if oracle else name


def category_order(categories: Iterable[str]) -> list[str]:
    """Categories in one fixed order whatever the reports hold: KITTI's label order
    (``envs.data.kitti.CATEGORIES``), then any other name alphabetically."""
    from envs.data.kitti import CATEGORIES

    names = set(categories)
    rank = {c: i for i, c in enumerate(CATEGORIES)}
    return sorted(names, key=lambda c: (rank.get(c, len(rank)), c))


def format_table(reports: Mapping[str, Mapping[str, Any]] | Sequence[Mapping[str, Any]]) -> str:
    """A plain-text table: one row per report, ``Success / Precision`` per category in a fixed
    order (:func:`category_order`; unseen ones marked ``*``), then the observed, unseen and
    frame-weighted mean groups, frames and the tracker's frames/s."""
    if not isinstance(reports, Mapping):
        reports = {r.get("tracker", f"#{i}"): r for i, r in enumerate(reports)}
    unseen: set[str] = set()
    found: set[str] = set()
    for r in reports.values():
        for c, e in r["categories"].items():
            found.add(c)
            if not e["observed"]:
                unseen.add(c)
    cats = category_order(found)
    cols = [c + ("*" if c in unseen else "") for c in cats] + ["observed", "unseen", "mean"]
    names = {n: display_name(n, r) for n, r in reports.items()}
    rows = {
        n: [_cell(r["categories"].get(c)) for c in cats]
        + [_cell(r[g]) for g in ("observed", "unseen", "mean")]
        for n, r in reports.items()
    }
    width = max(13, *(len(c) for c in cols), *(len(x) for cells in rows.values() for x in cells))
    namew = max(12, *(len(n) for n in names.values()))
    head = f"{'tracker':<{namew}} | " + " | ".join(f"{c:^{width}}" for c in cols)
    head += " | frames |   fps"
    sub = (
        f"{'':<{namew}} | " + " | ".join(f"{'Succ / Prec':^{width}}" for _ in cols) + " |        |"
    )
    lines = [head, sub, "-" * len(head)]
    for n, r in reports.items():
        cells = [f"{txt:^{width}}" for txt in rows[n]]
        fps = r.get("tracker_fps", float("nan"))
        fps_txt = "  inf" if fps == float("inf") else f"{fps:5.0f}"
        lines.append(
            f"{names[n]:<{namew}} | "
            + " | ".join(cells)
            + f" | {r['mean']['frames']:6d} | {fps_txt}"
        )
    if unseen:
        lines.append("* unseen category (not in the setting's observed categories)")
    notes = {json.dumps(r.get("interval"), sort_keys=True) for r in reports.values()}
    if any(r.get("interval") for r in reports.values()):
        level = next(r["interval"]["level"] for r in reports.values() if r.get("interval"))
        lines.append(
            f"± half-width of the {level:.0%} bootstrap interval over tracklets"
            + ("" if len(notes) == 1 else " (settings differ between rows)")
        )
    seeds = [r["eval_seeds"] for r in reports.values() if len(r.get("eval_seeds", ())) > 1]
    if seeds:
        lines.append(f"mean over eval seeds {seeds[0]}")
    if any(r.get("oracle") for r in reports.values()):
        lines.append("(oracle: ...) search area cut around the ground truth, not a tracking result")
    return "\n".join(lines)


def json_safe(x: Any) -> Any:
    """``x`` with numpy values as Python ones and NaN / inf as ``None`` (JSON-able)."""
    if isinstance(x, dict):
        return {str(k): json_safe(v) for k, v in x.items()}
    if isinstance(x, list | tuple):
        return [json_safe(v) for v in x]
    if isinstance(x, np.ndarray):
        return json_safe(x.tolist())
    if isinstance(x, np.generic):
        x = x.item()
    if isinstance(x, float) and not math.isfinite(x):
        return None
    return x


def save_report(report: Mapping[str, Any], path: str | Path) -> Path:
    """Write a report (or ``{name: report}``) as JSON (NaN / inf -> ``null``); returns the path.

    Written to a temporary file and renamed, so a killed run never leaves a truncated report (the
    selection in :mod:`training.selection` reuses reports as a cache)."""
    return atomic_write_text(path, json.dumps(json_safe(dict(report)), indent=2) + "\n")


def plot_curves(
    reports: Mapping[str, Mapping[str, Any]],
    out_dir: str | Path,
    prefix: str = "",
    workers: int | None = 1,
) -> list[Path]:
    """Draw ``<prefix>success.png`` and ``<prefix>precision.png`` in ``out_dir``: one panel per
    group (mean, observed, unseen) with one curve per tracker; returns the paths. ``workers >
    1`` draws the two in forked processes (:func:`~training.parallel.map_forked`)."""
    from training.parallel import map_forked

    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    groups = [
        g for g in ("mean", "observed", "unseen") if any(r[g]["frames"] for r in reports.values())
    ]

    def draw(key: str) -> Path:
        return _plot_curve(reports, groups, key, out / f"{prefix}{key}.png")

    return map_forked(draw, ["success", "precision"], workers, label=lambda key: f"{key} plot")


def _plot_curve(
    reports: Mapping[str, Mapping[str, Any]], groups: list[str], key: str, path: Path
) -> Path:
    xs, xlabel, ylabel = {
        "success": (THRESHOLDS_IOU, "overlap threshold (3D IoU)", "success rate"),
        "precision": (THRESHOLDS_M, "centre error threshold (m)", "precision"),
    }[key]
    plt = pyplot()
    fig, axes = plt.subplots(1, len(groups), figsize=(4.2 * len(groups), 3.6), squeeze=False)
    for ax, g in zip(axes[0], groups, strict=True):
        for n, r in reports.items():
            e = r[g]
            if not e["frames"] or f"{key}_curve" not in e:
                continue
            ax.plot(xs, e[f"{key}_curve"], label=f"{n} [{e[key]:.1f}]")
        ax.set_title(f"{key.capitalize()} — {g}")
        ax.set_xlabel(xlabel)
        ax.set_ylabel(ylabel)
        ax.set_ylim(0, 1.02)
        ax.grid(alpha=0.3)
        ax.legend(fontsize=7)
    fig.tight_layout()
    return save_figure(fig, path, 110)
