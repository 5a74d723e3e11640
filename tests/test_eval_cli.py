"""`pointtrack eval` flags: every argument checked before any work or directory, eval seeds,
intervals in the table, the oracle mark, --save-boxes and `pointtrack compare`."""

from __future__ import annotations

import json
import math
import os

import numpy as np
import pytest

from training.cli import main


def _one_line(capsys, *parts):
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1, err
    for part in parts:
        assert part in err[0], err[0]


@pytest.mark.parametrize(
    ("flags", "says"),
    [
        (["--weather", "fog", "--weather-seed=-4"], "--weather-seed must be >= 0, got -4"),
        (["--weather", "fog", "--weather-levels", ""], "--weather-levels '' names no level"),
        (["--weather", "fog", "--weather-levels", "1,9"], "unknown weather level 9"),
        (["--weather", "fog", "--weather-levels", "2,2"], "--weather-levels lists 2 twice"),
        (["--weather", "bogus"], "unknown weather kind 'bogus'"),
        (["--weather", "fog,rain,fog"], "--weather lists 'fog' twice"),
        (["--eval-seed", "-1"], "--eval-seed must be >= 0, got -1"),
        (["--eval-seeds", "0", "1", "0"], "lists seed 0 twice"),
        (["--eval-seeds", "2", "-3"], "--eval-seeds must be >= 0; got -3"),
        (["--eval-seed", "1", "--eval-seeds", "2"], "not both"),
        (["--save-boxes"], "--save-boxes writes into --out DIR"),
        (["--workers", "2", "--num-envs", "4"], "cannot be combined with --num-envs > 1"),
        (["--device", "tpu"], "--device must be cpu or cuda[:N], got 'tpu'"),
        (["--weather", "fog", "--eval-seeds", "0", "1"], "--weather takes one --eval-seed"),
    ],
)
def test_bad_arguments_fail_before_any_work_or_directory(
    flags, says, tmp_path, capsys, monkeypatch
):
    import training.commands.eval as eval_cmd

    def no_work(*_a, **_k):
        raise AssertionError("work started before the arguments were checked")

    monkeypatch.setattr(eval_cmd, "load_trackers", no_work)
    monkeypatch.setattr(eval_cmd, "build_env", no_work)
    out = tmp_path / "out"
    extra = [] if "--save-boxes" in flags else ["--out", str(out)]
    assert main(["eval", "--preset", "tiny", *flags, *extra]) == 2
    _one_line(capsys, "pointtrack eval:", says)
    assert not out.exists()


def test_save_boxes_into_an_unwritable_place_fails_before_evaluating(tmp_path, capsys, monkeypatch):
    import training.commands.eval as eval_cmd

    monkeypatch.setattr(eval_cmd, "build_env", lambda *a, **k: pytest.fail("evaluated"))
    out = tmp_path / "out"
    out.mkdir()
    (out / "boxes").write_text("a file where the boxes directory would go")
    assert main(["eval", "--preset", "tiny", "--save-boxes", "--out", str(out)]) == 2
    _one_line(capsys, "--save-boxes cannot write to", "boxes")


def _eval(tmp_path, name, *flags):
    out = tmp_path / name
    args = ["eval", "--preset", "tiny", "--tracker", "p2b-kitti1-u", "--max-tracklets", "4"]
    assert main([*args, "--no-progress", "--out", str(out), *flags]) == 0
    return out, json.loads((out / "report.json").read_text())["p2b-kitti1-u"]


def test_eval_seeds_mean_equals_the_mean_of_single_seed_runs(tmp_path, capsys):
    _, both = _eval(tmp_path, "both", "--eval-seeds", "0", "1")
    _, zero = _eval(tmp_path, "zero", "--eval-seed", "0")
    _, one = _eval(tmp_path, "one", "--eval-seeds", "1")
    assert both["eval_seeds"] == [0, 1] and both["eval"]["seeds"] == [0, 1]
    entries = [("mean",), ("observed",), ("unseen",)] + [
        ("categories", c) for c in zero["categories"]
    ]
    differs = False
    for path in entries:
        b, z, o = (_at(r, path) for r in (both, zero, one))
        for key in ("success", "precision"):
            assert b[key] == pytest.approx((z[key] + o[key]) / 2, rel=1e-12, abs=1e-12), path
            assert b[f"{key}_seeds"] == [z[key], o[key]]
            differs |= z[key] != o[key]
    assert differs  # the seed reaches the resampling, so the mean is a real mean
    table = capsys.readouterr().out
    assert "mean over eval seeds [0, 1]" in table and " ± " in table
    lo, hi = both["mean"]["success_interval"]
    assert lo <= both["mean"]["success"] <= hi


def _at(report, path):
    for key in path:
        report = report[key]
    return report


def test_oracle_reference_is_marked_everywhere(tmp_path, capsys):
    out = tmp_path / "oracle"
    with pytest.warns(UserWarning, match="oracle setting"):
        rc = main(
            ["eval", "--preset", "tiny", "--reference", "current_gt", "--no-progress"]
            + [
                "--out",
                str(out),
            ]
        )
    assert rc == 0
    assert "previous_box (oracle: current_gt)" in capsys.readouterr().out
    report = json.loads((out / "report.json").read_text())["previous_box"]
    assert report["oracle"] == "current_gt" and report["eval"]["oracle"] == "current_gt"


def test_saved_boxes_rescore_exactly_and_parse_back(tmp_path):
    from training.boxes import read_boxes, read_result_file, rescore

    out, report = _eval(tmp_path, "boxes", "--save-boxes", "--workers", "2")
    path = out / "boxes" / "p2b-kitti1-u.jsonl"
    again = rescore(path)
    for group in ("mean", "observed", "unseen"):
        for key in ("success", "precision", "frames"):
            assert again[group][key] == report[group][key] or (
                math.isnan(again[group][key]) and report[group][key] is None
            )
    for cat, entry in report["categories"].items():
        assert again["categories"][cat]["success"] == entry["success"]
        assert again["categories"][cat]["precision"] == entry["precision"]
    records = read_boxes(path)
    assert len(records) == report["frames"]
    assert {"pred", "gt", "iou", "center_error", "target_points", "seed"} <= set(records[0])
    files = sorted((out / "boxes" / "p2b-kitti1-u" / "seed0").glob("*.txt"))
    assert len(files) == report["tracklets"]
    for file in files:
        frames, boxes = read_result_file(file)
        saved = [r for r in records if r["tracklet"].replace("/", "_") == file.stem]
        assert frames.tolist() == [r["frame"] for r in saved]
        np.testing.assert_allclose(boxes, [r["pred"] for r in saved], rtol=0, atol=1e-12)


def test_read_result_file_names_a_bad_line(tmp_path):
    from training.boxes import read_result_file

    path = tmp_path / "x.txt"
    path.write_text("0 1 2 3 4 5 6 0.1\n1 1 2 3 four 5 6 0.1\n")
    with pytest.raises(ValueError, match=r"x.txt:2: could not convert"):
        read_result_file(path)


def test_compare_lists_the_tracklets_that_differ_most(tmp_path, capsys):
    base = ["eval", "--preset", "tiny", "--no-progress", "--workers", "1"]
    a, b = tmp_path / "a", tmp_path / "b"
    assert main([*base, "--tracker", "previous_box", "--out", str(a)]) == 0
    assert main([*base, "--tracker", "constant_velocity", "--out", str(b)]) == 0
    capsys.readouterr()
    assert main(["compare", str(a), str(b), "--top", "3", "--out", str(tmp_path / "c.json")]) == 0
    text = capsys.readouterr().out
    assert "A = " in text and "previous_box" in text and "the 3 that differ most" in text
    rows = json.loads((tmp_path / "c.json").read_text())["rows"]
    deltas = [abs(r["delta_success"]) for r in rows]
    assert deltas == sorted(deltas, reverse=True)
    assert main(["compare", str(a), str(tmp_path / "nowhere")]) == 2
    _one_line(capsys, "pointtrack compare:", "no eval report")


def test_select_and_demo_take_workers(tmp_path, capsys):
    assert main(["demo", "--preset", "tiny", "--workers", "0", "--out", str(tmp_path)]) == 2
    _one_line(capsys, "pointtrack demo:", "--workers must be an integer >= 1; got 0")
    assert main(["select", "previous_box", "--preset", "tiny", "--workers", "0"]) == 2
    _one_line(capsys, "pointtrack select:", "--workers must be an integer >= 1; got 0")
    assert os.listdir(tmp_path) == []


_ENTRY = """
import atexit, sys
class Teardown:
    def __del__(self):
        print("teardown ran", flush=True)
marker = Teardown()
atexit.register(lambda: print("atexit ran", flush=True))
from training.cli import entry
sys.argv = ["pointtrack", *sys.argv[1:]]
entry()
"""


def test_the_console_entry_skips_the_teardown_after_eval_and_keeps_its_output(tmp_path):
    """``training.cli.entry`` (the console script): ``eval`` (``FAST_EXIT``) ends the process
    after flushing its output and running the ``atexit`` handlers, without the interpreter's
    teardown (a module-level object's ``__del__`` does not run), and passes its status on (0,
    a refusal's 2); a command without ``FAST_EXIT`` exits as usual."""
    import subprocess
    import sys
    from pathlib import Path

    root = Path(__file__).resolve().parents[1]
    env = {**os.environ, "PYTHONPATH": str(root)}

    def entry(*argv):
        cmd = [sys.executable, "-c", _ENTRY, *argv]
        return subprocess.run(cmd, env=env, capture_output=True, text=True, cwd=tmp_path)

    out = tmp_path / "out"
    done = entry(
        "eval", "--preset", "tiny", "--max-tracklets", "2", "--no-progress", "--out", str(out)
    )
    assert done.returncode == 0, done.stderr
    assert "wrote" in done.stdout and "atexit ran" in done.stdout
    assert "teardown ran" not in done.stdout
    assert json.loads((out / "report.json").read_text())
    refused = entry("eval", "--preset", "tiny", "--eval-seed", "-1")
    assert refused.returncode == 2 and "--eval-seed must be >= 0" in refused.stderr
    assert "atexit ran" in refused.stdout and "teardown ran" not in refused.stdout
    other = entry("info", "p2b-kitti1-u")
    assert other.returncode == 0, other.stderr
    assert "atexit ran" in other.stdout and "teardown ran" in other.stdout


def test_network_alone_turns_the_files_inference_settings_off(tmp_path):
    import argparse
    import dataclasses

    from trackers.decision import InferenceConfig
    from training.commands.eval import EvalPlan, load_trackers

    args = argparse.Namespace(tracker=["p2b-kitti1-u", "previous_box"], eval_seed=0)
    plan = EvalPlan((0,), 1, 1, "cpu", True, None)
    shipped = load_trackers(args, plan)["p2b-kitti1-u"]
    assert shipped.inference != InferenceConfig()  # the file records a hold and a re-ranking
    alone = load_trackers(args, dataclasses.replace(plan, network_alone=True))
    assert alone["p2b-kitti1-u"].inference == InferenceConfig()
    out = tmp_path / "alone"
    flags = ["--preset", "tiny", "--max-tracklets", "1", "--workers", "1", "--no-progress"]
    assert (
        main(["eval", "--tracker", "p2b-kitti1-u", "--network-alone", *flags, "--out", str(out)])
        == 0
    )
    report = json.loads((out / "report.json").read_text())["p2b-kitti1-u"]
    assert report["eval"]["network_alone"] is True
