"""Uncertainty of OPE numbers: the one tracklet bootstrap, eval-seed means, intervals.

OPE pools frames, and a tracklet's Success is the AUC of its own frames, so a group's pooled
Success is the frame-weighted mean of its tracklets' Success (the AUC is linear in the curve).
Resampling tracklets with replacement and re-pooling therefore gives the spread a table's number
would have on another draw of tracklets of the same kind:

* :func:`resample_counts` draws, per stratum (a category; a selection part), as many tracklets
  as it has, with replacement: an ``(R, T)`` count matrix from one seeded generator;
* :func:`pooled_resamples` re-pools per-tracklet values under those counts, frame-weighted;
* :func:`percentile_interval` takes the two-sided percentile interval.

``training.selection.ranking_uncertainty`` (paired: every candidate on the same draws) and
:func:`add_intervals` (per category, observed, unseen and mean) both use these three.

:func:`combine_seeds` merges the reports of one tracker at several eval seeds into one: every
Success / Precision (and curve) is the mean over the seeds, and ``per_seed`` keeps each seed's.
"""

from __future__ import annotations

import copy
import math
from collections.abc import Hashable, Mapping, Sequence
from typing import Any

import numpy as np

__all__ = [
    "DEFAULT_LEVEL",
    "DEFAULT_RESAMPLES",
    "add_intervals",
    "check_seeds",
    "combine_seeds",
    "paired_t_interval",
    "percentile_interval",
    "pooled_resamples",
    "resample_counts",
    "welch_t_interval",
]

DEFAULT_LEVEL = 0.9
DEFAULT_RESAMPLES = 2000
GROUPS = ("observed", "unseen", "mean")
#: two-sided 90 % Student t quantiles by degrees of freedom (comparisons over 2-11 training seeds)
T90 = {
    1: 6.314, 2: 2.920, 3: 2.353, 4: 2.132, 5: 2.015, 6: 1.943, 7: 1.895, 8: 1.860, 9: 1.833,
    10: 1.812,
}  # fmt: skip


def _t90(df: int) -> float:
    """The 90 % two-sided t quantile at ``df`` degrees of freedom (``ValueError`` beyond T90)."""
    if df not in T90:
        raise ValueError(f"t interval over {df + 1} values: the table covers 2-{max(T90) + 1}")
    return T90[df]


def resample_counts(strata: Sequence[Hashable], resamples: int, seed: int) -> np.ndarray:
    """How often each of ``T`` tracklets is drawn in each of ``resamples`` bootstrap draws.

    Args:
        strata: ``(T,)`` the stratum of each tracklet; each stratum is redrawn with replacement
            to its own size, strata in the order of first appearance.
        resamples: ``R >= 1`` draws.
        seed: seed of the one ``numpy.random.Generator`` (same seed, same counts).

    Returns:
        ``(R, T)`` float counts; every row sums to ``T`` within each stratum.
    """
    if resamples < 1:
        raise ValueError(f"resamples must be >= 1, got {resamples}")
    labels = list(strata)
    rng = np.random.default_rng(seed)
    counts = np.zeros((resamples, len(labels)))
    for stratum in dict.fromkeys(labels):
        columns = np.flatnonzero([s == stratum for s in labels])
        counts[:, columns] = rng.multinomial(
            len(columns), np.full(len(columns), 1.0 / len(columns)), size=resamples
        )
    return counts


def pooled_resamples(counts: np.ndarray, frames: np.ndarray, values: np.ndarray) -> np.ndarray:
    """Frame-weighted pooled values under each draw.

    Args:
        counts: ``(R, T)`` from :func:`resample_counts` (columns outside a group set to 0).
        frames: ``(T,)`` frames per tracklet.
        values: ``(C, T)`` per-tracklet values of ``C`` candidates (or ``(T,)`` for one).

    Returns:
        ``(R, C)`` (or ``(R,)``): ``sum_t counts * frames * value / sum_t counts * frames``.
    """
    weights = counts * np.asarray(frames, dtype=np.float64)
    values = np.asarray(values, dtype=np.float64)
    return weights @ values.T / weights.sum(axis=1, keepdims=values.ndim > 1)


def percentile_interval(
    samples: np.ndarray, level: float = DEFAULT_LEVEL
) -> tuple[np.ndarray, np.ndarray]:
    """Two-sided percentile interval over axis 0 (``level`` 0.9: the 5th and 95th)."""
    if not 0.0 < level < 1.0:
        raise ValueError(f"level must be in (0, 1), got {level}")
    lo, hi = np.quantile(samples, [(1.0 - level) / 2, (1.0 + level) / 2], axis=0)
    return lo, hi


def add_intervals(
    report: dict[str, Any],
    *,
    level: float = DEFAULT_LEVEL,
    resamples: int = DEFAULT_RESAMPLES,
    seed: int = 0,
) -> dict[str, Any]:
    """Add ``success_interval`` / ``precision_interval`` ``[lo, hi]`` (percent) to every
    category of ``report`` and to its observed / unseen / mean groups, in place; returns it.

    The bootstrap redraws the tracklets of each category (stratified: a category keeps its
    number of tracklets, so the groups' category mix stays that of the split) and pools the
    per-tracklet values of ``report["per_tracklet"]`` frame-weighted over each draw; the same
    draws serve every group. ``report["interval"]`` records how.
    """
    rows = [r for r in report["per_tracklet"] if r["frames"]]
    if not rows:
        return report
    counts = resample_counts([r["category"] for r in rows], resamples, seed)
    frames = np.array([float(r["frames"]) for r in rows])
    values = np.array([[float(r[k]) for r in rows] for k in ("success", "precision")])  # (2, T)
    masks: dict[str, np.ndarray] = {
        "observed": np.array([bool(r["observed"]) for r in rows]),
        "mean": np.ones(len(rows), dtype=bool),
    }
    masks["unseen"] = ~masks["observed"]
    entries: list[tuple[dict[str, Any], np.ndarray]] = [
        (report[g], masks[g]) for g in GROUPS if masks[g].any()
    ]
    entries += [
        (entry, np.array([r["category"] == cat for r in rows]))
        for cat, entry in report["categories"].items()
        if any(r["category"] == cat for r in rows)
    ]
    for entry, mask in entries:
        lo, hi = percentile_interval(pooled_resamples(counts * mask, frames, values), level)
        entry["success_interval"] = [float(lo[0]), float(hi[0])]
        entry["precision_interval"] = [float(lo[1]), float(hi[1])]
    report["interval"] = {
        "level": level,
        "resamples": resamples,
        "seed": seed,
        "method": "percentile bootstrap over tracklets, stratified by category, frame-weighted",
    }
    return report


def paired_t_interval(diffs: Sequence[float]) -> tuple[float, float | None]:
    """Mean of paired differences (one per training seed) and the half width of its 90 % t
    interval; ``None`` with a single pair."""
    mean = float(np.mean(diffs))
    if len(diffs) < 2:
        return mean, None
    return mean, _t90(len(diffs) - 1) * float(np.std(diffs, ddof=1)) / math.sqrt(len(diffs))


def welch_t_interval(a: Sequence[float], b: Sequence[float]) -> tuple[float, float | None]:
    """``mean(a) - mean(b)`` and the half width of its 90 % Welch t interval, with the
    conservative degrees of freedom ``min(len(a), len(b)) - 1`` (the Welch-Satterthwaite lower
    bound); ``None`` when either side has one value."""
    diff = float(np.mean(a) - np.mean(b))
    if min(len(a), len(b)) < 2:
        return diff, None
    se = math.sqrt(np.var(a, ddof=1) / len(a) + np.var(b, ddof=1) / len(b))
    return diff, _t90(min(len(a), len(b)) - 1) * se


def check_seeds(seeds: Sequence[int]) -> list[int]:
    """Eval seeds, refused (``ValueError``, one line) when empty, negative or repeated."""
    seeds = [int(s) for s in seeds]
    if not seeds:
        raise ValueError("--eval-seeds needs at least one seed")
    negative = [s for s in seeds if s < 0]
    if negative:
        raise ValueError(f"--eval-seeds must be >= 0; got {negative[0]} in {seeds}")
    repeated = sorted({s for s in seeds if seeds.count(s) > 1})
    if repeated:
        raise ValueError(f"--eval-seeds lists seed {repeated[0]} twice: {seeds}")
    return seeds


def _mean(values: Sequence[float | None]) -> float:
    """The mean of the seeds' values (NaN when a seed has none: a group without frames)."""
    if any(v is None or (isinstance(v, float) and math.isnan(v)) for v in values):
        return math.nan
    return math.fsum(values) / len(values)


def _merge_entry(entries: Sequence[Mapping[str, Any]]) -> dict[str, Any]:
    """One category / group entry: the seeds' mean Success / Precision and curves."""
    merged = dict(copy.deepcopy(entries[0]))
    for key in ("success", "precision"):
        merged[key] = _mean([e[key] for e in entries])
        merged[f"{key}_seeds"] = [e[key] for e in entries]
        curve = f"{key}_curve"
        if curve in merged:
            merged[curve] = [_mean(v) for v in zip(*(e[curve] for e in entries), strict=True)]
    return merged


def combine_seeds(reports: Sequence[Mapping[str, Any]], seeds: Sequence[int]) -> dict[str, Any]:
    """One report from a tracker's reports at ``seeds`` (same tracklets; ``ValueError``
    otherwise): each Success / Precision is the mean over the seeds (``*_seeds``: each seed's
    value, in ``seeds`` order); ``per_tracklet`` likewise; ``eval_seeds`` lists the seeds."""
    if len(reports) != len(seeds) or not reports:
        raise ValueError("combine_seeds: one report per seed")
    if len(reports) == 1:
        return dict(reports[0]) | {"eval_seeds": [int(seeds[0])]}
    ids = [[r["tracklet"] for r in rep["per_tracklet"]] for rep in reports]
    if any(i != ids[0] for i in ids[1:]):
        raise ValueError("combine_seeds: the seeds' reports cover different tracklets")
    out = dict(copy.deepcopy(reports[0]))
    out.pop("boxes", None)
    for g in GROUPS:
        out[g] = _merge_entry([r[g] for r in reports])
    out["categories"] = {
        c: _merge_entry([r["categories"][c] for r in reports]) for c in reports[0]["categories"]
    }
    out["per_tracklet"] = [
        {**rows[0], **{k: _mean([r[k] for r in rows]) for k in ("success", "precision")}}
        | {f"{k}_seeds": [r[k] for r in rows] for k in ("success", "precision")}
        for rows in zip(*(r["per_tracklet"] for r in reports), strict=True)
    ]
    out["tracker_fps"] = _mean([r["tracker_fps"] for r in reports])
    out["wall_s"] = math.fsum(r["wall_s"] for r in reports)
    out["eval_seeds"] = [int(s) for s in seeds]
    return out
