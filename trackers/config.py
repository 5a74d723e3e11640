"""Config plumbing: nested dataclasses <-> plain dicts (JSON); unknown keys rejected by name."""

from __future__ import annotations

import dataclasses
import typing
from typing import Any

__all__ = ["config_from_dict", "config_to_dict"]


def config_to_dict(config: Any) -> dict[str, Any]:
    """A JSON-ready dict of a (nested) config dataclass; tuples become lists."""
    return dataclasses.asdict(config)


def config_from_dict(cls: type, data: Any, where: str = "config") -> Any:
    """Build dataclass ``cls`` from ``data`` (a dict, or already an instance).

    Nested dataclass fields accept dicts; lists become tuples where the field is a tuple.
    Unknown keys raise ``ValueError`` naming them and the valid ones; bad values raise
    ``ValueError`` naming the field.
    """
    if isinstance(data, cls):
        return data
    if not isinstance(data, dict):
        raise ValueError(
            f"{where}: expected a mapping for {cls.__name__}, got {type(data).__name__}"
        )
    hints = typing.get_type_hints(cls)
    names = {f.name for f in dataclasses.fields(cls) if f.init}
    unknown = sorted(set(data) - names)
    if unknown:
        raise ValueError(
            f"{where}: unknown key(s) {unknown} for {cls.__name__}; valid keys: {sorted(names)}"
        )
    kwargs = {}
    for key, value in data.items():
        hint = hints.get(key)
        if isinstance(hint, type) and dataclasses.is_dataclass(hint):
            value = config_from_dict(hint, value, f"{where}.{key}")
        elif isinstance(value, list):
            value = _to_tuple(value)
        kwargs[key] = value
    try:
        return cls(**kwargs)
    except (TypeError, ValueError) as exc:
        raise ValueError(f"{where}: invalid {cls.__name__}: {exc}") from exc


def _to_tuple(value: Any) -> Any:
    if isinstance(value, list):
        return tuple(_to_tuple(v) for v in value)
    return value
