"""Benchmark ``pointtrack sweep``'s wall-time overhead against the same trials in a shell loop.

Usage: ``python benchmarks/bench_sweep.py [SPEC] [--jobs 2] [--repeats 2]``
(default spec: ``configs/sweeps/p2b-slim-uw-small.yaml``, the -U vs -W three-seed goal run).

Runs, interleaved ``--repeats`` times each in fresh directories under ``--work``:

- ray: ``python -m training.cli sweep SPEC --num-cpus JOBS`` (start-up of a local Ray and Tune,
  the trials, the summary);
- loop: the trials' own command lines (``sweep --dry-run``) through ``xargs -P JOBS``, the shell
  loop of ``experiments/`` with the same concurrency and one torch thread per trial.

Prints every wall time, the best of each and the overhead ``ray / loop - 1`` (best against
best). The machine is shared: the load average is printed with the numbers.
"""

from __future__ import annotations

import argparse
import os
import shlex
import shutil
import subprocess
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]


def timed(command: list[str] | str, shell: bool = False) -> float:
    start = time.perf_counter()
    env = dict(os.environ, PYTHONPATH=str(ROOT), OMP_NUM_THREADS="1", MKL_NUM_THREADS="1")
    subprocess.run(command, shell=shell, check=True, cwd=ROOT, env=env, capture_output=True)
    return time.perf_counter() - start


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("spec", nargs="?", default="configs/sweeps/p2b-slim-uw-small.yaml")
    parser.add_argument("--jobs", type=int, default=2, help="trials at once (both ways)")
    parser.add_argument("--repeats", type=int, default=2)
    parser.add_argument("--work", default="runs/bench-sweep", help="scratch directory")
    args = parser.parse_args()
    work = Path(args.work).resolve()
    cli = [sys.executable, "-m", "training.cli", "sweep", args.spec]
    times: dict[str, list[float]] = {"ray": [], "loop": []}
    for r in range(args.repeats):
        for way in ("loop", "ray"):  # the loop first: it also generates the world once
            out = work / f"{way}-{r}"
            shutil.rmtree(out, ignore_errors=True)
            if way == "ray":
                seconds = timed([*cli, "--out", str(out), "--num-cpus", str(args.jobs)])
            else:
                lines = subprocess.run(
                    [*cli, "--out", str(out), "--dry-run"],
                    check=True,
                    cwd=ROOT,
                    capture_output=True,
                    text=True,
                    env=dict(os.environ, PYTHONPATH=str(ROOT)),
                ).stdout
                script = work / f"{way}-{r}.cmds"
                script.parent.mkdir(parents=True, exist_ok=True)
                script.write_text(lines)
                seconds = timed(
                    f"xargs -P {args.jobs} -I CMD sh -c CMD < {shlex.quote(str(script))}",
                    shell=True,
                )
            times[way].append(seconds)
            print(f"{way} #{r}: {seconds:.1f} s (load {os.getloadavg()[0]:.1f})", flush=True)
    best = {way: min(values) for way, values in times.items()}
    print(
        f"best: ray {best['ray']:.1f} s, loop {best['loop']:.1f} s, overhead "
        f"{100 * (best['ray'] / best['loop'] - 1):+.1f} % ({args.jobs} trials at once, "
        f"{args.repeats} repeats, shared machine)"
    )


if __name__ == "__main__":
    main()
