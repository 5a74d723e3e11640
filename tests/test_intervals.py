"""training.intervals: the one tracklet bootstrap (eval intervals and select's paired ranking),
eval-seed means."""

from __future__ import annotations

import math

import numpy as np
import pytest

from training.intervals import (
    add_intervals,
    check_seeds,
    combine_seeds,
    pooled_resamples,
    resample_counts,
)


def _row(tracklet, category, observed, frames, success, precision):
    return {
        "tracklet": tracklet,
        "category": category,
        "observed": observed,
        "frames": frames,
        "success": success,
        "precision": precision,
    }


def _tiny_report():
    """Car (unseen): one tracklet; Pedestrian (observed): two of 10 and 30 frames."""
    rows = [
        _row("a", "Car", False, 20, 50.0, 60.0),
        _row("b", "Pedestrian", True, 10, 20.0, 40.0),
        _row("c", "Pedestrian", True, 30, 80.0, 70.0),
    ]
    report = {"per_tracklet": rows, "categories": {"Car": {}, "Pedestrian": {}}}
    report |= {"observed": {}, "unseen": {}, "mean": {}}
    return report


def test_interval_equals_the_hand_computed_bootstrap():
    """By hand: Car has one tracklet, so every draw is it (interval [50, 50]). Pedestrian's two
    are drawn as (b, b), (b, c) or (c, c) with probabilities 1/4, 1/2, 1/4: pooled Success 20,
    (20*10 + 80*30) / 40 = 65, or 80. With 4000 draws the 5th percentile is the (b, b) value
    and the 95th the (c, c) one (each has 25 % > 5 % of the mass)."""
    report = add_intervals(_tiny_report(), resamples=4000, seed=3)
    assert report["categories"]["Car"]["success_interval"] == [50.0, 50.0]
    assert report["categories"]["Car"]["precision_interval"] == [60.0, 60.0]
    assert report["categories"]["Pedestrian"]["success_interval"] == [20.0, 80.0]
    assert report["categories"]["Pedestrian"]["precision_interval"] == [40.0, 70.0]
    assert report["unseen"]["success_interval"] == [50.0, 50.0]
    assert report["observed"]["success_interval"] == [20.0, 80.0]
    # mean: Car's 20 frames at 50 with each Pedestrian draw; by hand for (b, b) and (c, c)
    lo = (50 * 20 + 20 * 20) / 40
    hi = (50 * 20 + 80 * 60) / 80
    assert report["mean"]["success_interval"] == pytest.approx([lo, hi], abs=1e-12)
    assert report["interval"]["level"] == 0.9 and report["interval"]["resamples"] == 4000


def test_the_middle_draw_by_hand():
    """The (b, c) draw pools to the frame-weighted mean, 65 (probability 1/2: the median)."""
    report = add_intervals(_tiny_report(), resamples=4000, seed=3, level=0.01)
    assert report["categories"]["Pedestrian"]["success_interval"] == pytest.approx([65.0, 65.0])


def test_resample_counts_keep_each_stratum_size_and_are_seeded():
    strata = ["x", "y", "x", "y", "y"]
    counts = resample_counts(strata, 50, seed=1)
    assert counts.shape == (50, 5)
    assert (counts[:, [0, 2]].sum(1) == 2).all() and (counts[:, [1, 3, 4]].sum(1) == 3).all()
    assert (counts == resample_counts(strata, 50, seed=1)).all()
    assert (counts != resample_counts(strata, 50, seed=2)).any()
    pooled = pooled_resamples(np.ones((1, 3)), np.array([1.0, 1.0, 2.0]), np.array([0, 4, 8.0]))
    assert pooled.tolist() == [5.0]


def test_check_seeds_one_line_errors():
    assert check_seeds([0, 2, 1]) == [0, 2, 1]
    with pytest.raises(ValueError, match=r"lists seed 1 twice: \[1, 0, 1\]"):
        check_seeds([1, 0, 1])
    with pytest.raises(ValueError, match="must be >= 0; got -2"):
        check_seeds([0, -2])
    with pytest.raises(ValueError, match="at least one"):
        check_seeds([])


def test_combine_seeds_means_every_number():
    def report(s):
        entry = {"success": s, "precision": s + 1, "frames": 5, "success_curve": [s, s]}
        entry |= {"precision_curve": [0.0, s]}
        return {
            "categories": {"Car": dict(entry)},
            "observed": dict(entry),
            "unseen": dict(entry),
            "mean": dict(entry),
            "per_tracklet": [_row("a", "Car", False, 5, s, s + 1)],
            "tracker_fps": 10.0,
            "wall_s": 1.0,
            "boxes": [],
        }

    out = combine_seeds([report(10.0), report(13.0), report(20.0)], [0, 1, 2])
    assert out["mean"]["success"] == math.fsum([10.0, 13.0, 20.0]) / 3
    assert out["categories"]["Car"]["success_seeds"] == [10.0, 13.0, 20.0]
    assert out["per_tracklet"][0]["precision"] == pytest.approx(15.333333333333334)
    assert out["mean"]["success_curve"] == [pytest.approx(43 / 3)] * 2
    assert out["eval_seeds"] == [0, 1, 2] and out["wall_s"] == 3.0 and "boxes" not in out


def test_t_intervals_by_hand_and_beyond_the_table():
    from training.intervals import paired_t_interval, welch_t_interval

    # diffs 1, 2, 3: mean 2, sd 1, half width 2.920 / sqrt(3)
    mean, half = paired_t_interval([1.0, 2.0, 3.0])
    assert mean == 2.0 and abs(half - 2.920 / 3**0.5) < 1e-12
    assert paired_t_interval([4.0]) == (4.0, None)
    # a: mean 2, var 1; b: mean 0, var 4; se sqrt(1/3 + 4/3); df min(3, 3) - 1 = 2
    diff, half = welch_t_interval([1.0, 2.0, 3.0], [-2.0, 0.0, 2.0])
    assert diff == 2.0 and abs(half - 2.920 * (5 / 3) ** 0.5) < 1e-12
    with pytest.raises(ValueError, match="over 12 values: the table covers 2-11"):
        paired_t_interval([0.0] * 12)
