"""`pointtrack sweep`: run every combination of a spec's overrides as a Ray Tune trial.

Examples::

    pointtrack sweep configs/sweeps/p2b-slim-uwsd.yaml              # local Ray, all cores
    pointtrack sweep configs/sweeps/p2b-slim-uwsd.yaml --resume     # finish a killed sweep
    pointtrack sweep configs/sweeps/weather-shipped.yaml --address ray://head:10001
    pointtrack sweep my.yaml --dry-run                              # the trials' commands

Each trial is the ordinary command (``train``, ``finetune``, ``eval``, ``eval --weather``,
``select``) in its own run directory ``OUT/trials/NAME``; the summary (mean +- sd over the seeds
of each group) is printed and written to ``OUT/summary.csv`` and ``OUT/summary.md``. The spec is
validated before any trial starts. Needs the ``sweep`` extra (``pip install
'pointtrack[sweep]'``), except ``--dry-run``. See docs/cluster.md.
"""

from __future__ import annotations

import argparse
import shlex
from pathlib import Path


def add_arguments(parser: argparse.ArgumentParser) -> None:
    """Declare this command's flags."""
    parser.add_argument("spec", metavar="SPEC.yaml", help="the sweep spec (configs/sweeps/)")
    parser.add_argument(
        "--out", default=None, metavar="DIR", help="results directory (default: runs/sweeps/NAME)"
    )
    parser.add_argument(
        "--resume", action="store_true", help="skip finished trials, continue the others"
    )
    parser.add_argument(
        "--address",
        default=None,
        help="a running Ray cluster: auto, HOST:PORT or ray://HOST:PORT (default: start a "
        "local Ray); OUT must be on a file system every node sees",
    )
    parser.add_argument(
        "--num-cpus",
        type=int,
        default=None,
        help="CPUs of the local Ray (default: the usable cores)",
    )
    parser.add_argument(
        "--retries", type=int, default=None, help="tries after a failure (default: the spec's)"
    )
    parser.add_argument(
        "--dry-run", action="store_true", help="print the trials' commands, run nothing"
    )


def run(args: argparse.Namespace) -> int:
    from training.sweep.runner import check_out, run_sweep, trial_command
    from training.sweep.spec import load_spec
    from training.sweep.summary import format_markdown

    spec = load_spec(args.spec)  # SpecError (a ValueError): one line, status 2
    out = Path(args.out or Path("runs") / "sweeps" / spec.name)
    if args.num_cpus is not None and args.num_cpus < 1:
        raise SystemExit(f"--num-cpus must be >= 1, got {args.num_cpus}")
    if args.retries is not None and args.retries < 0:
        raise SystemExit(f"--retries must be >= 0, got {args.retries}")
    if args.dry_run:
        pending = check_out(spec, out, args.resume)
        for trial in pending:
            print(shlex.join(trial_command(spec, trial, out)))
        return 0
    # a missing extra, an unreachable address, a refused --out: one line (training.cli)
    result = run_sweep(
        spec,
        out,
        address=args.address,
        resume=args.resume,
        num_cpus=args.num_cpus,
        retries=args.retries,
    )
    if result.rows:
        print(format_markdown(result.rows, result.metrics, spec.seed_key))
    print(
        f"{len(result.ran)} trials run, {len(result.skipped)} skipped (finished before), "
        f"{len(result.failed)} failed, {result.wall_s:.0f} s; results in {out}"
    )
    if result.failed:
        names = ", ".join(result.failed)
        raise SystemExit(f"{len(result.failed)} trial(s) failed ({names}): see their trial.log")
    return 0
