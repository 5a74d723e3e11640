"""Checkpoint selection (``training.selection``, ``pointtrack select``): parts, pooling, ranking,
the per-part cache, and the refusals."""

from __future__ import annotations

import math

import numpy as np
import pytest

from envs.metrics import precision_auc, success_auc
from training.selection import (
    DEFAULT_PARTS,
    SelectionConfig,
    ValPart,
    check_parts,
    pooled,
    ranking_uncertainty,
    score_candidates,
)


def test_val_part_parse_round_trip_and_errors():
    assert ValPart.parse("2:val") == ValPart(2, "val")
    assert ValPart.parse(" 13 : test ") == ValPart(13, "test")
    assert str(ValPart(3, "test")) == "3:test"
    assert [str(p) for p in DEFAULT_PARTS] == [
        "0:val",
        "1:val",
        "1:test",
        "2:val",
        "2:test",
        "3:val",
        "3:test",
    ]
    for bad in ("2", "two:val", "2:dev", "-1:val", "2:val:x"):
        with pytest.raises(ValueError, match="validation part"):
            ValPart.parse(bad)


def test_check_parts_guards_the_training_world():
    check_parts([ValPart(0, "val"), ValPart(1, "test"), ValPart(1, "train")], train_world_seed=0)
    with pytest.raises(ValueError, match="0:test.*benchmark"):
        check_parts([ValPart(1, "val"), ValPart(0, "test")], train_world_seed=0)
    with pytest.raises(ValueError, match="5:train.*training data"):
        check_parts([ValPart(5, "train")], train_world_seed=5)
    with pytest.raises(ValueError, match="listed twice"):
        check_parts([ValPart(1, "val"), ValPart(1, "val")], train_world_seed=0)
    with pytest.raises(ValueError, match="no validation parts"):
        check_parts([], train_world_seed=0)
    with pytest.raises(ValueError, match="0:test"):
        SelectionConfig(parts=(ValPart(0, "test"),))


def test_pooled_scores_equal_the_scores_of_the_pooled_frames():
    rng = np.random.default_rng(0)
    parts = [(rng.uniform(0, 1, n), rng.uniform(0, 3, n)) for n in (7, 30, 1)]
    entries = [
        {"success": success_auc(iou), "precision": precision_auc(err), "frames": len(iou)}
        for iou, err in parts
    ]
    got = pooled(entries + [{"success": float("nan"), "precision": float("nan"), "frames": 0}])
    all_iou = np.concatenate([p[0] for p in parts])
    all_err = np.concatenate([p[1] for p in parts])
    assert got["frames"] == 38
    assert got["success"] == pytest.approx(success_auc(all_iou), abs=1e-9)
    assert got["precision"] == pytest.approx(precision_auc(all_err), abs=1e-9)
    assert math.isnan(pooled([])["success"])


@pytest.fixture(scope="module")
def tiny_config():
    # one env: a learned tracker's result per tracklet is then independent of which other
    # tracklets are evaluated (batched forwards can differ in the last bits with the batch layout,
    # and the closed loop amplifies that), so the check below can be exact
    return SelectionConfig(preset="tiny", parts=(ValPart(0, "val"), ValPart(1, "test")), num_envs=1)


def test_score_candidates_pools_observed_categories_and_ranks(
    tiny_config, tmp_path, one_torch_thread
):
    from envs.tracking_env import make_synthetic_env
    from training.evaluate import evaluate
    from training.loading import load_tracker

    candidates = ["previous_box", "p2b-kitti1-u"]
    rows = score_candidates(candidates, tiny_config, cache_dir=tmp_path)
    assert [r["success"] for r in rows] == sorted((r["success"] for r in rows), reverse=True)
    for row in rows:
        # independently: each part scored on the full setting (all categories), observed group
        entries = []
        for part in tiny_config.parts:
            env = make_synthetic_env(
                preset="tiny", seed=part.world_seed, split=part.split, setting="kitti-1"
            )
            full = evaluate(load_tracker(row["candidate"]), env, seed=0)["observed"]
            env.close()
            got = row["parts"][str(part)]
            assert got["frames"] == full["frames"] > 0
            assert got["success"] == pytest.approx(full["success"], abs=1e-9)
            assert got["precision"] == pytest.approx(full["precision"], abs=1e-9)
            entries.append(full)
        frames = sum(e["frames"] for e in entries)
        assert row["frames"] == frames
        assert row["success"] == pytest.approx(
            sum(e["success"] * e["frames"] for e in entries) / frames, abs=1e-9
        )
        # the per-tracklet scores the bootstrap resamples pool to the same Success
        tracklets = row["per_tracklet"].values()
        assert sum(t["frames"] for t in tracklets) == frames
        assert pooled(list(tracklets))["success"] == pytest.approx(row["success"], abs=1e-9)
    assert rows[0]["per_tracklet"].keys() == rows[1]["per_tracklet"].keys()


def test_score_candidates_reuses_its_cache_and_rescores_on_a_new_key(
    tiny_config, tmp_path, monkeypatch, one_torch_thread
):
    import training.evaluate

    first = score_candidates(["previous_box"], tiny_config, cache_dir=tmp_path)

    def no_evaluation(*args, **kwargs):
        raise AssertionError("evaluated although the cache holds this report")

    monkeypatch.setattr(training.evaluate, "evaluate", no_evaluation)
    assert score_candidates(["previous_box"], tiny_config, cache_dir=tmp_path) == first
    other_seed = SelectionConfig(preset="tiny", parts=tiny_config.parts, eval_seed=1, num_envs=1)
    with pytest.raises(AssertionError, match="evaluated although"):
        score_candidates(["previous_box"], other_seed, cache_dir=tmp_path)
    batched = SelectionConfig(preset="tiny", parts=tiny_config.parts, num_envs=2)
    with pytest.raises(AssertionError, match="evaluated although"):
        score_candidates(["previous_box"], batched, cache_dir=tmp_path)
    # a torn cache file is not trusted either
    cached = next(tmp_path.rglob("*.json"))
    cached.write_text(cached.read_text()[:50])
    with pytest.raises(AssertionError, match="evaluated although"):
        score_candidates(["previous_box"], tiny_config, cache_dir=tmp_path)


def test_cli_select_refuses_bad_input_naming_it(tmp_path, capsys):
    from training.cli import main

    for argv, expected in (
        (["previous_box", "--parts", "1:val", "0:test"], "validation part 0:test"),
        (["previous_box", "--parts", "2:dev"], "'2:dev'"),
        (["no-such.safetensors", "--parts", "1:val"], "candidate 'no-such.safetensors'"),
        (["previous_box", "previous_box", "--parts", "1:val"], "listed twice"),
        (["previous_box", "--logger", "csv"], "--logger writes into --out"),
        (["previous_box", "--logger", "csv,wandb", "--out", str(tmp_path)], "'csv,wandb'"),
    ):
        assert main(["select", *argv]) == 2
        err = capsys.readouterr().err
        assert err.startswith("pointtrack select: ") and expected in err, err
        assert err.count("\n") == 1


def test_load_candidate_reads_training_checkpoints_and_names_bad_files(tmp_path):
    import torch

    import trackers
    from training.checkpoint import CHECKPOINT_FORMAT
    from training.config import tracker_config
    from training.selection import load_candidate

    model = trackers.make("p2b", **tracker_config("p2b", "slim"))
    shadow = {k: v + 1.0 if v.is_floating_point() else v for k, v in model.state_dict().items()}
    config = {"tracker": "p2b", "model_size": "slim", "tracker_config": None}
    torch.save(
        {
            "format": CHECKPOINT_FORMAT,
            "model": model.state_dict(),
            "config": config,
            "ema": {"shadow": shadow},
        },
        tmp_path / "best.pt",
    )
    loaded = load_candidate(str(tmp_path / "best.pt"))
    for k, v in loaded.state_dict().items():  # the validated (averaged) weights
        assert torch.equal(v, shadow[k]), k
    trackers.save(model, tmp_path / "model.pt")  # a tracker file named .pt still loads
    for k, v in load_candidate(str(tmp_path / "model.pt")).state_dict().items():
        assert torch.equal(v, model.state_dict()[k]), k
    (tmp_path / "junk.pt").write_bytes(b"not a checkpoint")
    with pytest.raises(ValueError, match="candidate '.*junk.pt'"):
        load_candidate(str(tmp_path / "junk.pt"))


def test_score_candidates_gives_m2track_the_previous_frame(tiny_config, tmp_path, one_torch_thread):
    """A candidate that reads an opt-in observation key (M2-Track's ``previous_search``) is
    scored on an env that provides it, next to one that does not need it."""
    import torch

    import trackers

    torch.manual_seed(0)
    path = trackers.save(
        trackers.make("m2track", **trackers.size_config("m2track", "slim")),
        tmp_path / "m2track.safetensors",
    )
    rows = score_candidates([str(path), "previous_box"], tiny_config)
    assert {r["candidate"] for r in rows} == {str(path), "previous_box"}
    assert all(r["frames"] > 0 and 0.0 <= r["success"] <= 100.0 for r in rows)


def _rows(success_by_candidate, frames, parts):
    """Ranking rows for ``ranking_uncertainty``: one tracklet per column, in the given parts."""
    rows = []
    for name, success in success_by_candidate.items():
        per = {
            f"{part}/t{i}": {"success": float(s), "precision": float(s), "frames": float(f)}
            for i, (s, f, part) in enumerate(zip(success, frames, parts, strict=True))
        }
        rows.append({"candidate": name, "per_tracklet": per} | pooled(list(per.values())))
    return sorted(rows, key=lambda r: -r["success"])


def test_ranking_uncertainty_gaps_and_shares():
    rng = np.random.default_rng(3)
    frames = rng.integers(5, 60, 40)
    parts = ["0:val"] * 15 + ["1:val"] * 25
    base = rng.uniform(10, 80, 40)
    rows = _rows(
        {"a": base, "b": base + rng.normal(0.5, 4.0, 40), "c": base - 3.0, "d": base.copy()},
        frames,
        parts,
    )
    got = ranking_uncertainty(rows, resamples=500, seed=1)
    assert got == ranking_uncertainty(rows, resamples=500, seed=1)  # seeded
    assert got != ranking_uncertainty(rows, resamples=500, seed=2)
    assert sum(u["p_first"] for u in got) == pytest.approx(1.0)
    for row, u in zip(rows, got, strict=True):
        assert u["diff_to_first"] == pytest.approx(row["success"] - rows[0]["success"], abs=1e-9)
        assert (
            u["diff_lo"] <= u["diff_to_first"] + 1e-9 and u["diff_to_first"] - 1e-9 <= u["diff_hi"]
        )
    by_name = {r["candidate"]: u for r, u in zip(rows, got, strict=True)}
    # c is 3 points below a on every tracklet: the gap is exact in every resample, and c never wins
    gap_c = by_name["c"]["diff_to_first"] - by_name["a"]["diff_to_first"]
    assert gap_c == pytest.approx(-3.0)
    assert by_name["c"]["p_first"] == 0.0
    # a and d are the same candidate: ties go to the first-ranked of the two, d never wins
    assert by_name["a"]["diff_lo"] == by_name["d"]["diff_lo"]
    assert min(by_name["a"]["p_first"], by_name["d"]["p_first"]) == 0.0
    # a wider interval at a higher level
    wide = ranking_uncertainty(rows, resamples=500, seed=1, level=0.99)
    assert wide[-1]["diff_lo"] <= got[-1]["diff_lo"] and wide[-1]["diff_hi"] >= got[-1]["diff_hi"]


def test_ranking_uncertainty_resamples_within_parts():
    """With one tracklet per part every stratified resample is the data itself: no spread, and the
    best candidate wins every draw (a draw across parts would mix them and spread)."""
    rows = _rows(
        {"a": [50.0, 10.0, 30.0], "b": [10.0, 60.0, 31.0]},
        [10, 30, 5],
        ["0:val", "1:val", "1:test"],
    )
    got = ranking_uncertainty(rows, resamples=200)
    assert [r["candidate"] for r in rows] == ["b", "a"]
    assert got[1]["diff_lo"] == pytest.approx(got[1]["diff_to_first"])
    assert got[1]["diff_hi"] == pytest.approx(got[1]["diff_to_first"])
    assert got[0]["p_first"] == 1.0 and got[1]["p_first"] == 0.0


def test_ranking_uncertainty_refuses_unpaired_rows_naming_them():
    rows = _rows({"a": [1.0, 2.0], "b": [3.0, 4.0]}, [1, 1], ["0:val", "0:val"])
    del rows[1]["per_tracklet"]["0:val/t1"]
    with pytest.raises(ValueError, match=f"candidate '{rows[1]['candidate']}'.*same ones"):
        ranking_uncertainty(rows)
    with pytest.raises(ValueError, match="resamples"):
        ranking_uncertainty(rows[:1], resamples=0)
    with pytest.raises(ValueError, match="level"):
        ranking_uncertainty(rows[:1], level=1.0)
    assert ranking_uncertainty([]) == []


def test_cli_select_prints_and_saves_the_bootstrap_and_the_script_rebuilds_it(
    tmp_path, capsys, one_torch_thread
):
    """`pointtrack select --out` writes each row's uncertainty; the experiment script rebuilds the
    same rows (per-tracklet scores included) from the cache, even with a stale report of another
    file under a candidate's name beside the right one."""
    import importlib.util
    import json
    from pathlib import Path

    from training.cli import main

    out = tmp_path / "sel"
    argv = ["select", "previous_box", "constant_velocity", "--preset", "tiny", "--num-envs", "1"]
    assert main([*argv, "--parts", "0:val", "1:val", "--out", str(out), "--no-progress"]) == 0
    captured = capsys.readouterr()
    printed = captured.out
    assert "P(1st)" in printed
    # constant_velocity's velocity starts at 0 and stays there: an exact tie, reported as one
    assert "tie: previous_box and constant_velocity pool exactly the same" in printed
    assert "of tracklet resamples" not in printed
    assert "0:val previous_box: scored, observed Success" in captured.err  # logging, stderr
    saved = json.loads((out / "selection.json").read_text())["ranking"]
    # the ranking as scalars (stable-baselines3's logger): one step per rank
    dumps = [json.loads(line) for line in (out / "logs" / "progress.json").open()]
    assert [d["select/candidate"] for d in dumps] == [row["candidate"] for row in saved]
    assert [d["select/success"] for d in dumps] == [row["success"] for row in saved]
    assert [d["select/success_w1_val"] for d in dumps] == [
        row["parts"]["1:val"]["success"] for row in saved
    ]
    assert ranking_uncertainty(saved) == [row["uncertainty"] for row in saved]
    stale = next((out / "parts").rglob("previous_box-*.json"))
    report = json.loads(stale.read_text())
    report["observed"]["success"] += 1.0
    report["per_tracklet"] = [t | {"success": 0.0} for t in report["per_tracklet"]]
    (stale.parent / "previous_box-zzzzzzzzzzzz.json").write_text(json.dumps(report))

    path = Path(__file__).parents[1] / "experiments" / "selection_uncertainty.py"
    spec = importlib.util.spec_from_file_location("selection_uncertainty", path)
    script = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(script)
    rebuilt = script.rows_from_selection_dir(out)
    assert [r["per_tracklet"] for r in rebuilt] == [r["per_tracklet"] for r in saved]
