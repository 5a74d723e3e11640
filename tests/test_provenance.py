"""Checkpoint provenance (``trackers.provenance``, ``training.provenance``): the record, its
round trips through save / load / training checkpoints / select / finetune, the back-filled
shipped files, ``pointtrack info``, and the guards of eval, select and finetune."""

from __future__ import annotations

import argparse
import hashlib
import json
import re
import warnings
from pathlib import Path
from types import SimpleNamespace

import numpy as np
import pytest
import torch
import yaml

import trackers
from envs.data.settings import SETTINGS
from envs.metrics import OPEAccumulator
from trackers.provenance import (
    UNKNOWN,
    Provenance,
    strip_provenance_bytes,
    with_provenance_bytes,
)
from trackers.registry import CHECKPOINT_DIR, read_safetensors
from training.checkpoint import parent_entry
from training.provenance import (
    ProvenanceWarning,
    check_candidates,
    check_finetune_categories,
    eval_guard,
    finetune_provenance,
    mark_unseen,
    selection_round,
    train_provenance,
)
from training.selection import SelectionConfig, ValPart, save_selected

ROOT = Path(__file__).resolve().parents[1]
KITTI1_OBSERVED = ["Cyclist", "Pedestrian", "Van"]


def _stage(**changes) -> Provenance:
    """A complete from-scratch stage on world 0's train split of the default world."""
    fields = dict(
        written_by="train",
        dataset="synthetic",
        root_kind="generated",
        preset="default",
        sensor="hdl64",
        world_seed=0,
        setting="kitti-1",
        categories=KITTI1_OBSERVED,
        splits=["train"],
        selection=[],
        parent=None,
    )
    return Provenance(**(fields | changes))


def _slim_p2b():
    torch.manual_seed(0)
    return trackers.make("p2b", **trackers.size_config("p2b", "slim"))


# --------------------------------------------------------------------------- the record


def test_provenance_json_round_trip_and_lineage():
    parent = {"name": "base", "sha256": "ab" * 32, "provenance": _stage(categories=["Car"])}
    prov = _stage(written_by="finetune", steps=10, samples=10, parent=parent)
    again = Provenance.from_json(prov.to_json())
    assert again == prov
    assert [s.written_by for s in again.lineage()] == ["finetune", "train"]
    assert again.trained_categories() == ["Car", *KITTI1_OBSERVED]
    assert {p["split"] for p in again.trained_parts()} == {"train"}
    # an unknown parent makes the lineage unknown: nothing is guessed
    assert _stage(parent=UNKNOWN).trained_categories() is None
    assert _stage(parent={"name": "x"}).trained_parts() is None
    assert Provenance.from_json(None) == Provenance()
    assert Provenance().trained_categories() is None


@pytest.mark.parametrize(
    ("raw", "match"),
    [
        ("{", "not valid JSON"),
        ('{"bogus": 1}', r"unknown field\(s\) \['bogus'\]"),
        ('{"steps": -3}', "steps: expected an int >= 0"),
        ('{"categories": "Car"}', "categories: expected a list"),
        ('{"version": 9}', "version 9"),
        ('{"parent": {"sha256": "x"}}', "parent: expected null or an object with a name"),
        ('{"nuscenes_frame": "global"}', "nuscenes_frame: expected one of"),
    ],
)
def test_bad_provenance_is_refused_naming_the_field(raw, match):
    with pytest.raises(ValueError, match=match):
        Provenance.from_json(raw, "f.safetensors")


def test_save_load_round_trip_and_a_file_without_provenance(tmp_path):
    model = _slim_p2b()
    bare = trackers.save(model, tmp_path / "bare.safetensors")
    assert trackers.load(bare).provenance == Provenance()  # unknown, not guessed
    assert "provenance" not in read_safetensors(bare, "t")[0]
    prov = _stage(steps=5, samples=80)
    for suffix in (".safetensors", ".pt"):
        path = trackers.save(model, tmp_path / f"m{suffix}", provenance=prov)
        loaded = trackers.load(path)
        assert loaded.provenance == prov
        path2 = trackers.save(loaded, tmp_path / f"again{suffix}")  # carried by the tracker
        assert trackers.load(path2).provenance == prov
    data = (tmp_path / "m.safetensors").read_bytes()
    broken = with_provenance_bytes(data, SimpleNamespace(to_json=lambda: '{"steps": -5}'))
    (tmp_path / "broken.safetensors").write_bytes(broken)
    with pytest.raises(ValueError, match="broken.safetensors: provenance metadata: .*steps"):
        trackers.load(tmp_path / "broken.safetensors")


def test_save_refuses_non_finite_weights_naming_the_tensor(tmp_path):
    model = _slim_p2b()
    name, param = next(iter(model.named_parameters()))
    with torch.no_grad():
        param.view(-1)[0] = float("nan")
    with pytest.raises(ValueError, match=rf"tensor '{name}' has 1 NaN or inf.*refusing to save"):
        trackers.save(model, tmp_path / "nan.safetensors")
    assert not list(tmp_path.iterdir())  # nothing written, no temporary left


def test_header_rewrite_keeps_every_tensor_byte_and_other_key(tmp_path):
    path = trackers.save(_slim_p2b(), tmp_path / "m.safetensors")
    data = path.read_bytes()
    added = with_provenance_bytes(data, _stage())
    assert strip_provenance_bytes(added) == data
    assert with_provenance_bytes(added, _stage()) == added  # idempotent
    meta, tensors = read_safetensors(_write(tmp_path / "a.safetensors", added), "t")
    old_meta, old_tensors = read_safetensors(path, "t")
    assert {k: v for k, v in meta.items() if k != "provenance"} == old_meta
    assert all(torch.equal(tensors[k], old_tensors[k]) for k in old_tensors)


def _write(path: Path, data: bytes) -> Path:
    path.write_bytes(data)
    return path


# --------------------------------------------------------------------------- shipped files


def _recipes() -> dict[str, dict]:
    return {
        p.stem: yaml.safe_load(p.read_text())
        for p in sorted((ROOT / "configs" / "checkpoints").glob("*.yaml"))
    }


def test_every_shipped_file_has_a_recipe_and_its_provenance():
    recipes = _recipes()
    shipped = sorted(p.stem for p in CHECKPOINT_DIR.glob("*.safetensors"))
    assert sorted(recipes) == shipped
    for name in shipped:
        prov = trackers.load(name).provenance
        assert prov.config_file == f"configs/checkpoints/{name}.yaml"
        assert prov.written_by == "backfill"
        recorded = {k: v for k, v in prov.to_dict().items() if k in recipes[name]["provenance"]}
        assert Provenance.from_dict(recorded) == Provenance.from_dict(
            recipes[name]["provenance"]
        ), name
        setting = re.search(r"-(kitti|nuscenes)([12])-", name).expand(r"\1-\2")
        assert prov.setting == setting, name
        categories = prov.trained_categories()  # every shipped lineage is known to its start
        assert categories is not None and set(categories) == set(SETTINGS[setting].observed)


def test_backfill_changed_only_the_provenance_key():
    """Without its provenance key each shipped file is byte for byte the file before the
    back-fill (its SHA-256 recorded in the recipe): tensors and other metadata unchanged."""
    manifest = json.loads((CHECKPOINT_DIR / "manifest.json").read_text())["files"]
    for name, recipe in _recipes().items():
        data = (CHECKPOINT_DIR / f"{name}.safetensors").read_bytes()
        assert hashlib.sha256(data).hexdigest() == manifest[f"{name}.safetensors"]
        before = hashlib.sha256(strip_provenance_bytes(data)).hexdigest()
        assert before == recipe["sha256_without_provenance"], name


def test_cli_info_prints_the_provenance(capsys):
    from training.cli import main

    assert main(["info", "p2b-kitti2-u"]) == 0
    out = capsys.readouterr().out
    assert "setting: kitti-2" in out and "config_file: configs/checkpoints/p2b-kitti2-u.yaml" in out
    assert "categories trained on, every stage: Car, Cyclist, Van" in out
    assert main(["info", "--json", "p2b-kitti1-w"]) == 0
    data = json.loads(capsys.readouterr().out)
    assert data["tracker"] == "p2b" and data["provenance"]["parent"]["name"].startswith("p2b")
    assert main(["info", "no-such-file"]) == 2
    assert "no-such-file" in capsys.readouterr().err


# --------------------------------------------------------------------------- writers


def test_training_checkpoint_carries_train_provenance(tmp_path):
    from training.checkpoint import CHECKPOINT_FORMAT, tracker_from_checkpoint
    from training.config import TrainConfig

    model = _slim_p2b()
    cfg = TrainConfig(tracker="p2b", model_size="slim", batch_size=16, init_weights="p2b-kitti1-u")
    root = "/cache/worlds/default-hdl64-s0-0123456789ab"
    prov = train_provenance(cfg.to_dict(), root, 7, parent=parent_entry("p2b-kitti1-u"))
    assert (prov.samples, prov.steps, prov.generator_digest) == (112, 7, "0123456789ab")
    assert prov.categories == KITTI1_OBSERVED and prov.splits == ["train"]
    assert prov.parent["provenance"] == trackers.load("p2b-kitti1-u").provenance
    assert prov.trained_categories() == KITTI1_OBSERVED
    ckpt = {"format": CHECKPOINT_FORMAT, "model": model.state_dict(), "config": cfg.to_dict()}
    torch.save(ckpt | {"provenance": prov.to_json(), "step": 7}, tmp_path / "best.pt")
    tracker = tracker_from_checkpoint(tmp_path / "best.pt")
    assert tracker.provenance == prov
    trackers.save(tracker, tmp_path / "export.safetensors")  # `train --export`
    assert trackers.load(tmp_path / "export.safetensors").provenance == prov
    # a checkpoint written before provenance: what its config says, the rest unknown
    torch.save(ckpt | {"step": 3}, tmp_path / "old.pt")
    old = tracker_from_checkpoint(tmp_path / "old.pt").provenance
    assert (old.setting, old.steps, old.git_commit, old.generator_digest) == (
        "kitti-1",
        3,
        UNKNOWN,
        UNKNOWN,
    )


def test_finetune_provenance_names_the_base_and_its_categories(tmp_path):
    from training.rl.config import FinetuneConfig

    cfg = FinetuneConfig(tracker="p2b-kitti2-u", setting="kitti-1", data_root=str(tmp_path))
    prov = finetune_provenance(cfg, 4096, parent_entry(cfg.tracker))
    assert (prov.written_by, prov.steps, prov.root_kind, prov.dataset) == (
        "finetune",
        4096,
        "given",
        UNKNOWN,
    )
    base = CHECKPOINT_DIR / "p2b-kitti2-u.safetensors"
    assert prov.parent["sha256"] == hashlib.sha256(base.read_bytes()).hexdigest()
    assert prov.trained_categories() == ["Car", "Cyclist", "Pedestrian", "Van"]


def test_select_save_records_the_selection(tmp_path):
    path = trackers.save(_slim_p2b(), tmp_path / "cand.safetensors", provenance=_stage())
    config = SelectionConfig(preset="tiny", parts=(ValPart(0, "val"), ValPart(1, "test")))
    rows = [
        {"candidate": str(path), "success": 41.234},
        {"candidate": "previous_box", "success": 9},
    ]
    out = save_selected(rows, config, tmp_path / "chosen.safetensors")
    prov = trackers.load(out).provenance
    assert prov.written_by == "select"
    assert prov.selection == [selection_round(config, rows)]
    assert prov.selection[0]["scores"] == {str(path): 41.23, "previous_box": 9.0}
    assert prov.selection_parts()[1] == {
        "dataset": "synthetic",
        "preset": "tiny",
        "sensor": "hdl64",
        "world_seed": 1,
        "split": "test",
    }
    with pytest.raises(ValueError, match="'previous_box' is not a tracker file"):
        save_selected(rows[::-1], config, tmp_path / "x.safetensors")


# --------------------------------------------------------------------------- guards


def _args(**changes) -> argparse.Namespace:
    values = dict(
        dataset="synthetic",
        root=None,
        preset="default",
        sensor="hdl64",
        seed=0,
        split="test",
        setting="kitti-1",
        categories=None,
        reference="prediction",
        template_mode=None,
        strict=False,
    )
    return argparse.Namespace(**(values | changes))


def _tracker(prov: Provenance):
    return SimpleNamespace(provenance=prov)


def test_eval_guard_flags_a_file_trained_on_the_unseen_category():
    loaded = {"car-file": _tracker(_stage(categories=["Car", "Van"]))}
    with pytest.warns(ProvenanceWarning, match=r"'car-file' was trained on \['Car'\].*kitti-1"):
        trained = eval_guard(loaded, _args(), "kitti-1")
    assert trained == {"car-file": ["Car", "Van"]}
    with pytest.raises(ValueError, match=r"trained on \['Car'\].*--strict"):
        eval_guard(loaded, _args(strict=True), "kitti-1")


def test_eval_guard_flags_the_training_and_selection_data():
    chosen = _stage(selection=[{"parts": ["1:val"], "preset": "default", "sensor": "hdl64"}])
    loaded = {"f": _tracker(chosen)}
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        eval_guard(loaded, _args(), "kitti-1")  # world 0 test: held out, no warning
        eval_guard(loaded, _args(seed=1, split="test"), "kitti-1")
        eval_guard(loaded, _args(preset="small", split="train"), "kitti-1")  # another world
    with pytest.warns(
        ProvenanceWarning, match=r"'f' was trained on split\(s\) \['train'\].*seed 0"
    ):
        eval_guard(loaded, _args(split="all"), "kitti-1")
    with pytest.warns(ProvenanceWarning, match=r"'f' was selected on split\(s\) \['val'\].*seed 1"):
        eval_guard(loaded, _args(seed=1, split="val"), "kitti-1")
    with pytest.raises(ValueError, match="trained on split.*world evaluated"):
        eval_guard(loaded, _args(split="train", strict=True), "kitti-1")
    with pytest.warns(ProvenanceWarning, match="records no .*provenance"):
        assert eval_guard({"old": _tracker(Provenance())}, _args(), "kitti-1") == {}
    assert (
        eval_guard({"previous_box": object()}, _args(), "kitti-1") == {}
    )  # baselines learnt nothing


def test_the_nuscenes_frame_is_recorded_and_checked_by_eval():
    lidar = _stage(dataset="nuscenes", setting="nuscenes-1", categories=["Truck"])
    assert "nuscenes_frame" not in lidar.to_dict()  # records before the field: byte-identical
    scene = lidar.replace(nuscenes_frame="scene")
    assert Provenance.from_json(scene.to_json()) == scene
    assert scene.to_dict()["nuscenes_frame"] == "scene"
    nus = dict(dataset="nuscenes", preset="default-km", sensor="hdl32", setting="nuscenes-1")
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        eval_guard({"f": _tracker(scene)}, _args(**nus, nuscenes_frame="scene"), "nuscenes-1")
        eval_guard({"f": _tracker(lidar)}, _args(**nus), "nuscenes-1")
    with pytest.warns(ProvenanceWarning, match="'scene' frame and is evaluated in the 'lidar'"):
        eval_guard({"f": _tracker(scene)}, _args(**nus), "nuscenes-1")
    with pytest.raises(ValueError, match="--nuscenes-frame lidar"):
        eval_guard(
            {"f": _tracker(lidar)},
            _args(**nus, nuscenes_frame="scene", strict=True),
            "nuscenes-1",
        )


def _report(observed: dict[str, bool]) -> dict:
    rng = np.random.default_rng(0)
    acc = OPEAccumulator()
    for i, (category, flag) in enumerate(observed.items()):
        for t in range(2):
            n = 5 + 3 * i + t
            acc.add(f"{category}/{t}", category, flag, rng.uniform(0, 1, n), rng.uniform(0, 3, n))
    report = acc.report(curves=True)
    report["per_tracklet"] = [
        {"tracklet": r.tracklet_id, "category": r.category, "observed": r.observed}
        for r in acc.results
    ]
    return report


def test_mark_unseen_equals_an_evaluation_that_calls_the_category_observed():
    report = _report({"Car": False, "Van": True, "Pedestrian": True})
    expected = _report({"Car": True, "Van": True, "Pedestrian": True})
    got = mark_unseen({"f": report, "g": report}, {"f": ["Car", "Van"]})
    assert got["g"] is report  # nothing it trained on is unseen: unchanged
    f = got["f"]
    assert f["relabelled_observed"] == ["Car"] and f["categories"]["Car"]["observed"]
    for group in ("observed", "mean"):
        for key in ("success", "precision", "frames", "tracklets"):
            assert f[group][key] == pytest.approx(expected[group][key], abs=1e-9), (group, key)
        assert np.allclose(f[group]["success_curve"], expected[group]["success_curve"])
    assert f["unseen"]["frames"] == 0 and np.isnan(f["unseen"]["success"])
    assert all(t["observed"] for t in f["per_tracklet"])


def test_select_refuses_candidates_trained_on_the_parts_or_the_unseen_category():
    config = SelectionConfig(parts=(ValPart(0, "val"), ValPart(1, "test")))
    check_candidates({"ok": _tracker(_stage()), "previous_box": object()}, config)
    on_world1 = _stage(parent={"name": "w1", "provenance": _stage(world_seed=1, splits=["test"])})
    with pytest.raises(ValueError, match="candidate 'w1-file' was trained on world 1 test"):
        check_candidates({"w1-file": _tracker(on_world1)}, config)
    with pytest.raises(ValueError, match=r"candidate 'car' was trained on \['Car'\].*kitti-1"):
        check_candidates({"car": _tracker(_stage(categories=["Car"]))}, config)
    lines: list[str] = []
    check_candidates({"old": _tracker(Provenance())}, config, lines.append)
    assert lines == ["old: provenance unknown, not checked against the parts and setting"]
    tiny = SelectionConfig(preset="tiny", parts=(ValPart(1, "test"),))
    check_candidates({"w1-file": _tracker(on_world1)}, tiny)  # another preset: another world


def test_finetune_refuses_an_env_serving_a_held_out_category():
    base = _tracker(_stage())  # kitti-1: Car held out
    check_finetune_categories(base, "kitti-1", allow=False)
    with pytest.raises(ValueError, match=r"serves \['Car'\].*kitti-1.*--allow-held-out"):
        check_finetune_categories(base, "kitti-2", allow=False)
    check_finetune_categories(base, "kitti-2", allow=True)
    with pytest.warns(ProvenanceWarning, match="records no setting"):
        check_finetune_categories(_tracker(Provenance()), "kitti-2", allow=False)


# --------------------------------------------------------------------------- bad inputs


def test_select_refuses_one_file_given_by_name_and_path(tmp_path):
    from training.selection import score_candidates

    shipped = str(CHECKPOINT_DIR / "p2b-kitti2-u.safetensors")
    config = SelectionConfig(preset="tiny", parts=(ValPart(1, "val"),), setting="kitti-2")
    with pytest.raises(ValueError, match="'p2b-kitti2-u' and '.*p2b-kitti2-u.safetensors' are the"):
        score_candidates(["p2b-kitti2-u", shipped], config)


def test_tied_with_first_names_exact_ties_only():
    from training.selection import tied_with_first

    rows = [{"candidate": "a", "success": 40.0}, {"candidate": "b", "success": 40.0}]
    assert tied_with_first(rows + [{"candidate": "c", "success": 39.99}]) == ["b"]
    assert tied_with_first([rows[0], {"candidate": "c", "success": 39.99}]) == []


def test_cli_ctrl_c_prints_interrupted_and_exits_130(monkeypatch, capsys):
    from training import cli
    from training.commands import info

    def interrupted(args):
        raise KeyboardInterrupt

    monkeypatch.setattr(info, "run", interrupted)
    assert cli.main(["info", "p2b-kitti2-u"]) == 130
    assert capsys.readouterr().err.strip() == "pointtrack info: interrupted"


@pytest.mark.parametrize("size", [[0.0, 1.0, 1.0], [4.0, -1.0, 1.5]])
def test_act_refuses_a_non_positive_size_naming_the_field(size):
    obs = {
        "template": np.zeros((512, 3), np.float32),
        "search": np.zeros((1024, 3), np.float32),
        "size": np.array(size, np.float32),
        "motion": np.zeros(4, np.float32),
    }
    with pytest.raises(ValueError, match=r"observation\['size'\] must be > 0.*" + str(size[1])):
        _slim_p2b().act(obs)


def test_a_real_training_run_records_its_provenance(tmp_path, capsys):
    """``pointtrack train``'s trainer writes the provenance into its checkpoints, and the
    exported tracker file carries it (steps and samples as run; the data root of fake
    tracklets is not a generated world, so its digest stays unknown)."""
    from test_pretrain_support import train_slim_tracker

    from training.checkpoint import tracker_from_checkpoint
    from training.provenance import git_commit

    result = train_slim_tracker(tmp_path / "run", epochs=1, iters_per_epoch=2)
    tracker = tracker_from_checkpoint(result.out / "last.pt")
    prov = tracker.provenance
    assert (prov.written_by, prov.steps, prov.samples, prov.splits) == ("train", 2, 4, ["train"])
    assert (prov.setting, prov.categories, prov.parent) == ("kitti-1", KITTI1_OBSERVED, None)
    assert prov.git_commit == git_commit() != UNKNOWN and prov.generator_digest == UNKNOWN
    assert len(prov.config_hash) == 64
    path = trackers.save(tracker, tmp_path / "export.safetensors")
    assert trackers.load(path).provenance == prov
    from training.cli import main

    assert main(["info", str(result.out / "last.pt")]) == 0  # a training checkpoint too
    assert "written_by: train\n" in capsys.readouterr().out


def test_cli_eval_reports_a_category_the_file_trained_on_as_observed(tmp_path, capsys):
    """A file trained with Car evaluated as kitti-1 (Car unseen): a warning naming both, Car
    reported observed (no ``*``); ``--strict`` refuses it before any evaluation."""
    from training.cli import main

    car = _stage(categories=["Car", *KITTI1_OBSERVED])
    path = trackers.save(_slim_p2b(), tmp_path / "car.safetensors", provenance=car)
    argv = ["eval", "--tracker", str(path), "--preset", "tiny", "--max-tracklets", "2"]
    with pytest.warns(ProvenanceWarning, match=r"car.safetensors' was trained on \['Car'\]"):
        assert main([*argv, "--no-progress"]) == 0
    out = capsys.readouterr().out
    assert "Car*" not in out and "Car" in out
    assert main([*argv, "--strict"]) == 2
    err = capsys.readouterr().err
    assert "trained on ['Car'], which setting kitti-1 holds out" in err and "--strict" in err


def test_finetune_provenance_names_the_world_ensure_world_makes():
    """The generator digest a fine-tune records (computed without generating the world) is the
    one ``ensure_world`` names the world's directory by, as a training run records it."""
    from envs.synthetic import ensure_world
    from training.rl.config import FinetuneConfig

    cfg = FinetuneConfig(tracker="p2b-kitti1-u", preset="tiny", world_seed=0)
    root = ensure_world(preset="tiny", sensor="hdl64", seed=0)
    prov = finetune_provenance(cfg, 8, parent_entry(cfg.tracker))
    assert (prov.preset, prov.world_seed, prov.root_kind) == ("tiny", 0, "generated")
    assert (
        prov.generator_digest
        == train_provenance({"dataset": "synthetic"}, root, 0).generator_digest
    )
    assert root.name.endswith(prov.generator_digest)


def test_cli_finetune_refuses_a_held_out_category_before_any_work(tmp_path, capsys):
    from training.cli import main

    out = tmp_path / "ft"
    argv = ["finetune", "--tracker", "p2b-kitti1-u", "--setting", "kitti-2", "--out", str(out)]
    assert main([*argv, "--no-progress"]) == 2
    err = capsys.readouterr().err
    assert "pointtrack finetune: the training env (setting kitti-2) serves ['Car']" in err
    assert "--allow-held-out" in err and not out.exists()


def test_cli_select_save_appends_its_round_to_the_winner(tmp_path, capsys, one_torch_thread):
    from training.cli import main

    out = tmp_path / "chosen.safetensors"
    argv = ["select", "p2b-kitti1-u", "previous_box", "--preset", "tiny", "--parts", "0:val"]
    assert main([*argv, "--num-envs", "1", "--no-progress", "--save", str(out)]) == 0
    assert f"wrote {out}" in capsys.readouterr().out
    shipped, chosen = trackers.load("p2b-kitti1-u"), trackers.load(out)
    assert all(torch.equal(v, shipped.state_dict()[k]) for k, v in chosen.state_dict().items())
    prov = chosen.provenance
    assert prov.selection[:-1] == shipped.provenance.selection  # earlier rounds kept
    last = prov.selection[-1]
    assert (last["parts"], last["preset"], last["chosen"]) == (["0:val"], "tiny", "p2b-kitti1-u")
    assert set(last["scores"]) == {"p2b-kitti1-u", "previous_box"}
    assert prov.replace(written_by="backfill", selection=shipped.provenance.selection) == (
        shipped.provenance
    )
