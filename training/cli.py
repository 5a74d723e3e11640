"""The ``pointtrack`` command line: one sub-command per module in training.commands.

Messages of the library (``logging.getLogger(__name__)`` in each module) are printed as plain
lines on stderr at INFO and above (:func:`configure_logging`); progress bars are tqdm's; results
(tables, ``wrote ...``) are printed on stdout.

Error policy: an expected error (bad input, a missing or unwritable path, a refused resume, an
unavailable device) prints one line ``pointtrack COMMAND: message`` on stderr and exits with
status 2; ``--traceback`` shows the full traceback instead. Ctrl-C prints ``interrupted`` and
exits with status 130. Anything else is a bug and keeps its traceback.
"""

from __future__ import annotations

import argparse
import atexit
import contextlib
import importlib
import logging
import os
import sys

from training.argconfig import apply_config
from training.extras import MissingExtraError

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
    "render": ("render", "watch trackers on one tracklet: a video or a rerun 3D recording"),
    "demo": ("demo", "generate the small world and compare the trackers on it"),
    "info": ("info", "print a checkpoint's provenance: what it was trained and chosen on"),
    "compare": ("compare", "list the tracklets where two eval output directories differ most"),
}

# The exception types a command raises for expected errors (their message is the whole story).
# A missing optional package is one too: its message names the `pip install` command.
EXPECTED_ERRORS: tuple[type[BaseException], ...] = (
    ValueError,
    OSError,
    KeyError,
    MissingExtraError,
)


class HelpFormatter(argparse.RawDescriptionHelpFormatter, argparse.ArgumentDefaultsHelpFormatter):
    """Descriptions keep their line breaks; every flag's help ends with its default (unless the
    default is "not given" or off: ``None`` / ``False``)."""

    def _get_help_string(self, action: argparse.Action) -> str | None:
        if action.default is None or action.default is False or "(default" in (action.help or ""):
            return action.help
        return super()._get_help_string(action)


def build_parser(only: str | None = None) -> argparse.ArgumentParser:
    """The ``pointtrack`` parser; with ``only`` (a command's name) only that command's module is
    imported and given its flags (the others are listed with their help line): a command's
    start-up then skips the other commands' imports (stable-baselines3, Ray, ...)."""
    parser = argparse.ArgumentParser(
        prog="pointtrack", description=__doc__, formatter_class=HelpFormatter
    )
    parser.add_argument(
        "--traceback", action="store_true", help="show the full traceback of an expected error"
    )
    sub = parser.add_subparsers(dest="command", required=True, metavar="COMMAND")
    parser.command_parsers = {}  # name -> its parser (training.argconfig re-parses with a file)
    for name, (module, help_text) in COMMANDS.items():
        if only is not None and name != only:
            sub.add_parser(name, help=help_text)
            continue
        mod = _command_module(module)
        cmd = sub.add_parser(
            name,
            help=help_text,
            description=plain_text(mod.__doc__ or help_text),
            formatter_class=HelpFormatter,
        )
        cmd.set_defaults(_module=module)
        mod.add_arguments(cmd)
        parser.command_parsers[name] = cmd
    return parser


def _requested_command(argv: list[str]) -> str | None:
    """The command ``argv`` names (its first word that is not an option), if it is one."""
    words = [a for a in argv if not a.startswith("-")]
    return words[0] if words and words[0] in COMMANDS else None


def plain_text(doc: str) -> str:
    """A module docstring as terminal text: reST roles (``:mod:`x```) and backquotes become
    plain words, ``::`` becomes ``:``."""
    import re

    text = re.sub(r":[a-z]+:`~?([^`]+)`", r"\1", doc)
    text = text.replace("`", "").replace("::", ":")
    return text.strip()


def _command_module(module: str):
    return importlib.import_module(f"training.commands.{module}")


# the packages whose loggers the command line shows
LOGGED_PACKAGES = ("envs", "trackers", "training")


class _StderrHandler(logging.Handler):
    """Writes to the ``sys.stderr`` of the moment (a handler made once would keep the stream of
    its creation, e.g. a test's captured one)."""

    def emit(self, record: logging.LogRecord) -> None:
        try:
            print(self.format(record), file=sys.stderr, flush=True)
        except Exception:  # noqa: BLE001 - logging must never raise into the caller
            self.handleError(record)


def configure_logging(level: int = logging.INFO) -> None:
    """Show the project's log messages at ``level`` and above as plain lines on stderr (once per
    process; other libraries' loggers are left as they are)."""
    for name in LOGGED_PACKAGES:
        log = logging.getLogger(name)
        log.setLevel(level)
        if not any(isinstance(h, _StderrHandler) for h in log.handlers):
            handler = _StderrHandler()
            handler.setFormatter(logging.Formatter("%(message)s"))
            log.addHandler(handler)


def main(argv: list[str] | None = None) -> int:
    argv = sys.argv[1:] if argv is None else list(argv)
    parser = build_parser(_requested_command(argv))
    args = parser.parse_args(argv)
    configure_logging()
    prefix = f"pointtrack {args.command}: "
    try:
        if getattr(args, "config_file", None) or getattr(args, "set_values", None):
            command_parser = parser.command_parsers[args.command]
            args = apply_config(command_parser, args, lambda: parser.parse_args(argv))
        return int(_command_module(args._module).run(args) or 0)
    except KeyboardInterrupt:  # Ctrl-C: one line, the shell's status for SIGINT
        print(f"{prefix}interrupted", file=sys.stderr)
        return 130
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


def entry() -> None:
    """The ``pointtrack`` console script and ``python -m training.cli``: :func:`main`, then the
    exit. A command whose module sets ``FAST_EXIT = True`` (everything it writes is closed,
    atomically, before it returns) ends the process with ``os._exit`` once stdout, stderr and
    the ``atexit`` handlers are done: the interpreter's teardown of torch's and numba's modules
    alone costs ~0.6 s (8 % of a ``pointtrack eval`` of the ``small`` test split)."""
    argv = sys.argv[1:]
    code = main(argv)
    command = _requested_command(argv)
    module = sys.modules.get(f"training.commands.{COMMANDS[command][0]}") if command else None
    if getattr(module, "FAST_EXIT", False):
        with contextlib.suppress(OSError):  # a closed pipe: as a normal exit, not an error
            sys.stdout.flush()
            sys.stderr.flush()
        atexit._run_exitfuncs()  # what a normal exit runs before the teardown
        os._exit(code)
    sys.exit(code)


if __name__ == "__main__":
    entry()
