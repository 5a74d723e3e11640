"""`pointtrack render`: episodes recorded per frame, videos (MP4 / GIF) and rerun recordings.

The videos and recordings are written on the tiny synthetic world and read back with imageio and
rerun's own reader; they skip (with the reason) only when the optional extra is absent.
"""

from __future__ import annotations

import sys

import numpy as np
import pytest

TRACKLET = "0019/13"  # 5 frames in the tiny world's test split: 4 tracked frames
ARGS = ["--preset", "tiny", "--setting", "kitti-1"]


@pytest.fixture(scope="module")
def env():
    from envs.tracking_env import make_synthetic_env

    return make_synthetic_env(
        preset="tiny", split="test", setting="kitti-1", render_mode="rgb_array"
    )


@pytest.fixture(scope="module")
def traces(env, one_torch_thread):
    import trackers
    from training.video import run_episode

    return [
        run_episode(trackers.load(name), env, "0019/3", name=name, seed=1, max_steps=6)
        for name in ("previous_box", "p2b-kitti1-u")
    ]


def test_episode_trace_is_what_eval_scores(env, one_torch_thread):
    """The recorded IoUs give the per-tracklet Success that `evaluate` reports with the same
    seed, and each search crop, back in the box frame, lies in the search region."""
    import trackers
    from envs.geometry import world_to_box
    from envs.metrics import success_auc
    from training.evaluate import evaluate
    from training.video import run_episode

    tracker = trackers.load("p2b-kitti1-u")
    index = [t.tracklet_id for t in env.tracklets].index("0019/3")
    report = evaluate(tracker, env, seed=4, tracklets=[index])
    trace = run_episode(tracker, env, "0019/3", name="p2b", seed=4)
    assert len(trace) == len(env.tracklets[index]) - 1 == len(trace.images)
    assert trace.frames == list(range(1, len(env.tracklets[index])))
    assert success_auc(np.array([1.0, *trace.ious])) == pytest.approx(
        report["per_tracklet"][0]["success"], abs=1e-9
    )
    scale, offset = env.search_enlargement
    for k in range(1, len(trace)):
        ref = trace.pred_boxes[k - 1]  # reference="prediction": the previous prediction
        local = world_to_box(trace.search[k].astype(np.float64), ref)
        half = 0.5 * scale * ref[3:6] + offset
        assert np.all(np.abs(local) <= half + 1e-3)


def test_compose_frames_side_by_side(traces):
    from training.video import CAPTION_PX, compose_frames

    frames = compose_frames(traces)
    assert len(frames) == 6
    h, w = traces[0].images[0].shape[:2]
    assert frames[0].shape == (CAPTION_PX + h, 2 * w, 3) and frames[0].dtype == np.uint8
    np.testing.assert_array_equal(frames[3][CAPTION_PX:, :w], traces[0].images[3])
    np.testing.assert_array_equal(frames[3][CAPTION_PX:, w:], traces[1].images[3])
    assert frames[3][:CAPTION_PX].any()  # the caption is written
    with pytest.raises(ValueError, match="same frames"):
        short = type(traces[1])(**{**vars(traces[1]), "frames": traces[1].frames[:2]})
        compose_frames([traces[0], short])


@pytest.mark.parametrize("suffix", [".gif", ".mp4"])
def test_render_video_has_one_frame_per_tracked_frame(tmp_path, suffix, one_torch_thread):
    iio = pytest.importorskip("imageio.v3", reason="the video extra is not installed")
    if suffix == ".mp4":
        pytest.importorskip("imageio_ffmpeg", reason="the video extra is not installed")
    from training.cli import main

    out = tmp_path / f"clip{suffix}"
    argv = ["render", "--tracker", "previous_box", "constant_velocity", "--tracklet", TRACKLET]
    assert main([*argv, *ARGS, "--out", str(out)]) == 0
    plugin = "FFMPEG" if suffix == ".mp4" else "pillow"
    frames = iio.imread(out, index=None, plugin=plugin)
    assert frames.shape == (4, 288, 512, 3)
    assert not list(tmp_path.glob(".*tmp*"))  # the atomic write left no temporary
    # --max-frames cuts the episode; the same seed gives the same bytes
    cut = tmp_path / f"cut{suffix}"
    for path in (cut, out):
        assert main([*argv, *ARGS, "--out", str(path), "--max-frames", "2"]) == 0
    assert iio.imread(out, index=None, plugin=plugin).shape[0] == 2
    assert out.read_bytes() == cut.read_bytes()


def test_render_refuses_bad_input_naming_it(tmp_path, capsys):
    from training.cli import main

    base = ["render", "--tracker", "previous_box", *ARGS]
    assert main([*base, "--tracklet", "0019/999", "--out", str(tmp_path / "x.gif")]) == 2
    err = capsys.readouterr().err
    assert "unknown tracklet id '0019/999'" in err and "0019/13" in err and "0019/3" in err
    argv = ["render", "--tracker", "nope", *ARGS, "--tracklet", TRACKLET]
    assert main([*argv, "--out", str(tmp_path / "x.gif")]) == 2
    err = capsys.readouterr().err
    assert "'nope'" in err and "previous_box" in err and "p2b-kitti1-u" in err
    assert main([*base, "--tracklet", TRACKLET, "--out", str(tmp_path / "x.avi")]) == 2
    assert ".mp4 or .gif" in capsys.readouterr().err
    argv = [*base, "--tracklet", TRACKLET, "--viewer", "rerun", "--out", str(tmp_path / "x.mp4")]
    assert main(argv) == 2
    assert ".rrd" in capsys.readouterr().err
    argv = [*base, "--tracklet", TRACKLET, "--weather", "fog", "--out", str(tmp_path / "x.gif")]
    assert main(argv) == 2
    assert "KIND:LEVEL" in capsys.readouterr().err


def test_missing_video_extra_is_one_line(tmp_path, capsys, monkeypatch):
    from training.cli import main
    from training.extras import MissingExtraError
    from training.video import write_video

    monkeypatch.setitem(sys.modules, "imageio", None)  # import imageio now raises ImportError
    monkeypatch.setitem(sys.modules, "imageio.v3", None)
    with pytest.raises(MissingExtraError, match=r'pip install "pointtrack\[video\]"'):
        write_video([np.zeros((16, 16, 3), np.uint8)], tmp_path / "x.gif")
    argv = ["render", "--tracker", "previous_box", "--tracklet", TRACKLET, *ARGS]
    assert main([*argv, "--out", str(tmp_path / "x.gif")]) == 2
    err = capsys.readouterr().err.strip()
    assert err.count("\n") == 0 and 'pip install "pointtrack[video]"' in err


def test_rerun_recording_reads_back_with_its_entities(tmp_path, one_torch_thread):
    pytest.importorskip("rerun", reason="the viewer extra (rerun-sdk) is not installed")
    from training.cli import main
    from training.rerun_view import read_entities

    out = tmp_path / "episode.rrd"
    argv = ["render", "--tracker", "previous_box", "constant_velocity", "--tracklet", TRACKLET]
    argv += [*ARGS, "--viewer", "rerun", "--weather", "fog:3", "--out", str(out)]
    assert main(argv) == 0
    rows = read_entities(out)
    expected = {"/episode": 1, "/world/scan/clean": 5, "/world/scan/weather": 5}
    expected["/world/ground_truth"] = 5
    for name in ("previous_box", "constant_velocity"):
        expected[f"/world/trackers/{name}/prediction"] = 5  # frame 0: the given box
        expected[f"/world/trackers/{name}/search"] = 4
        for metric in ("iou", "center_error", "target_points"):
            expected[f"/metrics/{name}/{metric}"] = 4
    assert rows == expected
    # without weather there is no weathered scan to toggle
    argv = ["render", "--tracker", "previous_box", "--tracklet", TRACKLET, *ARGS]
    assert main([*argv, "--viewer", "rerun", "--out", str(out)]) == 0
    assert "/world/scan/weather" not in read_entities(out)
