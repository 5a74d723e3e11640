"""The KITTI tracking layout: labels, scans, and the tracklet loader (calibration and the box
conversions: :mod:`envs.data.kitti_calib`, re-exported here).

Layout under ``root`` (the KITTI tracking *training* folder, or a synthetic world)::

    label_02/SSSS.txt        one labelled object per line (17 fields, see :class:`LabelRow`)
    calib/SSSS.txt           P0..P3, R0_rect, Tr_velo_to_cam (object-style or raw tracking keys)
    velodyne/SSSS/FFFFFF.bin float32 (x, y, z, intensity) per point, LiDAR frame

Frames. Labels live in the rectified camera-0 frame (x right, y down, z forward; ``(x, y, z)`` is
the *bottom* centre, ``rotation_y`` is about the camera's y axis). A LiDAR point ``p`` maps to the
rectified camera frame by ``R0_rect @ (Tr_velo_to_cam[:, :3] @ p + Tr_velo_to_cam[:, 3])``; we go
through both matrices (Open3DSOT drops ``R0_rect``; we don't). A converted box has
``(x, y, z)`` = the LiDAR image of the bottom centre lifted by ``h / 2`` along LiDAR +z, size
``(l, w, h)``, and ``yaw`` = the angle about LiDAR +z of the LiDAR image of the camera heading
vector ``(cos ry, 0, -sin ry)``, wrapped to ``[-pi, pi)``.

Errors. Every file error names the file (and the line, for labels). Non-finite scan points are
dropped and counted: :func:`read_scan` emits a :class:`NonFinitePointsWarning` naming the file
and the count (``return_dropped=True`` also returns the count).
"""

from __future__ import annotations

import math
import warnings
from collections.abc import Iterable, Sequence
from pathlib import Path
from typing import NamedTuple

import numpy as np

from envs.data.kitti_calib import (
    BOX_CONVENTIONS,
    Calibration,
    camera_to_lidar_boxes,
    camera_to_open3dsot_boxes,
    lidar_to_camera_boxes,
    read_calibration,
    write_calibration,
)
from envs.data.tracklet import ScanCache, Tracklet, check_categories
from envs.geometry import wrap_yaw

__all__ = [
    "CATEGORIES",
    "SPLITS",
    "Calibration",
    "KittiTracking",
    "LabelRow",
    "MissingScanWarning",
    "MissingSceneWarning",
    "NonFinitePointsWarning",
    "SceneScans",
    "BOX_CONVENTIONS",
    "camera_to_lidar_boxes",
    "camera_to_open3dsot_boxes",
    "declare_scenes",
    "expected_scenes",
    "label_path",
    "lidar_to_camera_boxes",
    "read_calibration",
    "read_labels",
    "read_scan",
    "scan_path",
    "write_calibration",
    "write_labels",
    "write_scan",
]

# Scene numbers of each split (the standard KITTI tracking split of P2B / BAT / Open3DSOT).
SPLITS: dict[str, range | None] = {
    "train": range(0, 17),
    "val": range(17, 19),
    "test": range(19, 21),
    "all": None,
}

# Category names a loader accepts: KITTI spelling plus the nuScenes-style extras.
CATEGORIES: tuple[str, ...] = (
    "Car",
    "Van",
    "Truck",
    "Pedestrian",
    "Person_sitting",
    "Cyclist",
    "Tram",
    "Misc",
    "Bus",
    "Bicycle",
    "Motorcycle",
    "Trailer",
)


class NonFinitePointsWarning(RuntimeWarning):
    """A scan held NaN/inf points; they were dropped (the message names the file and count)."""


# --------------------------------------------------------------------------- labels


class LabelRow(NamedTuple):
    """One row of a KITTI tracking label file (17 fields, in file order)."""

    frame: int
    track_id: int
    type: str
    truncated: float
    occluded: int
    alpha: float
    bbox_left: float
    bbox_top: float
    bbox_right: float
    bbox_bottom: float
    height: float
    width: float
    length: float
    x: float
    y: float
    z: float
    rotation_y: float

    @property
    def hwl_xyz_ry(self) -> tuple[float, ...]:
        """``[h, w, l, x, y, z, ry]`` (the input of :func:`camera_to_lidar_boxes`)."""
        return (self.height, self.width, self.length, self.x, self.y, self.z, self.rotation_y)

    @classmethod
    def from_box(
        cls,
        frame: int,
        track_id: int,
        category: str,
        hwl_xyz_ry: Sequence[float],
        *,
        truncated: float = 0.0,
        occluded: int = 0,
        alpha: float | None = None,
        bbox: Sequence[float] = (-1.0, -1.0, -1.0, -1.0),
    ) -> LabelRow:
        """Row from a camera box ``[h, w, l, x, y, z, ry]``; ``alpha`` defaults to the KITTI
        observation angle ``ry - atan2(x, z)`` wrapped to ``[-pi, pi)``."""
        h, w, length, x, y, z, ry = (float(v) for v in hwl_xyz_ry)
        if alpha is None:
            alpha = float(wrap_yaw(ry - math.atan2(x, z)))
        left, top, right, bottom = (float(v) for v in bbox)
        return cls(
            int(frame),
            int(track_id),
            str(category),
            float(truncated),
            int(occluded),
            float(alpha),
            left,
            top,
            right,
            bottom,
            h,
            w,
            length,
            x,
            y,
            z,
            ry,
        )


_INT_FIELDS = (0, 1, 4)  # frame, track_id, occluded


def _parse_label_line(line: str, path: Path, lineno: int) -> LabelRow:
    """Strict parse of one row; errors name the file, line and field."""
    parts = line.split()
    if len(parts) != 17:
        raise ValueError(f"label file {path}, line {lineno}: expected 17 fields, got {len(parts)}")
    values: list = []
    for i, text in enumerate(parts):
        if i == 2:
            values.append(text)
            continue
        name = LabelRow._fields[i]
        try:
            value = float(text)
        except ValueError:
            raise ValueError(
                f"label file {path}, line {lineno}: field {i + 1} ({name}) "
                f"is not a number: {text!r}"
            ) from None
        if not math.isfinite(value):
            raise ValueError(f"label file {path}, line {lineno}: field {i + 1} ({name}) is {text}")
        if i in _INT_FIELDS:
            if value != int(value):
                raise ValueError(
                    f"label file {path}, line {lineno}: field {i + 1} ({name}) "
                    f"is not an integer: {text!r}"
                )
            value = int(value)
        values.append(value)
    return LabelRow(*values)


class _LabelTable(NamedTuple):
    """Column view of a label file: ``frame (N,)``, ``track_id (N,)`` int64, ``type`` list of
    str, ``values (N, 17)`` float64 (columns in :class:`LabelRow` order, ``type`` column NaN)."""

    frame: np.ndarray
    track_id: np.ndarray
    type: list[str]
    values: np.ndarray


def _read_label_table(path: Path) -> _LabelTable:
    try:
        text = path.read_text()
    except OSError as exc:
        raise FileNotFoundError(f"cannot read label file {path}: {exc}") from exc
    lines = text.splitlines()
    n_rows = sum(map(bool, map(str.strip, lines)))
    tokens = text.split()
    values = None
    types = tokens[2::17]
    # Fast path: one flat parse. A row with a wrong field count that another row compensates
    # would shift a type name into a numeric column (or a number into the type column), which
    # the checks below catch; anything odd falls back to the strict per-line parse.
    if len(tokens) == 17 * n_rows and all(t[:1].isalpha() for t in types):
        tokens[2::17] = ["nan"] * n_rows
        try:
            values = np.array(tokens, dtype=np.float64).reshape(n_rows, 17)
        except ValueError:
            values = None
        else:
            ints = values[:, _INT_FIELDS]
            numeric = np.delete(values, 2, axis=1)
            if not (np.isfinite(numeric).all() and np.array_equal(ints, np.round(ints))):
                values = None
    if values is None:  # slow path: find the offending line and name it
        for lineno, line in enumerate(lines, 1):
            if line.strip():
                _parse_label_line(line, path, lineno)
        raise ValueError(f"label file {path}: cannot be parsed")  # pragma: no cover
    _check_box_sizes(path, lines, types, values)
    return _LabelTable(values[:, 0].astype(np.int64), values[:, 1].astype(np.int64), types, values)


def _check_box_sizes(path: Path, lines: list[str], types: list[str], values: np.ndarray) -> None:
    """Refuse a labelled object (not ``DontCare``, whose sizes are ``-1`` by convention) with a
    box height, width or length that is not positive, naming the file, line and field."""
    sizes = values[:, 10:13]
    care = np.array([t != "DontCare" for t in types], dtype=bool)
    bad = np.flatnonzero(care & (sizes <= 0).any(axis=1))
    if not len(bad):
        return
    row = int(bad[0])
    lineno = [i for i, line in enumerate(lines, 1) if line.strip()][row]
    col = int(np.flatnonzero(sizes[row] <= 0)[0])
    name = LabelRow._fields[10 + col]
    raise ValueError(
        f"label file {path}, line {lineno}: field {11 + col} ({name}) is {sizes[row, col]:g}; "
        f"a {types[row]} box needs a positive height, width and length"
        + (f" ({len(bad) - 1} more such rows)" if len(bad) > 1 else "")
    )


def read_labels(path: str | Path) -> list[LabelRow]:
    """All rows of a KITTI tracking label file (DontCare included), in file order.

    Raises ``ValueError`` naming the file and line for a row with the wrong number of fields or a
    field that is not a (finite) number (or not an integer for frame, track id and occluded);
    ``FileNotFoundError`` naming the file when it is missing.
    """
    table = _read_label_table(Path(path))
    out = []
    for i, row in enumerate(table.values.tolist()):
        row[0], row[1], row[2], row[4] = int(row[0]), int(row[1]), table.type[i], int(row[4])
        out.append(LabelRow(*row))
    return out


def write_labels(path: str | Path, rows: Iterable[Sequence]) -> None:
    """Write rows of 17 fields (``LabelRow`` or any 17-sequence in :class:`LabelRow` order)."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    lines = []
    for i, row in enumerate(rows):
        row = tuple(row)
        if len(row) != 17:
            raise ValueError(f"label row {i} for {path} has {len(row)} fields, expected 17")
        r = LabelRow(*row)
        if not all(math.isfinite(float(v)) for v in (r[0], r[1], r[3], *r[4:])):
            raise ValueError(f"label row {i} for {path} has a non-finite field: {row}")
        if not str(r.type) or any(ch.isspace() for ch in str(r.type)):
            raise ValueError(f"label row {i} for {path}: bad type {r.type!r}")
        lines.append(
            f"{int(r.frame)} {int(r.track_id)} {r.type} {float(r.truncated):g} {int(r.occluded)} "
            + " ".join(repr(float(v)) for v in r[5:])
        )
    path.write_text("".join(line + "\n" for line in lines))


# --------------------------------------------------------------------------- scans


def read_scan(
    path: str | Path, *, return_dropped: bool = False
) -> np.ndarray | tuple[np.ndarray, int]:
    """Read a ``.bin`` scan -> ``(N, 4)`` float32 (x, y, z in metres, intensity).

    Points with any non-finite value are dropped; when there are any, a
    :class:`NonFinitePointsWarning` names the file and the count. With ``return_dropped=True``
    returns ``(points, n_dropped)``. A size that is not a multiple of 16 bytes raises
    ``ValueError`` naming the file; a missing file raises ``FileNotFoundError`` naming it.
    """
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"scan file {path} not found")
    size = path.stat().st_size
    if size % 16:
        raise ValueError(
            f"scan file {path}: size {size} bytes is not a multiple of 16 "
            "(x, y, z, intensity float32)"
        )
    points, dropped = finite_rows(
        np.fromfile(path, dtype="<f4").reshape(-1, 4), f"scan file {path}"
    )
    points = points.astype(np.float32, copy=False)
    return (points, dropped) if return_dropped else points


def finite_rows(points: np.ndarray, where: str) -> tuple[np.ndarray, int]:
    """``points (N, C)`` without its rows holding a non-finite value, and their count; a
    :class:`NonFinitePointsWarning` starting with ``where`` when there are any (the scan
    readers' check: a flat test first, ~25x cheaper than the per-row mask it rarely needs)."""
    if np.isfinite(points).all():
        return points, 0
    finite = np.isfinite(points).all(axis=1)
    dropped = int(len(points) - np.count_nonzero(finite))
    warnings.warn(
        f"{where}: dropped {dropped} non-finite points", NonFinitePointsWarning, stacklevel=3
    )
    return points[finite], dropped


def write_scan(path: str | Path, points: np.ndarray) -> None:
    """Write ``(N, 4)`` points (x, y, z, intensity) as little-endian float32; ``(N, 3)`` gets zero
    intensity. Non-finite points raise ``ValueError`` (never written)."""
    path = Path(path)
    pts = np.asarray(points, dtype=np.float32)
    if pts.ndim != 2 or pts.shape[1] not in (3, 4):
        raise ValueError(f"points for {path} must have shape (N, 3) or (N, 4); got {pts.shape}")
    if not np.isfinite(pts).all():
        raise ValueError(f"points for {path} contain non-finite values")
    if pts.shape[1] == 3:
        pts = np.concatenate([pts, np.zeros((len(pts), 1), np.float32)], axis=1)
    path.parent.mkdir(parents=True, exist_ok=True)
    np.ascontiguousarray(pts, dtype="<f4").tofile(path)


# --------------------------------------------------------------------------- the loader


def label_path(root: str | Path, scene: str) -> Path:
    """``root/label_02/SSSS.txt``."""
    return Path(root) / "label_02" / f"{scene}.txt"


def scan_path(root: str | Path, scene: str, frame: int) -> Path:
    """``root/velodyne/SSSS/FFFFFF.bin``."""
    return Path(root) / "velodyne" / scene / f"{int(frame):06d}.bin"


class MissingScanWarning(RuntimeWarning):
    """A labelled frame has no scan and ``missing_scans="empty"`` gave an empty one instead."""


class SceneScans:
    """Picklable scan loader of one scene: frame index -> ``(N, 4)`` float32 whole scan.

    ``missing="raise"`` (default): a missing ``.bin`` raises ``FileNotFoundError`` naming the
    scene, frame and file. ``missing="empty"``: it gives a ``(0, 4)`` scan and a
    :class:`MissingScanWarning` instead (the original KITTI sequence 0001 lacks frames 177-180).
    """

    def __init__(self, root: str | Path, scene: str, missing: str = "raise") -> None:
        if missing not in ("raise", "empty"):
            raise ValueError(f"missing must be 'raise' or 'empty'; got {missing!r}")
        self.root = Path(root)
        self.scene = scene
        self.missing = missing

    def __call__(self, frame: int) -> np.ndarray:
        path = scan_path(self.root, self.scene, frame)
        if not path.is_file():
            message = f"KITTI scene {self.scene} frame {int(frame)}: scan file {path} is missing"
            if self.missing == "raise":
                raise FileNotFoundError(message)
            warnings.warn(f"{message}; using an empty scan", MissingScanWarning, stacklevel=2)
            return np.zeros((0, 4), np.float32)
        return read_scan(path)

    def __repr__(self) -> str:
        return f"SceneScans({str(self.root)!r}, {self.scene!r}, missing={self.missing!r})"


class MissingSceneWarning(RuntimeWarning):
    """A split named scenes whose label files are missing; they were skipped on request."""


def expected_scenes(root: str | Path, split: str) -> list[str] | None:
    """Scene names (``"0019"``) that ``split`` needs under ``root``: the scenes the root's
    ``manifest.json`` lists within the split (a synthetic world's ``scene_stats``, or the
    ``scenes`` of :func:`declare_scenes`: such roots may hold a subset of the KITTI scenes), else
    the split's KITTI scene numbers; ``None`` (no expectation) for ``"all"`` without a
    manifest."""
    import json

    scene_range = _check_split(split)
    try:
        manifest = json.loads((Path(root) / "manifest.json").read_text())
        held = manifest["scene_stats"] if "scene_stats" in manifest else manifest["scenes"]
        listed = sorted(str(k) for k in held)
    except (OSError, ValueError, KeyError, TypeError, AttributeError):
        listed = None
    if listed is not None:
        return [s for s in listed if scene_range is None or int(s) in scene_range]
    if scene_range is None:
        return None
    return [f"{i:04d}" for i in scene_range]


def declare_scenes(root: str | Path, scenes: Iterable[str]) -> None:
    """Record in ``root/manifest.json`` that the KITTI-layout root holds ``scenes`` (names such
    as ``"0019"``; merged with any already declared), so that a split needs only those of its
    scenes (:func:`expected_scenes`). For roots written on purpose with a subset of the scenes
    (a toy dataset, a replay of a few scenes)."""
    import json

    path = Path(root) / "manifest.json"
    try:
        manifest = json.loads(path.read_text())
    except (OSError, ValueError):
        manifest = {}
    if "scene_stats" in manifest:
        raise ValueError(f"{path} is a synthetic world's manifest; its scenes are fixed")
    manifest["scenes"] = sorted(set(manifest.get("scenes", [])) | {str(s) for s in scenes})
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(f".{path.name}.tmp")
    tmp.write_text(json.dumps(manifest, indent=2) + "\n")
    tmp.replace(path)


def _check_split(split: str) -> range | None:
    if split not in SPLITS:
        raise ValueError(f"unknown split {split!r}; valid splits: {', '.join(SPLITS)}")
    return SPLITS[split]


class KittiTracking:
    """Tracklets of the KITTI tracking layout (real or synthetic).

    One :class:`~envs.data.tracklet.Tracklet` per ``(scene, track_id)`` of the requested
    categories (DontCare ignored), holding the track's *labelled* frames in increasing order —
    a track that leaves and re-enters the view keeps one tracklet with a gap in ``frames``
    (Open3DSOT does the same; the published frame counts count every labelled row). Boxes are in
    each frame's LiDAR frame (see the module docstring). Construction reads labels and
    calibration only; scans are read lazily through one shared :class:`ScanCache` per scene, and
    a missing scan raises ``FileNotFoundError`` naming scene and frame when that frame is read.

    Args:
        root: folder with ``label_02/``, ``calib/`` and ``velodyne/``.
        split: ``"train"`` (scenes 0–16), ``"val"`` (17–18), ``"test"`` (19–20) or ``"all"``.
            Every scene the split needs (:func:`expected_scenes`: a synthetic world's manifest
            may list a subset) must have a label file, else ``FileNotFoundError`` naming them.
        categories: category names (KITTI spelling), a single name, or ``None`` for every
            category except DontCare.
        cache_size: scans kept per scene.
        missing_scans: ``"raise"`` (default) or ``"empty"``: what reading a labelled frame
            without a scan does (see :class:`SceneScans`).
        allow_missing_scenes: go on without the split's missing scenes, with a
            :class:`MissingSceneWarning` listing them.
        box_convention: ``"lidar"`` (default; physically right, through ``R0_rect``) or
            ``"open3dsot"`` (Open3DSOT's boxes, to compare with published tables; see
            :data:`BOX_CONVENTIONS` and docs/recipe.md).

    Attributes:
        tracklets: list ordered by scene, then track id.
        root: the root folder read.
        split: the split read.
        categories: the categories kept (``None`` = all).
        scenes: the scene names read.
    """

    def __init__(
        self,
        root: str | Path,
        split: str = "all",
        categories: str | Sequence[str] | None = None,
        *,
        cache_size: int = 8,
        missing_scans: str = "raise",
        allow_missing_scenes: bool = False,
        box_convention: str = "lidar",
    ) -> None:
        if box_convention not in BOX_CONVENTIONS:
            raise ValueError(
                f"box_convention must be one of {', '.join(BOX_CONVENTIONS)}; got "
                f"{box_convention!r}"
            )
        self.box_convention = box_convention
        if missing_scans not in ("raise", "empty"):
            raise ValueError(f"missing_scans must be 'raise' or 'empty'; got {missing_scans!r}")
        self.root = Path(root)
        self.split = split
        self.missing_scans = missing_scans
        scene_range = _check_split(split)
        self.categories = check_categories(categories, CATEGORIES, "KITTI")
        label_dir = self.root / "label_02"
        if not label_dir.is_dir():
            raise FileNotFoundError(f"KITTI root {self.root}: no label_02 folder at {label_dir}")
        scenes = sorted(p.stem for p in label_dir.glob("*.txt") if p.stem.isdigit())
        if scene_range is not None:
            scenes = [s for s in scenes if int(s) in scene_range]
        missing = sorted(set(expected_scenes(self.root, split) or ()) - set(scenes))
        if missing:
            names = ", ".join(f"label_02/{s}.txt" for s in missing)
            if not allow_missing_scenes:
                raise FileNotFoundError(
                    f"KITTI root {self.root}: split {split!r} needs scenes {', '.join(missing)} "
                    f"but {names} {'is' if len(missing) == 1 else 'are'} missing (pass "
                    "allow_missing_scenes=True, --allow-missing-scenes, to go on without them)"
                )
            warnings.warn(
                f"KITTI root {self.root}: split {split!r} without its scenes "
                f"{', '.join(missing)} ({names} missing)",
                MissingSceneWarning,
                stacklevel=2,
            )
        self.scenes: list[str] = scenes
        self.tracklets: list[Tracklet] = []
        wanted = None if self.categories is None else set(self.categories)
        for scene in scenes:
            self.tracklets.extend(self._scene_tracklets(scene, wanted, cache_size))

    def _scene_tracklets(
        self, scene: str, wanted: set[str] | None, cache_size: int
    ) -> list[Tracklet]:
        path = label_path(self.root, scene)
        table = _read_label_table(path)
        keep = np.array(
            [t != "DontCare" and (wanted is None or t in wanted) for t in table.type], dtype=bool
        )
        if not keep.any():
            return []
        idx = np.flatnonzero(keep)
        # Sort by (track id, frame); stable so file order breaks ties.
        idx = idx[np.lexsort((table.frame[idx], table.track_id[idx]))]
        calib = read_calibration(self.root / "calib" / f"{scene}.txt")
        cam = table.values[idx][:, [10, 11, 12, 13, 14, 15, 16]]  # h w l x y z ry
        convert = (
            camera_to_open3dsot_boxes
            if self.box_convention == "open3dsot"
            else (camera_to_lidar_boxes)
        )
        boxes = convert(cam, calib)
        frames = table.frame[idx]
        tids = table.track_id[idx]
        same_track = tids[1:] == tids[:-1]
        dup = same_track & (frames[1:] == frames[:-1])
        if dup.any():
            k = int(np.flatnonzero(dup)[0])
            raise ValueError(
                f"label file {path}: track {int(tids[k])} labelled twice in frame {int(frames[k])}"
            )
        starts = np.concatenate([[0], np.flatnonzero(~same_track) + 1, [len(idx)]])
        cache = ScanCache(SceneScans(self.root, scene, self.missing_scans), cache_size)
        out = []
        for a, b in zip(starts[:-1], starts[1:], strict=True):
            track_id = int(tids[a])
            out.append(
                Tracklet(
                    tracklet_id=f"{scene}/{track_id}",
                    scene=scene,
                    track_id=track_id,
                    category=table.type[idx[a]],
                    frames=frames[a:b].copy(),
                    boxes=boxes[a:b].copy(),
                    scans=cache,
                )
            )
        return out

    def __len__(self) -> int:
        return len(self.tracklets)

    def __repr__(self) -> str:
        return (
            f"KittiTracking({str(self.root)!r}, split={self.split!r}, "
            f"categories={self.categories!r}, "
            f"tracklets={len(self.tracklets)})"
        )
