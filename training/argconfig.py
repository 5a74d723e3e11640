"""``--config FILE.yaml`` and ``--set KEY=VALUE`` for commands whose options are their flags.

``train`` and ``finetune`` map YAML onto their config dataclasses (:mod:`training.config`,
:mod:`training.rl.config`); ``eval`` and ``select`` are configured by their flags alone, and this
module gives them the same precedence: the parser's defaults < ``--config FILE`` (a YAML mapping
of option names, ``-`` or ``_``: ``eval_seeds: [0, 1, 2]``) < the flags given < ``--set
KEY=VALUE``. Every value goes through the flag's own type and choices, so a file cannot set what
the command line could not; an unknown key names the file and the valid keys. The effective
options are written to ``OUT/config.yaml`` by :func:`save_options`, so a run records how it was
asked for.
"""

from __future__ import annotations

import argparse
from collections.abc import Callable
from pathlib import Path
from typing import Any

__all__ = ["add_config_arguments", "apply_config", "read_yaml_mapping", "save_options"]

# options that say how a command runs, not what it computes: never taken from or saved to a file
NOT_CONFIGURABLE = frozenset({"config_file", "set_values", "help", "traceback", "command"})


def add_config_arguments(parser: argparse.ArgumentParser) -> None:
    """Add ``--config`` and ``--set`` to a command's parser (dests ``config_file``,
    ``set_values``)."""
    parser.add_argument(
        "--config",
        dest="config_file",
        metavar="FILE.yaml",
        help="YAML mapping of this command's options (names as the flags, - or _); "
        "flags given beat it, --set beats both",
    )
    parser.add_argument(
        "--set",
        dest="set_values",
        action="append",
        default=[],
        metavar="KEY=VALUE",
        help="one option (repeatable; beats the flags and --config), e.g. --set eval_seeds=0,1,2",
    )


def _actions(parser: argparse.ArgumentParser) -> dict[str, argparse.Action]:
    return {
        a.dest: a
        for a in parser._actions  # noqa: SLF001 - argparse has no public list of its actions
        if a.dest not in NOT_CONFIGURABLE and not a.dest.startswith("_")
    }


def _convert(action: argparse.Action, value: Any, where: str) -> Any:
    """``value`` (from YAML or a ``--set`` string) as the flag would have parsed it."""
    name = action.option_strings[-1] if action.option_strings else action.dest
    if value is None:  # YAML null: the option left unset, as a saved config writes it
        return None
    if action.nargs == 0:  # store_true / store_false
        if isinstance(value, str) and value.lower() in ("true", "false"):
            value = value.lower() == "true"
        if not isinstance(value, bool):
            raise ValueError(f"{where}: {name} is a switch: give true or false, got {value!r}")
        return value
    many = action.nargs in ("+", "*") or isinstance(action.nargs, int)
    if many:
        if isinstance(value, str):
            value = [v for v in value.replace(",", " ").split() if v]
        elif not isinstance(value, list):
            value = [value]
        return [_one(action, v, name, where) for v in value]
    if isinstance(value, list):
        raise ValueError(f"{where}: {name} takes one value, got a list {value!r}")
    return _one(action, value, name, where)


def _one(action: argparse.Action, value: Any, name: str, where: str) -> Any:
    if action.type is not None:
        try:
            value = action.type(value if isinstance(value, str) else str(value))
        except (TypeError, ValueError, argparse.ArgumentTypeError) as exc:
            raise ValueError(f"{where}: {name} {value!r}: {exc}") from None
    if action.choices is not None and value not in action.choices:
        choices = ", ".join(map(str, action.choices))
        raise ValueError(f"{where}: {name} {value!r}: must be one of {choices}")
    return value


def read_yaml_mapping(path: str | Path) -> dict[str, Any]:
    """The YAML mapping in ``path`` (an empty file: ``{}``); ``ValueError`` naming the file when
    it cannot be read, is not YAML or is not a mapping. The one reader of config files."""
    import yaml

    try:
        data = yaml.safe_load(Path(path).read_text())
    except OSError as exc:
        raise ValueError(f"{path}: cannot read ({exc.strerror or exc})") from None
    except yaml.YAMLError as exc:
        raise ValueError(f"{path}: not valid YAML ({exc})") from None
    if data is None:
        return {}
    if not isinstance(data, dict):
        raise ValueError(f"{path}: expected a mapping of options, got {type(data).__name__}")
    return data


def apply_config(
    parser: argparse.ArgumentParser,
    args: argparse.Namespace,
    reparse: Callable[[], argparse.Namespace],
) -> argparse.Namespace:
    """``args`` with ``args.config_file`` and ``args.set_values`` applied at their precedence.

    Args:
        parser: the command's own parser (its actions give names, types and choices); the
            file's values become its defaults.
        args: the namespace the command line parsed into.
        reparse: parses the same command line again (over the new defaults, so the flags given
            still win).
    """
    actions = _actions(parser)
    if args.config_file:
        values = {}
        try:
            mapping = read_yaml_mapping(args.config_file)
        except ValueError as exc:
            raise ValueError(f"--config {exc}") from None
        for key, value in mapping.items():
            dest = str(key).replace("-", "_")
            if dest not in actions:
                valid = ", ".join(sorted(actions))
                raise ValueError(
                    f"--config {args.config_file}: unknown key {key!r}; valid: {valid}"
                )
            values[dest] = _convert(actions[dest], value, f"--config {args.config_file}")
        parser.set_defaults(**values)
        args = reparse()
    for item in args.set_values:
        key, sep, text = item.partition("=")
        dest = key.strip().replace("-", "_")
        if not sep or dest not in actions:
            valid = ", ".join(sorted(actions))
            raise ValueError(f"--set {item!r}: expected KEY=VALUE with KEY one of {valid}")
        setattr(args, dest, _convert(actions[dest], text, f"--set {item}"))
    return args


def save_options(args: argparse.Namespace, out: str | Path) -> Path:
    """Write a command's effective options (every option of ``args`` but ``--config`` /
    ``--set`` themselves) to ``out/config.yaml`` atomically, loadable again with ``--config``."""
    import yaml

    from training.rundir import atomic_write_text

    values = {
        k: _plain(v)
        for k, v in sorted(vars(args).items())
        if k not in NOT_CONFIGURABLE and not k.startswith("_")
    }
    return atomic_write_text(Path(out) / "config.yaml", yaml.safe_dump(values, sort_keys=False))


def _plain(value: Any) -> Any:
    if value is None or isinstance(value, bool | int | float | str):
        return value
    if isinstance(value, list | tuple):
        return [_plain(v) for v in value]
    return str(value)
