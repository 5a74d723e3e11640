"""Supervised pretraining samples from tracklets, built as P2B / BAT / GPT build them.

One sample is ``(tracklet, frame t >= 1, candidate c)``:

* **template** (512 points): 256 from frame 0 cropped with the ground-truth box scaled 1.25, in
  that box's frame, plus 256 from frame ``t - 1`` cropped with the previous ground-truth box
  jittered uniformly by up to ±0.3 m in x, y and ±1.5° in yaw (candidate 0 is unjittered), in the
  jittered box's frame — the env's ``"first_and_previous"`` template with the previous
  prediction replaced by the jittered previous ground truth.
* **search** (1024 points): frame ``t`` cropped around the current ground-truth box perturbed by
  Gaussian noise (sigma 1 m in x and y, yaw variance 5 deg², i.e. sigma sqrt(5)°; z and size
  unchanged), scale 1.25 plus 2 m, in the perturbed (reference) box's frame.
* **size** (3,): the target's l, w, h from frame 0 (as the env gives it).
* **object resizing** (``size_jitter = a > 0``, off by default; not in the papers): before
  anything else, each sample draws one scale per box axis, ``s ~ U(1 - a, 1 + a)^3``, and every
  frame it reads is stretched by ``s`` along that frame's ground-truth box axes about the box
  centre (so the object and its surroundings grow or shrink together and it stays on the
  ground), the boxes' ``l, w, h`` multiplied by ``s``. Class-agnostic training sees only the
  observed categories' sizes; Tian et al. (TIP 2024) Sec. V suggests generating more diverse
  samples, and
  resizing makes the network read the target's extent from the template instead of from a
  category prior (measured without it: cars seen from behind are voted 0.4-0.55 m beyond
  their centre, as if they were vans; see the README).
* **motion** (4,): the ground-truth offset of frame ``t - 1`` relative to frame ``t - 2`` in the
  latter's box frame (what the env reports as the last motion for a perfect tracker), zeros at
  ``t = 1`` (the env's first step).

Targets (the ``targets`` contract of docs/design.md): ``search_box (7,)`` the ground truth in the
reference frame; ``search_labels (1024,)`` 1 for search points inside the exact ground-truth box;
``template_centers (512, 3)`` the true target centre in each template point's own box frame (the
origin for the first half, the previous ground truth's centre in the jittered frame for the
second); ``template_labels (512,)`` 1 for template points inside the exact box. Vote targets
(``search_box[:3] - point``), box offsets and BAT's Box-Cloud targets follow from these and are
computed by the trackers' losses. An empty crop gives zero points and zero labels.

Cropping and resampling are :mod:`envs.observation`'s (the same code as the env's observations).
Each sample is deterministic from ``(seed, epoch, index)``: its generator is
``numpy.random.default_rng([seed, epoch, index])``, so any number of DataLoader workers, and a
resumed run, produce the same samples; :meth:`TrackingSamples.set_epoch` gives fresh
perturbations every epoch.
"""

from __future__ import annotations

import math
from collections.abc import Sequence

import numpy as np
import torch
from torch.utils.data import Dataset

from envs.geometry import (
    box_to_world,
    boxes_in_frame,
    offset_between,
    points_in_box,
    world_to_box,
)
from envs.observation import (
    SEARCH_OFFSET_M,
    SEARCH_SCALE,
    SEARCH_SIZE,
    TEMPLATE_SCALE,
    TEMPLATE_SIZE,
    crop_box_frame,
    resample_into,
)

__all__ = ["TrackingSamples", "crop_near", "load_tracklets", "stretch_about_box"]

JITTER_XY_M = 0.3
JITTER_YAW_RAD = math.radians(1.5)
SEARCH_SIGMA_XY_M = 1.0
SEARCH_SIGMA_YAW_RAD = math.radians(math.sqrt(5.0))
SEARCH_CENTERS = ("current", "previous")


def _reach_m(box: np.ndarray, scale: float, offset_m: float) -> float:
    """How far (xy) from its centre the crop of ``box`` (scaled, plus ``offset_m``) reaches."""
    return math.hypot(0.5 * scale * box[3] + offset_m, 0.5 * scale * box[4] + offset_m)


def crop_near(points: np.ndarray, box: np.ndarray, scale: float, offset_m: float) -> np.ndarray:
    """Exactly ``crop_box_frame(points, box, scale, offset_m)``, faster on whole scans: a cheap
    axis-aligned pre-filter (a superset, order kept) before the exact crop."""
    r = _reach_m(box, scale, offset_m) + 1e-3
    near = (np.abs(points[:, 0] - box[0]) <= r) & (np.abs(points[:, 1] - box[1]) <= r)
    return crop_box_frame(points[near], box, scale, offset_m)


def stretch_about_box(
    points: np.ndarray, box: np.ndarray, scale: np.ndarray, reach_m: float
) -> np.ndarray:
    """The points within ``reach_m`` (after stretching) of the box centre, stretched by ``scale``
    ``(3,)`` along the box's own axes about its centre; ``(N, 3)`` LiDAR frame -> ``(M, 3)``.

    A point whose stretched xy distance from the centre is at most ``reach_m`` started within
    ``reach_m / min(scale[:2])``; only those are transformed (a cheap square pre-filter), so any
    crop that reaches no further than ``reach_m`` from the centre sees every point it should.
    """
    r = reach_m / float(min(scale[0], scale[1])) + 1e-3
    near = (np.abs(points[:, 0] - box[0]) <= r) & (np.abs(points[:, 1] - box[1]) <= r)
    local = world_to_box(points[near], box) * scale.astype(points.dtype)
    return box_to_world(local, box)


def _crop_stretched(
    points: np.ndarray,
    gt: np.ndarray,
    crop_box: np.ndarray,
    scale: float,
    offset_m: float,
    stretch: np.ndarray | None,
) -> np.ndarray:
    """``crop_near`` of ``crop_box`` after stretching the scene about the frame's GT box (none
    when ``stretch`` is None); only the points the crop can reach are stretched."""
    if stretch is not None:
        shift_m = float(np.hypot(*(crop_box[:2] - gt[:2])))
        points = stretch_about_box(
            points, gt, stretch, _reach_m(crop_box, scale, offset_m) + shift_m
        )
    return crop_near(points, crop_box, scale, offset_m)


class FrameCandidateSamples(Dataset):
    """Index arithmetic shared by the sample sets: sample ``i`` is candidate ``i % candidates``
    of frame ``t`` of one tracklet, frames counted from ``first_t`` (set by
    :meth:`_index_frames`); ``set_epoch`` changes every sample's random draws."""

    tracklets: list
    candidates: int
    epoch: int

    def _set_tracklets(self, tracklets: Sequence, candidates_per_frame: int, seed: int) -> None:
        """Keep the tracklets of >= 2 frames; check and set the candidates, seed and epoch."""
        self.tracklets = [tr for tr in tracklets if len(tr) >= 2]
        if not self.tracklets:
            raise ValueError("no tracklets with at least 2 frames to build training samples from")
        if candidates_per_frame < 1:
            raise ValueError(f"candidates_per_frame must be >= 1, got {candidates_per_frame}")
        self.candidates = int(candidates_per_frame)
        self.seed = int(seed)
        self.epoch = 0

    def _index_frames(self, first_t: int) -> None:
        frames = np.array([len(tr) - first_t for tr in self.tracklets], dtype=np.int64)
        self._first_t = first_t
        self._starts = np.concatenate([[0], np.cumsum(frames)])

    def __len__(self) -> int:
        return int(self._starts[-1]) * self.candidates

    def set_epoch(self, epoch: int) -> None:
        self.epoch = int(epoch)

    def locate(self, index: int) -> tuple[int, int, int]:
        """``index`` -> ``(tracklet position, frame t >= first_t, candidate)``."""
        if not 0 <= index < len(self):
            raise IndexError(f"sample index {index} out of range [0, {len(self)})")
        item, cand = divmod(int(index), self.candidates)
        k = int(np.searchsorted(self._starts, item, side="right") - 1)
        return k, item - int(self._starts[k]) + self._first_t, cand

    def describe(self, index: int) -> str:
        """Where sample ``index`` comes from, for error messages."""
        k, t, c = self.locate(index)
        tr = self.tracklets[k]
        return f"sample {index} (tracklet {tr.tracklet_id} {tr.category}, frame {t}, candidate {c})"


class TrackingSamples(FrameCandidateSamples):
    """A ``torch.utils.data.Dataset`` of supervised tracking samples (see the module docstring).

    Args:
        tracklets: the tracklets to sample from (already restricted to the trained categories).
        candidates_per_frame: samples per frame (candidate 0 has an unjittered previous box).
        seed: base seed; with the epoch and the index it determines every random draw.
        size_jitter: ``a`` of the object resizing (see the module docstring); 0 turns it off.
        search_enlargement: ``(scale, offset_m)`` of the search crop (the env's
            ``search_enlargement``; default P2B's 1.25 and 2 m).
        search_center: the box the search crop is cut around, Gaussian-perturbed: ``"current"``
            (the frame's own, P2B's samples: the target sits near the crop's centre) or
            ``"previous"`` (the previous frame's, as in tracking: the target's move between the
            two frames stays in the sample; for frames far apart such as nuScenes' 2 Hz).

    Recipe items (docs/recipe.md; the defaults are recipe v1, ``training.config.RECIPES``):
        zero_offset_candidate: candidate 0 of every frame crops its search region around the
            exact ground truth (Open3DSOT, when there is more than one candidate).
        min_crop_points: a sample whose template crops hold fewer points together (their
            union), or whose search crop holds fewer, is replaced by another one drawn
            uniformly from the whole data set (Open3DSOT's ``> 20`` assertions: 21); 0 = off.
        template_union: the template is ``template_size`` points drawn from the union of the
            first and previous crops (each in its own box frame; the env's
            ``"first_and_previous_merged"``) instead of half from each.
        frame0_samples: frame ``t = 0`` is sampled too, its previous frame being frame 0.
        limit_box: Open3DSOT's ``limit_box``: the search offset is drawn in the ground-truth
            box frame, and a longitudinal offset above the box width, or a lateral one above
            ``min(width, 2 m)``, is redrawn ``U(-1, 1)`` m (one-sided, as there).
    """

    MAX_REDRAWS = 100

    def __init__(
        self,
        tracklets: Sequence,
        *,
        candidates_per_frame: int = 4,
        seed: int = 0,
        template_size: int = TEMPLATE_SIZE,
        search_size: int = SEARCH_SIZE,
        size_jitter: float = 0.0,
        search_enlargement: tuple[float, float] = (SEARCH_SCALE, SEARCH_OFFSET_M),
        search_center: str = "current",
        zero_offset_candidate: bool = False,
        min_crop_points: int = 0,
        template_union: bool = False,
        frame0_samples: bool = False,
        limit_box: bool = False,
    ) -> None:
        self._set_tracklets(tracklets, candidates_per_frame, seed)
        if not 0.0 <= size_jitter < 1.0:
            raise ValueError(f"size_jitter must be in [0, 1), got {size_jitter}")
        if min_crop_points < 0:
            raise ValueError(f"min_crop_points must be >= 0, got {min_crop_points}")
        if search_center not in SEARCH_CENTERS:
            raise ValueError(
                f"search_center must be one of {SEARCH_CENTERS}, got {search_center!r}"
            )
        scale, offset_m = (float(v) for v in search_enlargement)
        if not (scale > 0 and offset_m >= 0):
            raise ValueError(
                f"search_enlargement must be (scale > 0, offset_m >= 0), got {search_enlargement}"
            )
        self.size_jitter = float(size_jitter)
        self.template_size = template_size
        self.search_size = search_size
        self.search_scale, self.search_offset_m = scale, offset_m
        self.search_center = search_center
        self.zero_offset_candidate = bool(zero_offset_candidate)
        self.min_crop_points = int(min_crop_points)
        self.template_union = bool(template_union)
        self.frame0_samples = bool(frame0_samples)
        self.limit_box = bool(limit_box)
        self._index_frames(0 if frame0_samples else 1)

    def __getitem__(self, index: int) -> dict[str, torch.Tensor]:
        rng = np.random.default_rng([self.seed, self.epoch, int(index)])
        source = int(index)
        for attempt in range(1, self.MAX_REDRAWS + 2):
            sample, n_template, n_search = self._build(source, rng)
            if min(n_template, n_search) >= self.min_crop_points:
                sample["index"] = torch.tensor(int(index), dtype=torch.int64)
                return sample
            # Open3DSOT's redraw: another sample uniformly from the whole data set, from a
            # generator of its own so the result depends only on (seed, epoch, index)
            rng = np.random.default_rng([self.seed, self.epoch, int(index), attempt])
            source = int(rng.integers(len(self)))
        raise ValueError(
            f"{self.describe(int(index))}: no sample with >= {self.min_crop_points} template and "
            f"search points in {self.MAX_REDRAWS} redraws (lower min_crop_points)"
        )

    def _search_offset(self, box: np.ndarray, rng: np.random.Generator) -> np.ndarray:
        """The Gaussian search offset ``(dx, dy)`` in the LiDAR frame, m, of the crop cut around
        ``box`` (the current or the previous ground truth; see ``limit_box``)."""
        d = rng.normal(0.0, SEARCH_SIGMA_XY_M, 2)
        if not self.limit_box:
            return d  # isotropic: drawn directly in the LiDAR frame
        width = float(box[4])
        if d[0] > width:
            d[0] = rng.uniform(-1.0, 1.0)
        if d[1] > min(width, 2.0):
            d[1] = rng.uniform(-1.0, 1.0)
        c, s = math.cos(box[6]), math.sin(box[6])
        return np.array([c * d[0] - s * d[1], s * d[0] + c * d[1]])

    def _build(
        self, index: int, rng: np.random.Generator
    ) -> tuple[dict[str, torch.Tensor], int, int]:
        """Sample ``index`` drawn with ``rng``, its template points (both crops) and its search
        points (before resampling)."""
        k, t, cand = self.locate(index)
        tr = self.tracklets[k]
        boxes = np.asarray(tr.boxes, dtype=np.float64)
        stretch = None
        if self.size_jitter > 0:
            stretch = rng.uniform(1.0 - self.size_jitter, 1.0 + self.size_jitter, 3)
            boxes = boxes.copy()
            boxes[:, 3:6] *= stretch
        t_prev = max(t - 1, 0)
        box0, prev_gt, gt = boxes[0], boxes[t_prev], boxes[t]

        # template: first GT + (jittered) previous GT, each in its own frame
        prev = prev_gt.copy()
        if cand > 0:
            prev[0:2] += rng.uniform(-JITTER_XY_M, JITTER_XY_M, 2)
            prev[6] += rng.uniform(-JITTER_YAW_RAD, JITTER_YAW_RAD)
        # search region around the Gaussian-perturbed current (or previous) GT (exactly that
        # box for candidate 0 under zero_offset_candidate, as Open3DSOT's when it has several)
        centre = prev_gt if self.search_center == "previous" else gt
        ref = centre.copy()
        if not (self.zero_offset_candidate and cand == 0 and self.candidates > 1):
            ref[0:2] += self._search_offset(centre, rng)
            ref[6] += rng.normal(0.0, SEARCH_SIGMA_YAW_RAD)
        ref[6] = (ref[6] + math.pi) % (2 * math.pi) - math.pi
        prev[6] = (prev[6] + math.pi) % (2 * math.pi) - math.pi

        first_crop = _crop_stretched(tr.points(0), box0, box0, TEMPLATE_SCALE, 0.0, stretch)
        prev_crop = _crop_stretched(tr.points(t_prev), prev_gt, prev, TEMPLATE_SCALE, 0.0, stretch)
        search_crop = _crop_stretched(
            tr.points(t), gt, ref, self.search_scale, self.search_offset_m, stretch
        )
        own0 = np.array([0, 0, 0, *box0[3:6], 0.0])
        prev_in_own = boxes_in_frame(prev_gt, prev)
        search_box = boxes_in_frame(gt, ref)
        template = np.empty((self.template_size, 3), np.float32)
        search = np.empty((self.search_size, 3), np.float32)
        if self.template_union:
            template_labels, centers, m_s = self._union_template(
                first_crop, prev_crop, own0, prev_in_own, search_crop, template, search, rng
            )
        else:
            # resampled as the env's observations are: one call, the template halves in place
            half = self.template_size // 2
            a, b = template[:half], template[half:]
            m_a, m_b, m_s = resample_into([first_crop, prev_crop, search_crop], [a, b, search], rng)
            labels_a = points_in_box(a, own0) & (m_a > 0)
            labels_b = points_in_box(b, prev_in_own) & (m_b > 0)
            template_labels = np.concatenate([labels_a, labels_b]).astype(np.float32)
            centers = np.zeros((self.template_size, 3), np.float32)
            centers[half:] = prev_in_own[:3]
        search_labels = points_in_box(search, search_box) & (m_s > 0)
        motion = offset_between(boxes[t - 2], prev_gt) if t >= 2 else np.zeros(4)

        f32 = torch.float32
        sample = {
            "template": torch.from_numpy(template),
            "search": torch.from_numpy(search),
            "size": torch.as_tensor(box0[3:6], dtype=f32),
            "motion": torch.as_tensor(motion, dtype=f32),
            "search_box": torch.as_tensor(search_box, dtype=f32),
            "search_labels": torch.from_numpy(search_labels.astype(np.float32)),
            "template_centers": torch.from_numpy(centers),
            "template_labels": torch.from_numpy(template_labels),
            "index": torch.tensor(int(index), dtype=torch.int64),
        }
        return sample, len(first_crop) + len(prev_crop), len(search_crop)

    def _union_template(
        self,
        first_crop: np.ndarray,
        prev_crop: np.ndarray,
        own0: np.ndarray,
        prev_in_own: np.ndarray,
        search_crop: np.ndarray,
        template: np.ndarray,
        search: np.ndarray,
        rng: np.random.Generator,
    ) -> tuple[np.ndarray, np.ndarray, int]:
        """Fill ``template`` from the union of the two template crops (first, then previous:
        the env's merge order) and ``search``; each union point carries its label and its
        crop's target centre through the resampling. Returns the template labels ``(T,)``,
        centres ``(T, 3)`` and the search crop's point count."""
        parts = []
        for crop, box in ((first_crop, own0), (prev_crop, prev_in_own)):
            part = np.empty((len(crop), 7), np.float32)
            part[:, :3] = crop
            part[:, 3] = points_in_box(crop, box)
            part[:, 4:] = box[:3]
            parts.append(part)
        union = np.concatenate(parts)
        rich = np.empty((self.template_size, 7), np.float32)
        _, m_s = resample_into([union, search_crop], [rich, search], rng)
        template[:] = rich[:, :3]
        return np.ascontiguousarray(rich[:, 3]), np.ascontiguousarray(rich[:, 4:]), m_s


BATCH_KEYS = ("template", "search", "size", "motion")
TARGET_KEYS = ("search_box", "search_labels", "template_centers", "template_labels")


def split_batch(
    sample: dict[str, torch.Tensor],
    device: str | torch.device = "cpu",
    batch_keys: Sequence[str] = BATCH_KEYS,
    target_keys: Sequence[str] = TARGET_KEYS,
):
    """A collated sample dict -> ``(batch, targets, indices)`` on ``device`` (the keys of the
    sample recipe: these samples' by default)."""
    batch = {k: sample[k].to(device) for k in batch_keys}
    targets = {k: sample[k].to(device) for k in target_keys}
    return batch, targets, sample["index"]


def load_tracklets(
    dataset: str,
    split: str,
    *,
    setting: str | None = None,
    category: str | None = None,
    preset: str = "default",
    sensor: str = "hdl64",
    world_seed: int = 0,
    data_root: str | None = None,
    trained_only: bool = True,
    version: str | None = None,
    nuscenes_frame: str = "lidar",
):
    """Tracklets of a split: the observed categories of ``setting`` (class-agnostic) or the one
    ``category`` (class-specific); ``trained_only=False`` keeps the unseen ones too (validation).

    ``dataset="nuscenes"`` reads the nuScenes layout (``data_root``, or the synthetic world in
    that layout) with ``split`` a role mapped by ``envs.data.nuscenes.SOT_SPLITS`` and
    ``version`` the table folder and ``nuscenes_frame`` the LiDAR frame served (``"lidar"`` or
    ``"scene"``, :class:`envs.data.nuscenes.NuScenesTracking`); other datasets refuse ``"scene"``.

    Returns ``(tracklets, categories, root)``; raises ``ValueError`` when none are found.
    """
    from envs.data import KittiTracking, class_specific, get_setting
    from envs.data.nuscenes import SOT_SPLITS, NuScenesTracking, check_frame
    from envs.data.settings import check_setting_layout

    st = class_specific(category) if category else get_setting(setting)
    check_setting_layout(st, "nuscenes" if dataset == "nuscenes" else "kitti")
    cats = st.observed if trained_only else st.categories
    check_frame(nuscenes_frame, dataset)
    if dataset == "nuscenes":
        if data_root:
            root, version = data_root, version or "v1.0-trainval"
        else:
            from envs.synthetic.nuscenes_layout import DEFAULT_VERSION, ensure_nuscenes_world

            version = version or DEFAULT_VERSION
            root = str(ensure_nuscenes_world(preset, sensor, world_seed, version))
        data = NuScenesTracking(root, version, SOT_SPLITS[split], list(cats), frame=nuscenes_frame)
    elif data_root:
        root = data_root
    elif dataset == "synthetic":
        from envs.synthetic import ensure_world

        root = str(ensure_world(preset=preset, sensor=sensor, seed=world_seed))
    else:
        raise ValueError("dataset=kitti needs data_root")
    if dataset != "nuscenes":
        data = KittiTracking(root, split=split, categories=list(cats))
    tracklets = [tr for tr in data.tracklets if len(tr) >= 2]
    missing = sorted(set(st.observed) - {tr.category for tr in tracklets})
    if missing:  # training on part of a setting's observed categories would be another setting
        raise ValueError(
            f"setting {st.name!r}: the {split} split of {root} has no tracklets of observed "
            f"{', '.join(missing)} (of {', '.join(st.observed)})"
        )
    return tracklets, st, root
