"""One-pass evaluation (OPE) metrics as P2B, SC3D and Open3DSOT compute them.

- Success: the fraction of frames whose 3D IoU is ``>= t`` for 21 thresholds ``t`` evenly
  spaced in ``[0, 1]``; its area under the curve by the trapezoid rule, normalised by the
  threshold range, in percent.
- Precision: the fraction of frames whose centre error is ``<= t`` for 21 thresholds evenly
  spaced in ``[0, 2]`` metres; area by the trapezoid rule over the range, in percent.

This is exactly ``np.trapz(curve, x=np.linspace(0, max, 21)) * 100 / max`` of Open3DSOT's /
P2B's ``Success`` and ``Precision`` classes. An empty input scores ``0.0`` as there.

Frames are pooled over every tracklet of a category (not averaged per tracklet), and the first
frame of each tracklet counts as perfect (IoU 1, error 0): :class:`OPEAccumulator` adds that
frame itself unless told the caller already did. Because the AUC is linear in the per-frame
indicators, the score of pooled frames equals the frame-weighted mean of the category scores,
which is how ``observed`` / ``unseen`` / ``mean`` are reported.

Weather robustness (Zhao et al., adverse-weather SOT, Sec. III-D): :func:`robustness_metrics`
gives the degradation
rate ``DR = S_weather / S_clean`` per level (Eq. 2), the tables' ``DR`` column (the mean
degradation ``1 - mean DR``), and the range ``R`` (max - min) and standard deviation ``S.d``
(sample, ``ddof=1``, which is what Table III's numbers are) of the scores across levels.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

__all__ = [
    "THRESHOLDS_IOU",
    "THRESHOLDS_M",
    "OPEAccumulator",
    "TrackletResult",
    "precision_auc",
    "robustness_metrics",
    "precision_curve",
    "success_auc",
    "success_curve",
]

THRESHOLDS_IOU: np.ndarray = np.linspace(0.0, 1.0, 21)
"""The 21 IoU thresholds of the Success curve, ``0, 0.05, …, 1``."""
THRESHOLDS_M: np.ndarray = np.linspace(0.0, 2.0, 21)
"""The 21 centre-error thresholds of the Precision curve in metres, ``0, 0.1, …, 2``."""

THRESHOLDS_IOU.setflags(write=False)
THRESHOLDS_M.setflags(write=False)


def _values(x: Sequence[float] | np.ndarray, what: str) -> np.ndarray:
    arr = np.asarray(x, dtype=np.float64).ravel()
    if not np.all(np.isfinite(arr)):
        raise ValueError(f"{what} must be finite; got {int((~np.isfinite(arr)).sum())} non-finite")
    return arr


def _trapezoid_percent(curve: np.ndarray, thresholds: np.ndarray) -> float:
    dx = np.diff(thresholds)
    area = float(np.sum(dx * (curve[1:] + curve[:-1]) * 0.5))
    return area * 100.0 / float(thresholds[-1] - thresholds[0])


def success_curve(ious: Sequence[float] | np.ndarray) -> np.ndarray:
    """Fraction of frames with IoU ``>= t`` for each ``t`` in :data:`THRESHOLDS_IOU`.

    Args:
        ious: ``(N,)`` per-frame IoUs in ``[0, 1]`` (any shape; flattened).

    Returns:
        ``(21,)`` float64 in ``[0, 1]``; zeros when ``N == 0``.
    """
    v = _values(ious, "ious")
    if v.size == 0:
        return np.zeros(len(THRESHOLDS_IOU))
    s = np.sort(v)
    # count of v >= t = N - (number of v < t)
    return (v.size - np.searchsorted(s, THRESHOLDS_IOU, side="left")) / v.size


def precision_curve(errors_m: Sequence[float] | np.ndarray) -> np.ndarray:
    """Fraction of frames with centre error ``<= t`` for each ``t`` in :data:`THRESHOLDS_M`.

    Args:
        errors_m: ``(N,)`` per-frame centre errors in metres (any shape; flattened).

    Returns:
        ``(21,)`` float64 in ``[0, 1]``; zeros when ``N == 0``.
    """
    v = _values(errors_m, "errors_m")
    if v.size == 0:
        return np.zeros(len(THRESHOLDS_M))
    s = np.sort(v)
    return np.searchsorted(s, THRESHOLDS_M, side="right") / v.size


def success_auc(ious: Sequence[float] | np.ndarray) -> float:
    """OPE Success in percent: trapezoid area under :func:`success_curve` over ``[0, 1]``."""
    return _trapezoid_percent(success_curve(ious), THRESHOLDS_IOU)


def precision_auc(errors_m: Sequence[float] | np.ndarray) -> float:
    """OPE Precision in percent: trapezoid area under :func:`precision_curve` over ``[0, 2]`` m."""
    return _trapezoid_percent(precision_curve(errors_m), THRESHOLDS_M)


# --------------------------------------------------------------------------- accumulator


@dataclass(frozen=True)
class TrackletResult:
    """Per-tracklet record kept by :class:`OPEAccumulator` (first frame included)."""

    tracklet_id: str
    category: str
    observed: bool
    frames: int
    success: float
    precision: float


class OPEAccumulator:
    """Collects per-tracklet IoUs and centre errors; reports OPE per category and group.

    Usage::

        acc = OPEAccumulator()
        acc.add("0019/3", "Car", observed=False, ious=step_ious, errors=step_errors)
        report = acc.report()

    First frame: by default (``first_frame_included=False``) the caller passes the results of
    frames ``1 .. T-1`` (one per env step) and the accumulator adds frame 0 as perfect (IoU 1,
    error 0). Pass ``first_frame_included=True`` when the arrays already hold frame 0 (its
    values are then taken as given).
    """

    def __init__(self) -> None:
        self._ious: dict[str, list[np.ndarray]] = {}
        self._errors: dict[str, list[np.ndarray]] = {}
        self._observed: dict[str, bool] = {}
        self._tracklets: dict[str, set[str]] = {}
        self.results: list[TrackletResult] = []

    def add(
        self,
        tracklet_id: str,
        category: str,
        observed: bool,
        ious: Sequence[float] | np.ndarray,
        errors: Sequence[float] | np.ndarray,
        *,
        first_frame_included: bool = False,
    ) -> TrackletResult:
        """Record one tracklet.

        Args:
            tracklet_id: e.g. ``"0019/3"``.
            category: e.g. ``"Car"``.
            observed: whether the category is an observed (training) one in the setting.
            ious: ``(T-1,)`` 3D IoUs of frames 1.. (or ``(T,)`` with ``first_frame_included``).
            errors: centre errors in metres, same length as ``ious``.
            first_frame_included: see the class docstring.

        Returns:
            The :class:`TrackletResult` (also appended to :attr:`results`).
        """
        iou = _values(ious, "ious")
        err = _values(errors, "errors")
        if iou.shape != err.shape:
            raise ValueError(f"ious {iou.shape} and errors {err.shape} differ in length")
        if np.any((iou < 0.0) | (iou > 1.0 + 1e-9)):
            raise ValueError(f"tracklet {tracklet_id}: IoUs must lie in [0, 1]")
        if np.any(err < 0.0):
            raise ValueError(f"tracklet {tracklet_id}: centre errors must be >= 0")
        if not first_frame_included:
            iou = np.concatenate([[1.0], iou])
            err = np.concatenate([[0.0], err])
        observed = bool(observed)
        if category in self._observed and self._observed[category] != observed:
            raise ValueError(
                f"category {category!r} was added as observed={self._observed[category]} before, "
                f"now observed={observed}"
            )
        self._observed[category] = observed
        self._ious.setdefault(category, []).append(iou)
        self._errors.setdefault(category, []).append(err)
        self._tracklets.setdefault(category, set()).add(tracklet_id)
        result = TrackletResult(
            tracklet_id, category, observed, int(iou.size), success_auc(iou), precision_auc(err)
        )
        self.results.append(result)
        return result

    def __len__(self) -> int:
        return len(self.results)

    @staticmethod
    def _entry(ious: list[np.ndarray], errors: list[np.ndarray], n_tracklets: int, curves: bool):
        iou = np.concatenate(ious) if ious else np.zeros(0)
        err = np.concatenate(errors) if errors else np.zeros(0)
        entry: dict = {
            "success": success_auc(iou) if iou.size else float("nan"),
            "precision": precision_auc(err) if err.size else float("nan"),
            "frames": int(iou.size),
            "tracklets": int(n_tracklets),
        }
        if curves:
            entry["success_curve"] = success_curve(iou).tolist()
            entry["precision_curve"] = precision_curve(err).tolist()
        return entry

    def report(self, curves: bool = False) -> dict:
        """The OPE report.

        Returns:
            ``{"categories": {category: entry + {"observed": bool}}, "observed": entry,
            "unseen": entry, "mean": entry}`` where ``entry`` is ``{"success": %, "precision": %,
            "frames": int, "tracklets": int}`` (plus ``success_curve`` / ``precision_curve``
            lists of 21 when ``curves``). Group entries pool the frames of their categories
            (= frame-weighted mean of category scores); an empty group scores NaN.
        """
        cats: dict[str, dict] = {}
        for cat in self._ious:
            entry = self._entry(
                self._ious[cat], self._errors[cat], len(self._tracklets[cat]), curves
            )
            entry["observed"] = self._observed[cat]
            cats[cat] = entry

        def group(names: list[str]) -> dict:
            return self._entry(
                [a for c in names for a in self._ious[c]],
                [a for c in names for a in self._errors[c]],
                sum(len(self._tracklets[c]) for c in names),
                curves,
            )

        return {
            "categories": cats,
            "observed": group([c for c in cats if self._observed[c]]),
            "unseen": group([c for c in cats if not self._observed[c]]),
            "mean": group(list(cats)),
        }


# --------------------------------------------------------------------------- weather


def robustness_metrics(clean: float, levels: Sequence[float]) -> dict[str, float | list[float]]:
    """Sec. III-D of Zhao et al. (adverse-weather SOT) for one score (Success or Precision, %).

    Returns ``{"dr": [S_j / S_clean per level], "DR": 1 - mean(dr), "R": max - min of the level
    scores, "Sd": sample standard deviation (ddof 1) of the level scores}``. Checked against
    Table III (BAT, rain, Car: clean 62.83 -> DR 0.42, R 1.33, S.d 0.50). NaN scores (a group
    without frames) propagate as NaN; ``clean <= 0`` gives NaN ratios.
    """
    s = np.asarray(list(levels), dtype=np.float64)
    if s.size == 0:
        raise ValueError("levels must not be empty")
    c = float(clean) if clean is not None else float("nan")
    dr = s / c if c > 0 else np.full_like(s, np.nan)
    return {
        "dr": dr.tolist(),
        "DR": float(1.0 - dr.mean()),
        "R": float(s.max() - s.min()),
        "Sd": float(s.std(ddof=1)) if s.size > 1 else 0.0,
    }
