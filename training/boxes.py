"""Per-frame results of ``pointtrack eval --save-boxes``, re-scoring, and ``pointtrack compare``.

Files (under ``OUT/boxes/``; the schema is documented in docs/evaluation.md):

* ``TRACKER.jsonl`` — one JSON object per frame, every tracklet, every eval seed::

      {"tracker": str, "seed": int, "tracklet": "0019/3", "category": "Car",
       "observed": bool, "frame": int, "pred": [x, y, z, l, w, h, yaw],
       "gt": [x, y, z, l, w, h, yaw], "iou": float, "center_error": float (m),
       "target_points": int | null}

  Boxes in the LiDAR frame of their frame, geometric centre (``docs/design.md``
  conventions); ``frame`` counts from the tracklet's first frame (0: the given box, IoU 1,
  error 0, ``target_points`` null). Floats are written exactly (``repr``).
* ``TRACKER/seedS/SCENE_ID.txt`` — one result file per tracklet, one line per frame from
  frame 0: ``frame h w l x y z ry``, KITTI label box fields (dimensions, location of the
  bottom centre, rotation) in the LiDAR frame: ``(x, y, z)`` the bottom-face centre
  (``z = z_centre - h / 2``), ``ry`` the yaw about +z (counter-clockwise from +x, radians).

:func:`rescore` recomputes OPE from a ``.jsonl`` exactly as ``evaluate`` did (the same arrays,
so the same Success / Precision to the last bit); :func:`read_result_file` parses a tracklet's
file back to ``(T, 7)`` boxes; :func:`compare_runs` lists the tracklets where two eval output
directories differ most.
"""

from __future__ import annotations

import json
import math
import os
import shutil
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

import numpy as np

from training.reporting import slug
from training.rundir import atomic_write_text

__all__ = [
    "compare_runs",
    "format_comparison",
    "read_boxes",
    "read_result_file",
    "rescore",
    "save_boxes",
]


def save_boxes(
    per_seed: Mapping[int, Sequence[Mapping[str, Any]]],
    name: str,
    out_dir: str | Path,
    observed: Mapping[str, bool],
) -> Path:
    """Write one tracker's boxes (``{seed: report["boxes"]}`` of ``evaluate(...,
    record_boxes=True)``) as ``out_dir/NAME.jsonl`` and its per-tracklet result files; each
    written to a temporary name and renamed, so a killed run leaves no half file. Returns the
    ``.jsonl`` path."""
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    tmp_dir = out / f".{slug(name)}.tmp{os.getpid()}"
    shutil.rmtree(tmp_dir, ignore_errors=True)
    lines = []
    for seed, tracklets in per_seed.items():
        seed_dir = tmp_dir / f"seed{int(seed)}"
        seed_dir.mkdir(parents=True)
        for t in tracklets:
            head = {"tracker": name, "seed": int(seed), "tracklet": t["tracklet"]}
            head |= {"category": t["category"], "observed": bool(observed[t["category"]])}
            lines += [json.dumps(head | f) for f in t["frames"]]
            text = "".join(_result_line(f) + "\n" for f in t["frames"])
            (seed_dir / f"{slug(str(t['tracklet']))}.txt").write_text(text)
    final_dir = out / slug(name)
    shutil.rmtree(final_dir, ignore_errors=True)
    os.replace(tmp_dir, final_dir)
    return atomic_write_text(out / f"{slug(name)}.jsonl", "".join(line + "\n" for line in lines))


def _result_line(frame: Mapping[str, Any]) -> str:
    """``frame h w l x y z ry`` of a frame's predicted box (bottom centre, LiDAR frame)."""
    x, y, z, length, width, height, yaw = (float(v) for v in frame["pred"])
    fields = (height, width, length, x, y, z - height / 2.0, yaw)
    return f"{int(frame['frame'])} " + " ".join(repr(v) for v in fields)


def read_result_file(path: str | Path) -> tuple[np.ndarray, np.ndarray]:
    """A per-tracklet result file -> ``(frames (T,) int, boxes (T, 7) float64)`` in the
    project's box convention (geometric centre; equal to the saved boxes to float rounding,
    ~1e-15 m from the bottom-centre shift). ``ValueError`` names the file and line."""
    frames, boxes = [], []
    for number, line in enumerate(Path(path).read_text().splitlines(), 1):
        parts = line.split()
        try:
            if len(parts) != 8:
                raise ValueError(f"{len(parts)} fields, expected 8 (frame h w l x y z ry)")
            height, width, length, x, y, z_bottom, yaw = (float(v) for v in parts[1:])
            frames.append(int(parts[0]))
        except ValueError as exc:
            raise ValueError(f"{path}:{number}: {exc}") from None
        boxes.append((x, y, z_bottom + height / 2.0, length, width, height, yaw))
    return np.array(frames, dtype=np.int64), np.array(boxes, dtype=np.float64).reshape(-1, 7)


def read_boxes(path: str | Path) -> list[dict[str, Any]]:
    """The records of a ``.jsonl`` box file (``ValueError`` naming the file and line)."""
    records = []
    with open(path) as f:
        for number, line in enumerate(f, 1):
            try:
                records.append(json.loads(line))
            except json.JSONDecodeError as exc:
                raise ValueError(f"{path}:{number}: not JSON ({exc.msg})") from None
    return records


def rescore(path: str | Path, seed: int | None = None) -> dict[str, Any]:
    """OPE recomputed from a ``.jsonl`` box file (one ``seed``; default: the file's only one):
    ``{"categories": {cat: entry}, "observed", "unseen", "mean"}`` as in an eval report."""
    from envs.metrics import OPEAccumulator

    records = read_boxes(path)
    seeds = sorted({r["seed"] for r in records})
    if seed is None:
        if len(seeds) != 1:
            raise ValueError(f"{path} holds eval seeds {seeds}: pass seed=")
        seed = seeds[0]
    by_tracklet: dict[str, list[dict[str, Any]]] = {}
    for r in records:
        if r["seed"] == seed:
            by_tracklet.setdefault(r["tracklet"], []).append(r)
    acc = OPEAccumulator()
    for tracklet, frames in by_tracklet.items():
        frames.sort(key=lambda r: r["frame"])
        ious = [r["iou"] for r in frames]
        errors = [r["center_error"] for r in frames]
        first = frames[0]
        acc.add(
            tracklet, first["category"], first["observed"], ious, errors, first_frame_included=True
        )
    return acc.report(curves=False)


def _load_report(run_dir: str | Path, tracker: str | None) -> tuple[str, dict[str, Any]]:
    """``(name, report)`` of one tracker in ``run_dir/report.json`` (``tracker`` may be left
    out when the run evaluated one tracker)."""
    path = Path(run_dir) / "report.json"
    if not path.is_file():
        raise FileNotFoundError(f"{path}: no eval report (run pointtrack eval --out {run_dir})")
    reports = json.loads(path.read_text())
    if tracker is None:
        if len(reports) != 1:
            raise ValueError(f"{path} holds trackers {sorted(reports)}: name one")
        tracker = next(iter(reports))
    if tracker not in reports:
        raise ValueError(f"{path} has no tracker {tracker!r}; it has {sorted(reports)}")
    return tracker, reports[tracker]


def compare_runs(
    run_a: str | Path,
    run_b: str | Path,
    *,
    tracker_a: str | None = None,
    tracker_b: str | None = None,
) -> dict[str, Any]:
    """Per-tracklet differences between two ``pointtrack eval --out`` directories.

    Returns ``{"a": name, "b": name, "rows": [...]}``, rows sorted by ``|b - a|`` Success,
    largest first (ties by tracklet id): ``{"tracklet", "category", "frames", "success_a",
    "success_b", "delta_success", "precision_a", "precision_b", "delta_precision"}``. Tracklets
    in one run only are refused (``ValueError`` listing a few): the runs must cover the same.
    """
    name_a, rep_a = _load_report(run_a, tracker_a)
    name_b, rep_b = _load_report(run_b, tracker_b)
    rows_a = {r["tracklet"]: r for r in rep_a["per_tracklet"]}
    rows_b = {r["tracklet"]: r for r in rep_b["per_tracklet"]}
    only = sorted(set(rows_a) ^ set(rows_b))
    if only:
        raise ValueError(
            f"the runs cover different tracklets ({len(only)} in one only, e.g. {only[:3]})"
        )
    rows = []
    for tracklet, a in rows_a.items():
        b = rows_b[tracklet]
        row = {"tracklet": tracklet, "category": a["category"], "frames": a["frames"]}
        for key in ("success", "precision"):
            row |= {f"{key}_a": a[key], f"{key}_b": b[key], f"delta_{key}": _delta(a, b, key)}
        rows.append(row)
    rows.sort(key=lambda r: (-abs(r["delta_success"]), -abs(r["delta_precision"]), r["tracklet"]))
    return {"a": f"{run_a}:{name_a}", "b": f"{run_b}:{name_b}", "rows": rows}


def _delta(a: Mapping[str, Any], b: Mapping[str, Any], key: str) -> float:
    if a[key] is None or b[key] is None:
        return math.nan
    return float(b[key]) - float(a[key])


def format_comparison(comparison: Mapping[str, Any], top: int = 15) -> str:
    """The ``top`` rows of :func:`compare_runs` as a text table."""
    rows = comparison["rows"][:top]
    idw = max(8, *(len(str(r["tracklet"])) for r in rows)) if rows else 8
    lines = [
        f"A = {comparison['a']}",
        f"B = {comparison['b']}",
        f"{'tracklet':<{idw}} {'category':<10} {'frames':>6} | "
        f"{'Succ A':>6} {'Succ B':>6} {'B - A':>6} | {'Prec A':>6} {'Prec B':>6} {'B - A':>6}",
    ]
    for r in rows:
        lines.append(
            f"{r['tracklet']:<{idw}} {r['category']:<10} {r['frames']:>6} | "
            f"{r['success_a']:6.1f} {r['success_b']:6.1f} {r['delta_success']:+6.1f} | "
            f"{r['precision_a']:6.1f} {r['precision_b']:6.1f} {r['delta_precision']:+6.1f}"
        )
    lines.append(f"{len(comparison['rows'])} tracklets; the {len(rows)} that differ most shown")
    return "\n".join(lines)
