"""Target motion of real KITTI train labels against a generated world, side by side.

Prints, per category and measure (ego-relative displacement a frame, acceleration, yaw rate,
still share), the median and 90th percentile of both and their 1-Wasserstein distance, and
optionally plots the displacement distributions (docs/data.md "Motion against KITTI").

    python experiments/motion_compare.py --real ../shared/kitti-tracking-labels \
        --world ~/.cache/pointtrack/worlds/small-hdl64-s0-... [--plot docs/motion.png]
"""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np

from envs.data.motion import CATEGORIES, compare, label_motion

TRAIN_SCENES = range(0, 17)  # the real train split (scenes 0-16): never fit to val or test


def label_files(root: Path, scenes: range | None) -> list[Path]:
    files = sorted((root / "label_02").glob("*.txt"))
    if not files:
        raise SystemExit(f"error: no label files under {root / 'label_02'}")
    return [f for f in files if scenes is None or int(f.stem) in scenes]


def _relative(value: float) -> str:
    """A relative difference as a percentage; "n/a" where the real value is 0 (no ratio)."""
    return f"{'n/a':>7}" if np.isnan(value) else f"{value:>7.0%}"


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--real", type=Path, required=True, help="KITTI root (label_02/)")
    parser.add_argument("--world", type=Path, required=True, help="generated world root")
    parser.add_argument("--plot", type=Path, help="write a displacement histogram PNG here")
    args = parser.parse_args()
    real = label_motion(label_files(args.real, TRAIN_SCENES))
    generated = label_motion(label_files(args.world, None))
    print(
        f"{'category':<11}{'measure':<19}{'real med':>9}{'gen med':>9}{'rel':>7}"
        f"{'real p90':>9}{'gen p90':>9}{'rel':>7}{'W1':>8}"
    )
    for row in compare(real, generated):
        if row["measure"] == "still_share":
            print(
                f"{row['category']:<11}{'still_share':<19}{row['real_median']:>9.3f}"
                f"{row['gen_median']:>9.3f}"
            )
            continue
        print(
            f"{row['category']:<11}{row['measure']:<19}{row['real_median']:>9.3f}"
            f"{row['gen_median']:>9.3f}{_relative(row['rel_median'])}{row['real_p90']:>9.3f}"
            f"{row['gen_p90']:>9.3f}{_relative(row['rel_p90'])}{row['w1']:>8.3f}"
        )
    if args.plot:
        import matplotlib

        matplotlib.use("Agg")
        import matplotlib.pyplot as plt

        fig, axes = plt.subplots(1, len(CATEGORIES), figsize=(4 * len(CATEGORIES), 3))
        bins = np.linspace(0.0, 2.5, 51)
        for ax, category in zip(axes, CATEGORIES, strict=True):
            for label, motion in (("KITTI train", real), ("generated", generated)):
                ax.hist(
                    motion[category].displacement_m,
                    bins=bins,
                    density=True,
                    histtype="step",
                    label=label,
                )
            ax.set_title(category)
            ax.set_xlabel("ego-relative displacement (m / frame)")
        axes[0].legend()
        fig.tight_layout()
        fig.savefig(args.plot, dpi=90)


if __name__ == "__main__":
    main()
