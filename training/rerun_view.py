"""A 3D view of episodes: a rerun recording (``.rrd``) to open with ``rerun x.rrd``.

:func:`write_recording` logs, on the timeline ``frame`` (the tracklet's frame index ``t``), in the
LiDAR frame of each frame (x forward, y left, z up, metres):

========================================  ======================================================
entity                                    what
========================================  ======================================================
``world/scan/clean``                      the whole scan ``(N, 3)`` (grey, frames ``0 .. S``)
``world/scan/weather``                    the scan the trackers saw under ``--weather`` (orange;
                                          only with weather: toggle it against ``clean``)
``world/ground_truth``                    the true box (green)
``world/trackers/NAME/prediction``        each tracker's predicted box (frame 0: the given box)
``world/trackers/NAME/search``            the search crop the tracker was given ``(1024, 3)``
``metrics/NAME/iou``                      3D IoU of the prediction per frame
``metrics/NAME/center_error``             centre distance per frame, m
``metrics/NAME/target_points``            points of the scan in the true box
``episode``                               a text document: tracklet, category, weather
========================================  ======================================================

The trackers expose no per-frame confidence, so the "score" logged is the IoU and the centre
error. Needs the optional ``viewer`` extra (rerun-sdk).
"""

from __future__ import annotations

import json
import os
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any

import numpy as np

from training.video import EpisodeTrace

__all__ = ["TIMELINE", "read_entities", "write_recording"]

TIMELINE = "frame"
# distinct colours for up to six trackers side by side (then they repeat)
TRACKER_COLORS = (
    (230, 40, 40),
    (70, 110, 255),
    (240, 200, 40),
    (200, 80, 220),
    (40, 210, 210),
    (255, 140, 60),
)


def _rerun() -> Any:
    from training.extras import require

    return require("rerun", "viewer", "the rerun 3D view")


def _boxes(rr: Any, boxes: np.ndarray, color: tuple[int, int, int], label: str) -> Any:
    """``rr.Boxes3D`` of ``boxes (K, 7)`` (x, y, z, l, w, h, yaw): centres, sizes, yaw about z."""
    boxes = np.asarray(boxes, np.float64).reshape(-1, 7)
    return rr.Boxes3D(
        centers=boxes[:, :3],
        half_sizes=boxes[:, 3:6] / 2.0,
        rotation_axis_angles=[rr.RotationAxisAngle(axis=(0, 0, 1), radians=y) for y in boxes[:, 6]],
        colors=[color] * len(boxes),
        labels=[label] * len(boxes),
    )


def write_recording(
    traces: Sequence[EpisodeTrace],
    tracklet: Any,
    path: str | Path,
    *,
    scan_transform: Callable[[np.ndarray, str, int], np.ndarray] | None = None,
) -> Path:
    """Write the episodes ``traces`` (one per tracker, all on ``tracklet``) as a rerun recording
    at ``path`` (atomically) and return the path. The entities are listed in the module docstring.

    Args:
        traces: from :func:`training.video.run_episode`, the same tracklet and frames.
        tracklet: the ``envs.data.Tracklet`` they ran on (its scans and boxes).
        path: the ``.rrd`` file to write.
        scan_transform: the env's weather hook (``envs.weather.WeatherTransform``) the episodes
            ran under, if any: the corrupted scan is logged beside the clean one.
    """
    rr = _rerun()
    path = Path(path)
    if path.suffix.lower() != ".rrd":
        raise ValueError(f"rerun recording {path}: the suffix must be .rrd")
    if not traces:
        raise ValueError("write_recording: no episode to log")
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(f".{path.stem}.tmp{os.getpid()}.rrd")
    # the same content for the same episodes; not the same bytes (rerun's chunk ids are unique)
    rec = rr.RecordingStream("pointtrack", recording_id=f"{traces[0].tracklet}")
    try:
        rec.save(tmp)
        _log_episodes(rr, rec, traces, tracklet, scan_transform)
        rec.flush()
        rec.disconnect()
        os.replace(tmp, path)
    finally:
        tmp.unlink(missing_ok=True)
    return path


def _log_episodes(rr, rec, traces, tracklet, scan_transform) -> None:
    first = traces[0]
    weather = first.weather
    header = {"tracklet": first.tracklet, "category": first.category, "weather": weather}
    rec.log(
        "episode",
        rr.TextDocument(json.dumps(header, indent=1), media_type="text/markdown"),
        static=True,
    )
    frames = [0, *first.frames]
    for k, t in enumerate(frames):
        rec.set_time(TIMELINE, sequence=t)
        scan = tracklet.points_with_intensity(t)
        rec.log("world/scan/clean", rr.Points3D(scan[:, :3], colors=(170, 170, 170), radii=0.03))
        if scan_transform is not None:
            seen = scan_transform(scan, str(tracklet.tracklet_id), int(tracklet.frames[t]))
            rec.log(
                "world/scan/weather", rr.Points3D(seen[:, :3], colors=(255, 150, 40), radii=0.03)
            )
        rec.log("world/ground_truth", _boxes(rr, tracklet.boxes[t], (40, 200, 40), "truth"))
        for j, trace in enumerate(traces):
            color = TRACKER_COLORS[j % len(TRACKER_COLORS)]
            base = f"world/trackers/{trace.tracker}"
            box = trace.init_box if k == 0 else trace.pred_boxes[k - 1]
            rec.log(f"{base}/prediction", _boxes(rr, box, color, trace.tracker))
            if k == 0:
                continue
            rec.log(f"{base}/search", rr.Points3D(trace.search[k - 1], colors=color, radii=0.05))
            metrics = f"metrics/{trace.tracker}"
            rec.log(f"{metrics}/iou", rr.Scalars(trace.ious[k - 1]))
            rec.log(f"{metrics}/center_error", rr.Scalars(trace.center_errors[k - 1]))
            rec.log(f"{metrics}/target_points", rr.Scalars(float(trace.target_points[k - 1])))


def read_entities(path: str | Path) -> dict[str, int]:
    """``{entity path: rows logged}`` of a rerun recording (rerun's own reader); the
    recording's properties (``/__properties``) are left out."""
    _rerun()
    from rerun.chunk import RrdReader

    counts: dict[str, int] = {}
    for chunk in RrdReader(str(path)).stream():
        entity = str(chunk.entity_path)
        if entity.startswith("/__"):
            continue
        counts[entity] = counts.get(entity, 0) + int(chunk.num_rows)
    return counts
