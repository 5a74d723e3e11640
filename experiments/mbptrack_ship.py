"""The steps of ``experiments/mbptrack_ship.sh`` and ``experiments/mbptrack_hold.sh`` that read
files and ship (docs/mbptrack.md, "Shipped-budget runs", "Still-target test on the shipped
files"); nothing here trains or evaluates.

    python experiments/mbptrack_ship.py best-val RUN [RUN ...]      # the run with the best val
    python experiments/mbptrack_ship.py first SELECTION CAND [CAND ...]  # the first-ranked CAND
    python experiments/mbptrack_ship.py ship SELECT NAME [--command CMD ...] [--not-if CAND ...]
    python experiments/mbptrack_ship.py report ROOT                 # the protocol's tables

``best-val`` prints the run whose trainer validation Success (``RUN/log.jsonl``) is highest (the
first run given on a tie). ``first`` prints whichever of the given candidates ranks first in a
``pointtrack select`` ranking. ``ship`` ships ``SELECT/NAME.safetensors`` (a ``pointtrack select
--save`` of one MBPTrack run and its three predecessors, or of a shipped file's hold variants)
as ``NAME`` unless a ``--not-if`` candidate ranks first (``experiments/table4_ship.py``'s recipe
and copy; ``scripts/backfill_provenance.py`` then records it). ``report`` prints the trainer's
validations, the selection with the shipping gates, and the test readings against the goals of
issue 46.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path
from typing import Any

sys.path.insert(0, str(Path(__file__).resolve().parent))

from epoch_losses import epoch_rows  # noqa: E402 - same folder
from table4 import cell, load_reports  # noqa: E402
from table4_ship import RECIPE_DIR, ship_file  # noqa: E402

from trackers.registry import CHECKPOINT_DIR  # noqa: E402

PREDECESSORS = {
    "u": ("p2b-kitti1-u", "bat-kitti1-u", "gpt-kitti1-u"),
    "w": ("p2b-kitti1-w", "bat-kitti1-w", "gpt-kitti1-w"),
}
OTHER_SHIPPED = ("p2b-kitti1-u-rl", "gpt-kitti1-u-rl", "p2b-kitti1-drct")


def val_successes(run: Path) -> list[float]:
    """Every trainer validation Success of ``run`` (``log.jsonl``'s epoch lines), in order."""
    return [row["val_success"] for row in epoch_rows(run).values() if "val_success" in row]


def best_val_run(runs: list[Path]) -> Path:
    """The run with the highest validation Success (the first given on a tie)."""
    best = {run: max(val_successes(run), default=float("-inf")) for run in runs}
    return max(runs, key=lambda run: (best[run], -runs.index(run)))


def ranking(selection: Path) -> list[dict[str, Any]]:
    """The rows of a ``pointtrack select`` ranking, first-ranked first."""
    try:
        rows = json.loads(selection.read_text()).get("ranking")
    except (OSError, ValueError) as exc:
        raise SystemExit(f"{selection}: cannot read ({exc})") from None
    if not rows:
        raise SystemExit(f"{selection}: no ranking")
    return rows


def first_of(selection: Path, candidates: list[str]) -> str:
    """Whichever of ``candidates`` ranks first in ``selection``."""
    for row in ranking(selection):
        if row["candidate"] in candidates:
            return row["candidate"]
    raise SystemExit(f"{selection}: ranks none of {candidates}")


def gate_lines(rows: list[dict[str, Any]], ours: str, arm: str) -> list[str]:
    """Whether ``ours`` ranks above each predecessor of ``arm`` in the selection."""
    rank = {row["candidate"]: i for i, row in enumerate(rows)}
    above = {name: rank[ours] < rank[name] for name in PREDECESSORS[arm]}
    lines = [f"  {'above' if up else 'below'} {name}" for name, up in above.items()]
    verdict = all(above.values())
    lines.append(f"  -> mbptrack-kitti1-{arm} {'ships' if verdict else 'does not ship'}")
    return lines


def ship(
    select: Path,
    name: str,
    commands: list[str],
    checkpoints: Path,
    recipes: Path,
    not_if: tuple[str, ...] = (),
    runs: str = "",
) -> bool:
    """Ship ``select/NAME.safetensors`` as ``NAME`` unless the selection in ``select`` ranks one
    of ``not_if`` first (default: the predecessors of ``NAME``'s arm; the hold selection names
    the shipped file itself and ``previous_box``); the recipe says the run directories ``runs``
    (default: ``select``'s parent) are not kept; -> whether it shipped."""
    first = ranking(select / "selection.json")[0]["candidate"]
    if first in (not_if or PREDECESSORS[name.split("-")[2]]):  # mbptrack-kitti1-ARM[-light]
        print(f"{name}: not shipped ({first} ranks first)")
        return False
    source = select / f"{name}.safetensors"
    if not source.is_file():
        raise SystemExit(f"{source}: missing (run pointtrack select --save {source})")
    target, recipe = ship_file(
        source,
        name,
        commands,
        checkpoints,
        recipes,
        doc="docs/mbptrack.md",
        lost=f"the run directories ({runs or select.parent}) are not kept in the repository",
    )
    print(f"{name}: shipped {first} as {target}, recipe {recipe}")
    return True


def report(root: Path) -> None:
    """Print the protocol's tables from the files ``mbptrack_ship.sh`` wrote under ``root``."""
    runs = sorted(root.glob("mbptrack-*-s*")) + [root / "mbptrack-w"]
    print("trainer validation Success (world 0 val), each validation in order:")
    for run in runs:
        print(f"  {run.name}: {', '.join(f'{v:.1f}' for v in val_successes(run))}")
    rows = ranking(root / "select" / "selection.json")
    print("\npointtrack select (pooled observed Success on the never-trained parts):")
    for i, row in enumerate(rows, 1):
        print(f"  {i:2d}. {row['candidate']}: {row['success']:.2f}")
    u_runs = [str(run / "best.pt") for run in runs if run.name.startswith("mbptrack-u-")]
    chosen = {"u": first_of(root / "select" / "selection.json", u_runs)}
    chosen["w"] = str(root / "mbptrack-w" / "best.pt")
    for arm, ours in chosen.items():
        print(f"\n-{arm.upper()}: {ours}")
        print("\n".join(gate_lines(rows, ours, arm)))
    tested = load_reports(root / "test")
    alone = load_reports(root / "test-network-alone")
    shipped = load_reports(root / "test-shipped")
    print("\ntest, world 0 of `default`, eval seeds 0-2: observed / unseen Car Success [90 %]")
    for name in chosen.values():
        print(f"  {name}: {cell(tested[name], 'observed')} / {cell(tested[name], 'unseen')}")
    for name in (*PREDECESSORS["u"], *PREDECESSORS["w"], *OTHER_SHIPPED):
        print(
            f"  {name}: network alone {cell(alone[name], 'observed')} / "
            f"{cell(alone[name], 'unseen')}; as shipped {cell(shipped[name], 'observed')} "
            f"/ {cell(shipped[name], 'unseen')}"
        )
    ours = tested[chosen["u"]]
    beats_networks = all(
        ours["observed"]["success"] > alone[name]["observed"]["success"] for name in alone
    )
    beats_shipped = all(
        ours["unseen"]["success"] > shipped[name]["unseen"]["success"] for name in shipped
    )
    print(
        f"\ngoal 1, observed above every network alone: {'met' if beats_networks else 'not met'}; "
        f"unseen Car above every shipped file: {'met' if beats_shipped else 'not met'}"
    )


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    sub = parser.add_subparsers(dest="step", required=True)
    best = sub.add_parser("best-val")
    best.add_argument("runs", nargs="+", type=Path)
    first = sub.add_parser("first")
    first.add_argument("selection", type=Path)
    first.add_argument("candidates", nargs="+")
    shipping = sub.add_parser("ship")
    shipping.add_argument("select", type=Path)
    shipping.add_argument(
        "name", choices=("mbptrack-kitti1-u", "mbptrack-kitti1-w", "mbptrack-kitti1-u-light")
    )
    shipping.add_argument("--command", action="append", default=[])
    shipping.add_argument(
        "--not-if",
        nargs="+",
        default=[],
        help="candidates whose first rank ships nothing (default: the arm's predecessors)",
    )
    shipping.add_argument("--runs", default="", help="the run directories the recipe names")
    shipping.add_argument("--checkpoints", type=Path, default=CHECKPOINT_DIR)
    shipping.add_argument("--recipes", type=Path, default=RECIPE_DIR)
    tables = sub.add_parser("report")
    tables.add_argument("root", type=Path)
    args = parser.parse_args(argv)
    if args.step == "best-val":
        print(best_val_run(args.runs))
    elif args.step == "first":
        print(first_of(args.selection, args.candidates))
    elif args.step == "ship":
        ship(
            args.select,
            args.name,
            args.command,
            args.checkpoints,
            args.recipes,
            tuple(args.not_if),
            args.runs,
        )
    else:
        report(args.root)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
