"""Write each shipped checkpoint's provenance from its recipe, ``configs/checkpoints/NAME.yaml``.

Only the ``provenance`` metadata key of ``trackers/checkpoints/NAME.safetensors`` changes: the
header is rewritten with the key added (or replaced), every tensor byte and every other metadata
key stay as they were (``trackers.provenance.with_provenance_bytes``; checked against the
recipe's ``sha256_without_provenance``, the digest of the file before any back-fill). Then the
manifest's
SHA-256 digests are recorded again. Idempotent: a rerun with unchanged recipes writes the same
bytes. Run from the repository root::

    python scripts/backfill_provenance.py
"""

from __future__ import annotations

import hashlib
import os
import sys
from pathlib import Path

import yaml

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from trackers.provenance import (  # noqa: E402
    Provenance,
    strip_provenance_bytes,
    with_provenance_bytes,
)
from trackers.registry import CHECKPOINT_DIR, write_manifest  # noqa: E402

CONFIG_DIR = ROOT / "configs" / "checkpoints"


def read_recipe(config: Path) -> dict:
    """The recipe file ``configs/checkpoints/NAME.yaml`` (``ValueError`` naming a missing key)."""
    data = yaml.safe_load(config.read_text())
    for key in ("provenance", "sha256_without_provenance"):
        if not isinstance(data, dict) or key not in data:
            raise ValueError(f"{config}: no {key!r} entry")
    return data


def recipe_provenance(config: Path) -> Provenance:
    """The provenance a recipe file records, written by ``backfill`` and naming the file."""
    data = read_recipe(config)
    fields = {
        **data["provenance"],
        "written_by": "backfill",
        "config_file": str(config.relative_to(ROOT)),
    }
    return Provenance.from_dict(fields, f"{config}: provenance")


def backfill(name: str) -> bool:
    """Write ``name``'s provenance into its shipped file; whether the file changed."""
    path, config = CHECKPOINT_DIR / f"{name}.safetensors", CONFIG_DIR / f"{name}.yaml"
    old = path.read_bytes()
    weights = hashlib.sha256(strip_provenance_bytes(old, str(path))).hexdigest()
    if weights != read_recipe(config)["sha256_without_provenance"]:
        raise SystemExit(
            f"{path}: without its provenance it hashes to {weights}, not the recipe's "
            f"sha256_without_provenance ({config}): the weights or other metadata changed"
        )
    new = with_provenance_bytes(old, recipe_provenance(config), str(path))
    if new == old:
        return False
    tmp = path.with_name(f".{path.name}.tmp{os.getpid()}")
    tmp.write_bytes(new)
    tmp.replace(path)
    return True


def main() -> int:
    shipped = sorted(p.stem for p in CHECKPOINT_DIR.glob("*.safetensors"))
    recipes = sorted(p.stem for p in CONFIG_DIR.glob("*.yaml"))
    if shipped != recipes:
        missing = sorted(set(shipped) ^ set(recipes))
        raise SystemExit(f"shipped files and recipes in {CONFIG_DIR} differ: {missing}")
    for name in shipped:
        print(f"{name}: {'written' if backfill(name) else 'unchanged'}")
    print(f"recorded {write_manifest()}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
