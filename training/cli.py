"""The ``pointtrack`` command line: one sub-command per module in :mod:`training.commands`."""

from __future__ import annotations

import argparse
import importlib
import sys

# name -> (module under training.commands, one-line help). Modules are imported only when their
# command runs, so `pointtrack --help` stays fast and one broken command cannot break the others.
COMMANDS: dict[str, tuple[str, str]] = {
    "generate": ("generate", "generate a synthetic LiDAR world in the KITTI tracking layout"),
    "eval": ("eval", "evaluate a tracker step-wise in the environment (OPE Success/Precision)"),
    "train": ("train", "pretrain P2B / BAT / GPT (plain, decorrelation-weighted, SAM)"),
    "select": ("select", "rank checkpoints by observed Success pooled over validation worlds"),
    "finetune": ("finetune", "RL fine-tuning of a pretrained tracker with stable-baselines3"),
    "bench": ("bench", "run the speed benchmarks and print their numbers"),
    "demo": ("demo", "generate the small world and compare the trackers on it"),
}


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="pointtrack", description=__doc__)
    sub = parser.add_subparsers(dest="command", required=True, metavar="COMMAND")
    for name, (module, help_text) in COMMANDS.items():
        cmd = sub.add_parser(name, help=help_text, description=help_text)
        cmd.set_defaults(_module=module)
        _command_module(module).add_arguments(cmd)
    return parser


def _command_module(module: str):
    return importlib.import_module(f"training.commands.{module}")


def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    return int(_command_module(args._module).run(args) or 0)


if __name__ == "__main__":
    sys.exit(main())
