"""Table IV from run reports: per-file Success, mean ± sd over training seeds, paired -W − -U.

Reads the eval reports that ``experiments/table4_pilot.sh`` writes (``ROOT/test/NAME/report.json``,
one ``pointtrack eval --eval-seeds ... --out`` per directory) and prints the markdown
tables of docs/table4.md. Nothing is typed in by hand but the paper's numbers.

    python experiments/table4.py runs/table4-pilot [--tracker p2b] [--setting kitti-1] \
        [--arms none decorrelation]
    python experiments/table4.py --grid kitti-1=runs/table4-pilot kitti-2=runs/table4-pilot-kitti2
    python experiments/table4.py runs/mbptrack-pilot --tracker mbptrack --arms none \
        --versus p2b=runs/table4-pilot   # another tracker's -U runs, unpaired
"""

from __future__ import annotations

import argparse
import json
import statistics
import sys
from collections.abc import Callable
from pathlib import Path
from typing import Any

from training.intervals import paired_t_interval, welch_t_interval

#: Success (observed, unseen) in the paper's Table IV, by tracker, setting and weighting
PAPER = {
    "p2b": {
        "kitti-1": {"none": (38.6, 32.4), "decorrelation": (41.0, 34.7), "sam": (31.4, 21.3)},
        "kitti-2": {"none": (55.6, 24.2), "decorrelation": (56.2, 26.6), "sam": (46.9, 20.9)},
        "nuscenes-1": {"none": (31.1, 34.3), "decorrelation": (32.6, 37.4), "sam": (26.1, 29.7)},
        "nuscenes-2": {"none": (42.5, 14.6), "decorrelation": (41.4, 16.2), "sam": (36.5, 13.3)},
    },
    "bat": {
        "kitti-1": {"none": (33.9, 24.9), "decorrelation": (35.7, 28.1), "sam": (22.5, 18.1)},
        "kitti-2": {"none": (59.6, 12.9), "decorrelation": (61.8, 14.6), "sam": (43.5, 10.6)},
        "nuscenes-1": {"none": (30.9, 33.6), "decorrelation": (33.4, 36.0), "sam": (29.7, 32.8)},
        "nuscenes-2": {"none": (38.6, 16.9), "decorrelation": (41.9, 19.0), "sam": (38.5, 19.3)},
    },
}
#: trackers whose runs the per-setting tables read (Table IV has rows for P2B and BAT only), by
#: their printed names
TRACKERS = {"bat": "BAT", "mbptrack": "MBPTrack", "p2b": "P2B"}
ARM_SUFFIX = {"none": "-U", "decorrelation": "-W", "sam": "-S"}
GROUPS = ("observed", "unseen")


def load_reports(folder: Path) -> dict[str, dict[str, Any]]:
    """``{tracker: report}`` of ``folder/report.json`` (a ``pointtrack eval --out`` directory)."""
    path = folder / "report.json"
    try:
        reports = json.loads(path.read_text())
    except (OSError, ValueError) as exc:
        raise SystemExit(f"{path}: cannot read an eval report ({exc})") from None
    if not isinstance(reports, dict) or not all("per_tracklet" in r for r in reports.values()):
        raise SystemExit(f"{path}: not a pointtrack eval report")
    return reports


def load_report(folder: Path) -> dict[str, Any]:
    """The one tracker's report in ``folder``."""
    reports = load_reports(folder)
    if len(reports) != 1:
        raise SystemExit(f"{folder}: expected one tracker's report, found {len(reports)}")
    return next(iter(reports.values()))


def success(report: dict[str, Any], group: str) -> tuple[float, list[float] | None]:
    """``report``'s Success of ``group`` (percent) and its bootstrap interval, if recorded."""
    entry = report[group]
    return float(entry["success"]), entry.get("success_interval")


def cell(report: dict[str, Any], group: str) -> str:
    value, interval = success(report, group)
    if interval is None:
        return f"{value:.1f}"
    return f"{value:.1f} [{interval[0]:.1f}, {interval[1]:.1f}]"


def mean_sd(values: list[float]) -> str:
    sd = statistics.stdev(values) if len(values) > 1 else float("nan")
    return f"{statistics.fmean(values):.1f} ± {sd:.1f}"


def interval(estimate: tuple[float, float | None], what: str) -> str:
    """``+m [lo, hi]`` of an estimate and its half width, or the reason it has no interval."""
    mean, half = estimate
    if half is None:
        return f"{mean:+.1f} ({what}: no interval)"
    return f"{mean:+.1f} [{mean - half:+.1f}, {mean + half:+.1f}]"


def paired(diffs: list[float]) -> str:
    """Mean of the paired differences and its 90 % t interval over the pairs."""
    return interval(paired_t_interval(diffs), "one pair")


def unpaired(a: list[float], b: list[float]) -> str:
    """Mean of ``a`` minus mean of ``b`` and its 90 % Welch t interval."""
    return interval(welch_t_interval(a, b), "one run")


def versus(root: Path, tracker: str, other: tuple[str, Path], seeds: list[int]) -> None:
    """Print ``tracker``'s -U runs in ``root`` against ``other``'s (TRACKER, ROOT) -U runs over
    the same training seeds: mean ± sd each, the unpaired difference per group."""
    runs = {
        name: [load_report(r / "test" / f"{name}-none-s{s}") for s in seeds]
        for name, r in ((tracker, root), other)
    }
    for group in GROUPS:
        values = {name: [success(rep, group)[0] for rep in reps] for name, reps in runs.items()}
        mine, theirs = values[tracker], values[other[0]]
        print(
            f"{group}: {TRACKERS[tracker]}-U {mean_sd(mine)}, {TRACKERS[other[0]]}-U "
            f"{mean_sd(theirs)}; difference (Welch, 90 %) {unpaired(mine, theirs)}"
        )


def setting_tables(root: Path, tracker: str, setting: str, arms: list[str], seeds: list[int]):
    """Print one setting's tables: per file, mean ± sd per arm, paired differences to arms[0]."""
    test = root / "test"
    label = TRACKERS[tracker]
    paper_cells = PAPER.get(tracker, {}).get(setting, {})
    reports = {
        (arm, seed): load_report(test / f"{tracker}-{arm}-s{seed}")
        for arm in arms
        for seed in seeds
    }
    print("| file | observed Success [90 % CI] | unseen Success [90 % CI] |")
    print("| --- | --- | --- |")
    for (arm, seed), rep in reports.items():
        name = f"{label}{ARM_SUFFIX[arm]} seed {seed}"
        print(f"| {name} | {cell(rep, 'observed')} | {cell(rep, 'unseen')} |")
    if (test / "baselines").is_dir():
        for name, rep in load_reports(test / "baselines").items():
            print(f"| `{name}` | {cell(rep, 'observed')} | {cell(rep, 'unseen')} |")
    print()
    print("| arm | observed, mean ± sd | unseen, mean ± sd | paper observed / unseen |")
    print("| --- | --- | --- | --- |")
    for arm in arms:
        row = [mean_sd([success(reports[arm, s], g)[0] for s in seeds]) for g in GROUPS]
        paper = "{} / {}".format(*paper_cells[arm]) if arm in paper_cells else "not in Table IV"
        print(f"| {label}{ARM_SUFFIX[arm]} | {row[0]} | {row[1]} | {paper} |")
    print()
    for arm in arms[1:] if paper_cells else ():
        result = difference(reports, arms[0], arm, seeds, paper_cells)
        print(
            f"{label}{ARM_SUFFIX[arm]} minus {label}{ARM_SUFFIX[arms[0]]}, paired by training "
            f"seed (mean [90 % t interval]): {result}"
        )


def difference(reports, ref: str, arm: str, seeds: list[int], paper_cells) -> str:
    """``arm`` minus ``ref`` paired by seed, observed and unseen, beside the paper's."""
    diffs = {
        g: [success(reports[arm, s], g)[0] - success(reports[ref, s], g)[0] for s in seeds]
        for g in GROUPS
    }
    paper = [paper_cells[arm][i] - paper_cells[ref][i] for i in range(2)]
    return (
        f"observed {paired(diffs['observed'])}, unseen {paired(diffs['unseen'])}; "
        f"paper {paper[0]:+.1f} / {paper[1]:+.1f}"
    )


def grid_table(roots: dict[str, Path], tracker: str, seeds: list[int]) -> None:
    """Print Table IV's layout: one row per arm, observed / unseen per setting, mean ± sd over
    the training seeds (the paper's number in brackets); "not run" where a setting's root lacks
    the arm's reports; then the paired differences to -U."""
    label, settings = TRACKERS[tracker], list(PAPER[tracker])
    test = {name: root / "test" for name, root in roots.items()}
    reports = {
        (name, arm, seed): load_report(test[name] / f"{tracker}-{arm}-s{seed}")
        for name in roots
        for arm in ARM_SUFFIX
        for seed in seeds
        if all((test[name] / f"{tracker}-{arm}-s{s}").is_dir() for s in seeds)
    }
    print("| | " + " | ".join(f"{n} observed | {n} unseen" for n in settings) + " |")
    print("| --- " * (1 + 2 * len(settings)) + "|")
    for arm, suffix in ARM_SUFFIX.items():
        cells = []
        for name in settings:
            for i, group in enumerate(GROUPS):
                paper = PAPER[tracker][name][arm][i]
                if (name, arm, seeds[0]) not in reports:
                    cells.append(f"not run ({paper})")
                    continue
                values = [success(reports[name, arm, s], group)[0] for s in seeds]
                cells.append(f"{mean_sd(values)} ({paper})")
        print(f"| {label}{suffix} | " + " | ".join(cells) + " |")
    print()
    for name in settings:
        for arm in ("decorrelation", "sam"):
            if (name, arm, seeds[0]) in reports and (name, "none", seeds[0]) in reports:
                by_arm = {(a, s): reports[name, a, s] for a in ("none", arm) for s in seeds}
                result = difference(by_arm, "none", arm, seeds, PAPER[tracker][name])
                print(f"* {name}, {label}{ARM_SUFFIX[arm]} minus {label}-U: {result}")


def name_root(what: str, valid) -> Callable[[str], tuple[str, Path]]:
    """The argparse type of ``WHAT=ROOT`` with ``WHAT`` one of ``valid`` (``--grid``,
    ``--versus``)."""

    def parse(text: str) -> tuple[str, Path]:
        name, sep, root = text.partition("=")
        if not sep or name not in valid:
            raise argparse.ArgumentTypeError(
                f"{text!r}: expected {what}=ROOT with {what} one of {', '.join(valid)}"
            )
        return name, Path(root)

    return parse


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("root", type=Path, nargs="?", help="one setting's run root")
    parser.add_argument(
        "--grid",
        nargs="+",
        type=name_root("SETTING", PAPER["p2b"]),
        metavar="SETTING=ROOT",
        help="print Table IV's layout over these settings' run roots instead",
    )
    parser.add_argument("--tracker", choices=sorted(TRACKERS), default="p2b")
    parser.add_argument(
        "--versus",
        type=name_root("TRACKER", TRACKERS),
        metavar="TRACKER=ROOT",
        help="also compare this root's -U runs with another tracker's -U runs (unpaired)",
    )
    parser.add_argument("--setting", choices=sorted(PAPER["p2b"]), default="kitti-1")
    parser.add_argument("--arms", nargs="+", default=["none", "decorrelation"])
    parser.add_argument("--seeds", nargs="+", type=int, default=[0, 1, 2])
    args = parser.parse_args(argv)
    if args.grid and args.tracker not in PAPER:
        parser.error(f"--grid lays out Table IV, which has no {args.tracker} rows")
    if args.grid:
        grid_table(dict(args.grid), args.tracker, args.seeds)
    elif args.root is None:
        parser.error("give a run root or --grid SETTING=ROOT ...")
    else:
        setting_tables(args.root, args.tracker, args.setting, args.arms, args.seeds)
        if args.versus:
            print()
            versus(args.root, args.tracker, args.versus, args.seeds)
    return 0


if __name__ == "__main__":
    sys.exit(main())
