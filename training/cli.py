"""The ``pointtrack`` command line: one sub-command per module in training.commands.

Error policy: an expected error (bad input, a missing or unwritable path, a refused resume, an
unavailable device) prints one line ``pointtrack COMMAND: message`` on stderr and exits with
status 2; ``--traceback`` shows the full traceback instead. Anything else is a bug and keeps its
traceback.
"""

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
    "sweep": ("sweep", "run a spec's seeds / grid / weather conditions as Ray Tune trials"),
    "bench": ("bench", "run the speed benchmarks and print their numbers"),
    "demo": ("demo", "generate the small world and compare the trackers on it"),
}

# The exception types a command raises for expected errors (their message is the whole story).
EXPECTED_ERRORS: tuple[type[BaseException], ...] = (ValueError, OSError, KeyError)


class HelpFormatter(argparse.RawDescriptionHelpFormatter, argparse.ArgumentDefaultsHelpFormatter):
    """Descriptions keep their line breaks; every flag's help ends with its default (unless the
    default is "not given" or off: ``None`` / ``False``)."""

    def _get_help_string(self, action: argparse.Action) -> str | None:
        if action.default is None or action.default is False or "(default" in (action.help or ""):
            return action.help
        return super()._get_help_string(action)


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="pointtrack", description=__doc__, formatter_class=HelpFormatter
    )
    parser.add_argument(
        "--traceback", action="store_true", help="show the full traceback of an expected error"
    )
    sub = parser.add_subparsers(dest="command", required=True, metavar="COMMAND")
    for name, (module, help_text) in COMMANDS.items():
        mod = _command_module(module)
        cmd = sub.add_parser(
            name,
            help=help_text,
            description=plain_text(mod.__doc__ or help_text),
            formatter_class=HelpFormatter,
        )
        cmd.set_defaults(_module=module)
        mod.add_arguments(cmd)
    return parser


def plain_text(doc: str) -> str:
    """A module docstring as terminal text: reST roles (``:mod:`x```) and backquotes become
    plain words, ``::`` becomes ``:``."""
    import re

    text = re.sub(r":[a-z]+:`~?([^`]+)`", r"\1", doc)
    text = text.replace("`", "").replace("::", ":")
    return text.strip()


def _command_module(module: str):
    return importlib.import_module(f"training.commands.{module}")


def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    prefix = f"pointtrack {args.command}: "
    try:
        return int(_command_module(args._module).run(args) or 0)
    except SystemExit as exc:
        if isinstance(exc.code, str):  # a command's own refusal: one line, status 2
            if args.traceback:
                raise
            message = exc.code if exc.code.startswith("pointtrack") else prefix + exc.code
            print(message, file=sys.stderr)
            return 2
        raise
    except EXPECTED_ERRORS as exc:
        if args.traceback:
            raise
        message = exc.args[0] if isinstance(exc, KeyError) and exc.args else exc
        print(f"{prefix}{message}", file=sys.stderr)
        return 2


if __name__ == "__main__":
    sys.exit(main())
