"""A sweep spec: one ``pointtrack`` command, base flags and the overrides that make its trials.

A spec is a YAML mapping (``configs/sweeps/*.yaml``; docs/cluster.md)::

    name: p2b-slim-u-vs-w            # optional; default: the file's stem
    command: train                   # train | finetune | eval | eval --weather | select
    base:                            # flags of every trial (the command's own flag names)
      tracker: p2b
      model-size: slim
      set: {iters_per_epoch: 20}     # train's --set KEY=VALUE, as a mapping
    grid:                            # every combination of these values ...
      seed: [0, 1, 2]
    trials:                          # ... crossed with each of these (optional)
      - {weighting: none}
      - {weighting: decorrelation}
    seed_key: seed                   # the summary's mean +- sd runs over this key
    retries: 1                       # a failed trial is run again this many times
    threads: 1                       # torch threads per trial
    resources: {cpu: 1, gpu: auto}   # per trial; gpu auto: 1 where the cluster has GPUs

Everything is checked by :func:`load_spec` before any trial starts: unknown spec keys, an
unknown command and flags the command does not have are errors naming the valid ones, and every
trial's command line is parsed by the command's own parser (and, for ``train``, turned into a
validated ``TrainConfig``), so a bad value fails in a second, not after hours of trials.
"""

from __future__ import annotations

import argparse
import importlib
import itertools
import re
from collections.abc import Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

__all__ = ["COMMANDS", "SpecError", "SweepSpec", "Trial", "load_spec", "parse_spec"]

# a spec's command -> its module under training.commands
COMMANDS: dict[str, str] = {
    "train": "train",
    "finetune": "finetune",
    "eval": "eval",
    "eval --weather": "eval",
    "select": "select",
}
# flags a trial never takes from the spec: the sweep gives each trial its own run directory
# and decides on resuming (docs/cluster.md)
SWEEP_OWNED = frozenset({"out", "resume", "overwrite", "no_progress", "export"})
SPEC_KEYS = (
    "name",
    "command",
    "base",
    "grid",
    "trials",
    "seed_key",
    "retries",
    "threads",
    "resources",
)
DEFAULT_SEED_KEY = {"train": "seed", "finetune": "seed", "select": "eval_seed"}


class SpecError(ValueError):
    """An invalid sweep spec (the message names the file, the key and the valid choices)."""


@dataclass(frozen=True)
class Trial:
    """One combination: ``overrides`` on top of the spec's base, run as ``argv`` (the command's
    flags, without ``--out``) in the run directory ``trials/<name>``."""

    name: str
    overrides: dict[str, Any]
    argv: list[str]


@dataclass(frozen=True)
class SweepSpec:
    """A validated spec (see the module docstring); ``trials`` in grid order."""

    name: str
    command: str
    base: dict[str, Any]
    trials: list[Trial]
    seed_key: str
    retries: int = 1
    threads: int = 1
    cpus: float = 1.0
    gpus: float | None = None  # None: 1 per trial where the cluster has GPUs, else 0
    source: dict[str, Any] = field(default_factory=dict)  # the YAML mapping as read


class _Parser(argparse.ArgumentParser):
    """The command's parser, raising instead of printing usage and exiting."""

    def error(self, message: str):  # type: ignore[override]
        raise SpecError(message)


def command_parser(command: str) -> argparse.ArgumentParser:
    """The argument parser of ``pointtrack COMMAND`` (the same flags as the CLI's)."""
    parser = _Parser(prog=f"pointtrack {command}", add_help=False)
    importlib.import_module(f"training.commands.{COMMANDS[command]}").add_arguments(parser)
    return parser


def load_spec(path: str | Path) -> SweepSpec:
    """Read and validate the spec file ``path`` (raises :class:`SpecError` naming the file)."""
    import yaml

    path = Path(path)
    try:
        raw = yaml.safe_load(path.read_text())
    except OSError as exc:
        raise SpecError(f"cannot read sweep spec {path}: {exc.strerror or exc}") from None
    except yaml.YAMLError as exc:
        raise SpecError(f"sweep spec {path} is not valid YAML: {exc}") from None
    try:
        return parse_spec(raw, default_name=path.stem)
    except SpecError as exc:
        raise SpecError(f"{path}: {exc}") from None


def parse_spec(raw: Any, default_name: str = "sweep") -> SweepSpec:
    """Validate a spec mapping and expand its trials (raises :class:`SpecError`)."""
    if not isinstance(raw, Mapping):
        raise SpecError(f"a sweep spec is a mapping of {', '.join(SPEC_KEYS)}; got {raw!r}")
    unknown = sorted(set(raw) - set(SPEC_KEYS))
    if unknown:
        raise SpecError(f"unknown spec key(s) {unknown}; valid: {', '.join(SPEC_KEYS)}")
    command = raw.get("command")
    if command not in COMMANDS:
        raise SpecError(f"command {command!r} is not one of: {', '.join(COMMANDS)}")
    parser = command_parser(command)
    flags = _flags(parser)
    base = _checked_overrides(raw.get("base") or {}, "base", flags, command)
    grid = _checked_grid(raw.get("grid") or {}, flags, command)
    listed = raw.get("trials") or [{}]
    if not isinstance(listed, list):
        raise SpecError(f"trials: a list of flag mappings; got {listed!r}")
    extra = [_checked_overrides(t, f"trials[{i}]", flags, command) for i, t in enumerate(listed)]
    seed_key = _dest(str(raw.get("seed_key") or DEFAULT_SEED_KEY.get(command, "eval_seed")))
    if seed_key not in flags:
        raise SpecError(f"seed_key {seed_key!r} is not a flag of pointtrack {command}")
    resources = raw.get("resources") or {}
    if not isinstance(resources, Mapping) or set(resources) - {"cpu", "gpu"}:
        raise SpecError(f"resources: a mapping of cpu and gpu (per trial); got {resources!r}")
    gpus = resources.get("gpu", "auto")
    spec = SweepSpec(
        name=_name(raw.get("name") or default_name),
        command=command,
        base=base,
        trials=[],
        seed_key=seed_key,
        retries=_count(raw.get("retries", 1), "retries", minimum=0),
        threads=_count(raw.get("threads", 1), "threads", minimum=1),
        cpus=_positive(resources.get("cpu", 1), "resources.cpu"),
        gpus=None if gpus == "auto" else _positive(gpus, "resources.gpu", allow_zero=True),
        source=dict(raw),
    )
    combos = [
        {**dict(zip(grid, values, strict=True)), **more}
        for values in itertools.product(*grid.values())
        for more in extra
    ]
    trials = [_trial(spec, parser, flags, combo) for combo in combos]
    names = [t.name for t in trials]
    if len(set(names)) != len(names):
        dup = sorted({n for n in names if names.count(n) > 1})
        raise SpecError(f"two trials have the same overrides {dup}: list each one once")
    return SweepSpec(**{**spec.__dict__, "trials": trials})


def _flags(parser: argparse.ArgumentParser) -> dict[str, argparse.Action]:
    """``dest -> action`` of the flags a spec may set."""
    return {
        a.dest: a
        for a in parser._actions
        if a.dest not in SWEEP_OWNED and a.dest != argparse.SUPPRESS
    }


def _dest(key: str) -> str:
    return key.lstrip("-").replace("-", "_")


def _checked_overrides(
    values: Any, where: str, flags: Mapping[str, argparse.Action], command: str
) -> dict[str, Any]:
    if not isinstance(values, Mapping):
        raise SpecError(f"{where}: a mapping of flag -> value; got {values!r}")
    out = {}
    for key, value in values.items():
        dest = _dest(str(key))
        if dest not in flags:
            owned = " (the sweep sets it for every trial)" if dest in SWEEP_OWNED else ""
            valid = ", ".join(sorted(k.replace("_", "-") for k in flags))
            raise SpecError(
                f"{where}: {key!r} is not a flag of pointtrack {command}{owned}; valid: {valid}"
            )
        out[dest] = value
    if command == "eval --weather" and where == "base" and "weather" not in out:
        out["weather"] = "all"
    return out


def _checked_grid(
    grid: Any, flags: Mapping[str, argparse.Action], command: str
) -> dict[str, list[Any]]:
    checked = _checked_overrides(grid, "grid", flags, command)
    for key, values in checked.items():
        if not isinstance(values, list) or not values:
            raise SpecError(f"grid: {key!r} needs a non-empty list of values; got {values!r}")
    return checked


def _trial(
    spec: SweepSpec, parser: argparse.ArgumentParser, flags: Mapping, overrides: dict
) -> Trial:
    values = {**spec.base, **overrides}
    argv = to_argv(values, flags)
    if "threads" in flags and "threads" not in values:
        argv += ["--threads", str(spec.threads)]
    name = trial_name(overrides)
    try:
        args = parser.parse_args(argv)
        if spec.command == "train":
            from training.commands.train import build_config

            build_config(args)  # ConfigError (a ValueError) names the key
    except (SpecError, ValueError) as exc:
        raise SpecError(f"trial {name}: {exc}") from None
    if (spec.command == "eval --weather") != bool(getattr(args, "weather", None)):
        raise SpecError(
            f"trial {name}: the weather benchmark is command 'eval --weather' (with a weather "
            "value); command 'eval' runs without one"
        )
    return Trial(name=name, overrides=dict(overrides), argv=argv)


def to_argv(values: Mapping[str, Any], flags: Mapping[str, argparse.Action]) -> list[str]:
    """Flags ``{dest: value}`` as command-line words: ``True`` -> the bare flag, ``False`` /
    ``None`` -> left out, a list -> several values (or a repeated flag for ``--set``), a mapping
    (``--set``) -> ``KEY=VALUE`` words, a positional's values -> plain words at the end."""
    argv: list[str] = []
    positional: list[str] = []
    for dest, value in values.items():
        action = flags[dest]
        if not action.option_strings:
            positional += [str(v) for v in (value if isinstance(value, list) else [value])]
            continue
        flag = next((s for s in action.option_strings if s.startswith("--")), None)
        flag = flag or action.option_strings[0]
        if value is None or value is False:
            continue
        if value is True and action.nargs == 0:
            argv.append(flag)
        elif isinstance(action, argparse._AppendAction):
            items = value.items() if isinstance(value, Mapping) else None
            words = [f"{k}={_word(v)}" for k, v in items] if items is not None else value
            for word in words if isinstance(words, list) else [words]:
                argv += [flag, _word(word)]
        elif isinstance(value, list):
            argv += [flag, *(_word(v) for v in value)]
        else:
            argv += [flag, _word(value)]
    return argv + positional


def _word(value: Any) -> str:
    """One value as a command-line word (YAML spelling, so ``--set`` reads it back the same)."""
    if isinstance(value, str):
        return value
    if isinstance(value, bool):
        return "true" if value else "false"
    if value is None:
        return "null"
    return str(value)


def trial_name(overrides: Mapping[str, Any]) -> str:
    """A file-name-safe name of a trial from its overrides, e.g. ``weighting-none_seed-0``."""
    if not overrides:
        return "base"
    parts = []
    for key, value in overrides.items():
        text = ",".join(map(_word, value)) if isinstance(value, list) else _word(value)
        if isinstance(value, Mapping):
            text = ",".join(f"{k}={_word(v)}" for k, v in value.items())
        parts.append(f"{key.replace('_', '-')}-{text}")
    return re.sub(r"[^A-Za-z0-9.,=+-]+", "_", "_".join(parts)).strip("_")[:200]


def _name(value: Any) -> str:
    text = str(value)
    if not re.fullmatch(r"[A-Za-z0-9][A-Za-z0-9._-]*", text):
        raise SpecError(f"name {text!r}: letters, digits, '.', '_' and '-' only")
    return text


def _count(value: Any, key: str, minimum: int) -> int:
    if isinstance(value, bool) or not isinstance(value, int) or value < minimum:
        raise SpecError(f"{key} must be an integer >= {minimum}; got {value!r}")
    return value


def _positive(value: Any, key: str, allow_zero: bool = False) -> float:
    ok = isinstance(value, (int, float)) and not isinstance(value, bool)
    if not ok or value < 0 or (value == 0 and not allow_zero):
        raise SpecError(f"{key} must be a number > 0; got {value!r}")
    return float(value)
