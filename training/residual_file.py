"""What marks a ``pointtrack finetune --algo residual`` result, readable without importing the
RL stack (stable-baselines3): ``training.loading`` asks it of every tracker it loads."""

from __future__ import annotations

from pathlib import Path

from safetensors import safe_open

__all__ = ["RESIDUAL_FORMAT", "is_residual_file"]

#: the ``format`` metadata of a ``residual.safetensors``
RESIDUAL_FORMAT = "pointtrack-residual"


def is_residual_file(path: str | Path) -> bool:
    """True for a ``residual.safetensors`` (or a run directory holding one)."""
    path = Path(path)
    if path.is_dir():
        path = path / "residual.safetensors"
    if not path.is_file() or path.suffix != ".safetensors":
        return False
    try:
        with safe_open(str(path), framework="pt", device="cpu") as f:
            return (f.metadata() or {}).get("format") == RESIDUAL_FORMAT
    except Exception:  # noqa: BLE001 - not a safetensors file: not ours
        return False
