"""OPE metrics against hand-computed curves and Open3DSOT's formula."""

from __future__ import annotations

import math

import numpy as np
import pytest

from envs.metrics import (
    THRESHOLDS_IOU,
    THRESHOLDS_M,
    OPEAccumulator,
    precision_auc,
    precision_curve,
    robustness_metrics,
    success_auc,
    success_curve,
)


def open3dsot_success(ious):
    """Open3DSOT / P2B ``Success.average``, re-derived: trapezoid over linspace(0, 1, 21)."""
    x = np.linspace(0, 1, 21)
    y = np.array([np.sum(np.asarray(ious) >= t) / len(ious) for t in x])
    return float(np.sum((y[1:] + y[:-1]) / 2 * np.diff(x)) * 100 / 1)


def open3dsot_precision(errors):
    x = np.linspace(0, 2, 21)
    y = np.array([np.sum(np.asarray(errors) <= t) / len(errors) for t in x])
    return float(np.sum((y[1:] + y[:-1]) / 2 * np.diff(x)) * 100 / 2)


def test_thresholds():
    assert THRESHOLDS_IOU.shape == (21,) and THRESHOLDS_M.shape == (21,)
    assert THRESHOLDS_IOU[0] == 0 and THRESHOLDS_IOU[-1] == 1
    assert THRESHOLDS_M[0] == 0 and THRESHOLDS_M[-1] == 2
    assert THRESHOLDS_M[1] == pytest.approx(0.1)


def test_perfect_and_worst():
    assert success_auc([1.0, 1.0]) == pytest.approx(100.0)
    assert precision_auc([0.0, 0.0]) == pytest.approx(100.0)
    # IoU 0 passes only the threshold 0: area of a triangle 1 x 0.05 / 2 over 1 -> 2.5 %
    assert success_auc([0.0]) == pytest.approx(2.5)
    # an error beyond 2 m passes no threshold
    assert precision_auc([5.0]) == 0.0


def test_hand_computed_success_curve():
    # IoU 0.5: thresholds 0 .. 0.5 pass (11 of 21), area = 0.5 + 0.025 = 0.525 -> 52.5 %
    curve = success_curve([0.5])
    assert curve.tolist() == [1.0] * 11 + [0.0] * 10
    assert success_auc([0.5]) == pytest.approx(52.5)
    # two frames, 1.0 and 0.0: curve is 1 at t=0 then 0.5 -> mean of the two single scores
    assert success_auc([1.0, 0.0]) == pytest.approx((100.0 + 2.5) / 2)


def test_hand_computed_precision_curve():
    # error 0.5 m: thresholds 0.5 .. 2 pass (16 of 21): area = (0.05 + 1.5) / 2 -> 77.5 %
    curve = precision_curve([0.5])
    assert curve.tolist() == [0.0] * 5 + [1.0] * 16
    assert precision_auc([0.5]) == pytest.approx(77.5)
    # error exactly 0: all 21 pass
    assert precision_curve([0.0]).tolist() == [1.0] * 21


def test_matches_open3dsot_formula():
    rng = np.random.default_rng(0)
    ious = np.concatenate([rng.uniform(0, 1, 300), [0.0, 1.0, 0.05, 0.5]])
    errs = np.concatenate([rng.exponential(0.8, 300), [0.0, 0.1, 2.0, 3.0]])
    assert success_auc(ious) == pytest.approx(open3dsot_success(ious), abs=1e-12)
    assert precision_auc(errs) == pytest.approx(open3dsot_precision(errs), abs=1e-12)


def test_empty_and_bad_input():
    assert success_auc([]) == 0.0 and precision_auc([]) == 0.0
    with pytest.raises(ValueError, match="finite"):
        success_auc([0.5, float("nan")])
    with pytest.raises(ValueError, match="finite"):
        precision_auc([float("inf")])


def test_accumulator_first_frame_and_pooling():
    acc = OPEAccumulator()
    # tracklet of 3 frames: the accumulator adds frame 0 as perfect
    r = acc.add("0019/1", "Car", False, ious=[0.5, 0.0], errors=[0.5, 5.0])
    assert r.frames == 3
    assert r.success == pytest.approx((100.0 + 52.5 + 2.5) / 3)
    assert r.precision == pytest.approx((100.0 + 77.5 + 0.0) / 3)
    acc.add("0019/2", "Car", False, ious=[1.0], errors=[0.0])
    acc.add(
        "0020/1", "Van", True, ious=[0.5, 1.0, 0.5], errors=[0.5] * 3, first_frame_included=True
    )
    report = acc.report()
    car = report["categories"]["Car"]
    assert car["frames"] == 5 and car["tracklets"] == 2 and car["observed"] is False
    # pooled frames of Car: IoUs 1, .5, 0, 1, 1
    assert car["success"] == pytest.approx((3 * 100.0 + 52.5 + 2.5) / 5)
    van = report["categories"]["Van"]
    assert van["frames"] == 3 and van["success"] == pytest.approx((100 + 2 * 52.5) / 3)
    assert report["unseen"]["success"] == pytest.approx(car["success"])
    assert report["observed"]["success"] == pytest.approx(van["success"])
    mean = report["mean"]
    assert mean["frames"] == 8 and mean["tracklets"] == 3
    # the pooled mean is the frame-weighted mean of the categories
    assert mean["success"] == pytest.approx((5 * car["success"] + 3 * van["success"]) / 8)
    assert mean["precision"] == pytest.approx((5 * car["precision"] + 3 * van["precision"]) / 8)
    with_curves = acc.report(curves=True)
    assert len(with_curves["mean"]["success_curve"]) == 21


def test_accumulator_empty_group_and_errors():
    acc = OPEAccumulator()
    acc.add("a", "Car", True, [0.7], [0.2])
    report = acc.report()
    assert math.isnan(report["unseen"]["success"]) and report["unseen"]["frames"] == 0
    with pytest.raises(ValueError, match="observed"):
        acc.add("b", "Car", False, [0.7], [0.2])
    with pytest.raises(ValueError, match="differ"):
        acc.add("c", "Van", True, [0.7, 0.1], [0.2])
    with pytest.raises(ValueError, match=r"\[0, 1\]"):
        acc.add("d", "Van", True, [1.5], [0.2])
    with pytest.raises(ValueError, match="finite"):
        acc.add("e", "Van", True, [float("nan")], [0.2])


def test_robustness_metrics_hand_computed():
    out = robustness_metrics(60.0, [30.0, 45.0, 60.0, 15.0, 30.0])
    assert out["dr"] == pytest.approx([0.5, 0.75, 1.0, 0.25, 0.5])
    assert out["DR"] == pytest.approx(0.4)
    assert out["R"] == pytest.approx(45.0)
    assert out["Sd"] == pytest.approx(np.std([30, 45, 60, 15, 30], ddof=1))
    assert np.isnan(robustness_metrics(0.0, [1.0, 2.0])["DR"])
    with pytest.raises(ValueError):
        robustness_metrics(50.0, [])
