"""Shared benchmark plumbing: the common options, the timer, and ``--baseline REV``.

Every benchmark that compares commits builds its parser with :func:`parser` and hands
:func:`run` a function that measures once and returns ``{metric: rate}`` (higher is faster).
Without ``--baseline`` :func:`run` prints that one measurement. With ``--baseline REV`` it
checks ``REV`` out in a temporary ``git worktree`` and runs the same benchmark script (this
commit's copy, so the options and the measurement are the same) in fresh subprocesses, once
against this commit's packages and once against ``REV``'s (``POINTTRACK_CODE_ROOT`` says which
tree :func:`use_code_root` puts first on ``sys.path``). The two alternate for ``--rounds``
rounds, this commit first in even rounds and the baseline first in odd ones, so drift on the
shared machine hits both; each metric keeps its best round. It prints both and their ratio,
and with several rounds the lowest and highest ratio of a single round (the spread).
"""

from __future__ import annotations

import argparse
import contextlib
import json
import os
import subprocess
import sys
import tempfile
import time
from collections.abc import Callable, Iterator
from pathlib import Path

__all__ = ["best_seconds", "parser", "run", "use_code_root"]

REPO = Path(__file__).resolve().parents[1]
_ROOT_ENV = "POINTTRACK_CODE_ROOT"


def use_code_root() -> Path:
    """Put the tree the benchmark measures first on ``sys.path`` and return it: this checkout,
    or the baseline worktree in a ``--baseline`` subprocess. Call before importing the project."""
    root = Path(os.environ.get(_ROOT_ENV, REPO))
    sys.path.insert(0, str(root))
    return root


def parser(doc: str, threads: int = 1, repeats: int = 5) -> argparse.ArgumentParser:
    """An argument parser with the options every benchmark shares: ``--threads``,
    ``--repeats`` (best of), ``--baseline REV``, ``--rounds`` (of the baseline comparison)."""
    p = argparse.ArgumentParser(
        description=doc.splitlines()[0], formatter_class=argparse.RawDescriptionHelpFormatter
    )
    p.add_argument("--threads", type=int, default=threads, help="torch threads")
    p.add_argument("--repeats", type=int, default=repeats, help="timed repeats (best of)")
    p.add_argument(
        "--baseline",
        metavar="REV",
        help="also run this benchmark on git revision REV (a temporary worktree) and print "
        "both and their ratio",
    )
    p.add_argument(
        "--rounds", type=int, default=3, help="interleaved rounds of the --baseline comparison"
    )
    p.add_argument(
        "--clock",
        choices=("wall", "cpu"),
        default="wall",
        help="time by the wall clock, or by this process's CPU time (all its threads): far less "
        "inflated than wall time when other processes share the cores (one thread, no workers)",
    )
    p.add_argument("--json-out", help=argparse.SUPPRESS)  # a --baseline subprocess's results
    return p


def best_seconds(
    fn: Callable[[], object],
    repeats: int,
    warmup: int = 1,
    sync: Callable[[], object] | None = None,
    clock: str = "wall",
) -> float:
    """The fastest of ``repeats`` timed calls of ``fn`` after ``warmup`` untimed ones, seconds
    of ``clock`` (``"wall"`` or ``"cpu"``: process CPU time); ``sync``, e.g.
    ``torch.cuda.synchronize``, runs before each clock read."""
    if repeats < 1:
        raise ValueError(f"repeats must be >= 1, got {repeats}")
    sync = sync or (lambda: None)
    now = {"wall": time.perf_counter, "cpu": time.process_time}[clock]
    for _ in range(warmup):
        fn()
    sync()
    best = float("inf")
    for _ in range(repeats):
        start = now()
        fn()
        sync()
        best = min(best, now() - start)
    return best


def run(args: argparse.Namespace, measure: Callable[[], dict[str, float]], unit: str) -> int:
    """Measure and print (``{metric: rate in unit}``), or compare with ``args.baseline``."""
    if args.json_out:
        _write_json(Path(args.json_out), measure())
        return 0
    if args.baseline is None:
        results = measure()
        _print_table({"this": results}, unit)
        return 0
    if args.rounds < 1:
        raise SystemExit(f"--rounds must be >= 1, got {args.rounds}")
    script = Path(sys.argv[0]).resolve()
    argv = _without_baseline(sys.argv[1:])
    sha = _git("rev-parse", "--verify", f"{args.baseline}^{{commit}}").strip()
    head = _git("rev-parse", "HEAD").strip()
    dirty = " (+ uncommitted changes)" if _git("status", "--porcelain", "-uno").strip() else ""
    print(f"this: {head[:10]}{dirty} at {REPO}; baseline: {args.baseline} = {sha[:10]}")
    print(f"{args.clock} clock, best of {args.repeats} repeats x {args.rounds} rounds")
    best: dict[str, dict[str, float]] = {"this": {}, "baseline": {}}
    ratios: dict[str, list[float]] = {}  # each round's this / baseline, per metric
    with _worktree(sha) as base_root:
        for r in range(args.rounds):
            sides = [("this", REPO), ("baseline", base_root)]
            round_results = {}
            for side, root in sides if r % 2 == 0 else sides[::-1]:
                round_results[side] = _subprocess(script, argv, root)
                for key, value in round_results[side].items():
                    best[side][key] = max(best[side].get(key, 0.0), value)
            for key, value in round_results["this"].items():
                base = round_results["baseline"].get(key)
                if base:
                    ratios.setdefault(key, []).append(value / base)
            print(f"round {r + 1}/{args.rounds} done, load average {os.getloadavg()[0]:.2f}")
    _print_table(best, unit, ratios if args.rounds > 1 else None)
    return 0


def _without_baseline(argv: list[str]) -> list[str]:
    """``argv`` less its ``--baseline REV`` / ``--baseline=REV``."""
    out, skip = [], False
    for arg in argv:
        if skip:
            skip = False
        elif arg == "--baseline":
            skip = True
        elif not arg.startswith("--baseline="):
            out.append(arg)
    return out


def _git(*args: str) -> str:
    return subprocess.run(
        ["git", "-C", str(REPO), *args], check=True, capture_output=True, text=True
    ).stdout


@contextlib.contextmanager
def _worktree(sha: str) -> Iterator[Path]:
    """A detached temporary ``git worktree`` of ``sha``, removed afterwards."""
    with tempfile.TemporaryDirectory(prefix="pointtrack-baseline-") as tmp:
        path = Path(tmp) / "tree"
        _git("worktree", "add", "--detach", str(path), sha)
        try:
            yield path
        finally:
            _git("worktree", "remove", "--force", str(path))


def _subprocess(script: Path, argv: list[str], root: Path) -> dict[str, float]:
    """One run of ``script`` on the packages of ``root`` -> its ``{metric: rate}``."""
    with tempfile.TemporaryDirectory(prefix="pointtrack-bench-") as tmp:
        out = Path(tmp) / "results.json"
        env = {**os.environ, _ROOT_ENV: str(root)}
        cmd = [sys.executable, str(script), *argv, "--json-out", str(out)]
        proc = subprocess.run(cmd, cwd=root, env=env, capture_output=True, text=True)
        if proc.returncode != 0:
            raise SystemExit(
                f"benchmark failed on {root} (exit {proc.returncode}):\n{proc.stderr[-2000:]}"
            )
        return json.loads(out.read_text())


def _write_json(path: Path, results: dict[str, float]) -> None:
    tmp = path.with_suffix(".tmp")
    tmp.write_text(json.dumps(results))
    tmp.replace(path)


def _print_table(
    results: dict[str, dict[str, float]],
    unit: str,
    round_ratios: dict[str, list[float]] | None = None,
) -> None:
    """One row per metric: each side's rate and, with a baseline, this / baseline (of the best
    rates), then the lowest and highest ratio of a single round when ``round_ratios`` is
    given: the spread of the comparison on this machine."""
    keys = list(dict.fromkeys(k for side in results.values() for k in side))
    width = max([len(k) for k in keys] + [6])
    sides = list(results)
    print(f"{'metric':<{width}}  " + "  ".join(f"{s + ' ' + unit:>18}" for s in sides), end="")
    print("  ratio" if "baseline" in results else "")
    for key in keys:
        values = [results[s].get(key) for s in sides]
        cells = "  ".join(f"{'-' if v is None else f'{v:.2f}':>18}" for v in values)
        ratio = ""
        if "baseline" in results and None not in values and values[1] > 0:
            ratio = f"  {values[0] / values[1]:.2f}x"
        if round_ratios and round_ratios.get(key):
            spread = round_ratios[key]
            ratio += f"  (rounds {min(spread):.2f}-{max(spread):.2f}x)"
        print(f"{key:<{width}}  {cells}{ratio}")
