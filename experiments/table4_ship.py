"""Ship a Table IV pilot cell's selected file if it beats both baselines (docs/table4.md).

Reads ``ROOT/select-ARM/selection.json`` (a ``pointtrack select --out``), finds the first-ranked
candidate's run, and compares that run's pilot test reading (``ROOT/test/RUN/report.json``) with
the baselines' (``ROOT/test/baselines/report.json``) on observed and unseen Success. On a pass it
copies ``ROOT/select-ARM/NAME.safetensors`` (``pointtrack select --save``) into the shipped
checkpoint directory and records its digest in the manifest; no test split is read here.

    python experiments/table4_ship.py ROOT ARM NAME [--dry-run]
"""

from __future__ import annotations

import argparse
import json
import shutil
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))

from table4 import GROUPS, load_report, load_reports, success  # noqa: E402 - same folder

from trackers.registry import CHECKPOINT_DIR, write_manifest  # noqa: E402


def selected_run(selection: Path) -> str:
    """The run folder name of the first-ranked candidate in ``selection`` (``RUN/best.pt``)."""
    try:
        ranking = json.loads(selection.read_text())["ranking"]
        candidate = Path(ranking[0]["candidate"])
    except (OSError, ValueError, KeyError, IndexError) as exc:
        raise SystemExit(f"{selection}: cannot read a pointtrack select ranking ({exc})") from None
    if candidate.suffix != ".pt":
        raise SystemExit(f"{selection}: first candidate {candidate} is not a RUN/best.pt")
    return candidate.parent.name


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


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("root", type=Path, help="the pilot's run root of one setting")
    parser.add_argument("arm", choices=("none", "decorrelation", "sam"))
    parser.add_argument("name", help="shipped name, e.g. p2b-nuscenes1-u")
    parser.add_argument("--dry-run", action="store_true", help="print the verdict only")
    parser.add_argument("--checkpoints", type=Path, default=CHECKPOINT_DIR)
    args = parser.parse_args(argv)
    folder = args.root / f"select-{args.arm}"
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
    target = args.checkpoints / source.name
    shutil.copyfile(source, target.with_suffix(".tmp"))
    target.with_suffix(".tmp").replace(target)
    print(f"{args.name}: shipped {run} as {target}; manifest {write_manifest(args.checkpoints)}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
