"""The adverse-weather robustness benchmark of Zhao et al. (adverse-weather SOT): any tracker,
clean and under
fog / rain / snow at levels 1..5, with the paper's robustness metrics and analysis.

:func:`run_weather_benchmark` evaluates a tracker with :func:`training.evaluate.evaluate` on the
clean env and on each ``(kind, level)`` (the env wrapped in :class:`envs.weather.WeatherWrapper`,
same weather seed and fog rule for every tracker), on one env or, with ``num_envs``, on a vector
env whose sub-envs each carry their own transform (batched ``act`` calls, as plain evaluation),
and returns a JSON-able result::

    {"tracker": name, "kinds": [...], "levels": [...], "weather_seed": int, "fog_mode": str,
     "num_envs": int,
     "clean": report, "weather": {kind: {level: report}},          # evaluate() reports
     "robustness": {kind: {group: {"clean": [S, P], "levels": [[S, P] x 5],
                                   "dr": [[S_j/S_c, P_j/P_c] x 5], "DR": [S, P],
                                   "R": [S, P], "Sd": [S, P]}}},
     "analysis": {kind: {level: {"distance"|"template"|"target": {"edges", "mean_delta_iou",
                                                                   "count"}}}}}

Metrics (Sec. III-D), per category and for the observed / unseen / mean groups, for Success and
Precision alike:

- ``dr`` — Eq. 2: ``DR_ij = S_ij / S_clean`` per level.
- ``DR`` — the table column of Tables III–IV: the mean degradation ``1 - mean_j DR_ij``
  (BAT, rain, Car in Table III: clean 62.83, levels average 36.69 -> 0.42; a category that
  gains under weather has a negative DR, as Pedestrian does there).
- ``R`` — range of the five level scores, ``max - min``.
- ``Sd`` — *sample* standard deviation (``ddof = 1``) of the five level scores, which is what
  the paper's numbers are (BAT, rain, Car: 0.50; the population value would be 0.44).

Analysis (Sec. IV-A, Fig. 3): per frame, the IoU change ``IoU_weather - IoU_clean`` of the same
tracklet frame, averaged in bins of (a) the target's distance from the sensor, (b) template
corruption — the Hausdorff distance between the clean and the corrupted points inside the
first frame's ground-truth box (the template), and (c) target corruption — the same for the
current frame's ground-truth box. A box that loses all its points has no Hausdorff distance;
such frames are counted in ``emptied`` and left out of the bins.
"""

from __future__ import annotations

import json
import math
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any

import numpy as np

# light imports only: `pointtrack --help` imports the eval command, which imports this module
# (gymnasium, torch via envs.geometry, and the weather wrapper are imported where used)
from envs.metrics import robustness_metrics
from envs.plotting import pyplot, save_figure
from envs.weather.levels import KINDS, LEVELS, check_kind, check_level, describe
from training.parallel import map_forked
from training.rundir import atomic_write_text

__all__ = [
    "DISTANCE_EDGES_M",
    "add_weather_arguments",
    "check_weather_arguments",
    "parse_weather_levels",
    "run_weather_eval",
    "save_weather",
    "HAUSDORFF_EDGES_M",
    "format_weather_table",
    "hausdorff",
    "plot_analysis",
    "plot_success_vs_level",
    "robustness_metrics",
    "run_weather_benchmark",
    "weather_kinds",
]

DISTANCE_EDGES_M = (0.0, 10.0, 20.0, 30.0, 40.0, 50.0, math.inf)
HAUSDORFF_EDGES_M = (0.0, 0.25, 0.5, 1.0, 1.5, 2.0, 3.0, 3.5, math.inf)
GROUPS = ("mean", "observed", "unseen")
BACKENDS = ("local", "ray")  # what runs the weather conditions (run_weather_benchmark)


# --------------------------------------------------------------------------- metrics


def hausdorff(a: np.ndarray, b: np.ndarray, chunk: int = 2048) -> float:
    """Symmetric Hausdorff distance between point sets ``(n, 3)`` and ``(m, 3)`` (metres).

    Both empty: 0. One empty: NaN (undefined; the caller counts it as a box that emptied).
    """
    a = np.asarray(a, dtype=np.float64)[:, :3]
    b = np.asarray(b, dtype=np.float64)[:, :3]
    if len(a) == 0 and len(b) == 0:
        return 0.0
    if len(a) == 0 or len(b) == 0:
        return math.nan

    def directed(x: np.ndarray, y: np.ndarray) -> float:
        yy = (y**2).sum(1)
        worst = 0.0
        for i in range(0, len(x), chunk):
            xs = x[i : i + chunk]
            d2 = (xs**2).sum(1)[:, None] + yy[None, :] - 2.0 * xs @ y.T
            worst = max(worst, float(np.maximum(d2.min(axis=1), 0.0).max()))
        return math.sqrt(worst)

    return max(directed(a, b), directed(b, a))


def weather_kinds(value: str | Sequence[str]) -> tuple[str, ...]:
    """``"all"`` -> every kind; ``"fog"`` / ``"fog,rain"`` / a sequence -> those (validated)."""
    if isinstance(value, str):
        value = KINDS if value.strip() == "all" else [v.strip() for v in value.split(",") if v]
    return tuple(check_kind(v) for v in value)


# --------------------------------------------------------------------------- per-frame records


def _frame_recorder(env, transform=None, corruption: bool = False):
    """Wrap ``env`` in a :class:`_FrameRecorder` (defined lazily: gymnasium and the geometry
    module are imported only when a benchmark runs)."""
    import gymnasium as gym

    from envs.geometry import points_in_box

    class _FrameRecorder(gym.Wrapper):
        """Records ``(tracklet, frame) -> iou, gt distance, target / template Hausdorff`` from step
        infos. With a weather transform, the clean and corrupted in-box points are compared (the
        transform's cache makes the corrupted scan of the current frame a cache hit)."""

        def __init__(self, env: gym.Env, transform=None, corruption: bool = False) -> None:
            super().__init__(env)
            self.transform = transform
            self.corruption = corruption and transform is not None
            # one dict (tracklet, frame) -> record per episode, in order: a vector env keeps
            # stepping a sub-env after its last tracklet, and those episodes must not count
            self.episodes: list[dict[tuple[str, int], dict[str, float]]] = []
            self.template_hd: dict[str, float] = {}
            self._tracklet = None
            self._by_id = None

        def reset(self, **kwargs):
            obs, info = self.env.reset(**kwargs)
            if self._by_id is None:
                self._by_id = {tr.tracklet_id: tr for tr in self.env.unwrapped.tracklets}
            self._tracklet = self._by_id[info["tracklet"]]
            self.episodes.append({})
            if self.corruption and self._tracklet.tracklet_id not in self.template_hd:
                self.template_hd[self._tracklet.tracklet_id] = self._box_hausdorff(0)
            return obs, info

        def _box_hausdorff(self, t: int) -> float:
            tr = self._tracklet
            clean = np.asarray(tr.points_with_intensity(t), dtype=np.float32)
            bad = self.transform(clean, tr.tracklet_id, int(tr.frames[t]))
            box = np.asarray(tr.boxes[t], dtype=np.float64)
            a = clean[points_in_box(clean[:, :3], box)]
            b = bad[points_in_box(bad[:, :3], box)]
            return hausdorff(a, b)

        def step(self, action):
            obs, reward, terminated, truncated, info = self.env.step(action)
            t = int(info["frame"])
            gt = np.asarray(info["gt_box"], dtype=np.float64)
            rec = {"iou": float(info["iou"]), "distance": float(np.linalg.norm(gt[:3]))}
            if self.corruption:
                rec["target_hd"] = self._box_hausdorff(t)
                rec["template_hd"] = self.template_hd.get(info["tracklet"], math.nan)
            self.episodes[-1][(info["tracklet"], t)] = rec
            return obs, reward, terminated, truncated, info

    return _FrameRecorder(env, transform, corruption)


def _binned(x: np.ndarray, y: np.ndarray, edges: Sequence[float]) -> dict[str, Any]:
    edges_a = np.asarray(edges, dtype=np.float64)
    idx = np.digitize(x, edges_a[1:-1])  # bin i: edges[i] <= x < edges[i+1]
    means, counts = [], []
    for i in range(len(edges_a) - 1):
        sel = idx == i
        counts.append(int(sel.sum()))
        means.append(float(y[sel].mean()) if sel.any() else None)
    return {
        "edges": [float(e) if math.isfinite(e) else None for e in edges_a],
        "mean_delta_iou": means,
        "count": counts,
    }


def _analysis(clean: dict, weather: dict) -> dict[str, Any]:
    keys = [k for k in weather if k in clean]
    if not keys:
        return {}
    delta = np.array([weather[k]["iou"] - clean[k]["iou"] for k in keys])
    dist = np.array([clean[k]["distance"] for k in keys])
    out: dict[str, Any] = {
        "distance": _binned(dist, delta, DISTANCE_EDGES_M),
        "mean_delta_iou": float(delta.mean()),
        "frames": len(keys),
    }
    for name, key in (("template", "template_hd"), ("target", "target_hd")):
        hd = np.array([weather[k].get(key, math.nan) for k in keys], dtype=np.float64)
        ok = np.isfinite(hd)
        out[name] = _binned(hd[ok], delta[ok], HAUSDORFF_EDGES_M)
        out[name]["emptied"] = int((~ok).sum())
    return out


# --------------------------------------------------------------------------- the runner


def _summary(report: dict, group: str) -> tuple[float, float]:
    if group in GROUPS:
        e = report.get(group)
    else:
        e = report["categories"].get(group)
    if not e or not e.get("frames"):
        return math.nan, math.nan
    s, p = e["success"], e["precision"]
    return (math.nan if s is None else float(s)), (math.nan if p is None else float(p))


def run_weather_benchmark(
    tracker: Any,
    make_env: Callable[[], Any],
    kinds: str | Sequence[str] = KINDS,
    levels: Sequence[int] = LEVELS,
    *,
    seed: int = 0,
    weather_seed: int = 0,
    name: str | None = None,
    analysis: bool = True,
    progress: bool = False,
    out_dir: str | Path | None = None,
    tracklets: Sequence[int] | None = None,
    log: Callable[[str], None] | None = None,
    num_envs: int | None = None,
    fog_mode: str = "reference",
    workers: int | None = None,
    backend: str = "local",
) -> dict[str, Any]:
    """Evaluate ``tracker`` clean and under every ``(kind, level)``; see the module docstring.

    Args:
        tracker: anything with ``act(obs)``.
        make_env: zero-argument factory of a fresh (clean) ``TrackingEnv``, possibly wrapped;
            called once per setting (1 + kinds x levels times).
        kinds: ``"all"``, one kind, or a sequence of kinds.
        levels: weather levels (default 1..5; R and S.d need at least two).
        seed: the evaluation seed (point-set resampling), the same for every setting.
        weather_seed: seed of the weather (the same corruption for every tracker).
        analysis: also record per-frame IoU changes and in-box Hausdorff distances (Sec. IV-A).
        out_dir: if given, write ``weather.json``, ``weather_table.txt``,
            ``weather_success.png`` and (with analysis) ``weather_analysis.png`` there.
        tracklets: indices of the env's tracklets to run (default all).
        log: called with a line after each setting (e.g. ``print``).
        num_envs: ``None``: one env, one observation per ``act`` call. An int ``N >= 1``: a
            ``SyncVectorEnv`` of ``N`` envs from ``make_env`` (each with its own weather
            transform: the corruption of a frame depends on the seed, scene and frame only), so
            ``act`` gets ``(N, ...)`` batches as in :func:`training.evaluate.evaluate`. With
            ``N = 1`` the result equals the single-env one exactly; with more, a learned
            tracker's batched forward can differ in the last bit (see ``evaluate``).
        fog_mode: the fog rule, ``"reference"`` (default) or ``"lossy"``
            (:mod:`envs.weather.fog`).
        workers: run the settings in this many forked processes (one torch thread each; the
            settings are independent, so the result is the same as with ``None``, one process).
            Needs the ``fork`` start method (Linux); progress bars are off in the workers.
        backend: ``"local"`` (the forked processes above) or ``"ray"``: the settings as Ray
            tasks (:func:`training.sweep.ray_backend.map_ray`; ``RAY_ADDRESS`` or a local Ray of
            ``workers`` CPUs), the same result bit for bit; needs the ``sweep`` extra.
    """
    import gymnasium as gym

    from envs.weather import WeatherWrapper, check_fog_mode
    from training.evaluate import evaluate
    from training.evaluate import tracker_name as _tracker_name

    kinds_t = weather_kinds(kinds)
    levels_t = tuple(check_level(v) for v in levels)
    _refuse_repeats("weather kinds", kinds_t)
    _refuse_repeats("weather levels", levels_t)
    check_fog_mode(fog_mode)
    _check_count("num_envs", num_envs)
    _check_count("workers", workers)
    name = _tracker_name(tracker, name)
    say = log or (lambda _msg: None)
    show_progress = progress and (workers or 1) == 1

    def one(condition: tuple[str | None, int | None]):
        kind, level = condition
        recorders = []
        for _ in range(num_envs or 1):
            env = make_env()
            transform = None
            if kind is not None:
                env = WeatherWrapper(env, kind, level, seed=weather_seed, fog_mode=fog_mode)
                transform = env.transform
            recorders.append(_frame_recorder(env, transform, corruption=analysis))
        target = recorders[0]
        if num_envs is not None:
            target = gym.vector.SyncVectorEnv([lambda r=r: r for r in recorders])
        try:
            report = evaluate(
                tracker, target, seed=seed, tracklets=tracklets, name=name, progress=show_progress
            )
        finally:
            target.close()
        return report, _real_records(recorders, tracklets, vector=num_envs is not None)

    conditions = [(None, None)] + [(k, lv) for k in kinds_t for lv in levels_t]

    def said(condition, outcome):
        kind, level = condition
        mean = outcome[0]["mean"]
        label = "clean" if kind is None else describe(kind, level)
        say(f"{label}: success {mean['success']:.2f} precision {mean['precision']:.2f}")

    if backend not in BACKENDS:
        raise ValueError(f"backend must be one of {BACKENDS}; got {backend!r}")
    if backend == "ray":
        from training.sweep.ray_backend import map_ray as run_all
    else:
        run_all = map_forked
    outcomes = dict(zip(conditions, run_all(one, conditions, workers, said), strict=True))
    clean, clean_records = outcomes[(None, None)]
    result: dict[str, Any] = {
        "tracker": name,
        "kinds": list(kinds_t),
        "levels": list(levels_t),
        "seed": seed,
        "weather_seed": weather_seed,
        "fog_mode": fog_mode,
        "num_envs": num_envs or 1,
        "clean": clean,
        "weather": {},
        "robustness": {},
        "analysis": {},
    }
    for kind in kinds_t:
        result["weather"][kind] = {}
        result["analysis"][kind] = {}
        for level in levels_t:
            report, records = outcomes[(kind, level)]
            result["weather"][kind][level] = report
            if analysis:
                result["analysis"][kind][level] = _analysis(clean_records, records)
        result["robustness"][kind] = _robustness(clean, result["weather"][kind], levels_t)
    if out_dir is not None:
        save_weather(result, out_dir)
    return result


def _check_count(name: str, value: Any) -> None:
    if value is not None and (isinstance(value, bool) or int(value) != value or value < 1):
        raise ValueError(f"{name} must be None or an integer >= 1; got {value!r}")


def _real_records(
    recorders: list, tracklets: Sequence[int] | None, vector: bool
) -> dict[tuple[str, int], dict[str, float]]:
    """The per-frame records of the episodes :func:`training.evaluate.evaluate` counted: all of
    a single env's; of a vector env, the first ``len(order_i)`` episodes of sub-env ``i`` (the
    same :func:`~training.evaluate.split_tracklets` assignment as ``evaluate``'s vector runner;
    later episodes of a sub-env that is done only keep the batch full)."""
    if not vector:
        return {k: v for episode in recorders[0].episodes for k, v in episode.items()}
    from training.evaluate import split_tracklets

    lengths = recorders[0].unwrapped.tracklet_lengths
    indices = range(len(lengths)) if tracklets is None else [int(i) for i in tracklets]
    counts = [len(o) for o in split_tracklets([lengths[i] for i in indices], len(recorders))]
    out: dict[tuple[str, int], dict[str, float]] = {}
    for rec, count in zip(recorders, counts, strict=True):
        for episode in rec.episodes[:count]:
            out.update(episode)
    return out


def _robustness(clean: dict, per_level: dict, levels: Sequence[int]) -> dict[str, Any]:
    groups = list(clean["categories"]) + [g for g in GROUPS if clean.get(g, {}).get("frames")]
    out = {}
    for g in groups:
        c = _summary(clean, g)
        lv = [_summary(per_level[level], g) for level in levels]
        ms = robustness_metrics(c[0], [x[0] for x in lv])
        mp = robustness_metrics(c[1], [x[1] for x in lv])
        cat = clean["categories"].get(g)
        out[g] = {
            "observed": None if cat is None else bool(cat.get("observed", True)),
            "clean": list(c),
            "levels": [list(x) for x in lv],
            "dr": [list(x) for x in zip(ms["dr"], mp["dr"], strict=True)],
            "DR": [ms["DR"], mp["DR"]],
            "R": [ms["R"], mp["R"]],
            "Sd": [ms["Sd"], mp["Sd"]],
        }
    return out


# --------------------------------------------------------------------------- output


def _sp(x: Sequence[float], digits: int = 2) -> str:
    def f(v):
        return "-" if v is None or (isinstance(v, float) and math.isnan(v)) else f"{v:.{digits}f}"

    return f"{f(x[0])}/{f(x[1])}"


def format_weather_table(results: dict[str, Any] | Sequence[dict[str, Any]]) -> str:
    """Tables III–IV layout: per weather kind, per category, one row per tracker — Clean, Lv-1..
    Lv-5 as Success/Precision, then DR, R and S.d as Success/Precision."""
    if isinstance(results, dict):
        results = [results]
    levels = results[0]["levels"]
    cols = ["Clean"] + [f"Lv-{lv}" for lv in levels] + ["DR", "R", "S.d"]
    namew = max(8, *(len(r["tracker"]) for r in results))
    cw = 13
    head = f"{'Category':<11}{'Method':<{namew}} " + " ".join(f"{c:^{cw}}" for c in cols)
    lines = [head, "-" * len(head)]
    for kind in results[0]["kinds"]:
        lines.append(kind.capitalize())
        groups: list[str] = []
        for r in results:
            for g in r["robustness"].get(kind, {}):
                if g not in groups:
                    groups.append(g)
        for g in groups:
            for i, r in enumerate(results):
                e = r["robustness"].get(kind, {}).get(g)
                if e is None:
                    continue
                cells = [_sp(e["clean"])] + [_sp(x) for x in e["levels"]]
                cells += [_sp(e["DR"]), _sp(e["R"]), _sp(e["Sd"])]
                label = (g + ("*" if e.get("observed") is False else "")) if i == 0 else ""
                lines.append(
                    f"{label:<11}{r['tracker']:<{namew}} " + " ".join(f"{c:^{cw}}" for c in cells)
                )
    lines.append(
        "Success/Precision in percent; DR = 1 - mean_j(S_j / S_clean) (Tables III-IV), "
        "R = max - min and S.d = sample std over the levels; * unseen category."
    )
    return "\n".join(lines)


def plot_success_vs_level(
    results: dict[str, Any] | Sequence[dict[str, Any]],
    path: str | Path,
    metric: str = "success",
    groups: Sequence[str] | None = None,
) -> Path:
    """One panel per weather kind: Success (or Precision) against level (0 = clean), one line per
    category and the mean, per tracker; ``groups`` restricts the lines (e.g. ``["mean",
    "unseen"]``; default: every category and the mean)."""
    plt = pyplot()

    if isinstance(results, dict):
        results = [results]
    kinds = results[0]["kinds"]
    k = 0 if metric == "success" else 1
    fig, axes = plt.subplots(1, len(kinds), figsize=(4.2 * len(kinds), 3.6), squeeze=False)
    for ax, kind in zip(axes[0], kinds, strict=True):
        for r in results:
            for g, e in r["robustness"][kind].items():
                if (g not in groups) if groups is not None else g in ("observed", "unseen"):
                    continue
                xs = [0] + list(r["levels"])
                ys = [e["clean"][k]] + [x[k] for x in e["levels"]]
                style = "-o" if g in ("mean", "observed") else "--."
                label = g if len(results) == 1 else f"{r['tracker']} {g}"
                ax.plot(xs, ys, style, label=label, lw=2 if g == "mean" else 1)
        ax.set_title(kind.capitalize())
        ax.set_xlabel("level (0 = clean)")
        ax.set_ylabel(f"{metric} (%)")
        ax.set_xticks([0] + list(results[0]["levels"]))
        ax.grid(alpha=0.3)
        ax.legend(fontsize=7)
    fig.tight_layout()
    return save_figure(fig, path, 110)


def plot_analysis(result: dict[str, Any], path: str | Path) -> Path:
    """Fig. 3 layout: rows target distance / template corruption / target corruption, one column
    per weather kind, mean IoU change per bin, one line per level."""
    plt = pyplot()

    kinds = result["kinds"]
    rows = (
        ("distance", "target distance (m)"),
        ("template", "template Hausdorff (m)"),
        ("target", "target Hausdorff (m)"),
    )
    fig, axes = plt.subplots(3, len(kinds), figsize=(4.2 * len(kinds), 9), squeeze=False)
    for j, kind in enumerate(kinds):
        for i, (key, xlabel) in enumerate(rows):
            ax = axes[i][j]
            for level, a in result["analysis"].get(kind, {}).items():
                b = a.get(key)
                if not b:
                    continue
                edges = [e if e is not None else math.inf for e in b["edges"]]
                labels = [
                    f"{edges[n]:g}-{edges[n + 1]:g}"
                    if math.isfinite(edges[n + 1])
                    else f">{edges[n]:g}"
                    for n in range(len(edges) - 1)
                ]
                ys = [np.nan if v is None else v for v in b["mean_delta_iou"]]
                ax.plot(range(len(labels)), ys, "-o", ms=3, label=f"L{level}")
                ax.set_xticks(range(len(labels)), labels, rotation=45, fontsize=7)
            ax.axhline(0, color="k", lw=0.5)
            ax.set_xlabel(xlabel)
            ax.set_ylabel("mean IoU change")
            if i == 0:
                ax.set_title(kind.capitalize())
            ax.grid(alpha=0.3)
            ax.legend(fontsize=6)
    fig.tight_layout()
    return save_figure(fig, path, 100)


def save_weather(result: dict[str, Any], out_dir: str | Path) -> list[Path]:
    """Write ``weather.json``, ``weather_table.txt``, ``weather_success.png`` (and
    ``weather_analysis.png`` when the result has analysis) into ``out_dir``."""
    from training.evaluate import json_safe as _json_safe

    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    paths = [out / "weather.json", out / "weather_table.txt"]
    atomic_write_text(paths[0], json.dumps(_json_safe(result), indent=1) + "\n")
    atomic_write_text(paths[1], format_weather_table(result) + "\n")
    paths.append(plot_success_vs_level(result, out / "weather_success.png"))
    if any(result["analysis"].get(k) for k in result["kinds"]):
        paths.append(plot_analysis(result, out / "weather_analysis.png"))
    return paths


# --------------------------------------------------------------------------- CLI glue


def add_weather_arguments(parser) -> None:
    """The ``pointtrack eval`` flags of the weather benchmark (``--weather`` and friends)."""
    parser.add_argument(
        "--weather",
        default=None,
        metavar="KINDS",
        help="run the adverse-weather benchmark: 'all' or a comma list of fog, rain, snow "
        "(clean + every level; Tables III-IV metrics DR, R, S.d)",
    )
    parser.add_argument(
        "--weather-levels",
        default="1,2,3,4,5",
        metavar="LEVELS",
        help="comma list of weather levels 1..5 (default all five)",
    )
    parser.add_argument(
        "--weather-seed", type=int, default=0, help="seed of the weather corruption (default 0)"
    )
    parser.add_argument(
        "--no-analysis",
        action="store_true",
        help="skip the Sec. IV-A analysis (IoU change vs distance / Hausdorff)",
    )
    parser.add_argument(
        "--fog-mode",
        default="reference",
        choices=("reference", "lossy"),
        help="fog rule: reference (the released fog simulation code: fog "
        "returns relocate points, none removed; default) or lossy (shifted "
        "tables, weak returns removed); docs/weather.md",
    )
    parser.add_argument(
        "--backend",
        default="local",
        choices=BACKENDS,
        help="what runs the weather conditions: local (forked processes, --workers) or ray "
        "(Ray tasks on RAY_ADDRESS or a local Ray of --workers CPUs; the same result; needs "
        "pip install 'pointtrack[sweep]')",
    )


def parse_weather_levels(text: str | Sequence[int]) -> tuple[int, ...]:
    """``"1,3,5"`` (or a sequence) -> ``(1, 3, 5)``; ``ValueError`` naming ``--weather-levels``
    for an empty list, a bad or repeated level (R and S.d over a repeated level mean nothing)."""
    values = [v.strip() for v in text.split(",")] if isinstance(text, str) else list(text)
    if not [v for v in values if v != ""]:
        raise ValueError(f"--weather-levels {text!r} names no level; valid levels 1..5")
    try:
        levels = tuple(check_level(int(v)) for v in values)
    except (TypeError, ValueError) as exc:
        raise ValueError(f"--weather-levels {text!r}: {exc}") from None
    _refuse_repeats("--weather-levels", levels)
    return levels


def _refuse_repeats(flag: str, values: Sequence[Any]) -> None:
    repeated = [v for i, v in enumerate(values) if v in values[:i]]
    if repeated:
        raise ValueError(f"{flag} lists {repeated[0]!r} twice: {list(values)}")


def check_weather_arguments(args) -> None:
    """Every ``--weather*`` flag checked before any work (``ValueError`` naming the flag):
    kinds known and not repeated, levels as :func:`parse_weather_levels`, a seed ``>= 0``."""
    try:
        kinds = weather_kinds(args.weather)
    except ValueError as exc:
        raise ValueError(f"--weather {args.weather!r}: {exc}") from None
    if not kinds:
        raise ValueError(f"--weather {args.weather!r} names no kind; valid: all, {KINDS}")
    _refuse_repeats("--weather", kinds)
    parse_weather_levels(args.weather_levels)
    if args.weather_seed < 0:
        raise ValueError(f"--weather-seed must be >= 0, got {args.weather_seed}")


def run_weather_eval(
    tracker: Any,
    make_env: Callable[[], Any],
    weather: str | Sequence[str],
    *,
    levels: str | Sequence[int] = LEVELS,
    seed: int = 0,
    weather_seed: int = 0,
    out_dir: str | Path | None = None,
    analysis: bool = True,
    progress: bool = False,
    name: str | None = None,
    tracklets: Sequence[int] | None = None,
    print_fn: Callable[[str], None] = print,
    num_envs: int | None = None,
    fog_mode: str = "reference",
    workers: int | None = None,
    backend: str = "local",
) -> dict[str, Any]:
    """What ``pointtrack eval --weather ...`` runs: :func:`run_weather_benchmark`, then print the
    Tables III–IV layout and (with ``out_dir``) write JSON, table and plots."""
    levels = parse_weather_levels(levels)
    result = run_weather_benchmark(
        tracker,
        make_env,
        weather,
        levels,
        seed=seed,
        weather_seed=weather_seed,
        name=name,
        analysis=analysis,
        progress=progress,
        out_dir=out_dir,
        tracklets=tracklets,
        log=print_fn,
        num_envs=num_envs,
        fog_mode=fog_mode,
        workers=workers,
        backend=backend,
    )
    print_fn(format_weather_table(result))
    if out_dir is not None:
        print_fn(f"wrote {Path(out_dir) / 'weather.json'} and the table / plots next to it")
    return result
