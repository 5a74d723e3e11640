"""The tracker registry (``register``, ``available``) and ``make`` / ``save`` / ``load``.

A tracker is a class with ``act(obs)`` registered under a name with the :func:`register` class
decorator: a learned tracker (a :class:`trackers.base.Tracker`, weights and a config) or a
baseline (any class with ``act``; ``make`` passes its keywords to the constructor). The registry
is the one list of names: ``make``, ``load``, ``save``, the training config's validation, the
CLI's choices and the tests' lists all read it (:func:`available`). It is the package's only
mutable global; the built-in trackers register when :mod:`trackers` is imported.

Checkpoint formats (never an arbitrary pickle):

* ``.safetensors`` (default): the state dict as tensors; metadata ``format = "pointtrack-tracker"``,
  ``version``, ``tracker`` (name) and ``config`` (JSON of the config dataclass);
* ``.pt`` / ``.pth``: ``{"format", "version", "tracker", "config": <JSON str>, "state_dict"}``
  written by ``torch.save`` and read with ``torch.load(weights_only=True)``.

Both formats carry an optional ``provenance`` entry (JSON, :mod:`trackers.provenance`: what
the weights were trained and chosen on) and an optional ``env_options`` entry (JSON): the
``TrackingEnv`` options the tracker must be evaluated with (``tracker.env_options``, keys in
:data:`ENV_OPTION_KEYS`, e.g. a recipe-v2 tracker's ``template_mode``). Each is written only when
known; a file without ``env_options`` loads with ``{}`` (the env's defaults), one without
``provenance`` with every field ``"unknown"``.

And an optional ``inference`` entry (JSON): how the tracker decides on its network's outputs
(``tracker.inference``, a :class:`trackers.decision.InferenceConfig`: the still-target test and
the re-ranking), written only when not the defaults. Older files kept those fields in
``config``; they migrate on load (:func:`trackers.decision.split_inference`) and act as before.
``load(..., inference=...)`` overrides the file's.

Integrity: a shipped checkpoint (``trackers/checkpoints/``) loads only when its SHA-256 matches
``trackers/checkpoints/manifest.json`` (:func:`write_manifest` records it); no checkpoint loads with
NaN or inf weights, and none is saved with them.

``load(name_or_path)``: an existing file; else a shipped checkpoint
``trackers/checkpoints/<name>.safetensors`` (or ``.pt``); else a registered tracker name (a fresh,
untrained learned tracker, or a baseline). ``expect=`` refuses a checkpoint of another tracker.
"""

from __future__ import annotations

import copy
import hashlib
import json
from collections.abc import Callable
from pathlib import Path
from typing import Any

import torch

from envs.files import atomic_path, atomic_save_safetensors, atomic_write_text
from envs.spec import TEMPLATE_MODES, TRACKER_OPTION_KEYS, EnvOptions

__all__ = [
    "CHECKPOINT_DIR",
    "ENV_OPTION_KEYS",
    "MANIFEST",
    "available",
    "check_env_options",
    "default_env_options",
    "env_options_from_metadata",
    "env_options_metadata",
    "inference_metadata",
    "find_checkpoint",
    "load",
    "load_file",
    "make",
    "read_safetensors",
    "register",
    "save",
    "size_config",
    "tracker_class",
    "tracker_from_metadata",
    "tracker_metadata",
    "unregister",
    "write_manifest",
]

CHECKPOINT_DIR = Path(__file__).resolve().parent / "checkpoints"
MANIFEST = CHECKPOINT_DIR / "manifest.json"
FORMAT = "pointtrack-tracker"
VERSION = "1"
_MANIFEST_FORMAT = "pointtrack-checkpoint-manifest"
_KINDS = ("all", "learned", "baseline", "checkpoint")
ENV_OPTION_KEYS = TRACKER_OPTION_KEYS
"""The ``TrackingEnv`` options a tracker may record (``tracker.env_options``): those where
training and evaluation must agree (the template composition, the search region); see
:data:`envs.spec.TRACKER_OPTION_KEYS`."""

# name -> class; filled by @register (the built-ins when the trackers package is imported)
_REGISTRY: dict[str, type] = {}


def register(name: str) -> Callable[[type], type]:
    """Class decorator: register a tracker class under ``name`` (lower case, no ``/``) and set
    its ``name`` attribute. A learned tracker subclasses :class:`trackers.base.Tracker`; a
    baseline needs only ``act``. A name already registered is an error naming the registered
    ones (:func:`unregister` first to replace a tracker)."""
    if not isinstance(name, str) or not name or name != name.lower() or "/" in name:
        raise ValueError(
            f"tracker name must be a non-empty lower-case string without '/', got {name!r}"
        )

    def decorate(cls: type) -> type:
        if name in _REGISTRY:
            raise ValueError(
                f"tracker name {name!r} is already registered (by "
                f"{_REGISTRY[name].__module__}.{_REGISTRY[name].__qualname__}); "
                f"registered: {sorted(_REGISTRY)}"
            )
        if not callable(getattr(cls, "act", None)):
            raise TypeError(f"tracker {name!r}: {cls.__qualname__} has no act(obs) method")
        cls.name = name
        _REGISTRY[name] = cls
        return cls

    return decorate


def unregister(name: str) -> type:
    """Remove ``name`` from the registry (tests, plug-ins replacing a tracker) -> its class."""
    tracker_class(name)  # the unknown-name error
    return _REGISTRY.pop(name.lower())


def tracker_class(name: str) -> type:
    """The class registered as ``name`` (case-insensitive); unknown names name the valid ones."""
    cls = _REGISTRY.get(str(name).lower())
    if cls is None:
        raise ValueError(f"unknown tracker {name!r}; registered: {sorted(_REGISTRY)}")
    return cls


def _is_learned(cls: type) -> bool:
    from trackers.base import Tracker

    return issubclass(cls, Tracker)


def available(kind: str = "all") -> list[str]:
    """Tracker names: ``"learned"`` (registered learned trackers), ``"baseline"``,
    ``"checkpoint"`` (the shipped checkpoints) or ``"all"`` (those three, in that order)."""
    if kind not in _KINDS:
        raise ValueError(f"unknown kind {kind!r}; valid: {list(_KINDS)}")
    learned = [n for n, c in _REGISTRY.items() if _is_learned(c)]
    baselines = [n for n, c in _REGISTRY.items() if not _is_learned(c)]
    shipped = sorted(
        {p.stem for suffix in ("*.safetensors", "*.pt") for p in CHECKPOINT_DIR.glob(suffix)}
    )
    parts = {"learned": learned, "baseline": baselines, "checkpoint": shipped}
    return parts[kind] if kind != "all" else [*learned, *baselines, *shipped]


def size_config(name: str, size: str = "default") -> dict[str, Any]:
    """The config keywords of learned tracker ``name`` at model size ``size`` (a copy of its
    class's ``sizes[size]``); unknown sizes name the valid ones."""
    cls = tracker_class(name)
    if not _is_learned(cls):
        raise ValueError(f"{name!r} is a baseline: it has no model sizes")
    if size not in cls.sizes:
        raise ValueError(f"tracker {name!r} has no model size {size!r}; valid: {sorted(cls.sizes)}")
    return copy.deepcopy(cls.sizes[size])


def check_env_options(options: Any, where: str) -> dict[str, Any]:
    """Validate a tracker's ``env_options`` -> a normalised copy (``search_enlargement`` as a
    ``(scale, offset_m)`` tuple of floats). ``ValueError`` naming ``where`` (e.g. the file), the
    key and the bad value: an unknown key, a template mode the env lacks, a search enlargement
    that is not two finite numbers with ``scale > 0`` and ``offset_m >= 0``."""
    import math
    import numbers

    if not isinstance(options, dict):
        raise ValueError(f"{where}: env_options must be a JSON object, got {options!r}")
    unknown = sorted(set(options) - set(ENV_OPTION_KEYS))
    if unknown:
        raise ValueError(
            f"{where}: unknown env_options key(s) {unknown}; valid: {list(ENV_OPTION_KEYS)}"
        )
    out: dict[str, Any] = {}
    if "template_mode" in options:
        mode = options["template_mode"]
        if mode not in TEMPLATE_MODES:
            raise ValueError(
                f"{where}: env_options template_mode {mode!r} is not one of {list(TEMPLATE_MODES)}"
            )
        out["template_mode"] = mode
    if "search_enlargement" in options:
        value = options["search_enlargement"]
        ok = (
            isinstance(value, list | tuple)
            and len(value) == 2
            and all(isinstance(v, numbers.Real) and not isinstance(v, bool) for v in value)
            and all(math.isfinite(v) for v in value)
        )
        if not ok or not (value[0] > 0 and value[1] >= 0):
            raise ValueError(
                f"{where}: env_options search_enlargement {value!r} must be "
                f"[scale > 0, offset_m >= 0] (finite numbers)"
            )
        out["search_enlargement"] = (float(value[0]), float(value[1]))
    return out


def default_env_options() -> dict[str, Any]:
    """The ``TrackingEnv`` defaults of the :data:`ENV_OPTION_KEYS` (what ``{}`` stands for)."""
    return EnvOptions().tracker_options()


def env_options_metadata(tracker: Any) -> str | None:
    """The checkpoint metadata (JSON) of ``tracker.env_options``, validated; ``None`` when
    empty (env defaults: the file is written exactly as before the options existed)."""
    options = check_env_options(
        dict(getattr(tracker, "env_options", None) or {}), f"{tracker.name} tracker"
    )
    if not options:
        return None
    if "search_enlargement" in options:
        options["search_enlargement"] = list(options["search_enlargement"])
    return json.dumps(options, sort_keys=True)


def inference_metadata(tracker: Any) -> str | None:
    """The checkpoint metadata (JSON) of ``tracker.inference``; ``None`` for the defaults."""
    from trackers.decision import InferenceConfig

    if tracker.inference == InferenceConfig():
        return None
    return json.dumps(tracker.inference.to_dict(), sort_keys=True)


def tracker_metadata(tracker: Any) -> dict[str, str]:
    """The metadata a checkpoint of ``tracker`` holds beside its weights: ``config`` (JSON) and
    the non-default ``env_options`` and ``inference`` (JSON)."""
    from trackers.config import config_to_dict

    meta = {"config": json.dumps(config_to_dict(tracker.config), sort_keys=True)}
    for key, value in (
        ("env_options", env_options_metadata(tracker)),
        ("inference", inference_metadata(tracker)),
    ):
        if value is not None:
            meta[key] = value
    return meta


def tracker_from_metadata(name: str, meta: dict[str, Any], path: str | Path) -> Any:
    """An untrained ``name`` tracker built from a checkpoint's metadata (``config``,
    ``env_options``, ``inference``; the inference fields of older files' ``config`` migrate)
    -> the tracker; ``ValueError`` naming the file ``path``."""
    from trackers.decision import InferenceConfig, split_inference

    env_options = env_options_from_metadata(path, meta.get("env_options"))
    try:
        config = _migrate(json.loads(meta["config"]))
        raw = meta.get("inference")
        stored = json.loads(raw) if isinstance(raw, str) else raw
    except json.JSONDecodeError as exc:
        raise ValueError(f"{path}: config or inference metadata is not valid JSON: {exc}") from exc
    config, legacy = split_inference(config)
    if legacy and stored is not None:
        raise ValueError(
            f"{path}: inference settings both in the config ({sorted(legacy)}) and in the "
            f"inference metadata; expected one"
        )
    inference = InferenceConfig.from_dict(
        legacy if stored is None else stored, where=f"{path}: inference"
    )
    try:
        model = make(name, **config)
    except (ValueError, TypeError) as exc:
        raise ValueError(f"{path}: checkpoint config does not fit {name!r}: {exc}") from exc
    model.env_options = env_options
    try:
        model.inference = inference
    except ValueError as exc:
        raise ValueError(f"{path}: {exc}") from exc
    return model


def make(name: str, **config: Any):
    """A fresh tracker: ``make("p2b", sampling_seed=1, head={"num_proposals": 32})``.

    Learned trackers take their config dataclass fields (nested ones as dicts); baselines take
    their constructor keywords.
    """
    return tracker_class(name)(**config)


def save(tracker: Any, path: str | Path, *, provenance: Any = None) -> Path:
    """Write ``tracker`` (a learned tracker) with its config, its non-default ``env_options`` and
    ``inference`` and its provenance (``provenance``, else ``tracker.provenance``; none: the key
    is left out) to ``path`` (atomically). NaN or inf weights are refused, naming the tensor:
    ``load`` would refuse the file."""
    from trackers.base import Tracker
    from trackers.provenance import METADATA_KEY

    if not isinstance(tracker, Tracker):
        raise TypeError(f"only learned trackers have weights to save, got {type(tracker).__name__}")
    if _REGISTRY.get(tracker.name) is not type(tracker):
        raise ValueError(
            f"{type(tracker).__qualname__} is not registered as {tracker.name!r}: "
            f"load could not rebuild it; registered: {sorted(_REGISTRY)}"
        )
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    meta = {"format": FORMAT, "version": VERSION, "tracker": tracker.name}
    meta.update(tracker_metadata(tracker))
    provenance = provenance if provenance is not None else getattr(tracker, "provenance", None)
    if provenance is not None:
        meta[METADATA_KEY] = provenance.to_json()
    state = {k: v.detach().cpu().contiguous() for k, v in tracker.state_dict().items()}
    _check_finite(path, state, "refusing to save")
    if path.suffix not in (".pt", ".pth"):
        return atomic_save_safetensors(path, state, meta)
    with atomic_path(path) as tmp:
        torch.save({**meta, "state_dict": state}, tmp)
    return path


def _read(path: Path) -> tuple[dict[str, str], dict[str, torch.Tensor]]:
    """-> (metadata with format/tracker/config, state dict); clear errors for bad files."""
    if path.suffix in (".pt", ".pth"):
        try:
            blob = torch.load(path, map_location="cpu", weights_only=True)
        except Exception as exc:  # corrupted, truncated or unsafe content
            raise ValueError(
                f"cannot read tracker checkpoint {path}: corrupted or not a "
                f"weights-only torch file ({type(exc).__name__}: {exc})"
            ) from exc
        if not isinstance(blob, dict) or "state_dict" not in blob:
            raise ValueError(f"{path} is not a pointtrack tracker checkpoint (no state_dict)")
        keys = ("format", "version", "tracker", "config", "env_options", "inference", "provenance")
        meta = {k: blob[k] for k in keys if k in blob}
        return meta, blob["state_dict"]
    return read_safetensors(path, "tracker checkpoint")


def read_safetensors(path: str | Path, what: str) -> tuple[dict[str, str], dict[str, torch.Tensor]]:
    """-> (metadata, tensors) of a safetensors file (no unpickling); a file that cannot be read
    is a ``ValueError`` naming ``what`` it should be and the path."""
    from safetensors import safe_open

    try:
        with safe_open(str(path), framework="pt", device="cpu") as f:
            meta = dict(f.metadata() or {})
            state = {k: f.get_tensor(k) for k in f.keys()}  # noqa: SIM118 - safe_open API
    except Exception as exc:
        raise ValueError(
            f"cannot read {what} {path}: corrupted or not a "
            f"safetensors file ({type(exc).__name__}: {exc})"
        ) from exc
    return meta, state


def _sha256(path: Path) -> str:
    digest = hashlib.sha256()
    with open(path, "rb") as f:
        for chunk in iter(lambda: f.read(1 << 20), b""):
            digest.update(chunk)
    return digest.hexdigest()


def _manifest(directory: Path) -> dict[str, str]:
    """File name -> SHA-256 of the checkpoints shipped in ``directory``."""
    manifest = directory / MANIFEST.name
    try:
        data = json.loads(manifest.read_text())
        files = data["files"]
        if data.get("format") != _MANIFEST_FORMAT or not isinstance(files, dict):
            raise ValueError(f"format {data.get('format')!r}")
    except (OSError, ValueError, KeyError, TypeError) as exc:
        raise ValueError(f"cannot read the checkpoint manifest {manifest}: {exc}") from exc
    return {str(k): str(v) for k, v in files.items()}


def write_manifest(directory: str | Path = CHECKPOINT_DIR) -> Path:
    """Record the SHA-256 of every checkpoint in ``directory`` in its ``manifest.json``
    (atomically); run it after replacing a shipped checkpoint."""
    directory = Path(directory)
    files = {
        p.name: _sha256(p)
        for suffix in ("*.safetensors", "*.pt")
        for p in sorted(directory.glob(suffix))
    }
    return atomic_write_text(
        directory / MANIFEST.name,
        json.dumps(
            {"format": _MANIFEST_FORMAT, "algorithm": "sha256", "files": files},
            indent=1,
            sort_keys=True,
        )
        + "\n",
    )


def _verify_shipped(path: Path) -> None:
    """A file in the shipped checkpoint directory must match its manifest digest."""
    directory = path.resolve().parent
    if directory != CHECKPOINT_DIR:
        return
    expected = _manifest(directory).get(path.name)
    if expected is None:
        raise ValueError(
            f"{path} is in the shipped checkpoint directory but not in its manifest "
            f"{directory / MANIFEST.name}; run trackers.registry.write_manifest() "
            f"after adding a checkpoint"
        )
    actual = _sha256(path)
    if actual != expected:
        raise ValueError(
            f"{path}: SHA-256 {actual} does not match the manifest's {expected} "
            f"({directory / MANIFEST.name}); the file is corrupted or was modified"
        )


def _check_finite(
    path: Path, state: dict[str, torch.Tensor], action: str = "refusing to load"
) -> None:
    for key, value in state.items():
        if (
            isinstance(value, torch.Tensor)
            and value.is_floating_point()
            and not bool(torch.isfinite(value).all())
        ):
            bad = int((~torch.isfinite(value)).sum())
            raise ValueError(
                f"{path}: tensor {key!r} has {bad} NaN or inf value(s) of {value.numel()}; {action}"
            )


def _migrate(config: dict[str, Any]) -> dict[str, Any]:
    """Config keys of older checkpoints: ``backbone.ragged_eval`` (now the runtime switch
    ``Tracker.fast_eval``) is dropped."""
    backbone = config.get("backbone")
    if isinstance(backbone, dict) and "ragged_eval" in backbone:
        config = {**config, "backbone": {k: v for k, v in backbone.items() if k != "ragged_eval"}}
    return config


def load_file(path: str | Path, expect: str | None = None, map_location: Any = "cpu"):
    """Load a checkpoint file -> tracker in eval mode on ``map_location``, its ``env_options``
    restored (``{}`` when the file records none), its ``inference`` and its ``provenance``
    (:class:`trackers.provenance.Provenance`, every field unknown when the file records none)."""
    from trackers.provenance import METADATA_KEY, Provenance

    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"no tracker checkpoint at {path}")
    _verify_shipped(path)
    meta, state = _read(path)
    if meta.get("format") != FORMAT or not meta.get("tracker") or meta.get("config") is None:
        raise ValueError(
            f"{path} is not a pointtrack tracker checkpoint "
            f"(metadata format={meta.get('format')!r})"
        )
    name = str(meta["tracker"])
    if expect is not None and name != expect.lower():
        raise ValueError(f"{path} holds a {name!r} checkpoint, not {expect!r}")
    learned = available("learned")
    if name not in learned:
        raise ValueError(
            f"{path}: unknown tracker {name!r} in checkpoint; registered learned "
            f"trackers: {learned}"
        )
    _check_finite(path, state)
    model = tracker_from_metadata(name, meta, path)
    try:
        model.load_state_dict(state, strict=True)
    except RuntimeError as exc:
        raise ValueError(
            f"{path}: weights do not match a {name!r} with the stored config: {exc}"
        ) from exc
    model.provenance = Provenance.from_json(meta.get(METADATA_KEY), f"{path}: provenance metadata")
    return model.to(map_location).eval()


def env_options_from_metadata(path: str | Path, raw: Any) -> dict[str, Any]:
    """The validated ``env_options`` metadata ``raw`` (JSON) of the checkpoint at ``path``
    (``{}`` when absent); ``ValueError`` naming the file, the key and the bad value."""
    if raw is None:
        return {}
    try:
        options = json.loads(raw) if isinstance(raw, str) else raw
    except json.JSONDecodeError as exc:
        raise ValueError(f"{path}: env_options metadata is not valid JSON: {exc}") from exc
    return check_env_options(options, f"{path}")


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


def load(
    name_or_path: str | Path,
    *,
    expect: str | None = None,
    map_location: Any = "cpu",
    inference: Any = None,
):
    """A tracker from a file path, a shipped checkpoint name (``"p2b-kitti1-w"``) or a
    registered name (``"p2b"``: untrained; ``"previous_box"``: a baseline).

    ``inference``: how the learned tracker decides, overriding the file's (evaluation under
    other settings): a :class:`trackers.decision.InferenceConfig`, or a mapping of some of its
    fields (the others stay the file's)."""
    tracker = _load(name_or_path, expect, map_location)
    if inference is not None:
        tracker.inference = _inference_override(tracker, inference, name_or_path)
    return tracker


def _inference_override(tracker: Any, inference: Any, source: Any) -> Any:
    """``inference`` (an ``InferenceConfig`` or a mapping of fields over the tracker's) ->
    the tracker's new ``InferenceConfig``; errors name ``source``."""
    from trackers.decision import InferenceConfig

    if not _is_learned(type(tracker)):
        raise ValueError(f"{source!r} is a baseline: it has no inference settings")
    if isinstance(inference, InferenceConfig):
        return inference
    where = f"inference override for {source}"
    if not isinstance(inference, dict):
        raise ValueError(f"{where}: expected an InferenceConfig or a dict of its fields")
    return InferenceConfig.from_dict({**tracker.inference.to_dict(), **inference}, where)


def _load(name_or_path: str | Path, expect: str | None, map_location: Any):
    checkpoint = find_checkpoint(name_or_path)
    if checkpoint is not None:
        return load_file(checkpoint, expect, map_location)
    path, name = Path(name_or_path), str(name_or_path)
    if name.lower() in _REGISTRY:
        if expect is not None and name.lower() != expect.lower():
            raise ValueError(f"{name!r} is not a {expect!r} tracker")
        tracker = make(name)
        if _is_learned(type(tracker)):
            tracker = tracker.to(map_location).eval()
        return tracker
    if path.suffix or "/" in name or "\\" in name:
        raise FileNotFoundError(f"no tracker checkpoint at {path}")
    raise ValueError(f"unknown tracker or checkpoint {name!r}; available: {available()}")
