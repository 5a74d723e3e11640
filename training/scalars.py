"""Scalars of a run (losses, learning rate, validation scores, selection scores) through
stable-baselines3's logger, to any of its ``csv``, ``json`` and ``tensorboard`` outputs.

One folder per run, ``RUN/logs``: ``progress.csv``, ``progress.json`` (one JSON object per dump)
and TensorBoard event files (``tensorboard --logdir runs/``). A key is ``KIND/NAME`` (e.g.
``train/total``, ``epoch/val_success``). TensorBoard is the optional ``tensorboard`` extra; a
missing one is a single line naming ``pip install "pointtrack[tensorboard]"``.

The outputs are a view of the run's own record (``log.jsonl`` for ``pointtrack train``): a
resumed run rewrites them from that record (:func:`open_scalar_logger` with ``replay``), so they
hold what an uninterrupted run would, never the steps of a killed attempt.
"""

from __future__ import annotations

import json
from collections.abc import Iterable, Mapping
from pathlib import Path
from typing import Any

__all__ = [
    "DEFAULT_FORMATS",
    "FORMATS",
    "log_record",
    "open_scalar_logger",
    "parse_formats",
    "require_formats",
]

FORMATS = ("csv", "json", "tensorboard")
DEFAULT_FORMATS = "csv,json"
SKIPPED_KEYS = frozenset({"kind", "step"})


def parse_formats(spec: str | Iterable[str]) -> tuple[str, ...]:
    """``"tensorboard,csv"`` (or a sequence) -> ``("tensorboard", "csv")``; ``ValueError`` naming
    an unknown or repeated output, or an empty list."""
    names = [s.strip() for s in (spec.split(",") if isinstance(spec, str) else spec)]
    names = [n for n in names if n]
    unknown = [n for n in names if n not in FORMATS]
    if unknown or not names or len(set(names)) != len(names):
        raise ValueError(
            f"logger {spec!r}: expected a comma list of distinct outputs among {', '.join(FORMATS)}"
        )
    return tuple(names)


def require_formats(formats: str | Iterable[str]) -> tuple[str, ...]:
    """:func:`parse_formats`, and the optional package of each output checked now (before a run
    does any work): :class:`training.extras.MissingExtraError` for TensorBoard without it."""
    formats = parse_formats(formats)
    if "tensorboard" in formats:
        from training.extras import require

        require("tensorboard", "tensorboard", "--logger tensorboard")
    return formats


def open_scalar_logger(
    folder: str | Path, formats: str | Iterable[str], *, replay: str | Path | None = None
) -> Any:
    """A ``stable_baselines3.common.logger.Logger`` writing ``formats`` into ``folder``.

    The CSV and JSON files start empty and earlier TensorBoard event files of ``folder`` are
    removed; with ``replay`` (a JSON-lines record such as ``log.jsonl``), its records are written
    again first (:func:`log_record`), so a resumed run's outputs equal an uninterrupted run's."""
    from stable_baselines3.common.logger import configure

    formats = require_formats(formats)
    folder = Path(folder)
    folder.mkdir(parents=True, exist_ok=True)
    for old in folder.glob("events.out.tfevents.*"):
        old.unlink()
    logger = configure(str(folder), list(formats))
    if replay is not None and Path(replay).is_file():
        for line in Path(replay).read_text().splitlines():
            if line.strip():
                log_record(logger, json.loads(line))
    return logger


def log_record(logger: Any, record: Mapping[str, Any], step: int | None = None) -> None:
    """Write the numbers of one record (``{"kind": ..., "step": ..., name: value}``) as
    ``KIND/NAME`` values at ``step`` (default ``record["step"]``) and dump them: numbers (and
    strings, e.g. a candidate's name: text in TensorBoard); lists, mappings and ``None`` are left
    to the record itself."""
    kind = record.get("kind", "train")
    for key, value in record.items():
        if key not in SKIPPED_KEYS and isinstance(value, int | float | str):
            logger.record(f"{kind}/{key}", value)
    logger.dump(int(record.get("step", 0) if step is None else step))
