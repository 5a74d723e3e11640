"""What a checkpoint was trained and chosen on: :class:`Provenance`, stored with the weights.

A tracker file records its architecture (``config``) and the env options it needs; this module
adds what it *learnt from*: the data (dataset, world preset / sensor / seed / generator digest,
setting, categories, splits), how much (samples, steps), the selection that chose it, the parent
checkpoint of a fine-tune, the git commit and a hash of the config. The class-agnostic claims rest
on a held-out category and held-out worlds, so evaluation, selection and fine-tuning read it to
refuse or flag a leak (``training.provenance``).

Every field may be ``"unknown"`` (:data:`UNKNOWN`): a file written before provenance existed, or a
fact nobody recorded. Unknown is never filled in by a guess, and a check that needs an unknown
field says it could not check.

Storage: JSON under the safetensors metadata key :data:`METADATA_KEY` (``.pt`` files: the same
key in the saved dict), written by ``trackers.save``; ``trackers.load(...).provenance``.
:func:`with_provenance_bytes` adds the key to an existing safetensors file without touching any
tensor byte or any other metadata key (the back-fill of the shipped files,
``scripts/backfill_provenance.py``).
"""

from __future__ import annotations

import dataclasses
import json
import struct
from collections.abc import Iterator, Mapping
from dataclasses import dataclass
from typing import Any

from envs.data.nuscenes import NUSCENES_FRAMES

__all__ = [
    "METADATA_KEY",
    "UNKNOWN",
    "Provenance",
    "strip_provenance_bytes",
    "with_provenance_bytes",
]

METADATA_KEY = "provenance"
UNKNOWN = "unknown"
VERSION = 1
_WORLD_FIELDS = ("dataset", "preset", "sensor", "world_seed")


def _is_unknown(value: Any) -> bool:
    return isinstance(value, str) and value == UNKNOWN


@dataclass(frozen=True)
class Provenance:
    """Where a checkpoint's weights come from; any field may be :data:`UNKNOWN`.

    Attributes:
        written_by: the command that wrote the file: ``train``, ``finetune``, ``select`` or
            ``backfill`` (recorded afterwards from the documented commands).
        dataset: ``synthetic``, ``kitti`` or ``nuscenes`` (the data of this stage).
        root_kind: ``generated`` (a synthetic world from the cache, named by preset / sensor /
            seed) or ``given`` (a root directory passed by path).
        preset, sensor, world_seed: the synthetic world (``envs.synthetic``).
        generator_digest: the world's identity hash (the suffix of its cache directory name,
            ``envs.synthetic.ensure_world``): which generator code and config made it.
        setting: the class-agnostic setting trained in (``kitti-1``) or ``class-specific:Car``.
        categories: the categories this stage trained on (sorted list).
        splits: the splits of the world this stage trained on (``["train"]``).
        samples, steps: training samples drawn and optimiser steps (RL: env steps) of this stage.
        selection: the ``pointtrack select`` rounds that chose this file, oldest first, each
            ``{"rule", "setting", "parts": ["1:val", ...], "eval_seed", "scores": {candidate:
            pooled observed Success}}``; ``[]``: never selected.
        parent: ``None`` (trained from scratch) or ``{"name", "sha256", "provenance"}`` of the
            checkpoint this stage started from (fine-tunes, ``--init-weights``).
        git_commit: the commit of the code that trained (``+dirty`` when it had changes).
        config_hash: SHA-256 of the stage's config (JSON, sorted keys).
        config_file: the repository file holding the recipe (``configs/checkpoints/NAME.yaml``).
        nuscenes_frame: the frame nuScenes data of this stage was served in, ``lidar`` (each
            key frame's own; every file before the ``scene`` frame existed) or ``scene``
            (``envs.data.nuscenes``); left out of the JSON when ``lidar``.
    """

    written_by: Any = UNKNOWN
    dataset: Any = UNKNOWN
    root_kind: Any = UNKNOWN
    preset: Any = UNKNOWN
    sensor: Any = UNKNOWN
    world_seed: Any = UNKNOWN
    generator_digest: Any = UNKNOWN
    setting: Any = UNKNOWN
    categories: Any = UNKNOWN
    splits: Any = UNKNOWN
    samples: Any = UNKNOWN
    steps: Any = UNKNOWN
    selection: Any = UNKNOWN
    parent: Any = UNKNOWN
    git_commit: Any = UNKNOWN
    config_hash: Any = UNKNOWN
    config_file: Any = UNKNOWN
    nuscenes_frame: Any = "lidar"

    def __post_init__(self) -> None:
        for name in ("world_seed", "samples", "steps"):
            value = getattr(self, name)
            if not _is_unknown(value) and (
                not isinstance(value, int) or isinstance(value, bool) or value < 0
            ):
                raise ValueError(f"provenance field {name}: expected an int >= 0, got {value!r}")
        if not (_is_unknown(self.nuscenes_frame) or self.nuscenes_frame in NUSCENES_FRAMES):
            raise ValueError(
                f"provenance field nuscenes_frame: expected one of {list(NUSCENES_FRAMES)}, "
                f"got {self.nuscenes_frame!r}"
            )
        for name in ("categories", "splits"):
            value = getattr(self, name)
            if _is_unknown(value):
                continue
            if not isinstance(value, list | tuple) or not all(isinstance(v, str) for v in value):
                raise ValueError(
                    f"provenance field {name}: expected a list of names, got {value!r}"
                )
            object.__setattr__(self, name, sorted(set(value)))
        if not _is_unknown(self.selection) and not (
            isinstance(self.selection, list) and all(isinstance(s, dict) for s in self.selection)
        ):
            raise ValueError(
                f"provenance field selection: expected a list of objects, got {self.selection!r}"
            )
        parent = self.parent
        if not (_is_unknown(parent) or parent is None):
            if not isinstance(parent, dict) or "name" not in parent:
                raise ValueError(
                    f"provenance field parent: expected null or an object with a name, "
                    f"got {parent!r}"
                )
            nested = parent.get("provenance", UNKNOWN)
            if not isinstance(nested, Provenance):
                nested = Provenance.from_dict(nested, "parent provenance")
            object.__setattr__(self, "parent", {**parent, "provenance": nested})

    # ------------------------------------------------------------------ (de)serialisation
    def to_dict(self) -> dict[str, Any]:
        """A JSON-able dict (the parent's provenance nested as a dict)."""
        out = {"version": VERSION}
        for f in dataclasses.fields(self):
            value = getattr(self, f.name)
            if f.name == "parent" and isinstance(value, dict):
                value = {**value, "provenance": value["provenance"].to_dict()}
            if f.name == "nuscenes_frame" and value == "lidar":
                continue  # the records written before the field existed stay byte-identical
            out[f.name] = value
        return out

    def to_json(self) -> str:
        return json.dumps(self.to_dict(), sort_keys=True)

    @classmethod
    def from_dict(cls, data: Any, where: str = "provenance") -> Provenance:
        """The provenance of a dict written by :meth:`to_dict` (``"unknown"`` or ``None``: all
        fields unknown). Missing fields are unknown; an unknown key or a bad value is a
        ``ValueError`` naming ``where`` and the field."""
        if data is None or _is_unknown(data):
            return cls()
        if isinstance(data, Provenance):
            return data
        if not isinstance(data, Mapping):
            raise ValueError(f"{where}: expected a JSON object, got {data!r}")
        data = dict(data)
        version = data.pop("version", VERSION)
        if version != VERSION:
            raise ValueError(f"{where}: version {version!r} is not {VERSION}")
        names = {f.name for f in dataclasses.fields(cls)}
        extra = sorted(set(data) - names)
        if extra:
            raise ValueError(f"{where}: unknown field(s) {extra}; valid: {sorted(names)}")
        try:
            return cls(**data)
        except ValueError as exc:
            raise ValueError(f"{where}: {exc}") from None

    @classmethod
    def from_json(cls, raw: str | None, where: str = "provenance") -> Provenance:
        """Parse the metadata string (``None``: a file without provenance: all unknown)."""
        if raw is None:
            return cls()
        try:
            data = json.loads(raw)
        except json.JSONDecodeError as exc:
            raise ValueError(f"{where}: not valid JSON: {exc}") from None
        return cls.from_dict(data, where)

    def replace(self, **changes: Any) -> Provenance:
        return dataclasses.replace(self, **changes)

    # ------------------------------------------------------------------ questions
    def lineage(self) -> Iterator[Provenance]:
        """This stage, then its parent's, and so on to the first (from-scratch or unknown)."""
        stage: Provenance | None = self
        while stage is not None:
            yield stage
            parent = stage.parent
            stage = parent["provenance"] if isinstance(parent, dict) else None

    def lineage_complete(self) -> bool:
        """Whether the chain of parents is known to its start (the last stage says "from
        scratch" rather than "unknown")."""
        return list(self.lineage())[-1].parent is None

    def trained_categories(self) -> list[str] | None:
        """The categories every stage of the lineage trained on; ``None`` when any stage's
        categories (or an earlier stage) are unknown."""
        if not self.lineage_complete():
            return None
        out: set[str] = set()
        for stage in self.lineage():
            if _is_unknown(stage.categories):
                return None
            out.update(stage.categories)
        return sorted(out)

    def trained_parts(self) -> list[dict[str, Any]] | None:
        """``[{"dataset", "preset", "sensor", "world_seed", "split"}]`` that some stage trained
        on; ``None`` when a stage's world or splits are unknown."""
        if not self.lineage_complete():
            return None
        parts = []
        for stage in self.lineage():
            world = {k: getattr(stage, k) for k in _WORLD_FIELDS}
            if _is_unknown(stage.splits) or _is_unknown(stage.dataset):
                return None
            if stage.dataset != "kitti" and any(_is_unknown(v) for v in world.values()):
                return None
            parts.extend({**world, "split": split} for split in stage.splits)
        return parts

    def selection_parts(self) -> list[dict[str, Any]]:
        """The world splits any ``select`` round in the lineage scored the file on, as
        ``{"world_seed", "split", "preset", "sensor", "dataset"}`` (known ones only)."""
        out = []
        for stage in self.lineage():
            if _is_unknown(stage.selection):
                continue
            for round_ in stage.selection:
                for part in round_.get("parts", []):
                    seed, _, split = str(part).partition(":")
                    out.append(
                        {
                            "dataset": round_.get("dataset", UNKNOWN),
                            "preset": round_.get("preset", UNKNOWN),
                            "sensor": round_.get("sensor", UNKNOWN),
                            "world_seed": int(seed) if seed.isdigit() else UNKNOWN,
                            "split": split,
                        }
                    )
        return out

    def format(self) -> str:
        """Readable lines, one field a line; the parent's provenance indented below it."""
        return "\n".join(self._lines(""))

    def _lines(self, indent: str) -> list[str]:
        lines = []
        for f in dataclasses.fields(self):
            value = getattr(self, f.name)
            if f.name == "parent" and isinstance(value, dict):
                head = {k: v for k, v in value.items() if k != "provenance"}
                lines.append(f"{indent}parent: {json.dumps(head, sort_keys=True)}")
                lines.extend(value["provenance"]._lines(indent + "  "))
                continue
            text = value if isinstance(value, str) else json.dumps(value, sort_keys=True)
            lines.append(f"{indent}{f.name}: {text}")
        return lines


# --------------------------------------------------------------------------- file bytes


def _split_header(data: bytes, where: str) -> tuple[dict[str, Any], bytes]:
    if len(data) < 8:
        raise ValueError(f"{where}: too short for a safetensors file")
    (size,) = struct.unpack("<Q", data[:8])
    if size > len(data) - 8:
        raise ValueError(f"{where}: header length {size} exceeds the file")
    try:
        header = json.loads(data[8 : 8 + size])
    except (json.JSONDecodeError, UnicodeDecodeError) as exc:
        raise ValueError(f"{where}: header is not JSON: {exc}") from None
    return header, data[8 + size :]


def _join_header(header: dict[str, Any], body: bytes) -> bytes:
    # the layout safetensors writes: compact JSON padded with spaces to a multiple of 8 bytes
    text = json.dumps(header, separators=(",", ":")).encode()
    text += b" " * (-len(text) % 8)
    return struct.pack("<Q", len(text)) + text + body


def _with_metadata(header: dict[str, Any], meta: dict[str, str]) -> dict[str, Any]:
    """``header`` with ``meta`` as its metadata, placed first as safetensors writes it."""
    return {"__metadata__": meta, **{k: v for k, v in header.items() if k != "__metadata__"}}


def with_provenance_bytes(data: bytes, provenance: Provenance, where: str = "file") -> bytes:
    """The safetensors file ``data`` with :data:`METADATA_KEY` set to ``provenance``: the tensor
    bytes and every other metadata key stay exactly as they were (the tensors' offsets are
    relative to the end of the header, so only the header is rewritten)."""
    header, body = _split_header(data, where)
    meta = dict(header.get("__metadata__") or {})
    meta.pop(METADATA_KEY, None)
    meta[METADATA_KEY] = provenance.to_json()
    return _join_header(_with_metadata(header, meta), body)


def strip_provenance_bytes(data: bytes, where: str = "file") -> bytes:
    """``data`` without the :data:`METADATA_KEY` entry: for a file back-filled by
    :func:`with_provenance_bytes`, byte for byte the file before it."""
    header, body = _split_header(data, where)
    meta = dict(header.get("__metadata__") or {})
    meta.pop(METADATA_KEY, None)
    return _join_header(_with_metadata(header, meta), body)
