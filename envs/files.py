"""Atomic file writes, the one implementation the project uses (re-exported by
:mod:`training.rundir`): a killed process leaves either the previous file or the new one, never
a truncated one."""

from __future__ import annotations

import contextlib
import os
from collections.abc import Iterator
from pathlib import Path

__all__ = ["atomic_path", "atomic_save_safetensors", "atomic_write_bytes", "atomic_write_text"]


def _temp_name(path: Path) -> Path:
    return path.with_name(f".{path.name}.tmp{os.getpid()}")


@contextlib.contextmanager
def atomic_path(path: str | Path) -> Iterator[Path]:
    """Yield a temporary sibling of ``path`` to write; on a clean exit it is fsynced and
    renamed onto ``path`` (``os.replace``), on an exception removed. The parent directory is
    created."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = _temp_name(path)
    try:
        yield tmp
        with open(tmp, "rb+") as f:
            os.fsync(f.fileno())
        os.replace(tmp, path)
    finally:
        tmp.unlink(missing_ok=True)


def atomic_write_bytes(path: str | Path, data: bytes) -> Path:
    """Write ``data`` to ``path`` atomically (:func:`atomic_path`); returns the path."""
    with atomic_path(path) as tmp:
        tmp.write_bytes(data)
    return Path(path)


def atomic_write_text(path: str | Path, text: str) -> Path:
    """Write ``text`` (UTF-8) to ``path`` atomically (:func:`atomic_path`); returns the path."""
    return atomic_write_bytes(path, text.encode())


def atomic_save_safetensors(
    path: str | Path, tensors: dict, metadata: dict[str, str] | None = None
) -> Path:
    """Write ``tensors`` (name -> CPU tensor) and string ``metadata`` to a safetensors file
    atomically; returns the path.

    Serialised in memory and written with :func:`atomic_write_bytes`, not with
    ``safetensors.torch.save_file``: that one (0.8) writes its own ``.tmpXXXXXX`` sibling, which a
    ``SIGKILL`` leaves behind under a name no cleanup can tie to its process."""
    from safetensors.torch import save

    return atomic_write_bytes(path, save(tensors, metadata=metadata))
