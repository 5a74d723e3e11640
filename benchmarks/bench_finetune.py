"""``pointtrack finetune`` as a user runs it: env steps per second of the whole fine-tune.

    python benchmarks/bench_finetune.py [--tracker gpt-kitti1-u] [--algo group] [--threads N]
                                        [--timesteps 1024] [--repeats 1] [--baseline REV]

Each repeat runs ``python -m training.cli finetune`` in a fresh process on the measured tree's
packages with issue 41's flags (``--train-parts head --group-size 8 --num-envs 4 --n-steps 64
--batch-size 64 --n-epochs 2 --preset tiny --no-val``) and reads ``steps_per_s`` from the last
line of the run's ``log.jsonl`` (env steps over the wall clock of the rollouts and updates).
``--threads 0`` (the default) passes no ``--threads``: the command's own default (every usable
core since this benchmark was written; one thread before). Wall clock only.
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
import tempfile
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))

from baseline import parser, run, use_code_root  # noqa: E402 - same folder

ISSUE_FLAGS = (
    "--train-parts head --group-size 8 --num-envs 4 --n-steps 64 --batch-size 64 "
    "--n-epochs 2 --preset tiny --no-val --no-progress"
).split()


def finetune_once(root: Path, argv: list[str]) -> float:
    """One ``pointtrack finetune`` process on the packages of ``root`` -> its env steps/s."""
    with tempfile.TemporaryDirectory(prefix="pointtrack-bench-finetune-") as tmp:
        out = Path(tmp) / "run"
        env = {**os.environ, "PYTHONPATH": str(root)}
        cmd = [sys.executable, "-m", "training.cli", "finetune", *argv, "--out", str(out)]
        proc = subprocess.run(cmd, cwd=root, env=env, capture_output=True, text=True)
        if proc.returncode != 0:
            raise SystemExit(f"pointtrack finetune failed (exit {proc.returncode}):\n{proc.stderr}")
        last = (out / "log.jsonl").read_text().splitlines()[-1]
    return float(json.loads(last)["steps_per_s"])


def main(argv: list[str] | None = None) -> int:
    p = parser(__doc__, threads=0, repeats=1)
    p.add_argument("--tracker", default="gpt-kitti1-u")
    p.add_argument("--algo", default="group", choices=("group", "ppo"))
    p.add_argument("--timesteps", type=int, default=1024)
    args = p.parse_args(argv)
    if args.clock != "wall":
        raise SystemExit("bench_finetune.py: --clock must be wall (steps/s of the run's log)")
    root = use_code_root()
    flags = ["--tracker", args.tracker, "--algo", args.algo, "--timesteps", str(args.timesteps)]
    flags += ISSUE_FLAGS + (["--threads", str(args.threads)] if args.threads else [])
    threads = args.threads or "default"

    def measure() -> dict[str, float]:
        rate = max(finetune_once(root, flags) for _ in range(args.repeats))
        return {f"{args.tracker} {args.algo}, threads {threads}": rate}

    return run(args, measure, "env steps/s")


if __name__ == "__main__":
    sys.exit(main())
