"""The env's template: which crops of the target an episode keeps, and how the five template
modes (:data:`envs.spec.TEMPLATE_MODES`) compose them into the ``template (512, 3)``
observation.

Every crop is a point set ``(M, 3)`` float32 in its own box frame (m): the frame's points
inside its box enlarged by :data:`envs.spec.TEMPLATE_ENLARGEMENT` (scaled 1.25), in the
canonical row order of :func:`envs.scan_cache.crop_canonical`. The resampling to 512 points is
the caller's (:func:`envs.observation.resample_into`, which draws for all sets at once).
"""

from __future__ import annotations

import numpy as np

from envs.spec import TEMPLATE_MODES, TEMPLATE_SIZE

__all__ = ["TemplateCrops"]


class TemplateCrops:
    """The crops one episode's template is built from.

    - ``"first_and_previous"`` (default): 256 points of the first crop (the given box's) and
      256 of the previous one (the previous prediction's), each resampled on its own;
    - ``"first"`` / ``"previous"``: 512 points of that crop;
    - ``"all"``: the first crop and every previous prediction's, merged, 512 points (P2B's
      "all previous results");
    - ``"first_and_previous_merged"``: the first and the previous crop merged, first then
      previous, 512 points (Open3DSOT's ``firstandprevious`` shape aggregation).
    """

    def __init__(self, mode: str, first: np.ndarray) -> None:
        if mode not in TEMPLATE_MODES:
            raise ValueError(f"unknown template_mode {mode!r}; valid: {list(TEMPLATE_MODES)}")
        self.mode = mode
        self.first = first
        self.previous = first  # at the first step the previous frame is the given one
        self.history = [first]  # "all" only: every crop so far

    def needs_previous(self, t: int, start: int) -> bool:
        """Whether the observation of frame ``t`` (episode from frame ``start``) needs a new
        crop of frame ``t - 1`` around the previous prediction (not at the first step, where
        it is the given box's; never in mode ``"first"``)."""
        return t >= start + 2 and self.mode != "first"

    def add_previous(self, crop: np.ndarray) -> None:
        """Record the previous frame's crop ``(M, 3)``."""
        self.previous = crop
        if self.mode == "all":
            self.history.append(crop)

    def point_sets(self, template: np.ndarray) -> tuple[list[np.ndarray], list[np.ndarray]]:
        """``(sets, outs)``: the point sets to resample and the views of ``template``
        ``(TEMPLATE_SIZE, 3)`` each fills, in drawing order."""
        mode = self.mode
        if mode == "first_and_previous":
            half = TEMPLATE_SIZE // 2
            return [self.first, self.previous], [template[:half], template[half:]]
        if mode == "first":
            return [self.first], [template]
        if mode == "previous":
            return [self.previous], [template]
        if mode == "first_and_previous_merged":
            return [np.concatenate([self.first, self.previous])], [template]
        merged = self.history
        return [np.concatenate(merged) if len(merged) > 1 else merged[0]], [template]
