"""`pointtrack bench`: run the speed benchmarks of a source checkout and print their numbers."""

from __future__ import annotations

import argparse
import subprocess
import sys
from pathlib import Path

BENCH_DIR = Path(__file__).resolve().parents[2] / "benchmarks"


def available() -> list[str]:
    """Names of the benchmark scripts (``bench_<name>.py``) next to the package."""
    return sorted(p.stem.removeprefix("bench_") for p in BENCH_DIR.glob("bench_*.py"))


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument(
        "names", nargs="*", help="benchmarks to run (default: all); e.g. geometry env trackers"
    )
    parser.add_argument("--quick", action="store_true", help="smaller problem sizes")


def run(args: argparse.Namespace) -> int:
    names = available()
    if not names:
        raise SystemExit(
            f"pointtrack bench: no benchmarks found in {BENCH_DIR} (a source checkout is needed)"
        )
    unknown = sorted(set(args.names) - set(names))
    if unknown:
        raise SystemExit(f"pointtrack bench: unknown benchmark(s) {unknown}; valid: {names}")
    failed = []
    for name in args.names or names:
        print(f"=== {name}", flush=True)
        cmd = [sys.executable, str(BENCH_DIR / f"bench_{name}.py")] + (
            ["--quick"] if args.quick else []
        )
        if subprocess.call(cmd) != 0:
            failed.append(name)
    if failed:
        print(f"failed: {failed}", file=sys.stderr)
    return 1 if failed else 0
