"""Checkpoint selection on validation data pooled over several synthetic worlds.

One world's val split holds a few tens of tracklets, and checkpoints of one model are often a few
Success points apart, so a ranking on it is mostly a ranking of which tracklets happen to be
there. Worlds with other seeds come from the same generator and no run trains on them, so their
val *and* test splits are fresh validation data. :func:`score_candidates` evaluates each
candidate on every part, pools Success / Precision over the frames of the setting's **observed**
categories and ranks the candidates. Two things are never scored: the unseen categories (the
class-agnostic study measures them, so choosing on them would leak the held-out category) and the
test split of the training world (the benchmark).

Pooling is exact: Success and Precision are means over thresholds of the fraction of frames that
pass, so the score of the pooled frames is the frames-weighted mean of the parts' scores.

Every (part, candidate) report is cached under ``cache_dir`` (written atomically, keyed by the
checkpoint's SHA-256 and the evaluation settings, ``num_envs`` included: batching can change a
learned tracker's result, see ``training.evaluate.evaluate``), so an interrupted selection
resumes where it stopped and adding a candidate scores only the new one.
"""

from __future__ import annotations

import json
import logging
import re
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import trackers
from envs.data.nuscenes import check_frame
from trackers.base import Tracker
from training.loading import load_tracker
from training.provenance import check_candidates, selected_provenance, selection_round
from training.rundir import file_sha256, remove_stale_temps

logger = logging.getLogger(__name__)

__all__ = [
    "DEFAULT_PARTS",
    "SelectionConfig",
    "ValPart",
    "check_parts",
    "format_ranking",
    "load_candidate",
    "observed_tracklet_scores",
    "pooled",
    "ranking_uncertainty",
    "score_candidates",
    "tied_with_first",
]

_SPLITS = ("train", "val", "test")


@dataclass(frozen=True)
class ValPart:
    """One split of one synthetic world, written ``"WORLD_SEED:SPLIT"`` (``"2:val"``)."""

    world_seed: int
    split: str

    @classmethod
    def parse(cls, text: str) -> ValPart:
        """``"2:val"`` -> ``ValPart(2, "val")``; ``ValueError`` naming ``text`` otherwise."""
        match = re.fullmatch(r"\s*(\d+)\s*:\s*(\w+)\s*", str(text))
        if match is None or match.group(2) not in _SPLITS:
            raise ValueError(
                f"validation part {text!r}: expected WORLD_SEED:SPLIT with SPLIT one of "
                f"{', '.join(_SPLITS)} (e.g. '2:val')"
            )
        return cls(int(match.group(1)), match.group(2))

    def __str__(self) -> str:
        return f"{self.world_seed}:{self.split}"


DEFAULT_PARTS: tuple[ValPart, ...] = tuple(
    ValPart.parse(p) for p in ("0:val", "1:val", "1:test", "2:val", "2:test", "3:val", "3:test")
)


def check_parts(parts: Sequence[ValPart], train_world_seed: int) -> None:
    """Refuse an empty or repeated part list and any part of the training world but its val split
    (its train split is what the candidates learnt from; its test split is the benchmark)."""
    if not parts:
        raise ValueError("no validation parts given")
    seen: set[ValPart] = set()
    for part in parts:
        if part in seen:
            raise ValueError(f"validation part {part} is listed twice")
        seen.add(part)
        if part.world_seed == train_world_seed and part.split != "val":
            role = "the benchmark" if part.split == "test" else "the training data"
            raise ValueError(
                f"validation part {part}: world {train_world_seed} is the training world and its "
                f"{part.split} split is {role}; use its val split or another world's splits"
            )


@dataclass(frozen=True)
class SelectionConfig:
    """What the candidates are scored on.

    Attributes:
        setting: class-agnostic setting (``"kitti-1"``) or ``"class-specific:<Category>"``; only
            its observed categories are scored.
        preset, sensor: the synthetic worlds (see ``envs.synthetic``).
        dataset: ``"synthetic"`` (KITTI layout) or ``"nuscenes"`` (the same worlds written in
            nuScenes layout; a part's split is a role, see ``envs.data.nuscenes.SOT_SPLITS``).
        nuscenes_frame: with ``dataset="nuscenes"``, the LiDAR frame served (``"lidar"`` or
            ``"scene"``, :class:`envs.data.nuscenes.NuScenesTracking`).
        parts: the world splits pooled into one score.
        train_world_seed: the world the candidates were trained on (guards its train/test).
        eval_seed: seed of the point resampling (``training.evaluate.evaluate``).
        num_envs: sub-envs per evaluation, so a tracker acts on batches (the trackers' eval
            forwards are batch-invariant on the CPU, so the scores do not depend on it).
        workers: processes each evaluation shards its tracklets over
            (``training.evaluate.evaluate``; ``None``: every usable core); only with
            ``num_envs=1``. The scores do not depend on it (not part of the cache key).
    """

    setting: str = "kitti-1"
    preset: str = "default"
    sensor: str = "hdl64"
    parts: tuple[ValPart, ...] = field(default=DEFAULT_PARTS)
    train_world_seed: int = 0
    eval_seed: int = 0
    num_envs: int = 1
    dataset: str = "synthetic"
    workers: int | None = 1
    nuscenes_frame: str = "lidar"

    def __post_init__(self) -> None:
        check_parts(self.parts, self.train_world_seed)
        if self.dataset not in ("synthetic", "nuscenes"):
            raise ValueError(f"dataset must be 'synthetic' or 'nuscenes', got {self.dataset!r}")
        check_frame(self.nuscenes_frame, self.dataset)
        if self.num_envs < 1:
            raise ValueError(f"num_envs must be >= 1, got {self.num_envs}")
        if self.num_envs > 1 and self.workers != 1:
            raise ValueError(
                f"workers={self.workers} shards tracklets over processes with one env each; "
                f"it cannot be combined with num_envs={self.num_envs} (choose one)"
            )


def pooled(entries: Sequence[Mapping[str, Any]]) -> dict[str, float]:
    """Pool report entries (each ``{"success", "precision", "frames"}``) over their frames.

    Returns ``{"success", "precision", "frames"}``; entries without frames do not count.
    """
    frames = sum(float(e["frames"]) for e in entries)
    if frames <= 0:
        return {"success": float("nan"), "precision": float("nan"), "frames": 0.0}
    return {
        key: sum(float(e[key]) * float(e["frames"]) for e in entries if e["frames"]) / frames
        for key in ("success", "precision")
    } | {"frames": frames}


def load_candidate(candidate: str) -> Any:
    """A tracker from a training checkpoint (``best.pt`` / ``last.pt``: the weights its run
    validated, see ``training.checkpoint.load_weights``) or anything ``trackers.load`` takes
    (:func:`training.loading.load_tracker`; a learned tracker's bare name is refused: it has no
    weights to select).

    Raises ``ValueError`` naming the candidate when it cannot be read."""
    try:
        return load_tracker(candidate)
    except (OSError, ValueError, KeyError) as exc:
        raise ValueError(f"candidate {candidate!r}: {exc}") from exc


def _candidate_digest(candidate: str) -> str:
    """SHA-256 of a checkpoint file, or the name itself for a baseline / registered tracker."""
    from trackers.registry import find_checkpoint

    path = find_checkpoint(candidate)
    if path is None:
        return f"name:{candidate}"
    return "sha256:" + file_sha256(path)


def _refuse_same_file(digests: Mapping[str, str]) -> None:
    """One file given twice (a shipped name and its path, two paths) would be scored twice
    and tie with itself: refuse it, naming both."""
    seen: dict[str, str] = {}
    for candidate, digest in digests.items():
        if digest.startswith("sha256:") and digest in seen:
            raise ValueError(
                f"candidates {seen[digest]!r} and {candidate!r} are the same file "
                f"(SHA-256 {digest[len('sha256:') :][:16]}...); give it once"
            )
        seen.setdefault(digest, candidate)


def tied_with_first(rows: Sequence[Mapping[str, Any]]) -> list[str]:
    """The candidates after the first whose pooled Success equals the first's exactly (a tie
    the ranking's order does not decide)."""
    return [str(r["candidate"]) for r in rows[1:] if r["success"] == rows[0]["success"]]


def _cache_path(cache_dir: Path, part: ValPart, candidate: str, digest: str) -> Path:
    stem = re.sub(r"[^A-Za-z0-9_.-]+", "_", Path(candidate).name)[:60]
    return cache_dir / f"w{part.world_seed}-{part.split}" / f"{stem}-{digest[-12:]}.json"


def score_candidates(
    candidates: Sequence[str],
    config: SelectionConfig | None = None,
    *,
    cache_dir: str | Path | None = None,
    progress: bool = False,
    log: Callable[[str], None] | None = None,
) -> list[dict[str, Any]]:
    """Score every candidate on every part of ``config`` and rank them.

    Args:
        candidates: training checkpoints (``OUT/best.pt``), tracker files, shipped checkpoint
            names or tracker names (:func:`load_candidate`).
        config: the parts, setting and evaluation settings (default: :class:`SelectionConfig`).
        cache_dir: keep each (part, candidate) report here and reuse it when its key matches.
        progress: tqdm bars while evaluating.
        log: called with one line per evaluated or reused (part, candidate) (default: this
            module's :mod:`logging` logger, at INFO).

    Returns:
        One row per candidate, best first (ties keep the given order): ``{"candidate", "success",
        "precision", "frames", "parts": {"2:val": {"success", "precision", "frames"}, ...},
        "per_tracklet": {"2:val/0017/10": {"success", "precision", "frames"}, ...}}``, Success /
        Precision in % over the observed categories (``per_tracklet`` feeds
        :func:`ranking_uncertainty`).
    """
    from envs.data import get_setting
    from envs.tracking_env import make_synthetic_env
    from training.evaluate import (
        env_options_for,
        evaluate,
        json_safe,
        observation_keys_for,
        save_report,
    )

    config = config if config is not None else SelectionConfig()
    if not candidates:
        raise ValueError("no candidates given")
    if len(set(candidates)) != len(candidates):
        raise ValueError(f"a candidate is listed twice: {list(candidates)}")
    observed = list(get_setting(config.setting).observed)
    # all of them before any scoring, so a typo fails in a second
    loaded = {c: load_candidate(c) for c in candidates}
    check_candidates(loaded, config, log)  # none trained on the parts or the unseen categories
    digests = {c: _candidate_digest(c) for c in candidates}
    _refuse_same_file(digests)
    cache = Path(cache_dir) if cache_dir is not None else None
    if cache is not None:  # temporaries of a killed selection (reports are renamed into place)
        for part in config.parts:
            remove_stale_temps(cache / f"w{part.world_seed}-{part.split}")
    per_part: dict[str, dict[str, dict[str, float]]] = {c: {} for c in candidates}
    per_tracklet: dict[str, dict[str, dict[str, float]]] = {c: {} for c in candidates}
    # each candidate is scored with the env options it records (e.g. recipe v2's template mode)
    options = {c: env_options_for([loaded[c]]) for c in candidates}
    # and with the opt-in observation keys it reads (M2-Track's previous frame)
    env_kwargs = {
        c: {**options[c], "observation_keys": observation_keys_for([loaded[c]])} for c in candidates
    }
    for part in config.parts:
        envs: dict[str, Any] = {}  # JSON of the options -> the part's env with them
        for candidate in candidates:
            key = {
                "candidate": candidate,
                "digest": digests[candidate],
                "part": str(part),
                "setting": config.setting,
                "preset": config.preset,
                "sensor": config.sensor,
                "eval_seed": config.eval_seed,
                "num_envs": config.num_envs,
            }
            if config.dataset != "synthetic":  # keys of earlier (synthetic) caches unchanged
                key["dataset"] = config.dataset
            if config.nuscenes_frame != "lidar":  # likewise
                key["nuscenes_frame"] = config.nuscenes_frame
            if options[candidate]:  # likewise: only a candidate that records options
                key["env_options"] = json_safe(options[candidate])
            path = _cache_path(cache, part, candidate, digests[candidate]) if cache else None
            report = _read_cached(path, key)
            if report is None:
                env_key = json.dumps(json_safe(env_kwargs[candidate]), sort_keys=True)
                env = envs.get(env_key)
                if env is None and config.dataset == "nuscenes":
                    from envs.data.nuscenes import SOT_SPLITS
                    from envs.nuscenes_env import make_nuscenes_env

                    env = make_nuscenes_env(
                        preset=config.preset,
                        sensor=config.sensor,
                        seed=part.world_seed,
                        split=SOT_SPLITS[part.split],
                        frame=config.nuscenes_frame,
                        setting=config.setting,
                        categories=observed,
                        **env_kwargs[candidate],
                    )
                if env is None:
                    env = make_synthetic_env(
                        preset=config.preset,
                        sensor=config.sensor,
                        seed=part.world_seed,
                        split=part.split,
                        setting=config.setting,
                        categories=observed,
                        **env_kwargs[candidate],
                    )
                envs[env_key] = env
                report = evaluate(
                    loaded[candidate],
                    env,
                    seed=config.eval_seed,
                    name=candidate,
                    progress=progress,
                    num_envs=config.num_envs,
                    workers=config.workers,
                )
                report = {
                    "selection_key": key,
                    "observed": report["observed"],
                    "per_tracklet": report["per_tracklet"],
                }
                if path is not None:
                    save_report(report, path)
                how = "scored"
            else:
                how = "cached"
            entry = report["observed"]
            per_part[candidate][str(part)] = {
                k: float(entry[k]) for k in ("success", "precision", "frames")
            }
            per_tracklet[candidate].update(observed_tracklet_scores(report, str(part)))
            (log or logger.info)(
                f"{part} {candidate}: {how}, observed Success {entry['success']:.1f} "
                f"over {int(entry['frames'])} frames"
            )
        for env in envs.values():
            env.close()
    rows = [
        {"candidate": c}
        | pooled(list(per_part[c].values()))
        | {"parts": per_part[c], "per_tracklet": per_tracklet[c]}
        for c in candidates
    ]
    return sorted(rows, key=lambda r: -r["success"])


def observed_tracklet_scores(report: Mapping[str, Any], part: str) -> dict[str, dict[str, float]]:
    """A part report's observed tracklets with frames, as ``{"PART/TRACKLET": {"success",
    "precision", "frames"}}`` (the ``per_tracklet`` of a :func:`score_candidates` row)."""
    return {
        f"{part}/{t['tracklet']}": {k: float(t[k]) for k in ("success", "precision", "frames")}
        for t in report["per_tracklet"]
        if t["observed"] and t["frames"]
    }


def ranking_uncertainty(
    rows: Sequence[Mapping[str, Any]],
    *,
    resamples: int = 2000,
    level: float = 0.9,
    seed: int = 0,
) -> list[dict[str, float]]:
    """How sure the ranking of :func:`score_candidates` is: a paired bootstrap over tracklets.

    A gap of a point between two checkpoints can come from a handful of tracklets. Each
    resample redraws the tracklets of every part with replacement (as many as the part has, so
    each part keeps its size) and pools every candidate's Success over the same draw, so the
    candidates are compared on identical data, as the ranking compares them.

    Args:
        rows: ranked rows with ``per_tracklet`` (all candidates scored on the same tracklets).
        resamples: bootstrap draws.
        level: two-sided coverage of the interval (0.9: the 5th and 95th percentiles).
        seed: seed of the ``numpy.random.Generator`` drawing the resamples.

    Returns:
        One dict per row, in the rows' order: ``diff_to_first`` (the row's pooled Success minus
        the first row's, in points), ``diff_lo`` / ``diff_hi`` (its bootstrap interval) and
        ``p_first`` (the fraction of resamples in which this candidate pools the highest Success,
        a tie going to the higher-ranked row; the values sum to 1).
    """
    import numpy as np

    if not rows:
        return []
    from training.intervals import percentile_interval, pooled_resamples, resample_counts

    keys = list(rows[0]["per_tracklet"])
    for row in rows[1:]:
        if set(row["per_tracklet"]) != set(keys):
            raise ValueError(
                f"candidate {row['candidate']!r} was scored on other tracklets than "
                f"{rows[0]['candidate']!r}: a paired comparison needs the same ones"
            )
    if not keys:
        raise ValueError("no tracklets with frames to resample")
    success = np.array([[r["per_tracklet"][k]["success"] for k in keys] for r in rows])  # (C, T)
    frames = np.array([rows[0]["per_tracklet"][k]["frames"] for k in keys])  # (T,)
    part_of = [k.split("/", 1)[0] for k in keys]  # each part keeps its size in a draw
    scores = pooled_resamples(resample_counts(part_of, resamples, seed), frames, success)  # (R, C)
    diffs = scores - scores[:, :1]
    observed = success @ frames / frames.sum()  # (C,) equals each row's pooled Success
    lo, hi = percentile_interval(diffs, level)
    first = np.bincount(scores.argmax(axis=1), minlength=len(rows)) / resamples
    return [
        {
            "diff_to_first": float(observed[c] - observed[0]),
            "diff_lo": float(lo[c]),
            "diff_hi": float(hi[c]),
            "p_first": float(first[c]),
        }
        for c in range(len(rows))
    ]


def _read_cached(path: Path | None, key: Mapping[str, Any]) -> dict[str, Any] | None:
    """The cached report at ``path`` if it was made with ``key``; ``None`` otherwise."""
    if path is None or not path.is_file():
        return None
    try:
        report = json.loads(path.read_text())
    except (OSError, json.JSONDecodeError):
        return None
    return report if report.get("selection_key") == dict(key) else None


def format_ranking(
    rows: Sequence[Mapping[str, Any]],
    uncertainty: Sequence[Mapping[str, float]] | None = None,
) -> str:
    """A text table of :func:`score_candidates` rows: rank, pooled Success / Precision, frames,
    each part's Success and, given :func:`ranking_uncertainty`'s output, the gap to the first
    with its interval and the share of resamples that rank the candidate first."""
    if not rows:
        return ""
    parts = list(rows[0]["parts"])
    name_w = max(len("candidate"), *(len(str(r["candidate"])) for r in rows))
    head = f"{'#':>2} {'candidate':<{name_w}} | {'Succ':>5} / {'Prec':>5} | {'frames':>6} | "
    if uncertainty is not None:
        head += f"{'vs 1st [interval]':>21} | {'P(1st)':>6} | "
    lines = [head + " ".join(f"{p:>7}" for p in parts)]
    for i, r in enumerate(rows, 1):
        line = (
            f"{i:>2} {r['candidate']:<{name_w}} | {r['success']:5.1f} / {r['precision']:5.1f} | "
            f"{int(r['frames']):6d} | "
        )
        if uncertainty is not None:
            u = uncertainty[i - 1]
            gap = f"{u['diff_to_first']:+.1f} [{u['diff_lo']:+.1f}, {u['diff_hi']:+.1f}]"
            line += f"{gap:>21} | {u['p_first']:6.2f} | "
        lines.append(line + " ".join(f"{r['parts'][p]['success']:7.1f}" for p in parts))
    return "\n".join(lines)


def save_selected(rows: Sequence[Mapping[str, Any]], config: Any, path: str | Path) -> Path:
    """Write the first of ``select``'s ranked ``rows`` to ``path`` as a tracker file whose
    provenance adds this selection round (:func:`selection_round`); ``ValueError`` when it has
    no weights (a baseline) or cannot be saved."""
    first = str(rows[0]["candidate"])
    tracker = load_candidate(first)
    if not isinstance(tracker, Tracker) or type(tracker) is not trackers.tracker_class(
        tracker.name
    ):
        raise ValueError(f"--save: the first-ranked candidate {first!r} is not a tracker file")
    round_ = selection_round(config, rows)
    return trackers.save(tracker, path, provenance=selected_provenance(tracker, round_))
