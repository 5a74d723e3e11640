"""Provenance written by ``train``, ``finetune`` and ``select``, and the guards that read it.

:class:`trackers.provenance.Provenance` (the record itself) lives in ``trackers`` so that
``trackers.load`` can read it; this module fills it from a run's config and checks it:

* :func:`train_provenance`, :func:`finetune_provenance`, :func:`selected_provenance`: the record
  each command writes (``docs/checkpoints.md``, "Provenance");
* :func:`eval_guard` / :func:`mark_unseen`: ``pointtrack eval`` reports a category as unseen only
  when the file never trained on it, and warns (``--strict``: refuses) when the world and split
  evaluated on are ones the file trained or was selected on;
* :func:`check_candidates`: ``pointtrack select`` refuses a candidate trained on a selection part
  or on one of the setting's unseen categories;
* :func:`check_finetune_categories`: ``pointtrack finetune`` refuses a training env that serves a
  category the base file holds out, unless asked.

Unknown fields are never guessed: a check that needs one says it could not check.
"""

from __future__ import annotations

import hashlib
import json
import re
import subprocess
import warnings
from collections.abc import Callable, Mapping, Sequence
from pathlib import Path
from typing import Any

from trackers.provenance import UNKNOWN, Provenance

__all__ = [
    "ProvenanceWarning",
    "check_candidates",
    "check_finetune_categories",
    "config_hash",
    "eval_guard",
    "finetune_provenance",
    "git_commit",
    "mark_unseen",
    "selected_provenance",
    "selection_round",
    "train_provenance",
]

_REPO = Path(__file__).resolve().parents[1]
_RUNTIME_KEYS = ("out", "progress", "num_workers", "num_threads", "threads", "device")
SELECTION_RULE = "pooled observed Success over the parts (training.selection.score_candidates)"


class ProvenanceWarning(UserWarning):
    """A result that a checkpoint's provenance makes suspect (trained or selected on the data)."""


def git_commit(repo: str | Path = _REPO) -> str:
    """The commit checked out in ``repo`` (``+dirty`` when tracked files changed), or
    ``"unknown"`` outside a git work tree or without git."""
    try:
        head = subprocess.run(
            ["git", "-C", str(repo), "rev-parse", "HEAD"],
            capture_output=True,
            text=True,
            timeout=10,
        )
        if head.returncode != 0:
            return UNKNOWN
        status = subprocess.run(
            ["git", "-C", str(repo), "status", "--porcelain", "--untracked-files=no"],
            capture_output=True,
            text=True,
            timeout=10,
        )
    except (OSError, subprocess.SubprocessError):
        return UNKNOWN
    dirty = status.returncode != 0 or bool(status.stdout.strip())
    return head.stdout.strip() + ("+dirty" if dirty else "")


def config_hash(config: Mapping[str, Any]) -> str:
    """SHA-256 of a run's config (JSON, sorted keys) without the keys that only say where and
    how fast it ran (:data:`_RUNTIME_KEYS`)."""
    kept = {k: v for k, v in config.items() if k not in _RUNTIME_KEYS}
    return hashlib.sha256(json.dumps(kept, sort_keys=True, default=str).encode()).hexdigest()


def _world_digest(root: str | Path | None) -> str:
    """The identity hash a generated world's cache directory ends with
    (``<preset>-<sensor>-s<seed>-<hash>``), else unknown."""
    match = re.search(r"-s\d+-([0-9a-f]{12})$", str(root or ""))
    return match.group(1) if match else UNKNOWN


def _setting_categories(setting: str | None, category: str | None) -> list[str] | str:
    from envs.data import get_setting

    if category:
        return [category]
    return list(get_setting(setting).observed) if setting else UNKNOWN


def train_provenance(
    config: Mapping[str, Any],
    root: str | Path | None,
    step: int,
    *,
    parent: dict[str, Any] | None = None,
    commit: str | None = None,
) -> Provenance:
    """The provenance of a ``pointtrack train`` run after ``step`` optimiser steps: its config
    (a ``TrainConfig.to_dict()``), the root its samples came from (``None``: unknown), the
    checkpoint it started from (``training.checkpoint.parent_entry`` of its ``init_weights``)
    and the commit (default: the checked-out one)."""
    dataset = config.get("dataset", UNKNOWN)
    synthetic = dataset in ("synthetic", "nuscenes") and not config.get("data_root")
    return Provenance(
        written_by="train",
        dataset=dataset,
        root_kind="generated" if synthetic else "given",
        preset=config.get("preset", UNKNOWN) if synthetic else UNKNOWN,
        sensor=config.get("sensor", UNKNOWN) if synthetic else UNKNOWN,
        world_seed=int(config.get("world_seed", 0)) if synthetic else UNKNOWN,
        generator_digest=_world_digest(root) if synthetic else UNKNOWN,
        setting=config.get("setting") or f"class-specific:{config.get('category')}",
        categories=_setting_categories(config.get("setting"), config.get("category")),
        splits=["train"],
        samples=int(step) * int(config.get("batch_size", 0)),
        steps=int(step),
        selection=[],
        parent=parent,
        git_commit=git_commit() if commit is None else commit,
        config_hash=config_hash(config),
        nuscenes_frame=config.get("nuscenes_frame", "lidar"),
    )


def finetune_provenance(cfg: Any, steps: int, parent: dict[str, Any]) -> Provenance:
    """The provenance of a ``pointtrack finetune`` result after ``steps`` env steps
    (``cfg``: a ``training.rl.config.FinetuneConfig``): the train split of its world, its
    setting's observed categories (what ``train_env_factory`` serves), the base as ``parent``
    (``training.checkpoint.parent_entry(cfg.tracker)``).
    A library caller that passes its own ``make_env`` to ``training.rl.run.finetune`` must
    make ``cfg`` describe that env: the record is ``cfg``'s."""
    from dataclasses import asdict

    from envs.synthetic.world import world_identity

    generated = not cfg.data_root
    digest = UNKNOWN
    if generated:  # the hash ensure_world names the world's directory by, without generating it
        identity = world_identity(cfg.preset, cfg.sensor, cfg.world_seed)
        digest = hashlib.sha256(json.dumps(identity, sort_keys=True).encode()).hexdigest()[:12]
    return Provenance(
        written_by="finetune",
        dataset="synthetic" if generated else UNKNOWN,
        root_kind="generated" if generated else "given",
        preset=cfg.preset if generated else UNKNOWN,
        sensor=cfg.sensor if generated else UNKNOWN,
        world_seed=int(cfg.world_seed) if generated else UNKNOWN,
        generator_digest=digest,
        setting=cfg.setting,
        categories=_setting_categories(cfg.setting, None),
        splits=["train"],
        samples=int(steps),
        steps=int(steps),
        selection=[],
        parent=parent,
        git_commit=git_commit(),
        config_hash=config_hash(asdict(cfg)),
    )


def _frame_entry(frame: str) -> dict[str, str]:
    """A nuScenes frame other than the default, as a record entry (earlier records unchanged)."""
    return {} if frame == "lidar" else {"nuscenes_frame": frame}


def selection_round(config: Any, rows: Sequence[Mapping[str, Any]]) -> dict[str, Any]:
    """One ``select`` round as provenance records it: the rule, the setting and world, the
    parts, the eval seed and every candidate's pooled observed Success (``config``: a
    ``training.selection.SelectionConfig``; ``rows``: ``score_candidates``' ranking)."""
    return {
        "rule": SELECTION_RULE,
        "setting": config.setting,
        "dataset": config.dataset,
        **_frame_entry(getattr(config, "nuscenes_frame", "lidar")),
        "preset": config.preset,
        "sensor": config.sensor,
        "parts": [str(p) for p in config.parts],
        "eval_seed": config.eval_seed,
        "scores": {str(r["candidate"]): round(float(r["success"]), 2) for r in rows},
        "chosen": str(rows[0]["candidate"]),
    }


def selected_provenance(tracker: Any, round_: Mapping[str, Any]) -> Provenance:
    """``tracker``'s provenance with one more selection round (``written_by`` ``select``)."""
    provenance = getattr(tracker, "provenance", None) or Provenance()
    before = [] if provenance.selection == UNKNOWN else list(provenance.selection)
    return provenance.replace(written_by="select", selection=[*before, dict(round_)])


# --------------------------------------------------------------------------- guards


def _same_world(a: Mapping[str, Any], b: Mapping[str, Any]) -> bool:
    """Whether two world descriptions (dataset, preset, sensor, world_seed) are one world; the
    synthetic worlds are the same in KITTI and nuScenes layout."""
    kitti = {a.get("dataset") == "kitti", b.get("dataset") == "kitti"}
    if True in kitti:
        return kitti == {True}
    return all(a.get(k) == b.get(k) for k in ("preset", "sensor", "world_seed"))


def check_candidates(
    loaded: Mapping[str, Any], config: Any, log: Callable[[str], None] | None = None
) -> None:
    """Refuse (``ValueError`` naming the candidate and what it trained on) a ``select``
    candidate trained on one of ``config``'s parts or on one of its setting's unseen categories;
    ``log`` a line for a learned candidate whose provenance is unknown (not checked)."""
    from envs.data import get_setting

    unseen = set(get_setting(config.setting).unseen)
    for name, tracker in loaded.items():
        provenance = getattr(tracker, "provenance", None)
        if provenance is None:
            continue  # a baseline: it learnt nothing
        categories, parts = provenance.trained_categories(), provenance.trained_parts()
        if categories is not None and unseen & set(categories):
            raise ValueError(
                f"candidate {name!r} was trained on {sorted(unseen & set(categories))}, which "
                f"setting {config.setting} holds out: selecting it would choose on the unseen "
                "category"
            )
        for part in config.parts:
            world = {
                "dataset": config.dataset,
                "preset": config.preset,
                "sensor": config.sensor,
                "world_seed": part.world_seed,
            }
            for trained in parts or []:
                if trained["split"] == part.split and _same_world(trained, world):
                    raise ValueError(
                        f"candidate {name!r} was trained on world {part.world_seed} "
                        f"{part.split} ({config.preset}, {config.sensor}): selection part "
                        f"{part} would score it on its own training data"
                    )
        if (categories is None or parts is None) and log is not None:
            log(f"{name}: provenance unknown, not checked against the parts and setting")


def _eval_world(args: Any) -> dict[str, Any] | None:
    """The world an ``eval`` command line evaluates on, or ``None`` when it is named by a root
    path only (a generated world given by ``--root``: its seed is not known here)."""
    if args.dataset == "kitti":
        return {"dataset": "kitti"}
    if args.root:
        return None
    return {
        "dataset": args.dataset,
        "preset": args.preset,
        "sensor": args.sensor,
        "world_seed": args.seed,
    }


def eval_guard(loaded: Mapping[str, Any], args: Any, setting: str | None) -> dict[str, list[str]]:
    """Check every tracker ``eval`` is about to run against its provenance, before any work.

    Warns (:class:`ProvenanceWarning`; ``args.strict``: ``ValueError``) naming the file and the
    data when it trained on a category the setting holds out (it is then reported as observed),
    or trained or was selected on the world and split evaluated; notes a learned file whose
    provenance is unknown. Returns ``{tracker: categories it trained on}`` for
    :func:`mark_unseen` (only trackers whose categories are known)."""
    from envs.data import get_setting

    unseen = set(get_setting(setting).unseen) if setting else set()
    world = _eval_world(args)
    splits = {"train", "val", "test"} if args.split == "all" else {args.split}
    trained: dict[str, list[str]] = {}
    for name, tracker in loaded.items():
        provenance = getattr(tracker, "provenance", None)
        if provenance is None:
            continue
        problems = []
        categories = provenance.trained_categories()
        if categories is None:
            warnings.warn(
                f"eval: {name!r} records no (complete) provenance: 'unseen' follows setting "
                f"{setting} only, and its training data are not checked",
                ProvenanceWarning,
                stacklevel=2,
            )
        else:
            trained[name] = categories
            leaked = sorted(unseen & set(categories))
            if leaked:
                problems.append(
                    f"{name!r} was trained on {leaked}, which setting {setting} holds out: "
                    "reported as observed, not unseen"
                )
        frame = getattr(args, "nuscenes_frame", None) or "lidar"
        trained_frame = provenance.nuscenes_frame if provenance.dataset == "nuscenes" else UNKNOWN
        if args.dataset == "nuscenes" and trained_frame not in (UNKNOWN, frame):
            problems.append(
                f"{name!r} was trained on nuScenes data in the {trained_frame!r} frame and is "
                f"evaluated in the {frame!r} frame (--nuscenes-frame {trained_frame})"
            )
        if world is not None:
            for role, parts in (
                ("trained", provenance.trained_parts() or []),
                ("selected", provenance.selection_parts()),
            ):
                hits = sorted(
                    {p["split"] for p in parts if p["split"] in splits and _same_world(p, world)}
                )
                if hits:
                    problems.append(
                        f"{name!r} was {role} on split(s) {hits} of the world evaluated "
                        f"({_describe(world)}, --split {args.split}): not held-out data"
                    )
        for problem in problems:
            if getattr(args, "strict", False):
                raise ValueError(f"{problem} (refused under --strict)")
            warnings.warn(f"eval: {problem}", ProvenanceWarning, stacklevel=2)
    return trained


def _describe(world: Mapping[str, Any]) -> str:
    if world.get("dataset") == "kitti":
        return "kitti"
    return f"{world['dataset']} {world['preset']} {world['sensor']} seed {world['world_seed']}"


def mark_unseen(
    reports: Mapping[str, dict[str, Any]], trained: Mapping[str, Sequence[str]]
) -> dict[str, dict[str, Any]]:
    """The reports with every category a tracker trained on marked observed (its observed /
    unseen groups pooled again over their categories' frames, which is exact: Success and
    Precision are frame-weighted means of their curves). A relabelled report lists the
    categories under ``"relabelled_observed"``."""
    return {
        name: _relabelled(report, set(trained.get(name, ()))) for name, report in reports.items()
    }


def _relabelled(report: dict[str, Any], categories: set[str]) -> dict[str, Any]:
    cats = report["categories"]
    moved = sorted(c for c in cats if c in categories and not cats[c]["observed"])
    if not moved:
        return report
    out = dict(report)
    out["categories"] = {c: {**e, "observed": e["observed"] or c in moved} for c, e in cats.items()}
    for group, flag in (("observed", True), ("unseen", False)):
        out[group] = _pooled([e for e in out["categories"].values() if e["observed"] is flag])
    out["per_tracklet"] = [
        {**t, "observed": t["observed"] or t["category"] in moved}
        for t in report.get("per_tracklet", [])
    ]
    out["relabelled_observed"] = moved
    return out


def _pooled(entries: Sequence[Mapping[str, Any]]) -> dict[str, Any]:
    """An OPE group entry pooled over category entries (``envs.metrics`` report layout)."""
    import numpy as np

    frames = sum(int(e["frames"]) for e in entries)
    out: dict[str, Any] = {
        "success": float("nan"),
        "precision": float("nan"),
        "frames": frames,
        "tracklets": sum(int(e["tracklets"]) for e in entries),
    }
    keys = ("success", "precision", "success_curve", "precision_curve")
    for key in keys:
        if entries and all(key in e for e in entries) and frames:
            values = np.array([e[key] for e in entries], dtype=np.float64)
            weights = np.array([e["frames"] for e in entries], dtype=np.float64)
            mean = np.tensordot(weights, values, axes=1) / frames
            out[key] = mean.tolist() if key.endswith("curve") else float(mean)
    return out


def check_finetune_categories(base: Any, setting: str, allow: bool) -> None:
    """Refuse (``ValueError``) to fine-tune ``base`` (a tracker, its ``provenance`` read) in an
    env serving ``setting``'s observed categories when one of them is a category the base file
    holds out (its setting's unseen ones), unless ``allow``; a warning when its provenance does
    not say what it holds out."""
    from envs.data import get_setting

    provenance = getattr(base, "provenance", None) or Provenance()
    if provenance.setting == UNKNOWN:
        warnings.warn(
            "finetune: the base file records no setting: whether the training env serves a "
            "category it holds out is not checked",
            ProvenanceWarning,
            stacklevel=2,
        )
        return
    served = set(get_setting(setting).observed)
    held = sorted(served & set(get_setting(provenance.setting).unseen))
    if held and not allow:
        raise ValueError(
            f"the training env (setting {setting}) serves {held}, which the base file holds out "
            f"(trained in setting {provenance.setting}): fine-tuning on it ends the class-agnostic "
            "study of those categories; pass --allow-held-out to do it on purpose"
        )
