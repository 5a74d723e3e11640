"""The decision step: from a tracker's network outputs to the action it executes.

A tracker's network (``forward``) scores proposals; which box the tracker then executes is
decided here, by settings that act at inference only and are no part of the architecture
(:class:`InferenceConfig`, ``tracker.inference``; the weights do not depend on them):

* the **still-target test** (``hold_chamfer_m > 0``, :func:`keeps_box`): the tracker keeps the
  reference box (action 0) where the current points inside it (scaled 1.25) lie within
  ``hold_chamfer_m`` metres (symmetric Chamfer distance) of both template crops: the target
  has not moved against the sensor. Not in the papers: the matching head alone lets a parked
  car's box slide along it (docs/notes/checkpoints-history.md, "Holding still targets");
* the **re-ranking** (``rerank_top_k = K > 0``, :func:`choose_action`): of the reference box and
  the ``K`` best-scored proposals, the box whose crop lies nearest (symmetric Chamfer distance)
  to the first frame's crop, a proposal counting ``rerank_margin_m`` farther than it is: the
  network moves the box only where the move matches the target better. Not in the papers
  either (docs/notes/checkpoints-history.md, "Re-ranking by the first crop");
* the **dead zone** (``min_motion_m > 0``, :func:`decide`): an action whose translation is
  shorter than ``min_motion_m`` metres keeps the box: at a low frame rate (nuScenes' 2 Hz key
  frames) a target stands or moves far, and a short move is mostly the network's jitter, which
  walks a parked target's box away frame by frame. Not in the papers either (docs/table4.md,
  "Budget pilot");
* the **clip** to ``max_action`` (:func:`clip_action`).

:func:`decide` is the one place these run, in this order: ``Tracker.act`` and the RL policy
(``training.rl.TrackerPolicy``) both call it. Both tests need the matching trackers' observation
layout (``template (B, 512, 3)`` as the first and the previous frame's crops, ``search``,
``size``), the re-ranking their ``proposals`` / ``scores`` too; a tracker sets only the fields
that fit it away from their defaults (``Tracker.inference_fields``: every field for the matching
trackers, the still-target test and the dead zone for MBPTrack, none for M2-Track).

Cost (issue 41): one observation at a time (as the eval forward; a row's decision does not
depend on its batch), every candidate's crop and Chamfer distance in one vectorised pass, the
first crop prepared once for all candidates, and copies of a point (the env's resampling
repeats points) compared once (:func:`trackers.ops.distinct_points`); the distances are bit for
bit those of :func:`trackers.ops.chamfer_distance` one candidate at a time. On CPU float32 with
the ``fast`` extra, compiled passes (:func:`trackers.kernels.scene_kernel` once per
observation, :func:`~trackers.kernels.crop_distance_kernel` per template crop measured against)
give the same point sets and crops, and the same distances to float32 rounding (their sums run
in float64), and the choice runs in numpy: ~30 small torch ops fewer per observation.
"""

from __future__ import annotations

import functools
import math
import numbers
from collections.abc import Mapping
from dataclasses import asdict, dataclass, fields
from typing import TYPE_CHECKING, Any, TypeVar

import numpy as np
import torch

from envs.geometry import world_to_box_torch
from envs.observation import TEMPLATE_SCALE
from trackers import kernels, ops

if TYPE_CHECKING:
    from trackers.base import Tracker

_Array = TypeVar("_Array", torch.Tensor, np.ndarray)

__all__ = [
    "HOLD_GROUND_CLEARANCE_M",
    "HOLD_MIN_POINTS",
    "INFERENCE_FIELDS",
    "InferenceConfig",
    "Scene",
    "choose_action",
    "clip_action",
    "decide",
    "keeps_box",
    "load_kernels",
    "scenes",
    "split_inference",
    "template_crops",
]

#: Fewest points in a crop for the still-target test (or a re-ranking candidate) to count.
HOLD_MIN_POINTS = 5
#: The still-target test and the re-ranking leave out points this close above the box's bottom
#: (m): the ground the crops share whether or not the target moves.
HOLD_GROUND_CLEARANCE_M = 0.2


@dataclass(frozen=True)
class InferenceConfig:
    """How a tracker decides on its network's outputs (see the module doc); the defaults (0)
    turn both the still-target test and the re-ranking off: the best-scored proposal, clipped.

    ``hold_chamfer_m``: the still-target test's distance (metres, finite, >= 0);
    ``rerank_top_k``: how many best-scored proposals the re-ranking weighs (an integer >= 0);
    ``rerank_margin_m``: how much farther a proposal's crop counts than it is (metres, >= 0);
    ``min_motion_m``: the dead zone, the shortest move executed (metres, >= 0; 0: off).
    """

    hold_chamfer_m: float = 0.0
    rerank_top_k: int = 0
    rerank_margin_m: float = 0.0
    min_motion_m: float = 0.0

    def __post_init__(self) -> None:
        for name, meaning in (
            ("hold_chamfer_m", "metres; 0 turns the still-target test off"),
            ("rerank_margin_m", "metres"),
            ("min_motion_m", "metres; 0 turns the dead zone off"),
        ):
            value = getattr(self, name)
            real = isinstance(value, numbers.Real) and not isinstance(value, bool)
            if not (real and math.isfinite(value) and value >= 0):
                raise ValueError(
                    f"InferenceConfig.{name} = {value!r}: expected a finite distance >= 0 "
                    f"({meaning})"
                )
            object.__setattr__(self, name, float(value))
        k = self.rerank_top_k
        if isinstance(k, bool) or not isinstance(k, numbers.Integral) or k < 0:
            raise ValueError(
                f"InferenceConfig.rerank_top_k = {k!r}: expected an integer >= 0 (proposals; "
                f"0 turns the re-ranking off)"
            )
        object.__setattr__(self, "rerank_top_k", int(k))

    @classmethod
    def from_dict(cls, data: Any, where: str = "inference") -> InferenceConfig:
        """From a mapping of fields (JSON metadata, a CLI's overrides); ``ValueError`` naming
        ``where``, the key or the field and the bad value."""
        if not isinstance(data, Mapping):
            raise ValueError(
                f"{where}: expected a mapping of {list(INFERENCE_FIELDS)}, got {data!r}"
            )
        unknown = sorted(set(data) - set(INFERENCE_FIELDS))
        if unknown:
            raise ValueError(
                f"{where}: unknown field(s) {unknown}; valid: {list(INFERENCE_FIELDS)}"
            )
        try:
            return cls(**data)
        except ValueError as exc:
            raise ValueError(f"{where}: {exc}") from exc

    def to_dict(self) -> dict[str, Any]:
        return asdict(self)


#: The :class:`InferenceConfig` fields (checkpoints of before it stored them in the architecture
#: config: :func:`split_inference` moves them out).
INFERENCE_FIELDS = tuple(f.name for f in fields(InferenceConfig))


def split_inference(config: Mapping[str, Any]) -> tuple[dict[str, Any], dict[str, Any]]:
    """An architecture config of an older checkpoint -> (the config without the
    :data:`INFERENCE_FIELDS`, those fields): how old files migrate on load."""
    inference = {k: v for k, v in config.items() if k in INFERENCE_FIELDS}
    return {k: v for k, v in config.items() if k not in INFERENCE_FIELDS}, inference


def clip_action(action: torch.Tensor, max_action: Any) -> torch.Tensor:
    """``action (..., 4)`` clipped to ``[-max_action, max_action]`` per component (a NaN stays
    NaN)."""
    a_max = torch.as_tensor(max_action, device=action.device, dtype=action.dtype)
    return action.clamp(-a_max, a_max)


def template_crops(tracker: Tracker, template: torch.Tensor) -> torch.Tensor:
    """The first and the previous frame's crops ``(B, 2, 256, 3)`` of ``template (B, 512,
    3)`` (``[:, 0]`` the first), laid out by the env's ``template_mode`` ``"first_and_previous"``
    (the default; see ``tracker.env_options``); other modes do not keep the two apart, and the
    still-target test and the re-ranking refuse them."""
    mode = tracker.env_options.get("template_mode", "first_and_previous")
    if mode != "first_and_previous":
        raise ValueError(
            f"{tracker.name}: the still-target test and the re-ranking need the first and "
            f"previous crops apart in the template (template_mode 'first_and_previous'); this "
            f"tracker's env runs template_mode {mode!r}"
        )
    return template.reshape(template.shape[0], 2, template.shape[1] // 2, 3)


def _floor(size: _Array) -> _Array:
    """The lowest height the tests read, ``(..., 1)`` of box sizes ``(..., 3)`` (torch or numpy,
    the same float32 bits): the box's bottom plus :data:`HOLD_GROUND_CLEARANCE_M` (box frame)."""
    return -size[..., 2:] / 2 + HOLD_GROUND_CLEARANCE_M


def _half_extent(size: _Array) -> _Array:
    """Half the box scaled :data:`TEMPLATE_SCALE` (the template's crop), ``(..., 3)`` (torch or
    numpy)."""
    return size * (TEMPLATE_SCALE / 2)


def _above_ground(points: torch.Tensor, size: torch.Tensor) -> torch.Tensor:
    """``(B, ..., N)`` bool: the points ``(B, ..., N, 3)`` (box frame; zero rows are padding)
    at least :data:`HOLD_GROUND_CLEARANCE_M` above the bottom of the box of ``size (B, 3)``."""
    size = size.reshape(size.shape[0], *([1] * (points.dim() - 2)), 3)
    return (points != 0).any(-1) & (points[..., 2] > _floor(size)[..., 0])


def _crop_mask(points: torch.Tensor, size: torch.Tensor) -> torch.Tensor:
    """``(B, ..., N)`` bool: the points ``(B, ..., N, 3)`` of :func:`_above_ground` inside the
    box scaled :data:`TEMPLATE_SCALE` (the template's crop of them)."""
    half = _half_extent(size.reshape(size.shape[0], *([1] * (points.dim() - 2)), 3))
    return (points.abs() <= half).all(-1) & _above_ground(points, size)


@dataclass(frozen=True)
class _SceneArrays:
    """A :class:`Scene` from one compiled pass (:func:`trackers.kernels.scene_kernel`): the
    search's real rows ``(N,)``, its distinct points ``(U, 3)``, ``layout (N,)`` and how many
    rows each distinct point stands for, ``weights (U,)``; the crops' masks ``(2, L)``
    (``crop_masked[k]`` rows each), distinct points ``crop_points[k, :crop_counts[k]]``,
    layouts ``(2, L)`` and weights ``(2, L)``; and the crop box's ``half`` extent ``(3,)`` and
    ``floor`` ``(1,)``."""

    real: np.ndarray
    points: np.ndarray
    layout: np.ndarray
    weights: np.ndarray
    crop_masks: np.ndarray
    crop_points: np.ndarray
    crop_layouts: np.ndarray
    crop_weights: np.ndarray
    crop_counts: np.ndarray
    crop_masked: np.ndarray
    half: np.ndarray
    floor: np.ndarray


class Scene:
    """One observation as the still-target test and the re-ranking read it: ``search (N, 3)``,
    ``size (3,)`` and the template crops ``(2, 256, 3)`` (first, previous), with the point sets
    both need computed once, when first asked (``act`` builds the scenes before the test and
    hands the moving ones to the re-ranking after the network). On CPU float32 with the
    ``fast`` extra they come from one compiled pass (:attr:`arrays`; the same sets), else from
    the torch ops."""

    def __init__(self, search: torch.Tensor, size: torch.Tensor, crops: torch.Tensor) -> None:
        self.search, self.size, self.crops = search.detach(), size, crops

    @functools.cached_property
    def arrays(self) -> _SceneArrays | None:
        """The scene's point sets from :func:`trackers.kernels.scene_kernel`, or ``None`` (no
        numba, not CPU float32)."""
        float32 = self.search.dtype == self.crops.dtype == torch.float32
        kernel = kernels.scene_kernel() if float32 and kernels.compilable(self.search) else None
        if kernel is None:
            return None
        search, crops = self.search.contiguous().numpy(), self.crops.contiguous().numpy()
        size = self.size.numpy()
        half, floor = _half_extent(size), _floor(size)
        n, length = len(search), crops.shape[1]
        real, layout, weights = np.empty(n, np.bool_), np.empty(n, np.int64), np.empty(n, np.int64)
        points, crop_points = np.empty_like(search), np.empty_like(crops)
        crop_masks = np.empty((2, length), np.bool_)
        crop_layouts, crop_weights = np.empty((2, 2, length), np.int64)
        counts = np.empty(5, np.int64)
        kernel(
            search, search.view(np.int32), crops, crops.view(np.int32), floor, real, points,
            layout, weights, crop_masks, crop_points, crop_layouts, crop_weights, counts,
        )  # fmt: skip
        u = counts[0]
        return _SceneArrays(
            real, points[:u], layout, weights[:u], crop_masks, crop_points, crop_layouts,
            crop_weights, counts[1:3], counts[3:], half, floor,
        )  # fmt: skip

    @functools.cached_property
    def real(self) -> torch.Tensor:
        """``(N,)`` bool: the search's points (zero rows pad it, wherever a box moves them)."""
        if self.arrays is not None:
            return torch.from_numpy(self.arrays.real)
        return (self.search != 0).any(-1)

    @functools.cached_property
    def points(self) -> tuple[torch.Tensor, torch.Tensor]:
        """The search's distinct real points ``(U, 3)`` and their layout ``(N,)``
        (:func:`trackers.ops.distinct_points`)."""
        if self.arrays is not None:
            return torch.from_numpy(self.arrays.points), torch.from_numpy(self.arrays.layout)
        return ops.distinct_points(self.search, self.real)

    @functools.cached_property
    def crop_masks(self) -> torch.Tensor:
        """``(2, 256)`` bool: the crops' points above the ground (the env cropped them)."""
        if self.arrays is not None:
            return torch.from_numpy(self.arrays.crop_masks)
        return _above_ground(self.crops.reshape(1, -1, 3), self.size[None]).reshape(2, -1)

    @functools.cached_property
    def first(self) -> tuple[torch.Tensor, torch.Tensor]:
        """The first crop's distinct points ``(F, 3)`` and their layout ``(256,)``."""
        return self._crop(0)

    @functools.cached_property
    def previous(self) -> tuple[torch.Tensor, torch.Tensor]:
        """The previous crop's distinct points ``(P, 3)`` and their layout ``(256,)``."""
        return self._crop(1)

    def _crop(self, k: int) -> tuple[torch.Tensor, torch.Tensor]:
        a = self.arrays
        if a is not None:
            points = a.crop_points[k, : a.crop_counts[k]]
            return torch.from_numpy(points), torch.from_numpy(a.crop_layouts[k])
        return ops.distinct_points(self.crops[k], self.crop_masks[k])


def load_kernels() -> bool:
    """Run the compiled passes once on a tiny observation through the still-target test and the
    re-ranking's crops (numba's start and disk cache), e.g. in a parent before it forks
    workers, as :func:`trackers.ops.load_kernels` does for the ops; ``False`` without numba."""
    if kernels.scene_kernel() is None:
        return False
    search = torch.zeros(8, 3)
    search[:, 0] = torch.arange(8.0) / 10  # enough points in the box and the crops to decide
    scene = Scene(search, torch.full((3,), 4.0), search.expand(2, -1, -1))
    still_distances(scene)
    _crop_distances(scene, torch.zeros(2, 4))
    return True


def scenes(tracker: Tracker, batch: Mapping[str, torch.Tensor]) -> list[Scene]:
    """The :class:`Scene` of each observation of ``batch``."""
    crops = template_crops(tracker, batch["template"])
    return [Scene(*row) for row in zip(batch["search"], batch["size"], crops, strict=True)]


def keeps_box(
    tracker: Tracker,
    batch: Mapping[str, torch.Tensor],
    inference: InferenceConfig,
    observed: list[Scene] | None = None,
) -> torch.Tensor:
    """``(B,)`` True where the tracker keeps the reference box (action 0) without running the
    network: its empty observations (``tracker.empty_observations``) and, with
    ``inference.hold_chamfer_m > 0``, the still targets: the search points inside the reference
    box scaled 1.25 (the template's crop) lie within ``hold_chamfer_m``
    (:func:`trackers.ops.chamfer_distance`) of both template crops, the previous frame's (it has
    not moved) and the first frame's (the box is still on the target, not on background it lost
    it to). Points less than :data:`HOLD_GROUND_CLEARANCE_M` above the box's bottom are left
    out, and a crop of fewer than :data:`HOLD_MIN_POINTS` points decides nothing. ``observed``:
    the batch's :func:`scenes`, if built already."""
    keep = tracker.empty_observations(batch)
    if inference.hold_chamfer_m <= 0:
        return keep
    observed = scenes(tracker, batch) if observed is None else observed
    return keep | torch.stack([_still(scene, inference.hold_chamfer_m) for scene in observed])


def _reference_crop(scene: Scene) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """The reference box's crop of a non-empty search: ``in_crop (1, U)`` over the distinct
    points, ``in_box (N,)`` over the search's rows, and whether it and both template crops hold
    :data:`HOLD_MIN_POINTS` points (a bool scalar: the still-target test decides only then)."""
    points, layout = scene.points
    in_crop = _crop_mask(points[None], scene.size[None])
    in_box = in_crop[0].gather(0, layout.clamp(max=len(points) - 1)) & scene.real
    enough = (in_box.sum() >= HOLD_MIN_POINTS) & (scene.crop_masks.sum(1) >= HOLD_MIN_POINTS).all()
    return in_crop, in_box, enough


def _still(scene: Scene, hold_m: float) -> torch.Tensor:
    """The still-target test of one observation -> a bool scalar: the reference box's crop
    within ``hold_m`` of both template crops (:func:`still_distances`)."""
    distances = still_distances(scene)
    if distances is None:
        return torch.zeros((), dtype=torch.bool, device=scene.search.device)
    return (distances < hold_m).all()


def still_distances(scene: Scene) -> torch.Tensor | None:
    """The symmetric Chamfer distances ``(2,)`` of the reference box's crop of the search to
    the first and the previous crop, in one pass; ``None`` where the test decides nothing (an
    empty search, or fewer than :data:`HOLD_MIN_POINTS` points in the box or a crop). Compiled
    on CPU float32 with the ``fast`` extra (:func:`_still_distances_compiled`: the same crops,
    the same distances to float32 rounding)."""
    if scene.arrays is not None:
        return _still_distances_compiled(scene.arrays)
    points, layout = scene.points
    if not len(points):  # an empty search
        return None
    in_crop, in_box, enough = _reference_crop(scene)
    if not bool(enough):
        return None
    (first, first_layout), (previous, previous_layout) = scene.first, scene.previous
    crop_points = torch.cat([first, previous])  # the two crops as two sets of one cloud
    held = torch.arange(len(crop_points), device=first.device) < len(first)
    held = torch.stack([held, ~held])
    crop_layout = torch.stack([first_layout, previous_layout + len(first)])
    cropped = in_crop[0].nonzero()[:, 0]
    crop_near, near = ops.nearest_distances(
        crop_points.expand(2, -1, -1), held, points.index_select(0, cropped)
    )
    search_near = near.new_zeros(2, len(points)).index_copy_(1, cropped, near)
    crop_to_search = ops.layout_mean(crop_near, crop_layout, scene.crop_masks)
    search_to_crop = ops.layout_mean(search_near, layout, in_box.expand(2, -1))
    return 0.5 * (crop_to_search + search_to_crop)


#: The reference box as a candidate in its own frame (the zero action): centre 0, yaw 0, as the
#: compiled pass takes it (its yaw's cosine and sine, its centre).
_REFERENCE_BOX = (np.ones(1, np.float32), np.zeros(1, np.float32), np.zeros((1, 3), np.float32))


def _still_distances_compiled(a: _SceneArrays) -> torch.Tensor | None:
    """:func:`still_distances` compiled: the reference box (the zero action, where the crop is
    the search's points as they are) measured against both crops, as the re-ranking measures
    its candidates (:func:`_compiled_crop_distances`)."""
    if (a.crop_masked < HOLD_MIN_POINTS).any():
        return None
    distances, in_box = _compiled_crop_distances(a, *_REFERENCE_BOX, crops=2)
    return None if in_box[0] < HOLD_MIN_POINTS else torch.from_numpy(distances[:, 0])


def choose_action(
    tracker: Tracker,
    batch: Mapping[str, torch.Tensor],
    outputs: dict[str, torch.Tensor],
    inference: InferenceConfig,
    max_action: Any,
    observed: list[Scene] | None = None,
) -> torch.Tensor:
    """``tracker.best_action(outputs)``, or with ``inference.rerank_top_k = K > 0`` the
    re-ranked action ``(B, 4)``: of the reference box (action 0) and the ``K`` best-scored
    proposals (each clipped to ``max_action``), the box whose crop (search points inside it
    scaled 1.25, above the ground as in :func:`keeps_box`) has the smallest Chamfer distance to
    the first frame's crop, a proposal's distance counted ``rerank_margin_m`` larger (ties: the
    earlier, the reference box first). A candidate whose crop has fewer than
    :data:`HOLD_MIN_POINTS` points is out; where the first crop has fewer, or no candidate is
    left, or a proposal is not finite, the best action stands. Differentiable in the chosen
    proposal (not in the choice). ``observed``: the batch's :func:`scenes`, if built already."""
    reranked = _rerank(tracker, batch, outputs, inference, max_action, observed)
    if reranked is None:
        return tracker.best_action(outputs)
    candidates, _, choice, decides = reranked
    chosen = candidates.gather(1, choice[:, None, None].expand(-1, 1, 4))[:, 0]
    if bool(decides.all()):  # the re-ranking decides every row (mostly): no best action
        return chosen
    return torch.where(decides[:, None], chosen, tracker.best_action(outputs))


def chosen_proposal(
    tracker: Tracker,
    batch: Mapping[str, torch.Tensor],
    outputs: dict[str, torch.Tensor],
    inference: InferenceConfig,
    max_action: Any,
    observed: list[Scene] | None = None,
) -> torch.Tensor:
    """Which proposal :func:`choose_action` takes, for a tracker whose best action is its
    best-scored proposal (``Tracker.best_action``): ``(B,)`` indices into
    ``outputs["proposals"]``, ``-1`` where the re-ranking keeps the reference box."""
    best = outputs["scores"].argmax(dim=1)
    reranked = _rerank(tracker, batch, outputs, inference, max_action, observed)
    if reranked is None:
        return best
    _, top, choice, decides = reranked
    proposal = top.gather(1, (choice - 1).clamp(min=0)[:, None])[:, 0]
    chosen = torch.where(choice == 0, torch.full_like(proposal, -1), proposal)
    return torch.where(decides, chosen, best)


def _rerank(
    tracker: Tracker,
    batch: Mapping[str, torch.Tensor],
    outputs: dict[str, torch.Tensor],
    inference: InferenceConfig,
    max_action: Any,
    observed: list[Scene] | None,
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor] | None:
    """The re-ranking of :func:`choose_action` (None when ``rerank_top_k`` is 0): the
    candidates ``(B, 1 + K, 4)`` (the reference box first), the proposals' indices ``top (B,
    K)``, the chosen candidate ``(B,)`` and where the choice stands ``decides (B,)`` bool."""
    k = min(inference.rerank_top_k, outputs["scores"].shape[1])
    if k == 0:
        return None
    top = outputs["scores"].topk(k, dim=1).indices  # (B, K)
    proposals = outputs["proposals"].gather(1, top[..., None].expand(-1, -1, 4))
    candidates = torch.cat(  # (B, 1 + K, 4): the reference box first
        [torch.zeros_like(proposals[:, :1]), clip_action(proposals, max_action)], dim=1
    )
    observed = scenes(tracker, batch) if observed is None else observed
    rows = candidates.detach()  # the choice, in numpy: a few values a row, no autograd
    distance = np.stack([_crop_distances(*row) for row in zip(observed, rows, strict=True)])
    if inference.rerank_margin_m:
        distance[:, 1:] += np.float32(inference.rerank_margin_m)
    first_points = np.array([_masked_rows(scene, 0) for scene in observed]) >= HOLD_MIN_POINTS
    finite = np.isfinite(proposals.detach().cpu().numpy()).all((1, 2))
    decides = first_points & np.isfinite(distance).any(1) & finite
    choice = torch.from_numpy(distance.argmin(1)).to(top.device)  # ties: the earlier
    return candidates, top, choice, torch.from_numpy(decides).to(top.device)


def _masked_rows(scene: Scene, crop: int) -> int:
    """How many rows of template crop ``crop`` the tests read (above the ground)."""
    a = scene.arrays
    return int(a.crop_masked[crop]) if a is not None else int(scene.crop_masks[crop].sum())


def _crop_distances(scene: Scene, candidates: torch.Tensor) -> np.ndarray:
    """The Chamfer distance of each candidate box's crop of one observation's search to its
    first crop, ``inf`` for a crop of fewer than :data:`HOLD_MIN_POINTS` points: candidates
    ``(C, 4)`` (actions: the box moved by ``(dx, dy, dz, dyaw)`` in the search frame) ->
    ``(C,)`` float32, in numpy (the re-ranking's choice reads a few values). The search's
    distinct points (copies stay copies in every frame) in every candidate's frame, one pass
    for all (compiled on CPU float32 with the ``fast`` extra:
    :func:`trackers.kernels.crop_distance_kernel`)."""
    inf = np.full(len(candidates), np.inf, np.float32)
    if not (_masked_rows(scene, 0) and len(scene.points[0])):  # an empty first crop or search
        return inf
    a = scene.arrays
    if a is not None and candidates.dtype == torch.float32:
        yaw, centres = candidates[:, 3], np.ascontiguousarray(candidates[:, :3].numpy())
        distances, in_box = _compiled_crop_distances(
            a, torch.cos(yaw).numpy(), torch.sin(yaw).numpy(), centres, crops=1
        )
        distance = distances[0]
    else:
        (points, layout), (first, first_layout) = scene.points, scene.first
        zeros = torch.zeros_like(candidates[:, :3])  # the boxes' sizes: no test reads them
        boxes = torch.cat([candidates[:, :3], zeros, candidates[:, 3:]], 1)
        crops = _crops_and_nearest(scene.size, points, first, boxes)
        if crops is None:  # no candidate's crop holds a point
            return inf
        in_crop, crop_near, first_near = crops
        boxed = in_crop.gather(1, layout.clamp(max=len(points) - 1).expand(len(boxes), -1))
        boxed &= scene.real
        first_mask = scene.crop_masks[0].expand(len(boxes), -1)
        crop_to_first = ops.layout_mean(crop_near, layout, boxed)
        first_to_crop = ops.layout_mean(first_near, first_layout, first_mask)
        distance = (0.5 * (crop_to_first + first_to_crop)).cpu().numpy()
        in_box = boxed.sum(1).cpu().numpy()
    return np.where(in_box >= HOLD_MIN_POINTS, distance, inf)


def _compiled_crop_distances(
    a: _SceneArrays, cos: np.ndarray, sin: np.ndarray, centres: np.ndarray, crops: int
) -> tuple[np.ndarray, np.ndarray]:
    """The Chamfer distances of each candidate box's crop of the search to the first ``crops``
    template crops (1: the first; 2: the first and the previous) ``(crops, C)`` float32
    (``inf`` for an empty crop) and how many search rows each candidate's crop holds ``(C,)``
    int64, the boxes given by their yaws' ``cos (C,)``, ``sin (C,)`` and ``centres (C, 3)``
    (:func:`trackers.kernels.crop_distance_kernel`: the torch ops' distances to float32
    rounding)."""
    distances = np.empty((crops, len(cos)), np.float32)
    in_box = np.empty(len(cos), np.int64)
    kernels.crop_distance_kernel()(
        a.points, a.weights, cos, sin, centres, a.half, a.floor, a.crop_points[:crops],
        a.crop_counts[:crops], a.crop_weights[:crops], a.crop_masked[:crops], distances, in_box,
    )  # fmt: skip
    return distances, in_box


def _crops_and_nearest(
    size: torch.Tensor, points: torch.Tensor, first: torch.Tensor, boxes: torch.Tensor
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor] | None:
    """Which of ``points (U, 3)`` each candidate box ``(C, 7)`` crops, ``(C, U)`` bool, their
    distances to the nearest point of ``first (F, 3)``, ``(C, U)`` (any value outside the crop),
    and ``first``'s to the nearest point of each crop, ``(C, F)``; None when no crop holds a
    point (the torch ops of :func:`trackers.kernels.crop_distance_kernel`)."""
    in_frames = world_to_box_torch(points[None], boxes)  # (C, U, 3)
    in_crop = _crop_mask(in_frames, size[None].expand(len(boxes), 3))  # (C, U)
    # only the points some crop holds meet the first crop's (the rest of the search is far)
    cropped = in_crop.any(0).nonzero()[:, 0]
    if not len(cropped):
        return None
    near, first_near = ops.nearest_distances(
        in_frames.index_select(1, cropped), in_crop.index_select(1, cropped), first
    )
    return in_crop, near.new_zeros(in_crop.shape).index_copy_(1, cropped, near), first_near


def decide(
    tracker: Tracker,
    batch: Mapping[str, torch.Tensor],
    outputs: dict[str, torch.Tensor],
    inference: InferenceConfig,
    *,
    action: torch.Tensor | None = None,
    max_action: Any = None,
    keep: torch.Tensor | None = None,
    observed: list[Scene] | None = None,
) -> torch.Tensor:
    """The action ``(B, 4)`` (env units: metres, radians) the tracker executes on ``batch``
    from its forward's ``outputs``: zero where it keeps the box (:func:`keeps_box`; ``keep
    (B,)`` bool gives it where it is known already: ``act`` tests it before the network, to skip
    the network there); elsewhere ``action (B, 4)`` if given (the RL policy's soft mode), else
    :func:`choose_action`; then the one clip to ``max_action`` (default
    ``tracker.max_action``). With ``inference.min_motion_m > 0`` an action whose translation is
    shorter keeps the box too (the dead zone). A non-finite action comes out NaN (the caller
    decides: ``act`` moves nowhere, the RL policy raises). ``observed``: the batch's
    :func:`scenes`, if built already. Differentiable in the chosen action."""
    max_action = tracker.max_action if max_action is None else max_action
    if observed is None and (inference.hold_chamfer_m > 0 or inference.rerank_top_k > 0):
        observed = scenes(tracker, batch)  # what the test and the re-ranking share
    if keep is None:
        keep = keeps_box(tracker, batch, inference, observed)
    if action is None:
        action = choose_action(tracker, batch, outputs, inference, max_action, observed)
    finite = action.abs() < math.inf  # torch.isfinite in two ops (it runs four)
    if inference.min_motion_m > 0:  # the dead zone (inf and NaN compare False: they stay)
        keep = keep | (torch.linalg.vector_norm(action[:, :3], dim=1) < inference.min_motion_m)
    action = torch.where(keep[:, None], 0.0, torch.where(finite, action, math.nan))
    return clip_action(action, max_action)
