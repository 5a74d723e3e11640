"""Step-wise evaluation of any tracker in the environment: OPE Success / Precision.

:func:`evaluate` runs every tracklet of an env once (sequentially, or spread over the sub-envs
of a Gymnasium vector env so a batched tracker acts on ``(B, ...)`` observations), pools the
frames per category with each tracklet's first frame counted perfect (``envs.metrics``), and
returns a report. :func:`format_table`, :func:`save_report` and :func:`plot_curves` print it,
write it as JSON, and draw the success / precision curves as PNG.

Report (a JSON-able dict)::

    {"tracker": name, "categories": {cat: {"success", "precision", "frames", "tracklets",
     "observed", "success_curve", "precision_curve"}}, "observed": {...}, "unseen": {...},
     "mean": {...}, "tracker_fps": frames per second spent in act(), "frames": int,
     "tracklets": int, "wall_s": float, "env": {...}, "per_tracklet": [{...}, ...] (by tracklet id)}

Success / precision are percent; a group without frames scores NaN (``null`` in JSON).
"""

from __future__ import annotations

import contextlib
import json
import math
import time
from collections.abc import Callable, Iterable, Iterator, Mapping, Sequence
from pathlib import Path
from typing import Any

import gymnasium as gym
import numpy as np

from envs.metrics import THRESHOLDS_IOU, THRESHOLDS_M, OPEAccumulator
from envs.plotting import pyplot, save_figure
from training.rundir import atomic_write_text

__all__ = [
    "env_option_groups",
    "env_options_for",
    "evaluate",
    "format_table",
    "json_safe",
    "observation_keys_for",
    "plot_curves",
    "save_report",
    "split_tracklets",
    "tracker_name",
]


def observation_keys_for(trackers: Sequence[Any]) -> tuple[str, ...]:
    """The env's ``observation_keys`` that serve every tracker in ``trackers``: the default
    observation plus each tracker's opt-in keys (a tracker's ``observation_keys`` class
    attribute, e.g. M2-Track's ``("previous_search",)``), in the env's order."""
    from envs.tracking_env import OBSERVATION_KEYS, OPTIONAL_OBSERVATION_KEYS

    wanted = {key for tracker in trackers for key in getattr(tracker, "observation_keys", ())}
    return (*OBSERVATION_KEYS, *(k for k in OPTIONAL_OBSERVATION_KEYS if k in wanted))


def _recorded_options(tracker: Any) -> dict[str, Any]:
    """A tracker's ``env_options`` (``{}`` for one without: a baseline, the env's defaults)."""
    return dict(getattr(tracker, "env_options", None) or {})


def env_options_for(trackers: Sequence[Any]) -> dict[str, Any]:
    """The ``TrackingEnv`` keywords (``template_mode``, ``search_enlargement``) every tracker in
    ``trackers`` must be evaluated with: their recorded ``tracker.env_options`` (``{}``, the
    env's defaults, for a tracker that records none, e.g. a baseline or a recipe-v1 checkpoint).

    Raises ``ValueError`` naming each tracker and its options when they differ: one env cannot
    serve them all (:func:`env_option_groups` gives one option set per env)."""
    groups = _group((tracker_name(t), _recorded_options(t)) for t in trackers)
    if len(groups) > 1:
        listed = "; ".join(f"{', '.join(n)}: {o or 'env defaults'}" for o, n in groups)
        raise ValueError(
            f"these trackers must be evaluated on envs with different options: {listed}"
        )
    return groups[0][0] if groups else {}


def env_option_groups(
    trackers: Mapping[str, Any], explicit: Mapping[str, Any] | None = None
) -> list[tuple[dict[str, Any], list[str]]]:
    """Group named trackers by the env options each is evaluated with: its recorded
    ``env_options`` updated by ``explicit`` (a user's choice, e.g. ``--template-mode``; keys
    whose value is ``None`` are not a choice). Returns ``[(options, [names]), ...]`` in the
    order of first appearance, so a command builds one env per distinct option set.

    An explicit choice wins over a tracker's recorded option; :func:`evaluate` then warns that
    the tracker runs on another setup than it was trained with."""
    chosen = {k: v for k, v in (explicit or {}).items() if v is not None}
    return _group((name, {**_recorded_options(t), **chosen}) for name, t in trackers.items())


def _group(
    pairs: Iterable[tuple[str, dict[str, Any]]],
) -> list[tuple[dict[str, Any], list[str]]]:
    """``(name, options)`` pairs -> ``[(options, [names]), ...]``, equal options together."""
    groups: list[tuple[dict[str, Any], list[str]]] = []
    for name, options in pairs:
        for existing, names in groups:
            if _same_options(existing, options):
                names.append(name)
                break
        else:
            groups.append((options, [name]))
    return groups


def _same_options(a: Mapping[str, Any], b: Mapping[str, Any]) -> bool:
    """Equal env options once missing keys read as the env's defaults."""
    from trackers.registry import default_env_options

    defaults = default_env_options()
    full_a, full_b = {**defaults, **a}, {**defaults, **b}
    return all(_option_value(full_a[k]) == _option_value(full_b[k]) for k in defaults)


def _option_value(value: Any) -> Any:
    """A comparable form of an env option value (a tuple and a list of numbers compare equal)."""
    if isinstance(value, list | tuple):
        return tuple(float(v) for v in value)
    return value


def _warn_env_mismatch(tracker: Any, name: str, env_info: Mapping[str, Any]) -> None:
    """Warn when the env differs from the options ``tracker`` records (only trackers that
    record options, i.e. have ``env_options``: learned ones)."""
    import warnings

    from trackers.registry import default_env_options

    if getattr(tracker, "env_options", None) is None:
        return
    wanted = {**default_env_options(), **_recorded_options(tracker)}
    for key, value in wanted.items():
        if key in env_info and _option_value(env_info[key]) != _option_value(value):
            warnings.warn(
                f"evaluate: tracker {name!r} was trained with {key}={_option_value(value)!r} "
                f"but the env uses {key}={_option_value(env_info[key])!r}: its scores are not "
                "those of its training setup (docs/recipe.md, 'Eval options travel with the "
                "checkpoint')",
                UserWarning,
                stacklevel=3,
            )


def tracker_name(tracker: Any, name: str | None = None) -> str:
    """``name`` if given, else ``tracker.name``, else the tracker's class name."""
    if name:
        return name
    return str(getattr(tracker, "name", None) or type(tracker).__name__)


def split_tracklets(lengths: Sequence[int], num_envs: int) -> list[list[int]]:
    """Spread tracklet indices over ``num_envs`` sub-envs so their step counts are balanced
    (longest first, each to the least-loaded sub-env). Sub-envs left empty get ``[]``."""
    loads = [0] * num_envs
    orders: list[list[int]] = [[] for _ in range(num_envs)]
    for i in sorted(range(len(lengths)), key=lambda k: (-lengths[k], k)):
        j = min(range(num_envs), key=lambda e: (loads[e], e))
        orders[j].append(i)
        loads[j] += max(int(lengths[i]) - 1, 0)
    return [sorted(o) for o in orders]


def _progress(total: int, enabled: bool | Callable, desc: str):
    if callable(enabled):
        return enabled(total=total, desc=desc)
    if not enabled:
        return None
    from tqdm.auto import tqdm

    return tqdm(total=total, desc=desc, unit="frame", leave=False, dynamic_ncols=True)


def evaluate(
    tracker: Any,
    env: gym.Env | gym.vector.VectorEnv,
    *,
    seed: int = 0,
    tracklets: Sequence[int] | None = None,
    name: str | None = None,
    progress: bool | Callable = False,
    out_dir: str | Path | None = None,
    num_envs: int = 1,
) -> dict[str, Any]:
    """Run ``tracker`` over every tracklet of ``env`` once and report OPE Success / Precision.

    Args:
        tracker: anything with ``act(obs) -> (4,)`` (or ``(B, 4)`` for a batch).
        env: a :class:`~envs.tracking_env.TrackingEnv`, possibly wrapped (``act`` sees the
            wrapped observations; actions are passed through the wrappers), or a Gymnasium vector
            env of them (``NEXT_STEP`` autoreset, the default): the tracklets are spread over the
            sub-envs and ``act`` gets ``(B, ...)`` batches.
        seed: seeds the resampling of point sets: each episode draws from its own generator
            seeded by ``(seed, tracklet id)`` (the env's ``episode_seed``, restored afterwards),
            so with one env a tracklet's result depends on the tracker, the env and this seed
            only — not on ``tracklets`` or the order. Batched (``num_envs > 1``), a learned
            tracker's forward can differ in the last bit with the batch layout, and its closed
            loop can amplify that into another trajectory.
        tracklets: indices of the tracklets to run (default: all).
        name: the tracker's name in the report (default: ``tracker.name`` or its class).
        progress: show a tqdm progress bar (or pass a tqdm-like factory).
        out_dir: if given, write ``<name>.json`` and curve plots there.
        num_envs: with an unwrapped ``TrackingEnv`` and ``num_envs > 1``, run a
            ``SyncVectorEnv`` of ``num_envs`` clones of it (shared data) so ``act`` gets batches.

    Returns:
        The report described in the module docstring. ``act`` is called once per step;
        ``tracker_fps`` counts only the time spent inside ``act``.
    """
    name = tracker_name(tracker, name)
    if tracklets is not None:
        tracklets = [int(i) for i in tracklets]
        if not tracklets:
            raise ValueError("evaluate: tracklets=[] selects no tracklet (None means all)")
    start = time.perf_counter()
    owned = None
    if num_envs > 1 and not isinstance(env, gym.vector.VectorEnv):
        if env is not env.unwrapped or not hasattr(env, "clone"):
            raise ValueError(
                "num_envs > 1 needs an unwrapped TrackingEnv; for wrapped envs pass a vector env"
            )
        owned = env = gym.vector.SyncVectorEnv([env.clone for _ in range(num_envs)])
    run = _run_vector if isinstance(env, gym.vector.VectorEnv) else _run_single
    try:
        with _episodes_seeded(env, seed):
            acc, frames, act_s, env_info = run(tracker, env, seed, tracklets, progress, name)
        _warn_env_mismatch(tracker, name, env_info)
    finally:
        if owned is not None:
            owned.close()
    report: dict[str, Any] = {"tracker": name}
    report.update(acc.report(curves=True))
    report["tracker_fps"] = frames / act_s if act_s > 0 else float("inf")
    report["frames"] = int(report["mean"]["frames"])
    report["tracklets"] = len(acc)
    report["wall_s"] = time.perf_counter() - start
    report["env"] = env_info
    report["per_tracklet"] = [
        {
            "tracklet": r.tracklet_id,
            "category": r.category,
            "observed": r.observed,
            "frames": r.frames,
            "success": r.success,
            "precision": r.precision,
        }
        for r in sorted(acc.results, key=lambda r: str(r.tracklet_id))  # layout-independent
    ]
    if out_dir is not None:
        out = Path(out_dir)
        save_report(report, out / f"{_slug(name)}.json")
        plot_curves({name: report}, out, prefix=f"{_slug(name)}_")
    return report


@contextlib.contextmanager
def _episodes_seeded(env: gym.Env | gym.vector.VectorEnv, seed: int) -> Iterator[None]:
    """Set the ``episode_seed`` of ``env`` (or of every sub-env) for the block, then restore it."""
    if isinstance(env, gym.vector.VectorEnv):
        saved = list(env.get_attr("episode_seed"))
        env.set_attr("episode_seed", seed)
        try:
            yield
        finally:
            env.set_attr("episode_seed", saved)
    else:
        u = env.unwrapped
        saved_one = u.episode_seed
        u.episode_seed = seed
        try:
            yield
        finally:
            u.episode_seed = saved_one


def _env_info(u: Any) -> dict[str, Any]:
    setting = getattr(u, "setting", None)
    return {
        "num_tracklets": int(u.num_tracklets),
        "setting": getattr(setting, "name", None),
        "split": getattr(u, "split", None),
        "template_mode": getattr(u, "template_mode", None),
        "search_enlargement": _listed(getattr(u, "search_enlargement", None)),
        "reference": getattr(u, "reference", None),
    }


def _listed(value: Any) -> Any:
    return list(value) if isinstance(value, tuple) else value


def _check_indices(count: int, tracklets: Sequence[int] | None) -> list[int]:
    """The tracklet indices to run; ``ValueError`` for an env without tracklets or an index out
    of range (a report over nothing would be NaN)."""
    if count == 0:
        raise ValueError(
            "evaluate: the env holds no tracklets (check the split, the setting and the categories)"
        )
    indices = list(range(count)) if tracklets is None else list(tracklets)
    bad = [i for i in indices if not 0 <= i < count]
    if bad:
        raise ValueError(f"evaluate: tracklet indices {bad[:5]} out of range for {count} tracklets")
    return indices


def _run_single(tracker, env, seed, tracklets, progress, name):
    u = env.unwrapped
    indices = _check_indices(u.num_tracklets, tracklets)
    lengths = u.tracklet_lengths
    bar = _progress(sum(lengths[i] for i in indices), progress, name)
    acc = OPEAccumulator()
    frames, act_s = 0, 0.0
    for k, index in enumerate(indices):
        obs, info = env.reset(seed=seed if k == 0 else None, options={"tracklet": index})
        tracklet_id, category, observed = info["tracklet"], info["category"], info["observed"]
        ious: list[float] = []
        errors: list[float] = []
        while True:
            t0 = time.perf_counter()
            action = tracker.act(obs)
            act_s += time.perf_counter() - t0
            obs, _, terminated, truncated, info = env.step(action)
            ious.append(info["iou"])
            errors.append(info["center_error"])
            if terminated or truncated:
                break
        frames += len(ious)
        acc.add(tracklet_id, category, observed, ious, errors)
        if bar is not None:
            bar.update(len(ious) + 1)
    if bar is not None:
        bar.close()
    return acc, frames, act_s, _env_info(u)


def _run_vector(tracker, vec, seed, tracklets, progress, name):
    mode = vec.metadata.get("autoreset_mode", gym.vector.AutoresetMode.NEXT_STEP)
    if str(getattr(mode, "value", mode)) != gym.vector.AutoresetMode.NEXT_STEP.value:
        raise ValueError(f"evaluate needs a vector env with NEXT_STEP autoreset; got {mode}")
    num = vec.num_envs
    lengths = vec.get_attr("tracklet_lengths")[0]
    indices = _check_indices(len(lengths), tracklets)
    sub = split_tracklets([lengths[i] for i in indices], num)
    orders = [[indices[i] for i in o] for o in sub]
    remaining = np.array([len(o) for o in orders])
    # a sub-env with nothing to do still needs a valid order; its episodes are ignored
    vec.set_attr("tracklet_order", [o if o else [indices[0]] for o in orders])
    bar = _progress(sum(lengths[i] for i in indices), progress, name)
    acc = OPEAccumulator()
    frames, act_s = 0, 0.0
    active = remaining > 0
    resetting = np.zeros(num, dtype=bool)  # the sub-env autoresets during this step
    ious: list[list[float]] = [[] for _ in range(num)]
    errors: list[list[float]] = [[] for _ in range(num)]
    obs, infos = vec.reset(seed=seed)
    meta = [
        (infos["tracklet"][i], infos["category"][i], bool(infos["observed"][i])) for i in range(num)
    ]
    while active.any():
        t0 = time.perf_counter()
        actions = np.asarray(tracker.act(obs), dtype=np.float32).reshape(num, -1)
        act_s += time.perf_counter() - t0
        frames += int((active & ~resetting).sum())
        obs, _, term, trunc, infos = vec.step(actions)
        for i in range(num):
            if resetting[i]:  # this step was the sub-env's reset: a new tracklet starts
                resetting[i] = False
                meta[i] = (infos["tracklet"][i], infos["category"][i], bool(infos["observed"][i]))
                continue
            if not active[i]:
                resetting[i] = bool(term[i] or trunc[i])
                continue
            ious[i].append(float(infos["iou"][i]))
            errors[i].append(float(infos["center_error"][i]))
            if term[i] or trunc[i]:
                acc.add(meta[i][0], meta[i][1], meta[i][2], ious[i], errors[i])
                if bar is not None:
                    bar.update(len(ious[i]) + 1)
                ious[i], errors[i] = [], []
                remaining[i] -= 1
                active[i] = remaining[i] > 0
                resetting[i] = True
    if bar is not None:
        bar.close()
    info = {
        "num_tracklets": len(lengths),
        "setting": getattr(vec.get_attr("setting")[0], "name", None),
        "split": vec.get_attr("split")[0],
        "template_mode": vec.get_attr("template_mode")[0],
        "search_enlargement": _listed(vec.get_attr("search_enlargement")[0]),
        "reference": vec.get_attr("reference")[0],
        "num_envs": num,
    }
    return acc, frames, act_s, info


# --------------------------------------------------------------------------- output


def _slug(name: str) -> str:
    return "".join(c if c.isalnum() or c in "-_." else "_" for c in name)


def _fmt(x: float) -> str:
    return "  -  " if x is None or (isinstance(x, float) and math.isnan(x)) else f"{x:5.1f}"


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
    width = max(13, *(len(c) for c in cols))
    namew = max(12, *(len(n) for n in reports))
    head = f"{'tracker':<{namew}} | " + " | ".join(f"{c:^{width}}" for c in cols)
    head += " | frames |   fps"
    sub = (
        f"{'':<{namew}} | " + " | ".join(f"{'Succ / Prec':^{width}}" for _ in cols) + " |        |"
    )
    lines = [head, sub, "-" * len(head)]
    for n, r in reports.items():
        entries = [r["categories"].get(c) for c in cats] + [r["observed"], r["unseen"], r["mean"]]
        cells = []
        for e in entries:
            txt = "-" if e is None else f"{_fmt(e['success'])} / {_fmt(e['precision'])}"
            cells.append(f"{txt:^{width}}")
        fps = r.get("tracker_fps", float("nan"))
        fps_txt = "  inf" if fps == float("inf") else f"{fps:5.0f}"
        lines.append(
            f"{n:<{namew}} | " + " | ".join(cells) + f" | {r['mean']['frames']:6d} | {fps_txt}"
        )
    if unseen:
        lines.append("* unseen category (not in the setting's observed categories)")
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
    reports: Mapping[str, Mapping[str, Any]], out_dir: str | Path, prefix: str = ""
) -> list[Path]:
    """Draw ``<prefix>success.png`` and ``<prefix>precision.png`` in ``out_dir``: one panel per
    group (mean, observed, unseen) with one curve per tracker; returns the paths."""
    plt = pyplot()

    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    paths = []
    groups = [
        g for g in ("mean", "observed", "unseen") if any(r[g]["frames"] for r in reports.values())
    ]
    for key, xs, xlabel, ylabel in (
        ("success", THRESHOLDS_IOU, "overlap threshold (3D IoU)", "success rate"),
        ("precision", THRESHOLDS_M, "centre error threshold (m)", "precision"),
    ):
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
        path = out / f"{prefix}{key}.png"
        paths.append(save_figure(fig, path, 110))
    return paths
