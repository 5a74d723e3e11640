"""The experiments/ scripts whose output goes into docs/ tables."""

from __future__ import annotations

import importlib.util
import json
import shutil
import types
from pathlib import Path
from types import SimpleNamespace

import numpy as np
import pytest
import torch
import yaml
from test_pretrain_support import fake_tracklets

import trackers
from trackers.head import HeadConfig
from training.samples import TrackingSamples


def _script(name: str):
    path = Path(__file__).parents[1] / "experiments" / f"{name}.py"
    spec = importlib.util.spec_from_file_location(name, path)
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def _run(tmp_path: Path, name: str, epochs: dict[int, dict]) -> Path:
    run = tmp_path / name
    run.mkdir()
    rows = [{"kind": "data", "step": 0}]
    for epoch, values in epochs.items():
        rows.append({"kind": "train", "step": 50 * epoch - 40, "epoch": epoch, "total": 9.0})
        rows.append({"kind": "epoch", "epoch": epoch, "step": 50 * epoch, **values})
    (run / "log.jsonl").write_text("".join(json.dumps(r) + "\n" for r in rows))
    return run


def test_epoch_losses_pairs_runs_by_epoch(tmp_path):
    script = _script("epoch_losses")
    a = _run(tmp_path, "slim", {1: {"total": 1.5, "vote": 0.25}, 2: {"total": 1.0, "vote": 0.125}})
    b = _run(tmp_path, "full", {1: {"total": 1.25, "vote": 0.5, "val_success": 12.34}})
    lines = script.table([a, b], ["total", "vote"], None).splitlines()
    assert lines[0] == (
        "| epoch | slim: total | slim: vote | slim: val | full: total | full: vote | full: val |"
    )
    # mean epoch losses, not the per-step "train" rows; blanks where a run has no such epoch
    assert lines[2] == "| 1 | 1.500 | 0.250 |  | 1.250 | 0.500 | 12.3 |"
    assert lines[3] == "| 2 | 1.000 | 0.125 |  |  |  |  |"
    assert len(script.table([a, b], ["total"], 1).splitlines()) == 3


def test_epoch_losses_names_a_run_without_a_log(tmp_path):
    script = _script("epoch_losses")
    with pytest.raises(SystemExit, match="nope/log.jsonl: no such file"):
        script.epoch_rows(tmp_path / "nope")
    empty = _run(tmp_path, "empty", {})
    with pytest.raises(SystemExit, match="no finished epoch yet"):
        script.epoch_rows(empty)


class _StayingTracker(torch.nn.Module):
    """Votes, proposals and the chosen box all at the search frame's origin, yaw 0: every
    measure of ``vote_diagnostics`` then follows from the ground-truth offsets alone."""

    config = SimpleNamespace(head=HeadConfig())  # the papers' 0.3 m positive radius

    def forward(self, batch):
        b, n = batch["search"].shape[:2]
        m, p = 32, 8
        return {
            "seed_idx": torch.arange(m).expand(b, m),
            "votes": torch.zeros(b, m, 3),
            "proposal_centers": torch.zeros(b, p, 3),
            "proposals": torch.zeros(b, p, 4),
            "scores": torch.zeros(b, p),
        }

    def best_action(self, outputs):
        return outputs["proposals"][:, 0]


def test_vote_diagnostics_against_the_ground_truth_offsets():
    script = _script("vote_diagnostics")
    data = TrackingSamples(fake_tracklets(n=3, frames=6), candidates_per_frame=3, seed=5)
    indices = np.arange(0, len(data), 2)
    result = script.diagnose(_StayingTracker(), data, indices, batch_size=4)

    items = [data[int(i)] for i in indices]
    offset = np.array([np.linalg.norm(item["search_box"][:3].numpy()) for item in items])
    yaw = np.array([abs(float(item["search_box"][6])) for item in items])
    targets = np.array([int(item["search_labels"][:32].sum()) for item in items])
    assert targets.sum() > 0 and np.ptp(offset) > 0  # the check below is not vacuous

    def median(values):  # torch.median: the lower of the two middle values
        return float(np.quantile(values, 0.5, method="lower"))

    assert result["samples"] == len(indices)
    assert result["stay_error_m"] == pytest.approx(median(offset), abs=1e-6)
    assert result["box_error_m"] == pytest.approx(median(offset), abs=1e-6)
    assert result["vote_miss_m"] == pytest.approx(median(np.repeat(offset, targets)), abs=1e-6)
    assert result["no_positive"] == pytest.approx(100 * np.mean(offset >= 0.3))
    assert result["top_positive"] == pytest.approx(100 * np.mean(offset < 0.3))
    assert result["yaw_error_deg"] == pytest.approx(np.degrees(median(yaw)), abs=1e-4)


def test_vote_diagnostics_correction_is_zero_for_a_tracker_that_stays():
    script = _script("vote_diagnostics")
    tracklets = fake_tracklets(n=3, frames=6)
    tracker = _StayingTracker()
    fixed = script.samples_for(tracker, tracklets, 5, script.FixedOffsetSamples)
    indices = np.arange(len(fixed))
    for axis in (0, 1):
        # the box it keeps is the search region's centre: the whole offset stays as the error
        # (up to the search region's yaw noise, a few degrees)
        assert script.correction(tracker, fixed, indices, axis, 0.8) == pytest.approx(0, abs=0.01)
    fixed.offset_box_m = (0.5, -0.25)
    box = fixed[0]["search_box"].numpy()
    assert box[:2] == pytest.approx([-0.5, 0.25], abs=0.05)  # the offset, in the box's axes


def test_motion_breakdown_bins_tracklets_by_speed_and_weights_by_frames():
    script = _script("motion_breakdown")
    parked = np.zeros((4, 7))
    moving = np.zeros((3, 7))
    moving[:, 0] = [0.0, 0.8, 1.6]  # 0.8 m a frame
    assert script.mean_step_m(parked) == 0.0
    assert script.mean_step_m(moving) == pytest.approx(0.8)
    steps = {"a": 0.0, "b": 0.01, "c": 0.8}
    report = {
        "per_tracklet": [
            {"tracklet": "a", "category": "Van", "frames": 30, "success": 90.0, "precision": 80.0},
            {"tracklet": "b", "category": "Car", "frames": 10, "success": 50.0, "precision": 40.0},
            {"tracklet": "c", "category": "Van", "frames": 20, "success": 20.0, "precision": 30.0},
        ]
    }
    result = script.breakdown(report, steps)
    assert list(result) == ["[0, 0.05)", "[0.05, 0.5)", "[0.5, 1.5)", "[1.5, inf)"]
    static = result["[0, 0.05)"]
    assert (static["tracklets"], static["frames"]) == (2, 40)
    assert static["success"] == pytest.approx((90 * 30 + 50 * 10) / 40)
    assert static["precision"] == pytest.approx((80 * 30 + 40 * 10) / 40)
    assert result["[0.5, 1.5)"]["success"] == pytest.approx(20.0)
    assert result["[0.05, 0.5)"]["tracklets"] == 0 and np.isnan(result["[0.05, 0.5)"]["success"])
    vans = script.breakdown(report, steps, category="Van")
    assert vans["[0, 0.05)"]["frames"] == 30 and vans["[0, 0.05)"]["success"] == 90.0


def test_motion_breakdown_names_a_tracklet_missing_from_the_data():
    script = _script("motion_breakdown")
    report = {"per_tracklet": [{"tracklet": "0007/3", "frames": 5, "success": 1, "precision": 1}]}
    with pytest.raises(KeyError, match="0007/3"):
        script.breakdown(report, {"0001/1": 0.0})


def _eval_report(folder: Path, name: str, observed: float, unseen: float) -> None:
    """A minimal ``pointtrack eval --out`` report.json: groups with Success and its interval."""
    folder.mkdir(parents=True)
    report = {
        "tracker": name,
        "observed": {"success": observed, "success_interval": [observed - 1, observed + 1]},
        "unseen": {"success": unseen, "success_interval": [unseen - 2, unseen + 2]},
        "per_tracklet": [],
    }
    (folder / "report.json").write_text(json.dumps({name: report}))


def test_table4_reproduces_cells_and_paired_difference(tmp_path, capsys):
    script = _script("table4")
    values = {  # (arm, seed): (observed, unseen)
        ("none", 0): (30.0, 20.0),
        ("none", 1): (32.0, 22.0),
        ("none", 2): (34.0, 21.0),
        ("decorrelation", 0): (31.0, 23.0),
        ("decorrelation", 1): (33.0, 24.0),
        ("decorrelation", 2): (35.0, 23.0),
    }
    for (arm, seed), (obs, uns) in values.items():
        _eval_report(tmp_path / "test" / f"p2b-{arm}-s{seed}", "best.pt", obs, uns)
    assert script.main([str(tmp_path)]) == 0
    out = capsys.readouterr().out
    assert "| P2B-U seed 1 | 32.0 [31.0, 33.0] | 22.0 [20.0, 24.0] |" in out
    # -U observed 30/32/34: mean 32.0, sd 2.0; -W unseen 23/24/23: mean 23.3, sd 0.6
    assert "| P2B-U | 32.0 ± 2.0 | 21.0 ± 1.0 | 38.6 / 32.4 |" in out
    assert "| P2B-W | 33.0 ± 2.0 | 23.3 ± 0.6 | 41.0 / 34.7 |" in out
    # unseen differences 3, 2, 2: mean 2.33, sd 0.577, half width 2.920 * 0.577 / sqrt(3) = 0.97
    assert "observed +1.0 [+1.0, +1.0]" in out
    assert "unseen +2.3 [+1.4, +3.3]" in out
    assert "paper +2.4 / +2.3" in out


def test_table4_reads_another_tracker_and_setting(tmp_path, capsys):
    script = _script("table4")
    for arm, obs in (("none", 30.0), ("decorrelation", 31.5)):
        for seed in (0, 1):
            _eval_report(tmp_path / "test" / f"bat-{arm}-s{seed}", "best.pt", obs + seed, 20.0)
    argv = [str(tmp_path), "--tracker", "bat", "--setting", "nuscenes-1", "--seeds", "0", "1"]
    assert script.main(argv) == 0
    out = capsys.readouterr().out
    assert "| BAT-W seed 1 | 32.5 [31.5, 33.5] | 20.0 [18.0, 22.0] |" in out
    assert "| BAT-U | 30.5 ± 0.7 | 20.0 ± 0.0 | 30.9 / 33.6 |" in out
    # the paper's BAT nuScenes-1: -W 33.4 / 36.0 against -U 30.9 / 33.6
    assert "BAT-W minus BAT-U" in out and "paper +2.5 / +2.4" in out


def test_table4_versus_compares_two_trackers_unpaired(tmp_path, capsys):
    script = _script("table4")
    for seed, (obs, uns) in enumerate(((30.0, 20.0), (34.0, 22.0), (32.0, 24.0))):
        _eval_report(tmp_path / "m" / "test" / f"mbptrack-none-s{seed}", "best.pt", obs, uns)
    for seed, (obs, uns) in enumerate(((20.0, 10.0), (22.0, 12.0), (24.0, 14.0))):
        _eval_report(tmp_path / "p" / "test" / f"p2b-none-s{seed}", "best.pt", obs, uns)
    argv = [str(tmp_path / "m"), "--tracker", "mbptrack", "--arms", "none"]
    assert script.main([*argv, "--versus", f"p2b={tmp_path / 'p'}"]) == 0
    out = capsys.readouterr().out
    assert "| MBPTrack-U | 32.0 ± 2.0 | 22.0 ± 2.0 | not in Table IV |" in out
    # observed 32 - 22 = 10; se = sqrt(4/3 + 4/3) = 1.633; half = 2.920 * 1.633 = 4.77
    assert "observed: MBPTrack-U 32.0 ± 2.0, P2B-U 22.0 ± 2.0; difference" in out
    assert "(Welch, 90 %) +10.0 [+5.2, +14.8]" in out
    with pytest.raises(SystemExit):
        script.main(["--grid", f"kitti-1={tmp_path / 'm'}", "--tracker", "mbptrack"])
    with pytest.raises(SystemExit):
        script.main([*argv, "--versus", f"gpt={tmp_path / 'p'}"])


def test_table4_grid_lays_out_settings_and_marks_what_did_not_run(tmp_path, capsys):
    script = _script("table4")
    for arm, unseen in (("none", (20.0, 22.0, 21.0)), ("decorrelation", (23.0, 24.0, 23.0))):
        for seed in (0, 1, 2):
            folder = tmp_path / "k2" / "test" / f"p2b-{arm}-s{seed}"
            _eval_report(folder, "best.pt", 30.0 + seed, unseen[seed])
    assert script.main(["--grid", f"kitti-2={tmp_path / 'k2'}"]) == 0
    out = capsys.readouterr().out
    row = next(line for line in out.splitlines() if line.startswith("| P2B-W |"))
    cells = [c.strip() for c in row.strip("|").split("|")]
    # kitti-1 columns first (not given), then kitti-2's observed and unseen with the paper's
    assert cells[1:5] == [
        "not run (41.0)",
        "not run (34.7)",
        "31.0 ± 1.0 (56.2)",
        "23.3 ± 0.6 (26.6)",
    ]
    assert "| P2B-S | not run (31.4)" in out
    assert (
        "* kitti-2, P2B-W minus P2B-U: observed +0.0 [+0.0, +0.0], unseen +2.3 [+1.4, +3.3]" in out
    )
    with pytest.raises(SystemExit):
        script.main(["--grid", "kitti-9=x"])


def _ship_root(tmp_path: Path, unseen: float) -> Path:
    """A pilot root: seed 1 selected for -U, its test reading, two baselines at 10 / 12."""
    root = tmp_path / "nus1"
    _eval_report(root / "test" / "p2b-none-s1", "best.pt", 20.0, unseen)
    baselines = {
        name: {"observed": {"success": 10.0}, "unseen": {"success": 12.0}, "per_tracklet": []}
        for name in ("previous_box", "constant_velocity")
    }
    (root / "test" / "baselines").mkdir()
    (root / "test" / "baselines" / "report.json").write_text(json.dumps(baselines))
    select = root / "select-none"
    select.mkdir()
    ranking = [{"candidate": str(root / "p2b-none-s1" / "best.pt")}, {"candidate": "other"}]
    (select / "selection.json").write_text(json.dumps({"ranking": ranking}))
    torch.manual_seed(0)
    tracker = trackers.make("p2b", **trackers.size_config("p2b", "slim"))
    trackers.save(tracker, select / "p2b-nuscenes1-u.safetensors")
    return root


def test_table4_ship_copies_the_selected_file_only_past_both_baselines(
    tmp_path, capsys, monkeypatch
):
    """The shipped directory stands in for the real one (a file there loads only once its
    manifest lists it, which the back-fill writes after the ship)."""
    import trackers.registry

    script = _script("table4_ship")
    shipped, recipes = tmp_path / "checkpoints", tmp_path / "recipes"
    shipped.mkdir()
    recipes.mkdir()
    trackers.registry.write_manifest(shipped)
    monkeypatch.setattr(trackers.registry, "CHECKPOINT_DIR", shipped.resolve())
    dirs = ["--checkpoints", str(shipped), "--recipes", str(recipes), "--command", "make it"]
    root = _ship_root(tmp_path, unseen=11.0)  # unseen 11 < 12: not shipped
    assert script.main([str(root), "none", "p2b-nuscenes1-u", *dirs]) == 0
    out = capsys.readouterr().out
    assert "p2b-none-s1 unseen 11.0 does not beat previous_box 12.0" in out
    assert "p2b-nuscenes1-u: not shipped" in out
    assert [p.name for p in shipped.iterdir()] == ["manifest.json"]
    assert not list(recipes.iterdir())
    root = _ship_root(tmp_path / "again", unseen=13.0)
    assert script.main([str(root), "none", "p2b-nuscenes1-u", *dirs]) == 0
    source = root / "select-none" / "p2b-nuscenes1-u.safetensors"
    assert (shipped / source.name).read_bytes() == source.read_bytes()
    recipe = yaml.safe_load((recipes / "p2b-nuscenes1-u.yaml").read_text())
    assert recipe["checkpoint"] == "p2b-nuscenes1-u" and recipe["commands"] == ["make it"]
    assert "written_by" not in recipe["provenance"]


def test_table4_ship_reads_a_file_candidates_own_test_reading(tmp_path, capsys):
    """A selection in another folder (``--select``) whose first candidate is a tracker file (a
    hold variant): the gate reads ``test/STEM``, not a run's reading."""
    script = _script("table4_ship")
    root = _ship_root(tmp_path, unseen=11.0)  # the run itself would not pass
    variant = root / "hold" / "p2b-none-s1-h0.3.safetensors"
    _eval_report(root / "test" / variant.stem, "variant", 20.0, 13.0)
    folder = root / "select-hold-none"
    folder.mkdir()
    ranking = [{"candidate": str(variant)}, {"candidate": str(root / "p2b-none-s1" / "best.pt")}]
    (folder / "selection.json").write_text(json.dumps({"ranking": ranking}))
    shutil.copyfile(
        root / "select-none" / "p2b-nuscenes1-u.safetensors", folder / "p2b-nuscenes1-u.safetensors"
    )
    argv = [str(root), "none", "p2b-nuscenes1-u", "--select", "select-hold-none", "--dry-run"]
    assert script.main(argv) == 0
    out = capsys.readouterr().out
    assert "p2b-none-s1-h0.3 unseen 13.0 beats previous_box 12.0" in out
    assert "p2b-nuscenes1-u: would ship p2b-none-s1-h0.3" in out


def test_hold_variants_change_only_the_still_target_test(tmp_path):
    """Each variant of a run's validated weights: the given hold, every weight and every other
    inference setting as the run's; a rerun keeps the files it finds."""
    script = _script("hold_variants")
    torch.manual_seed(0)
    tracker = trackers.make("p2b", **trackers.size_config("p2b", "slim"))
    run = tmp_path / "p2b-none-s0"
    run.mkdir()
    trackers.save(tracker, run / "model.safetensors")
    script.load_tracker = lambda path: trackers.load(run / "model.safetensors")
    paths = script.write_variants(run, [0.15, 0.6], tmp_path / "hold")
    assert [p.name for p in paths] == [
        "p2b-none-s0-h0.15.safetensors",
        "p2b-none-s0-h0.6.safetensors",
    ]
    for path, hold in zip(paths, (0.15, 0.6), strict=True):
        variant = trackers.load(path)
        assert variant.inference.hold_chamfer_m == hold
        assert variant.inference.rerank_top_k == tracker.inference.rerank_top_k
        state, reference = variant.state_dict(), tracker.state_dict()
        assert all(torch.equal(state[k], reference[k]) for k in reference)
    stamp = paths[0].stat().st_mtime_ns
    script.write_variants(run, [0.15], tmp_path / "hold")
    assert paths[0].stat().st_mtime_ns == stamp
    with pytest.raises(SystemExit):
        script.main([str(run), "--holds", "0", "--out", str(tmp_path / "x")])
    zones = script.write_variants(run, [0.0, 2.5], tmp_path / "zone", min_motions=[1.0])
    assert [p.name for p in zones] == [
        "p2b-none-s0-h0-m1.safetensors",
        "p2b-none-s0-h2.5-m1.safetensors",
    ]
    for path, hold in zip(zones, (0.0, 2.5), strict=True):
        inference = trackers.load(path).inference
        assert (inference.hold_chamfer_m, inference.min_motion_m) == (hold, 1.0)
    other = script.write_variants(run, [2.5], tmp_path / "zone", [1.0], prefix="budget-")
    assert [p.name for p in other] == ["budget-p2b-none-s0-h2.5-m1.safetensors"]
    script.load_tracker = trackers.load  # a tracker file (or a shipped name) as it is
    (held,) = script.write_variants(run / "model.safetensors", [0.2], tmp_path / "file")
    assert held.name == "model-h0.2.safetensors"
    assert trackers.load(held).inference.hold_chamfer_m == 0.2


def test_still_moving_splits_tracklets_by_previous_box_and_weights_by_frames():
    still_moving = _script("still_moving")

    def row(name, scores):  # tracklet -> (Success, frames)
        per = {k: {"success": s, "frames": f} for k, (s, f) in scores.items()}
        return {"candidate": name, "per_tracklet": per}

    ranking = [
        row("a.safetensors", {"t0": (50.0, 10), "t1": (90.0, 30), "t2": (20.0, 20)}),
        row("previous_box", {"t0": (100.0, 10), "t1": (80.0, 30), "t2": (10.0, 20)}),
    ]
    out = still_moving.split_scores(ranking, still=80.0)
    assert out["still"]["tracklets"] == 2 and out["still"]["frames"] == 40
    assert out["still"]["a.safetensors"] == pytest.approx((50 * 10 + 90 * 30) / 40)
    assert out["still"]["previous_box"] == pytest.approx((100 * 10 + 80 * 30) / 40)
    assert out["moving"]["tracklets"] == 1
    assert out["moving"]["a.safetensors"] == pytest.approx(20.0)
    with pytest.raises(SystemExit, match="previous_box"):
        still_moving.split_scores(ranking[:1], still=80.0)


def test_still_test_variants_hold_sparse_crops_and_put_the_first_crop_back():
    from trackers import decision

    variants = _script("still_test_variants")
    gen = torch.Generator().manual_seed(0)
    size = torch.tensor([4.0, 2.0, 1.5])
    target = (torch.rand(64, 3, generator=gen) - 0.5) * size * 0.8 + torch.tensor([0, 0, 0.2])
    search = torch.cat([target, torch.zeros(64, 3)])  # zero rows pad the search
    crops = torch.stack([target[:32].repeat(8, 1), target[32:].repeat(8, 1)])  # (2, 256, 3)
    scene = decision.Scene(search, size, crops)
    first = scene.first
    held = variants._still_variant("previous")(scene, 0.5)
    assert scene.first is first  # the re-ranking after the test reads the real first crop
    assert bool(held) == bool(decision._still(decision.Scene(search, size, crops[[1, 1]]), 0.5))
    sparse = decision.Scene(search[:3].clone(), size, crops)  # 3 points: too few to decide
    assert not bool(decision._still(sparse, 0.5))
    assert bool(variants._still_variant("sparse")(sparse, 0.5))


def test_table4_names_a_folder_without_one_report(tmp_path):
    script = _script("table4")
    (tmp_path / "test" / "p2b-none-s0").mkdir(parents=True)
    with pytest.raises(SystemExit, match="p2b-none-s0/report.json: cannot read an eval report"):
        script.main([str(tmp_path)])


def test_results_markdown_cells_carry_intervals_and_skip_the_unseen_category():
    script = _script("results_markdown")

    def entry(s, p, lo, hi, seeds=None):
        out = {"success": s, "precision": p, "success_interval": [lo, hi]}
        return out | ({"success_seeds": seeds} if seeds else {})

    report = {
        "observed": entry(44.85, 60.25, 34.61, 55.19),
        "unseen": entry(40.5, 49.1, 31.8, 49.3, [41.6, 39.6, 40.3]),
        "categories": {
            "Pedestrian": entry(28.0, 43.4, 19.6, 39.6),
            "Car": entry(40.5, 49.1, 31.8, 49.3),
        },
        "per_tracklet": [
            {"category": "Pedestrian", "observed": True},
            {"category": "Car", "observed": False},
        ],
    }
    lines = script.table({"p2b-kitti1-u": report}).splitlines()
    assert lines[0] == "| tracker | observed | unseen | unseen Success per eval seed | Pedestrian |"
    assert lines[2] == (
        "| `p2b-kitti1-u` | 44.9 [34.6, 55.2] / 60.2 | 40.5 [31.8, 49.3] / 49.1 "
        "| 41.6 / 39.6 / 40.3 | 28.0 [19.6, 39.6] / 43.4 |"
    )


def test_search_coverage_flags_centres_outside_the_previous_crop():
    script = _script("search_coverage")
    # a 4 x 2 m box heading along +y: its crop reaches 1.25 * 4 / 2 + 2 = 4.5 m along, 3.25 across
    centres = np.array([[0.0, 0.0], [0.0, 4.4], [3.3, 4.4], [3.3, 4.4]])
    yaw = np.full(4, np.pi / 2)
    flags = script.outside(centres, yaw, np.full(4, 4.0), np.full(4, 2.0))
    assert flags.tolist() == [False, True, False]
    # + 3 m a side: 5.5 m along, 4.25 across
    wide = script.outside(centres, yaw, np.full(4, 4.0), np.full(4, 2.0), (1.25, 3.0))
    assert wide.tolist() == [False, False, False]
    boxes = np.zeros((4, 7))
    boxes[:, :2] = centres
    boxes[3, 0] += 0.09  # under STILL_M (0.1 m)
    tracklet = types.SimpleNamespace(boxes=boxes, category="Car")
    assert script.still_pairs([tracklet])["Car"][0].tolist() == [False, False, True]


def _weather_result(folder: Path, clean: float, levels: dict[str, list[float]]) -> None:
    """A minimal ``weather.json`` whose groups all share ``clean`` and per-kind ``levels``."""
    entry = {
        kind: {
            "clean": [clean, 0.0],
            "levels": [[v, 0.0] for v in values],
            "DR": [1 - sum(values) / len(values) / clean, 0.0],
        }
        for kind, values in levels.items()
    }
    robustness = {kind: {g: e for g in ("mean", "observed", "unseen")} for kind, e in entry.items()}
    (folder / "weather_x").mkdir(parents=True)
    result = {"tracker": folder.name, "kinds": list(levels), "robustness": robustness}
    (folder / "weather_x" / "weather.json").write_text(json.dumps(result))


def test_drct_seeds_tables_paired_differences_and_verdict(tmp_path, capsys):
    script = _script("drct_seeds")
    runs = {  # name: (clean, fog levels, rain levels)
        "plain-s21": (40.0, [36.0, 32.0], [38.0, 34.0]),  # weather mean 35.0
        "plain-s22": (42.0, [38.0, 34.0], [40.0, 36.0]),  # 37.0
        "drct-s21": (40.5, [40.0, 38.0], [40.0, 38.0]),  # 39.0
        "drct-s22": (41.5, [41.0, 39.0], [41.0, 39.0]),  # 40.0
    }
    for name, (clean, fog, rain) in runs.items():
        _weather_result(tmp_path / "weather" / name, clean, {"fog": fog, "rain": rain})
    assert script.main([str(tmp_path), "--arms", "plain", "drct", "--seeds", "21", "22"]) == 0
    out = capsys.readouterr().out
    # plain-s21: DR fog 1 - 34/40 = 0.15, rain 1 - 36/40 = 0.10: mean 0.125
    assert "| plain-s21 | 40.0 | 35.0 | 0.125 |" in out
    # drct DR 1 - 39 / 40.5 = 0.0370 and 1 - 40 / 41.5 = 0.0361: mean 0.0366, sd 0.0006
    assert "| drct (mean ± sd) | 41.0 ± 0.7 | 39.5 ± 0.7 | 0.037 ± 0.001 |" in out
    # clean differences +0.5, -0.5 and weather differences 4, 3: sd 0.707 each, half width
    # 6.314 * 0.707 / sqrt(2) = 3.16
    assert "| drct − plain (paired, 90 %) | +0.0 [-3.2, 3.2] | +3.5 [0.3, 6.7] |" in out
    # gain 3.5 > larger sd 1.41, interval above 0, clean +0.0: helps
    assert "weather-mean Success +3.50 [+0.34, +6.66] (paired, 90 %; larger sd 1.41)" in out
    assert "clean +0.00: DRCT helps" in out


def test_drct_seeds_takes_a_later_roots_runs(tmp_path, capsys):
    script = _script("drct_seeds")
    first, second = tmp_path / "a", tmp_path / "b"
    for name, clean in (("plain-s21", 40.0), ("drct-s21", 40.0), ("plain-s22", 42.0)):
        _weather_result(first / "weather" / name, clean, {"fog": [30.0]})
    _weather_result(second / "weather" / "drct-s21", 50.0, {"fog": [45.0]})  # replaces a's
    _weather_result(second / "weather" / "drct-s22", 44.0, {"fog": [33.0]})
    argv = [str(first), str(second), "--arms", "plain", "drct", "--seeds", "21", "22"]
    assert script.main(argv) == 0
    out = capsys.readouterr().out
    assert "| drct-s21 | 50.0 | 45.0 | 0.100 |" in out and "start" not in out


def test_drct_seeds_names_a_missing_run(tmp_path):
    script = _script("drct_seeds")
    with pytest.raises(SystemExit, match="plain-s21: expected one"):
        script.main([str(tmp_path), "--arms", "plain", "drct", "--seeds", "21"])


def test_search_lever_pairs_the_seeds_and_gives_the_verdict(tmp_path, capsys):
    script = _script("search_lever")
    new, pilot = tmp_path / "new", tmp_path / "pilot"
    rows = [{"candidate": "previous_box", "success": 40.0}]
    for seed, (ours, theirs) in enumerate([(30.0, 25.0), (31.0, 24.0), (29.0, 26.0)]):
        rows.append({"candidate": str(new / f"p2b-none-s{seed}/best.pt"), "success": ours})
        rows.append({"candidate": str(pilot / f"p2b-none-s{seed}/best.pt"), "success": theirs})
    selection = tmp_path / "selection.json"
    selection.write_text(json.dumps({"ranking": rows}))
    assert script.main([str(selection), str(new), str(pilot)]) == 0
    out = capsys.readouterr().out
    # differences 5, 7, 3: mean 5, sd 2, half width 2.92 * 2 / sqrt(3) = 3.37
    assert "new - reference: +5.0 [+1.6, +8.4] (90 %, t, 2 df)" in out
    assert "the region is a lever" in out
    rows[1]["success"] = 20.0  # differences -5, 7, 3: the interval reaches below 0
    selection.write_text(json.dumps({"ranking": rows}))
    script.main([str(selection), str(new), str(pilot)])
    assert "not a lever at this budget" in capsys.readouterr().out
    script.main([str(selection), str(new), str(pilot), "--seeds", "2"])
    assert "new - reference: +3.0 (one seed: no interval" in capsys.readouterr().out
    with pytest.raises(SystemExit, match="lacks"):
        script.main([str(selection), str(new), str(tmp_path / "elsewhere")])
    with pytest.raises(SystemExit, match="p2b-decorrelation-s0"):  # -W runs' names
        script.main([str(selection), str(new), str(pilot), "--arm", "decorrelation"])


def test_mbptrack_ship_picks_the_best_val_run_and_gates_on_the_predecessors(tmp_path):
    script = _script("mbptrack_ship")
    a = _run(tmp_path, "a", {4: {"val_success": 30.0}, 8: {"val_success": 41.5}})
    b = _run(tmp_path, "b", {4: {"val_success": 41.5}})
    c = _run(tmp_path, "c", {4: {"val_success": 45.0}})
    assert script.best_val_run([a, b]) == a  # a tie: the first run given
    assert script.best_val_run([a, b, c]) == c
    rows = [
        {"candidate": name, "success": 50.0 - i}
        for i, name in enumerate(["bat-kitti1-u", "u1/best.pt", "u0/best.pt", "p2b-kitti1-u"])
    ] + [{"candidate": "gpt-kitti1-u", "success": 1.0}]
    selection = tmp_path / "selection.json"
    selection.write_text(json.dumps({"ranking": rows}))
    assert script.first_of(selection, ["u0/best.pt", "u1/best.pt"]) == "u1/best.pt"
    lines = script.gate_lines(rows, "u1/best.pt", "u")
    assert lines == [
        "  above p2b-kitti1-u",
        "  below bat-kitti1-u",
        "  above gpt-kitti1-u",
        "  -> mbptrack-kitti1-u does not ship",
    ]
    assert script.gate_lines(rows[1:] + rows[:1], "u1/best.pt", "u")[-1].endswith(" ships")
    with pytest.raises(SystemExit, match="ranks none of"):
        script.first_of(selection, ["other/best.pt"])


def test_mbptrack_ship_ships_only_where_the_mbptrack_run_ranks_first(tmp_path, capsys, monkeypatch):
    import trackers.registry

    script = _script("mbptrack_ship")
    shipped, recipes, select = tmp_path / "checkpoints", tmp_path / "recipes", tmp_path / "sel"
    for folder in (shipped, recipes, select):
        folder.mkdir()
    trackers.registry.write_manifest(shipped)
    monkeypatch.setattr(trackers.registry, "CHECKPOINT_DIR", shipped.resolve())
    torch.manual_seed(0)
    tracker = trackers.make("mbptrack", **trackers.size_config("mbptrack", "slim"))
    trackers.save(tracker, select / "mbptrack-kitti1-u.safetensors")
    order = ["bat-kitti1-u", "runs/m/mbptrack-u-s1/best.pt", "p2b-kitti1-u", "gpt-kitti1-u"]
    (select / "selection.json").write_text(
        json.dumps({"ranking": [{"candidate": c} for c in order]})
    )
    assert not script.ship(select, "mbptrack-kitti1-u", ["make it"], shipped, recipes)
    assert "not shipped (bat-kitti1-u ranks first)" in capsys.readouterr().out
    assert [p.name for p in shipped.iterdir()] == ["manifest.json"]
    order = order[1:] + order[:1]
    (select / "selection.json").write_text(
        json.dumps({"ranking": [{"candidate": c} for c in order]})
    )
    assert script.ship(select, "mbptrack-kitti1-u", ["make it"], shipped, recipes)
    source = select / "mbptrack-kitti1-u.safetensors"
    assert (shipped / source.name).read_bytes() == source.read_bytes()
    recipe_text = (recipes / "mbptrack-kitti1-u.yaml").read_text()
    assert "(docs/mbptrack.md)" in recipe_text.splitlines()[0]
    assert yaml.safe_load(recipe_text)["commands"] == ["make it"]
    light = "mbptrack-kitti1-u-light"  # gated on the -U predecessors by default
    trackers.save(tracker, select / f"{light}.safetensors")
    (select / "selection.json").write_text(json.dumps({"ranking": [{"candidate": order[-1]}]}))
    assert not script.ship(select, light, ["make it"], shipped, recipes)
    assert f"{light}: not shipped (bat-kitti1-u ranks first)" in capsys.readouterr().out
    held = ("mbptrack-kitti1-u", "previous_box")  # the hold selection: the file itself first
    (select / "selection.json").write_text(json.dumps({"ranking": [{"candidate": held[0]}]}))
    assert not script.ship(select, held[0], ["make it"], shipped, recipes, not_if=held)
    assert "not shipped (mbptrack-kitti1-u ranks first)" in capsys.readouterr().out
