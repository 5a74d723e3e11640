"""``make`` / ``save`` / ``load`` for trackers.

Checkpoint formats (never an arbitrary pickle):

* ``.safetensors`` (default): the state dict as tensors; metadata ``format = "pointtrack-tracker"``,
  ``version``, ``tracker`` (name) and ``config`` (JSON of the config dataclass);
* ``.pt`` / ``.pth``: ``{"format", "version", "tracker", "config": <JSON str>, "state_dict"}``
  written by ``torch.save`` and read with ``torch.load(weights_only=True)``.

``load(name_or_path)``: an existing file; else a shipped checkpoint
``trackers/checkpoints/<name>.safetensors`` (or ``.pt``); else a registered tracker name (a fresh,
untrained learned tracker, or a baseline). ``expect=`` refuses a checkpoint of another tracker.
"""

from __future__ import annotations

import importlib
import json
from pathlib import Path
from typing import Any

import torch

__all__ = ["CHECKPOINT_DIR", "available", "find_checkpoint", "load", "make", "save"]

CHECKPOINT_DIR = Path(__file__).resolve().parent / "checkpoints"
FORMAT = "pointtrack-tracker"
VERSION = "1"

# name -> (module, class); baselines live in trackers.baselines (env builder), imported lazily
_LEARNED = {"p2b": ("trackers.p2b", "P2B"), "bat": ("trackers.bat", "BAT"),
            "gpt": ("trackers.gpt", "GPT")}
_BASELINES = {"previous_box": ("trackers.baselines", "PreviousBox"),
              "constant_velocity": ("trackers.baselines", "ConstantVelocity")}


def _class(name: str) -> type:
    key = name.lower()
    entry = _LEARNED.get(key) or _BASELINES.get(key)
    if entry is None:
        raise ValueError(f"unknown tracker {name!r}; available: {available()}")
    module, attr = entry
    try:
        return getattr(importlib.import_module(module), attr)
    except (ImportError, AttributeError) as exc:
        raise ImportError(f"tracker {name!r} needs {module}.{attr}, which is not available: "
                          f"{exc}") from exc


def available() -> list[str]:
    """Registered tracker names followed by the shipped checkpoint names."""
    shipped = sorted({p.stem for suffix in ("*.safetensors", "*.pt")
                      for p in CHECKPOINT_DIR.glob(suffix)})
    return [*_LEARNED, *_BASELINES, *shipped]


def make(name: str, **config: Any):
    """A fresh tracker: ``make("p2b", sampling_seed=1, head={"num_proposals": 32})``.

    Learned trackers take their config dataclass fields (nested ones as dicts); baselines take
    their constructor keywords.
    """
    cls = _class(name)
    return cls(**config)


def save(tracker: Any, path: str | Path) -> Path:
    """Write ``tracker`` (a learned tracker) with its config to ``path`` (atomically)."""
    from trackers.base import Tracker
    from trackers.config import config_to_dict

    if not isinstance(tracker, Tracker):
        raise TypeError(f"only learned trackers have weights to save, got {type(tracker).__name__}")
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    config_json = json.dumps(config_to_dict(tracker.config), sort_keys=True)
    state = {k: v.detach().cpu().contiguous() for k, v in tracker.state_dict().items()}
    tmp = path.with_name(path.name + ".tmp")
    if path.suffix in (".pt", ".pth"):
        torch.save({"format": FORMAT, "version": VERSION, "tracker": tracker.name,
                    "config": config_json, "state_dict": state}, tmp)
    else:
        from safetensors.torch import save_file

        save_file(state, str(tmp), metadata={"format": FORMAT, "version": VERSION,
                                              "tracker": tracker.name, "config": config_json})
    tmp.replace(path)
    return path


def _read(path: Path) -> tuple[dict[str, str], dict[str, torch.Tensor]]:
    """-> (metadata with format/tracker/config, state dict); clear errors for bad files."""
    if path.suffix in (".pt", ".pth"):
        try:
            blob = torch.load(path, map_location="cpu", weights_only=True)
        except Exception as exc:  # corrupted, truncated or unsafe content
            raise ValueError(f"cannot read tracker checkpoint {path}: corrupted or not a "
                             f"weights-only torch file ({type(exc).__name__}: {exc})") from exc
        if not isinstance(blob, dict) or "state_dict" not in blob:
            raise ValueError(f"{path} is not a pointtrack tracker checkpoint (no state_dict)")
        meta = {k: blob.get(k) for k in ("format", "version", "tracker", "config")}
        return meta, blob["state_dict"]
    try:
        from safetensors import safe_open

        with safe_open(str(path), framework="pt", device="cpu") as f:
            meta = dict(f.metadata() or {})
            state = {k: f.get_tensor(k) for k in f.keys()}  # noqa: SIM118 - safe_open API
    except Exception as exc:
        raise ValueError(f"cannot read tracker checkpoint {path}: corrupted or not a "
                         f"safetensors file ({type(exc).__name__}: {exc})") from exc
    return meta, state


def load_file(path: str | Path, expect: str | None = None, map_location: Any = "cpu"):
    """Load a checkpoint file -> tracker in eval mode on ``map_location``."""
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"no tracker checkpoint at {path}")
    meta, state = _read(path)
    if meta.get("format") != FORMAT or not meta.get("tracker") or meta.get("config") is None:
        raise ValueError(f"{path} is not a pointtrack tracker checkpoint "
                         f"(metadata format={meta.get('format')!r})")
    name = str(meta["tracker"])
    if expect is not None and name != expect.lower():
        raise ValueError(f"{path} holds a {name!r} checkpoint, not {expect!r}")
    if name not in _LEARNED:
        raise ValueError(f"{path}: unknown tracker {name!r} in checkpoint")
    try:
        config = json.loads(meta["config"])
    except json.JSONDecodeError as exc:
        raise ValueError(f"{path}: config metadata is not valid JSON: {exc}") from exc
    try:
        model = make(name, **config)
    except (ValueError, TypeError) as exc:
        raise ValueError(f"{path}: checkpoint config does not fit {name!r}: {exc}") from exc
    try:
        model.load_state_dict(state, strict=True)
    except RuntimeError as exc:
        raise ValueError(f"{path}: weights do not match a {name!r} with the stored config: "
                         f"{exc}") from exc
    return model.to(map_location).eval()


def find_checkpoint(name_or_path: str | Path) -> Path | None:
    """The checkpoint file that ``load`` reads for a file path or a shipped checkpoint name;
    ``None`` for anything else (a registered tracker name, a missing file)."""
    path = Path(name_or_path)
    if path.is_file():
        return path
    for suffix in (".safetensors", ".pt"):
        shipped = CHECKPOINT_DIR / f"{name_or_path}{suffix}"
        if shipped.is_file():
            return shipped
    return None


def load(name_or_path: str | Path, *, expect: str | None = None, map_location: Any = "cpu"):
    """A tracker from a file path, a shipped checkpoint name (``"p2b-kitti1-w"``) or a
    registered name (``"p2b"``: untrained; ``"previous_box"``: a baseline)."""
    checkpoint = find_checkpoint(name_or_path)
    if checkpoint is not None:
        return load_file(checkpoint, expect, map_location)
    path, name = Path(name_or_path), str(name_or_path)
    if name.lower() in _LEARNED or name.lower() in _BASELINES:
        if expect is not None and name.lower() != expect.lower():
            raise ValueError(f"{name!r} is not a {expect!r} tracker")
        tracker = make(name)
        if hasattr(tracker, "to") and name.lower() in _LEARNED:
            tracker = tracker.to(map_location).eval()
        return tracker
    if path.suffix or "/" in name or "\\" in name:
        raise FileNotFoundError(f"no tracker checkpoint at {path}")
    raise ValueError(f"unknown tracker or checkpoint {name!r}; available: {available()}")
