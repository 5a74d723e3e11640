"""Ship a Table IV pilot cell's selected file if it beats both baselines (docs/table4.md).

Reads ``ROOT/select-ARM/selection.json`` (a ``pointtrack select --out``; ``--select`` names
another folder), finds the first-ranked candidate's run (or tracker file), and compares its
test reading (``ROOT/test/RUN/report.json``) with
the baselines' (``ROOT/test/baselines/report.json``) on observed and unseen Success. On a pass it
copies ``ROOT/select-ARM/NAME.safetensors`` (``pointtrack select --save``) into the shipped
checkpoint directory and writes its recipe ``configs/checkpoints/NAME.yaml`` (the file's own
provenance, the commands given by ``--command``); ``python scripts/backfill_provenance.py`` then
records the recipe in the file and the manifest. No test split is read here.

    python experiments/table4_ship.py ROOT ARM NAME [--command CMD ...] [--dry-run]
"""

from __future__ import annotations

import argparse
import hashlib
import json
import shutil
import sys
from pathlib import Path

import yaml

sys.path.insert(0, str(Path(__file__).resolve().parent))

from table4 import GROUPS, load_report, load_reports, success  # noqa: E402 - same folder

import trackers  # noqa: E402
from trackers.provenance import strip_provenance_bytes  # noqa: E402
from trackers.registry import CHECKPOINT_DIR  # noqa: E402

RECIPE_DIR = Path(__file__).resolve().parents[1] / "configs" / "checkpoints"


def selected_run(selection: Path) -> str:
    """The name of the first-ranked candidate in ``selection``: its run folder (``RUN/best.pt``)
    or its file's stem (a tracker file); its test reading is ``ROOT/test/NAME``."""
    try:
        ranking = json.loads(selection.read_text())["ranking"]
        candidate = Path(ranking[0]["candidate"])
    except (OSError, ValueError, KeyError, IndexError) as exc:
        raise SystemExit(f"{selection}: cannot read a pointtrack select ranking ({exc})") from None
    if candidate.suffix == ".pt":
        return candidate.parent.name
    if candidate.suffix == ".safetensors":  # a variant of a run (experiments/hold_variants.py)
        return candidate.stem
    raise SystemExit(f"{selection}: first candidate {candidate} is not a RUN/best.pt or a file")


def gate(root: Path, run: str) -> tuple[bool, list[str]]:
    """Whether ``run``'s test reading beats every baseline on observed and unseen Success, and
    one line per comparison."""
    chosen = load_report(root / "test" / run)
    lines, passed = [], True
    for name, base in load_reports(root / "test" / "baselines").items():
        for group in GROUPS:
            ours, theirs = success(chosen, group)[0], success(base, group)[0]
            passed &= ours > theirs
            verdict = "beats" if ours > theirs else "does not beat"
            lines.append(f"{run} {group} {ours:.1f} {verdict} {name} {theirs:.1f}")
    return passed, lines


def write_recipe(
    source: Path,
    name: str,
    commands: list[str],
    folder: Path,
    doc: str = "docs/table4.md",
    lost: str = "the run directories (runs/table4-pilot*) are not kept in the repository",
) -> Path:
    """``folder/NAME.yaml``: the recipe of the file ``source`` that ships as ``NAME`` (its
    provenance as the selection wrote it, the digest of its bytes without provenance, the
    commands, what is ``lost``), its header pointing to ``doc``."""
    provenance = trackers.load(source).provenance.to_dict()
    for key in ("written_by", "config_file"):  # the back-fill sets these
        provenance.pop(key, None)
    digest = hashlib.sha256(strip_provenance_bytes(source.read_bytes(), str(source))).hexdigest()
    recipe = {
        "checkpoint": name,
        "sha256_without_provenance": digest,
        "commands": commands,
        "lost": [lost],
        "provenance": provenance,
    }
    path = folder / f"{name}.yaml"
    header = f"# {name}: how trackers/checkpoints/{name}.safetensors was made ({doc})\n"
    tmp = path.with_suffix(".tmp")
    tmp.write_text(header + yaml.safe_dump(recipe, sort_keys=False, width=100))
    tmp.replace(path)
    return path


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("root", type=Path, help="the pilot's run root of one setting")
    parser.add_argument("arm", choices=("none", "decorrelation", "sam"))
    parser.add_argument("name", help="shipped name, e.g. p2b-nuscenes1-u")
    parser.add_argument("--dry-run", action="store_true", help="print the verdict only")
    parser.add_argument(
        "--select", default=None, help="the selection's folder under ROOT (default: select-ARM)"
    )
    parser.add_argument(
        "--command", action="append", default=[], help="a command of the recipe (repeatable)"
    )
    parser.add_argument("--checkpoints", type=Path, default=CHECKPOINT_DIR)
    parser.add_argument("--recipes", type=Path, default=RECIPE_DIR)
    args = parser.parse_args(argv)
    folder = args.root / (args.select or f"select-{args.arm}")
    run = selected_run(folder / "selection.json")
    passed, lines = gate(args.root, run)
    print("\n".join(lines))
    if not passed:
        print(f"{args.name}: not shipped ({run} does not beat both baselines on both groups)")
        return 0
    source = folder / f"{args.name}.safetensors"
    if not source.is_file():
        raise SystemExit(f"{source}: missing (run pointtrack select --save {source})")
    if args.dry_run:
        print(f"{args.name}: would ship {run} ({source})")
        return 0
    target, recipe = ship_file(source, args.name, args.command, args.checkpoints, args.recipes)
    print(f"{args.name}: shipped {run} as {target}, recipe {recipe}")
    return 0


def ship_file(
    source: Path, name: str, commands: list[str], checkpoints: Path, recipes: Path, **recipe_keys
) -> tuple[Path, Path]:
    """Copy ``source`` (a ``pointtrack select --save`` file) into ``checkpoints`` as
    ``NAME.safetensors`` and write its recipe (:func:`write_recipe`, ``recipe_keys`` passed on);
    -> (the shipped file, the recipe). ``python scripts/backfill_provenance.py`` then records
    the recipe in the file and the manifest."""
    # the recipe from the selection's copy: a file in the shipped directory loads only once
    # the manifest lists it, which the back-fill writes
    recipe = write_recipe(source, name, commands, recipes, **recipe_keys)
    target = checkpoints / f"{name}.safetensors"
    shutil.copyfile(source, target.with_suffix(".tmp"))
    target.with_suffix(".tmp").replace(target)
    return target, recipe


if __name__ == "__main__":
    sys.exit(main())
