"""Watch what a tracker did: one episode per tracker, rendered frame by frame, as a video.

:func:`run_episode` runs a tracker through one tracklet of a ``TrackingEnv`` made with
``render_mode="rgb_array"`` and keeps, per tracked frame, the env's bird's-eye image
(:func:`envs.render.render_birds_eye`: points grey, reference box blue, ground truth green,
prediction red), the boxes, the IoU and the search crop. :func:`compose_frames` puts several
trackers' episodes side by side under a caption (name, frame, IoU) and :func:`write_video` writes
them as MP4 or GIF (the optional ``video`` extra: imageio, imageio-ffmpeg).

A video has one frame per tracked frame: frames ``1 .. T-1`` of a tracklet of ``T`` frames
(frame 0's box is given), fewer with ``max_steps``.
"""

from __future__ import annotations

import os
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

__all__ = [
    "CAPTION_PX",
    "VIDEO_SUFFIXES",
    "EpisodeTrace",
    "check_tracklet",
    "compose_frames",
    "run_episode",
    "write_video",
]

VIDEO_SUFFIXES = (".mp4", ".gif")
CAPTION_PX = 32  # two text lines; 256 + 32 = 288 keeps MP4 frame sides multiples of 16
CAPTION_BACKGROUND = (0, 0, 0)
CAPTION_TEXT = (235, 235, 235)


@dataclass
class EpisodeTrace:
    """What one tracker did on one tracklet, one entry per tracked frame (``S`` steps).

    Boxes are ``(S, 7)`` ``(x, y, z, l, w, h, yaw)`` in the LiDAR frame (m, rad); ``search`` holds
    each step's search crop ``(1024, 3)`` in the LiDAR frame (m); ``images`` the env's
    ``(H, W, 3)`` uint8 bird's-eye views."""

    tracker: str
    tracklet: str
    category: str
    init_box: np.ndarray
    frames: list[int] = field(default_factory=list)
    scene_frames: list[int] = field(default_factory=list)
    images: list[np.ndarray] = field(default_factory=list)
    ious: list[float] = field(default_factory=list)
    center_errors: list[float] = field(default_factory=list)
    target_points: list[int] = field(default_factory=list)
    pred_boxes: list[np.ndarray] = field(default_factory=list)
    gt_boxes: list[np.ndarray] = field(default_factory=list)
    search: list[np.ndarray] = field(default_factory=list)
    weather: dict[str, Any] | None = None

    def __len__(self) -> int:
        return len(self.frames)


def check_tracklet(env: Any, tracklet: str) -> int:
    """The index of tracklet id ``tracklet`` in ``env`` (a ``TrackingEnv``, possibly wrapped);
    ``ValueError`` listing the valid ids (the first 60) when it holds none of that id."""
    ids = [str(tr.tracklet_id) for tr in env.unwrapped.tracklets]
    if tracklet in ids:
        return ids.index(tracklet)
    shown = ", ".join(ids[:60]) + (f", ... ({len(ids) - 60} more)" if len(ids) > 60 else "")
    raise ValueError(f"unknown tracklet id {tracklet!r}; this env's {len(ids)} tracklets: {shown}")


def run_episode(
    tracker: Any,
    env: Any,
    tracklet: str,
    *,
    name: str,
    seed: int = 0,
    max_steps: int | None = None,
) -> EpisodeTrace:
    """Run ``tracker`` through tracklet id ``tracklet`` of ``env`` and record every step.

    Args:
        tracker: anything with ``act(obs) -> (4,)``.
        env: a ``TrackingEnv`` (possibly wrapped) with ``render_mode="rgb_array"``.
        tracklet: the tracklet id (``ValueError`` listing the valid ones when unknown).
        name: the tracker's name in captions and recordings.
        seed: the episode seed of the point resampling (as ``pointtrack eval --eval-seed``: the
            same seed gives the observations ``eval`` scored).
        max_steps: stop after this many tracked frames (``None``: the whole tracklet).
    """
    from envs.geometry import box_to_world

    u = env.unwrapped
    if u.render_mode != "rgb_array":
        raise ValueError(f"run_episode needs render_mode='rgb_array', not {u.render_mode!r}")
    index = check_tracklet(env, tracklet)
    tr = u.tracklets[index]
    saved, u.episode_seed = u.episode_seed, seed
    try:
        options: dict[str, Any] = {"tracklet": index, "start_frame": 0}
        if max_steps is not None:
            options["max_steps"] = int(max_steps)
        obs, info = env.reset(seed=seed, options=options)
        trace = EpisodeTrace(name, str(tr.tracklet_id), tr.category, info["init_box"].copy())
        while True:
            t = u.current_frame
            search = box_to_world(np.asarray(obs["search"], np.float64), u.reference_box)
            obs, _, terminated, truncated, info = env.step(tracker.act(obs))
            trace.frames.append(t)
            trace.scene_frames.append(int(tr.frames[t]))
            trace.images.append(env.render())
            trace.ious.append(float(info["iou"]))
            trace.center_errors.append(float(info["center_error"]))
            trace.target_points.append(int(info["target_points"]))
            trace.pred_boxes.append(np.asarray(info["pred_box"], np.float64))
            trace.gt_boxes.append(np.asarray(info["gt_box"], np.float64))
            trace.search.append(search.astype(np.float32))
            trace.weather = info.get("weather")
            if terminated or truncated:
                return trace
    finally:
        u.episode_seed = saved


def _caption(image: np.ndarray, lines: Sequence[str]) -> np.ndarray:
    """``image (H, W, 3)`` under a ``CAPTION_PX`` strip holding ``lines`` (Pillow's font)."""
    from PIL import Image, ImageDraw, ImageFont

    strip = Image.new("RGB", (image.shape[1], CAPTION_PX), CAPTION_BACKGROUND)
    draw = ImageDraw.Draw(strip)
    font = ImageFont.load_default()
    for k, line in enumerate(lines):
        draw.text((4, 2 + 15 * k), line, fill=CAPTION_TEXT, font=font)
    return np.concatenate([np.asarray(strip, np.uint8), image], axis=0)


def compose_frames(traces: Sequence[EpisodeTrace]) -> list[np.ndarray]:
    """One ``(CAPTION_PX + H, K * W, 3)`` uint8 frame per step: the ``K`` traces' images side by
    side, each captioned with its tracker, the frame ``t/T-1`` and the step's IoU.

    The traces must cover the same frames (one tracklet, the same ``max_steps``)."""
    if not traces:
        raise ValueError("compose_frames: no episode to show")
    frames = traces[0].frames
    for trace in traces[1:]:
        if trace.frames != frames or trace.tracklet != traces[0].tracklet:
            raise ValueError(
                f"compose_frames: {trace.tracker!r} ran tracklet {trace.tracklet} frames "
                f"{trace.frames[:3]}..., {traces[0].tracker!r} tracklet {traces[0].tracklet} "
                f"frames {frames[:3]}...: side by side needs the same frames"
            )
    last = frames[-1] if frames else 0
    out = []
    for k, t in enumerate(frames):
        panels = [
            _caption(
                trace.images[k],
                [trace.tracker, f"{trace.tracklet} frame {t}/{last}  IoU {trace.ious[k]:.2f}"],
            )
            for trace in traces
        ]
        out.append(np.concatenate(panels, axis=1))
    return out


def write_video(frames: Sequence[np.ndarray], path: str | Path, fps: float = 10.0) -> Path:
    """Write ``frames`` (each ``(H, W, 3)`` uint8) as ``path`` (``.mp4``: H.264 through
    imageio-ffmpeg; ``.gif``: Pillow, looping) atomically; returns the path.

    Raises ``ValueError`` for another suffix or no frames, :class:`training.extras.
    MissingExtraError` without the ``video`` extra."""
    from training.extras import require

    path = Path(path)
    suffix = path.suffix.lower()
    if suffix not in VIDEO_SUFFIXES:
        raise ValueError(f"video {path}: the suffix must be one of {list(VIDEO_SUFFIXES)}")
    if not frames:
        raise ValueError(f"video {path}: no frames to write")
    if not fps > 0:
        raise ValueError(f"video {path}: fps must be > 0, got {fps}")
    iio = require("imageio.v3", "video", "writing a video")
    stack = np.stack([np.asarray(f, np.uint8) for f in frames])
    path.parent.mkdir(parents=True, exist_ok=True)
    # the temporary keeps the suffix: imageio picks the format from it
    tmp = path.with_name(f".{path.stem}.tmp{os.getpid()}{suffix}")
    try:
        if suffix == ".mp4":
            require("imageio_ffmpeg", "video", "writing an MP4 video")
            iio.imwrite(tmp, stack, plugin="FFMPEG", fps=fps, codec="libx264", macro_block_size=16)
        else:
            iio.imwrite(tmp, stack, plugin="pillow", duration=1000.0 / fps, loop=0)
        os.replace(tmp, path)
    finally:
        tmp.unlink(missing_ok=True)
    return path
