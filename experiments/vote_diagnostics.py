"""Per-category vote and proposal diagnostics of matching trackers (P2B, BAT, GPT) on
supervised samples of a split: how far the target seeds' votes land from the box centre, and
whether the head then has a positive proposal and scores it first. Descriptive only: it reads
the train or val split, never test. ::

    python experiments/vote_diagnostics.py p2b-kitti1-u runs22/gpt-kitti1-default-u/last.pt \\
        --setting kitti-1 --split train --samples 160

Per candidate and category (``S`` samples, drawn with a seeded ``numpy.random.Generator`` from
``training.samples.TrackingSamples`` built with the candidate's own template composition and
search region; the search offset is perturbed as in training):

* ``vote_miss_m``: median distance (m) from a target seed's vote to the box centre, pooled
  over every target seed of every sample;
* ``no_positive``: % of samples where no proposal is a positive of the head's loss
  (``trackers.head.proposal_labels``: within 0.3 m in the papers), so the objectness and box
  terms have no positive to learn from;
* ``top_positive``: % of samples whose best-scored proposal is such a positive;
* ``box_error_m`` / ``yaw_error_deg``: median centre distance and absolute yaw error of the
  best-scored box (the action the tracker would take);
* ``stay_error_m``: median centre distance of not moving (the search region's centre, i.e.
  the perturbed previous box), the bar ``box_error_m`` has to clear;
* ``correction_length`` / ``correction_width``: with the search region centred ``-D`` and
  ``+D`` m (``--offset-m``, default 1) off the ground truth along the box's length (width)
  axis, the slope of the chosen box's mean residual along that axis against the offset,
  subtracted from 1: 1 = the offset is corrected fully, 0 = the tracker stays where the
  search region is.
"""

from __future__ import annotations

import argparse
import math
from collections.abc import Sequence

import numpy as np
import torch

from trackers.head import proposal_labels
from training.loading import load_tracker
from training.samples import BATCH_KEYS, TrackingSamples, load_tracklets


class FixedOffsetSamples(TrackingSamples):
    """Samples whose search region is centred ``offset_box_m`` (along the ground-truth box's
    length and width axes, m) off the ground truth instead of a Gaussian draw."""

    offset_box_m: tuple[float, float] = (0.0, 0.0)

    def _search_offset(self, gt: np.ndarray, rng: np.random.Generator) -> np.ndarray:
        c, s = math.cos(gt[6]), math.sin(gt[6])
        along, across = self.offset_box_m
        return np.array([c * along - s * across, s * along + c * across])


def samples_for(
    tracker: torch.nn.Module, tracklets: Sequence, seed: int, kind: type = TrackingSamples
) -> TrackingSamples:
    """Supervised samples (of class ``kind``) of ``tracklets`` with the observation options
    ``tracker`` was trained with (``tracker.env_options``: template composition, search region)."""
    options = getattr(tracker, "env_options", None) or {}
    kwargs = {}
    if "search_enlargement" in options:
        kwargs["search_enlargement"] = tuple(options["search_enlargement"])
    merged = options.get("template_mode") == "first_and_previous_merged"
    return kind(tracklets, seed=seed, template_union=merged, **kwargs)


def _batch(data: TrackingSamples, indices: np.ndarray) -> dict[str, torch.Tensor]:
    items = [data[int(i)] for i in indices]
    return {k: torch.stack([item[k] for item in items]) for k in items[0]}


@torch.no_grad()
def correction(
    tracker: torch.nn.Module,
    data: FixedOffsetSamples,
    indices: np.ndarray,
    axis: int,
    offset_m: float = 1.0,
) -> float:
    """1 - the slope of the chosen box's mean residual (along box axis ``axis``: 0 length,
    1 width) against a search offset of ``-offset_m`` / ``+offset_m`` along it."""
    tracker.eval()
    mean_residual = []
    for sign in (-1.0, 1.0):
        offset = [0.0, 0.0]
        offset[axis] = sign * offset_m
        data.offset_box_m = (offset[0], offset[1])
        sample = _batch(data, indices)
        out = tracker({k: sample[k] for k in BATCH_KEYS})
        action = tracker.best_action(out)
        box = sample["search_box"].float()
        # the search frame is the offset box's (yaw noise aside): its axes are the box's
        mean_residual.append((action[:, axis] - box[:, axis]).mean().item())
    return 1.0 - (mean_residual[1] - mean_residual[0]) / (2 * offset_m)


@torch.no_grad()
def diagnose(
    tracker: torch.nn.Module, data: TrackingSamples, indices: np.ndarray, batch_size: int = 16
) -> dict[str, float]:
    """The module docstring's measures over ``data[indices]`` (eval-mode forward)."""
    tracker.eval()
    misses, no_positive, top_positive, box_error, yaw_error, stay = [], [], [], [], [], []
    for start in range(0, len(indices), batch_size):
        sample = _batch(data, indices[start : start + batch_size])
        out = tracker({k: sample[k] for k in BATCH_KEYS})
        box = sample["search_box"].float()  # (B, 7) in the search frame
        centre = box[:, None, :3]
        labels = torch.gather(sample["search_labels"].float(), 1, out["seed_idx"]) > 0.5
        miss = (out["votes"] - centre).norm(dim=-1)  # (B, M)
        misses.append(miss[labels])
        positive, _ = proposal_labels(out["proposal_centers"], box, tracker.config.head)
        no_positive.append(1.0 - positive.amax(dim=1))
        best = out["scores"].argmax(dim=1)
        rows = torch.arange(len(best))
        top_positive.append(positive[rows, best])
        action = out["proposals"][rows, best]  # (B, 4): x, y, z, yaw (rad)
        box_error.append((action[:, :3] - box[:, :3]).norm(dim=-1))
        stay.append(box[:, :3].norm(dim=-1))
        dyaw = torch.remainder(action[:, 3] - box[:, 6] + math.pi, 2 * math.pi) - math.pi
        yaw_error.append(dyaw.abs().rad2deg())
    return {
        "samples": len(indices),
        "vote_miss_m": torch.cat(misses).median().item(),
        "no_positive": 100 * torch.cat(no_positive).mean().item(),
        "top_positive": 100 * torch.cat(top_positive).mean().item(),
        "box_error_m": torch.cat(box_error).median().item(),
        "yaw_error_deg": torch.cat(yaw_error).median().item(),
        "stay_error_m": torch.cat(stay).median().item(),
    }


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("candidates", nargs="+", help="shipped names or RUN/best.pt, RUN/last.pt")
    parser.add_argument("--setting", default="kitti-1")
    parser.add_argument("--split", default="train", choices=["train", "val"])
    parser.add_argument("--preset", default="default")
    parser.add_argument("--samples", type=int, default=160, help="samples per category")
    parser.add_argument("--world-seed", type=int, default=0, help="synthetic world seed")
    parser.add_argument("--seed", type=int, default=0, help="seeds the samples and their choice")
    parser.add_argument("--offset-m", type=float, default=1.0, help="D of the corrections")
    parser.add_argument(
        "--correction-samples", type=int, default=64, help="the first N samples' corrections"
    )
    args = parser.parse_args()

    tracklets, setting, _ = load_tracklets(
        "synthetic",
        args.split,
        setting=args.setting,
        preset=args.preset,
        world_seed=args.world_seed,
        trained_only=False,
    )
    header = (
        "| candidate | category | samples | vote miss (m) | no positive (%) | top positive (%) "
    )
    header += "| box error (m) | yaw error (deg) | stay error (m) | correction length / width |"
    print(header + "\n|" + " --- |" * 10)
    for candidate in args.candidates:
        tracker = load_tracker(candidate)
        for category in setting.categories:
            own = [t for t in tracklets if t.category == category]
            data = samples_for(tracker, own, args.seed)
            rng = np.random.default_rng([args.seed, len(data)])
            indices = rng.choice(len(data), size=min(args.samples, len(data)), replace=False)
            indices = np.sort(indices)
            r = diagnose(tracker, data, indices)
            fixed = samples_for(tracker, own, args.seed, FixedOffsetSamples)
            first = indices[: args.correction_samples]
            along, across = (correction(tracker, fixed, first, a, args.offset_m) for a in (0, 1))
            print(
                f"| {candidate} | {category} | {r['samples']} | {r['vote_miss_m']:.2f} | "
                f"{r['no_positive']:.0f} | {r['top_positive']:.0f} | {r['box_error_m']:.2f} | "
                f"{r['yaw_error_deg']:.1f} | {r['stay_error_m']:.2f} | {along:.2f} / "
                f"{across:.2f} |",
                flush=True,
            )


if __name__ == "__main__":
    main()
