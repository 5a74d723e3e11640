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
import time
from collections.abc import Callable, Iterable, Iterator, Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import gymnasium as gym
import numpy as np

from envs.metrics import OPEAccumulator

# the output half lives in training.reporting; its names stay importable from here
from training.reporting import (
    category_order,
    display_name,
    format_table,
    json_safe,
    plot_curves,
    save_report,
    slug,
)

__all__ = [
    "category_order",
    "env_option_groups",
    "env_options_for",
    "evaluate",
    "display_name",
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


def _warn_oracle(name: str, reference: str) -> None:
    import warnings

    warnings.warn(
        f"evaluate: tracker {name!r} runs with reference={reference!r}: the search area is cut "
        "around the ground truth, an oracle setting (its table row is marked)",
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
    workers: int | None = 1,
    record_boxes: bool = False,
    warm_up: Callable[[], Any] | None = None,
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
        workers: shard the tracklets over this many forked processes (one torch thread each,
            :mod:`training.parallel`; ``None``: every usable core; more than the usable cores
            is clamped with a warning). Each tracklet seeds its own episode and every path runs
            torch on one thread (:func:`~training.parallel.one_torch_thread`), so the
            per-tracklet results are bit-identical to ``workers=1``. Needs a single env (not
            a vector env, ``num_envs=1``); a worker that dies raises
            :class:`~training.parallel.WorkerDiedError` naming its tracklets.
        record_boxes: also return every frame's predicted and true box as ``report["boxes"]``
            (:mod:`training.boxes` writes and re-scores them).
        warm_up: the caller's next step's preparation (e.g. importing matplotlib for the
            plots), run in a thread of this process while the forked workers run
            (:func:`~training.parallel.map_forked`); not run without workers.

    Returns:
        The report described in the module docstring. ``act`` is called once per step;
        ``tracker_fps`` counts only the time spent inside ``act`` (summed over the workers).
    """
    name = tracker_name(tracker, name)
    if tracklets is not None:
        tracklets = [int(i) for i in tracklets]
        if not tracklets:
            raise ValueError("evaluate: tracklets=[] selects no tracklet (None means all)")
    start = time.perf_counter()
    from training.parallel import one_torch_thread, resolve_workers

    workers = resolve_workers(workers)
    if workers > 1 and (num_envs > 1 or isinstance(env, gym.vector.VectorEnv)):
        raise ValueError(
            "evaluate: workers > 1 shards the tracklets over processes with one env each; "
            "it cannot be combined with a vector env or num_envs > 1 (choose one)"
        )
    owned = None
    if num_envs > 1 and not isinstance(env, gym.vector.VectorEnv):
        if env is not env.unwrapped or not hasattr(env, "clone"):
            raise ValueError(
                "num_envs > 1 needs an unwrapped TrackingEnv; for wrapped envs pass a vector env"
            )
        owned = env = gym.vector.SyncVectorEnv([env.clone for _ in range(num_envs)])
    run = _run_vector if isinstance(env, gym.vector.VectorEnv) else _run_single
    opts = _RunOptions(seed, progress, name, workers, record_boxes, warm_up)
    try:
        with _episodes_seeded(env, seed), one_torch_thread():
            episodes, env_info = run(tracker, env, tracklets, opts)
        _warn_env_mismatch(tracker, name, env_info)
    finally:
        if owned is not None:
            owned.close()
    acc = OPEAccumulator()
    for e in episodes:
        acc.add(e.tracklet_id, e.category, e.observed, e.ious, e.errors)
    frames = sum(len(e.ious) for e in episodes)
    act_s = sum(e.act_s for e in episodes)
    report: dict[str, Any] = {"tracker": name}
    report.update(acc.report(curves=True))
    report["tracker_fps"] = frames / act_s if act_s > 0 else float("inf")
    report["frames"] = int(report["mean"]["frames"])
    report["tracklets"] = len(acc)
    report["wall_s"] = time.perf_counter() - start
    report["env"] = env_info
    if env_info.get("reference") not in (None, "prediction"):
        report["oracle"] = env_info["reference"]  # format_table marks the row
        _warn_oracle(name, env_info["reference"])
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
    if record_boxes:
        report["boxes"] = [
            {"tracklet": e.tracklet_id, "category": e.category, "frames": e.boxes}
            for e in sorted(episodes, key=lambda e: str(e.tracklet_id))
        ]
    if out_dir is not None:
        out = Path(out_dir)
        save_report(report, out / f"{slug(name)}.json")
        plot_curves({name: report}, out, prefix=f"{slug(name)}_")
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


@dataclass(frozen=True)
class _RunOptions:
    """What every runner needs besides the tracker, the env and the tracklets."""

    seed: int
    progress: bool | Callable
    name: str
    workers: int
    record_boxes: bool
    warm_up: Callable[[], Any] | None = None


@dataclass
class _Episode:
    """One evaluated tracklet: the step results of frames 1.. (``ious``, ``errors`` in metres),
    the seconds spent in ``act`` and, when recorded, every frame's boxes (frame 0 included)."""

    tracklet_id: str
    category: str
    observed: bool
    ious: list[float] = field(default_factory=list)
    errors: list[float] = field(default_factory=list)
    act_s: float = 0.0
    boxes: list[dict[str, Any]] | None = None

    def start(self, init_box: Any, start_frame: int) -> None:
        """Begin the box record with the given first frame (the ground truth, IoU 1)."""
        box = [float(v) for v in init_box]
        self.boxes = [_frame_record(int(start_frame), box, box, 1.0, 0.0, None)]

    def step(self, info: Mapping[str, Any], record: bool) -> None:
        """Add one step's result (``info`` of a ``TrackingEnv`` step, or one sub-env's)."""
        self.ious.append(float(info["iou"]))
        self.errors.append(float(info["center_error"]))
        if record and self.boxes is not None:
            self.boxes.append(
                _frame_record(
                    int(info["frame"]),
                    [float(v) for v in info["pred_box"]],
                    [float(v) for v in info["gt_box"]],
                    self.ious[-1],
                    self.errors[-1],
                    int(info["target_points"]),
                )
            )


def _frame_record(frame, pred, gt, iou, error, points) -> dict[str, Any]:
    """One line of the ``--save-boxes`` file (schema: :mod:`training.boxes`)."""
    return {
        "frame": frame,
        "pred": pred,
        "gt": gt,
        "iou": iou,
        "center_error": error,
        "target_points": points,
    }


def _run_episode(tracker: Any, env: Any, index: int, reset_seed: int | None, record: bool):
    """Track tracklet ``index`` of ``env`` to its end; returns its :class:`_Episode`."""
    obs, info = env.reset(seed=reset_seed, options={"tracklet": index})
    episode = _Episode(info["tracklet"], info["category"], bool(info["observed"]))
    if record:
        episode.start(info["init_box"], info.get("start_frame", 0))
    while True:
        t0 = time.perf_counter()
        action = tracker.act(obs)
        episode.act_s += time.perf_counter() - t0
        obs, _, terminated, truncated, info = env.step(action)
        episode.step(info, record)
        if terminated or truncated:
            return episode


def _run_single(tracker, env, tracklets, opts: _RunOptions):
    u = env.unwrapped
    indices = _check_indices(u.num_tracklets, tracklets)
    lengths = u.tracklet_lengths
    bar = _progress(sum(lengths[i] for i in indices), opts.progress, opts.name)

    def tick(_index: int, episode: _Episode) -> None:
        if bar is not None:
            bar.update(len(episode.ious) + 1)

    try:
        if opts.workers > 1:
            episodes = _run_sharded(tracker, env, indices, opts, tick)
        else:
            episodes = []
            for k, index in enumerate(indices):
                reset_seed = opts.seed if k == 0 else None
                episodes.append(_run_episode(tracker, env, index, reset_seed, opts.record_boxes))
                tick(index, episodes[-1])
    finally:
        if bar is not None:
            bar.close()
    info = _env_info(u)
    if opts.workers > 1:
        info["workers"] = opts.workers
    return episodes, info


def _run_sharded(tracker, env, indices: list[int], opts: _RunOptions, tick) -> list[_Episode]:
    """The tracklets over ``opts.workers`` forked processes, longest first (balance); each
    worker resets its first episode with the seed, as :func:`_run_single` does (the episodes
    are seeded per tracklet, so this only keeps ``env.np_random`` the same)."""
    from training.loading import load_kernels
    from training.parallel import map_forked

    lengths = env.unwrapped.tracklet_lengths
    ids = [t.tracklet_id for t in env.unwrapped.tracklets]
    order = sorted(indices, key=lambda i: (-lengths[i], i))
    # workers inherit them: each would otherwise start numba and read its cache again
    load_kernels(tracker)

    def one(index: int) -> _Episode:
        return _run_episode(tracker, env, index, opts.seed, opts.record_boxes)

    episodes = map_forked(
        one, order, opts.workers, tick, label=lambda i: f"tracklet {ids[i]}", warm_up=opts.warm_up
    )
    by_index = dict(zip(order, episodes, strict=True))
    return [by_index[i] for i in indices]


def _run_vector(tracker, vec, tracklets, opts: _RunOptions):
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
    bar = _progress(sum(lengths[i] for i in indices), opts.progress, opts.name)
    episodes: list[_Episode] = []
    active = remaining > 0
    resetting = np.zeros(num, dtype=bool)  # the sub-env autoresets during this step
    obs, infos = vec.reset(seed=opts.seed)
    current = [_vector_episode(infos, i, opts.record_boxes) for i in range(num)]
    while active.any():
        t0 = time.perf_counter()
        actions = np.asarray(tracker.act(obs), dtype=np.float32).reshape(num, -1)
        act_s = time.perf_counter() - t0
        stepping = active & ~resetting
        obs, _, term, trunc, infos = vec.step(actions)
        for i in range(num):
            if resetting[i]:  # this step was the sub-env's reset: a new tracklet starts
                resetting[i] = False
                current[i] = _vector_episode(infos, i, opts.record_boxes)
                continue
            if not active[i]:
                resetting[i] = bool(term[i] or trunc[i])
                continue
            # the batch's act time, shared by the sub-envs that stepped in it
            current[i].act_s += act_s / max(int(stepping.sum()), 1)
            current[i].step({k: infos[k][i] for k in _STEP_KEYS}, opts.record_boxes)
            if term[i] or trunc[i]:
                episodes.append(current[i])
                if bar is not None:
                    bar.update(len(current[i].ious) + 1)
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
    return episodes, info


# the step info a vector env's sub-env result is read from
_STEP_KEYS = ("iou", "center_error", "frame", "pred_box", "gt_box", "target_points")


def _vector_episode(infos: Mapping[str, Any], i: int, record: bool) -> _Episode:
    """The episode sub-env ``i`` starts (its reset info in a vector env's ``infos``)."""
    episode = _Episode(infos["tracklet"][i], infos["category"][i], bool(infos["observed"][i]))
    if record:
        episode.start(infos["init_box"][i], infos["start_frame"][i])
    return episode
