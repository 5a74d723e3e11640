"""The pretraining loop (training.pretrain) with a stand-in tracker and fake tracklets."""

from __future__ import annotations

import pytest
import torch
from test_pretrain_support import TinyTracker, small_dataset, tiny_config

from training.config import ConfigError, TrainConfig, config_from_dict, load_config
from training.pretrain import TrainingError, train


def _run(out, *, resume=False, nan_at=None, val_fn=False, **kw):
    cfg = tiny_config(out, **kw)
    return train(
        cfg,
        resume=resume,
        model_factory=lambda c: TinyTracker(nan_at_step=nan_at),
        train_data=small_dataset(),
        val_fn=val_fn,
    )


def _weights(path):
    return torch.load(path, weights_only=True)["model"]


def test_two_epoch_run_lowers_the_loss(tmp_path):
    res = _run(
        tmp_path / "a",
        epochs=2,
        iters_per_epoch=8,
        val_fn=lambda m: {"success": 1.0, "precision": 2.0},
    )
    first, second = res.history[0]["total"], res.history[1]["total"]
    assert second < first
    assert res.epochs_done == 2 and res.steps == 16
    assert (tmp_path / "a" / "last.pt").exists() and (tmp_path / "a" / "best.pt").exists()
    assert (tmp_path / "a" / "log.jsonl").read_text().count("\n") >= 2
    assert res.best_epoch == 1 and res.history[0]["val_success"] == 1.0


@pytest.mark.parametrize("weighting", ["none", "decorrelation", "sam"])
def test_resume_after_kill_equals_uninterrupted(tmp_path, weighting):
    full = _run(tmp_path / "full", weighting=weighting, epochs=2)
    _run(tmp_path / "cut", weighting=weighting, epochs=1)  # "killed" after epoch 1
    resumed = _run(tmp_path / "cut", weighting=weighting, epochs=2, resume=True)
    assert resumed.steps == full.steps
    a, b = _weights(tmp_path / "full" / "last.pt"), _weights(tmp_path / "cut" / "last.pt")
    for k in a:
        assert torch.equal(a[k], b[k]), k


def test_weightings_differ(tmp_path):
    u = _weights(_run(tmp_path / "u", weighting="none", epochs=1).out / "last.pt")
    w = _weights(_run(tmp_path / "w", weighting="decorrelation", epochs=1).out / "last.pt")
    s = _weights(_run(tmp_path / "s", weighting="sam", epochs=1).out / "last.pt")
    k = "head.weight"
    assert not torch.equal(u[k], w[k]) and not torch.equal(u[k], s[k])


def test_resume_refuses_other_tracker_or_config(tmp_path):
    _run(tmp_path / "r", epochs=1)
    with pytest.raises(TrainingError, match="tracker 'p2b'"):
        _run(tmp_path / "r", epochs=2, resume=True, tracker="bat")
    with pytest.raises(TrainingError, match="lr"):
        _run(tmp_path / "r", epochs=2, resume=True, lr=5e-3)
    with pytest.raises(TrainingError, match="already holds a run"):
        _run(tmp_path / "r", epochs=2)


def test_resume_reads_a_missing_new_key_as_its_default(tmp_path):
    """A checkpoint written before a config key existed resumes when the key is at its default
    (that is what the run did) and refuses when it is not."""
    _run(tmp_path / "r", epochs=1)
    path = tmp_path / "r" / "last.pt"
    ckpt = torch.load(path, weights_only=False)
    del ckpt["config"]["size_jitter"]
    torch.save(ckpt, path)
    with pytest.raises(TrainingError, match="size_jitter: checkpoint 0.0 vs now 0.3"):
        _run(tmp_path / "r", epochs=2, resume=True, size_jitter=0.3)
    assert _run(tmp_path / "r", epochs=2, resume=True).epochs_done == 2


def test_nan_loss_stops_naming_step_and_samples(tmp_path):
    out = tmp_path / "n"
    _run(out, epochs=1)
    before = _weights(out / "last.pt")
    # 4 steps per epoch: the 6th loss call is step 5 of the resumed run (epoch 2)
    with pytest.raises(TrainingError, match=r"step 5 .*sample \d+ \(tracklet"):
        cfg = tiny_config(out, epochs=2)
        model = TinyTracker(nan_at_step=1)
        train(
            cfg,
            resume=True,
            model_factory=lambda c: model,
            train_data=small_dataset(),
            val_fn=False,
        )
    after = torch.load(out / "last.pt", weights_only=True)
    assert after["epoch"] == 1
    for k in before:
        assert torch.equal(before[k], after["model"][k])


def test_bad_configs_fail_naming_keys(tmp_path):
    with pytest.raises(ConfigError, match="unknown keys: bogus, lrr"):
        config_from_dict({"bogus": 1, "lrr": 0.1})
    with pytest.raises(ConfigError) as err:
        config_from_dict({"epochs": 0, "weighting": "magic", "lr": "fast"})
    msg = str(err.value)
    assert "epochs=0" in msg or "epochs" in msg
    assert "lr='fast'" in msg
    with pytest.raises(ConfigError, match="weighting='magic'"):
        config_from_dict({"weighting": "magic"})
    with pytest.raises(ConfigError, match=r"size_jitter=1\.2: must be in \[0, 1\)"):
        config_from_dict({"size_jitter": 1.2})
    f = tmp_path / "c.yaml"
    f.write_text("tracker: gpt\nbatchsize: 12\n")
    with pytest.raises(ConfigError, match=r"c.yaml.*unknown keys: batchsize"):
        load_config(f)
    f.write_text("tracker: gpt\nbatch_size: 12\n")
    cfg = load_config(f)
    assert cfg.tracker == "gpt" and cfg.batch_size == 12
    assert TrainConfig().batch_size == 48 and TrainConfig().lr == 1e-3


def test_train_command_rejects_bad_flags_before_training(tmp_path, capsys):
    from training.cli import main

    assert main(["train", "--tracker", "p2b", "--out", str(tmp_path / "x"), "--set", "nope=1"]) == 2
    err = capsys.readouterr().err
    assert err.startswith("pointtrack train: ") and "nope" in err and err.count("\n") == 1
    assert not (tmp_path / "x").exists()


def test_resume_exact_with_a_real_tracker(tmp_path):
    """The same kill-and-resume equality with P2B (slim widths), whose backbone samples points
    with its own generator."""
    from test_pretrain_support import train_slim_tracker

    def run(out, epochs, resume=False):
        return train_slim_tracker(out, "p2b", resume=resume, epochs=epochs, iters_per_epoch=1)

    run(tmp_path / "full", 2)
    run(tmp_path / "cut", 1)
    run(tmp_path / "cut", 2, resume=True)
    a, b = _weights(tmp_path / "full" / "last.pt"), _weights(tmp_path / "cut" / "last.pt")
    for k in a:
        assert torch.equal(a[k], b[k]), k


def test_init_weights_starts_from_a_checkpoint_and_checks_it(tmp_path):
    """``init_weights`` copies a saved tracker's weights into the run's model before step 1 (so
    zero epochs of training would return them unchanged) and refuses another tracker or config."""
    from test_pretrain_support import fake_tracklets

    import trackers
    from training.config import tracker_config
    from training.pretrain import Trainer
    from training.samples import TrackingSamples

    slim = tracker_config("p2b", "slim")
    source = trackers.make("p2b", **slim)
    with torch.no_grad():
        for p in source.parameters():
            p.add_(0.01)
    path = trackers.save(source, tmp_path / "start.safetensors")
    data = TrackingSamples(fake_tracklets(n=2, frames=4), candidates_per_frame=1)

    def trainer(init, **extra):
        cfg = tiny_config(
            tmp_path / "run", batch_size=2, model_size="slim", init_weights=str(init), **extra
        )
        return Trainer(cfg, train_data=data, val_fn=False)

    model = trainer(path).model
    for k, v in source.state_dict().items():
        assert torch.equal(model.state_dict()[k], v), k
    with pytest.raises(TrainingError, match="holds a 'p2b' checkpoint, not 'bat'"):
        trainer(path, tracker="bat")
    with pytest.raises(TrainingError, match="another tracker config"):
        trainer(path, tracker_config={"hidden_channels": 32})
    # what only labels or weighs the loss may differ: the weights fit the same architecture
    relabelled = trainer(path, tracker_config={"head": {"positive_fraction": 0.2}}).model
    assert relabelled.config.head.positive_fraction == 0.2
    assert relabelled.config.head.vote_channels == source.config.head.vote_channels  # merged
    for k, v in source.state_dict().items():
        assert torch.equal(relabelled.state_dict()[k], v), k
    # a file that holds and re-ranks (tracker.inference, beside the config) starts a run too
    from trackers.decision import InferenceConfig

    source.inference = InferenceConfig(hold_chamfer_m=0.15, rerank_top_k=4)
    held = trainer(trackers.save(source, tmp_path / "held.safetensors")).model
    for k, v in source.state_dict().items():
        assert torch.equal(held.state_dict()[k], v), k
    with pytest.raises(ValueError, match="hold_chamfer_m.*inference settings"):
        trainer(path, tracker_config={"hold_chamfer_m": 0.15})
    with pytest.raises(TrainingError, match="another tracker config.*cluster_radius"):
        trainer(path, tracker_config={"head": {"cluster_radius": 0.5}})
    with pytest.raises(TrainingError, match="no such checkpoint"):
        trainer(tmp_path / "missing.safetensors")
    with pytest.raises(ConfigError, match="init_weights"):
        config_from_dict({"init_weights": " "})
    # a training checkpoint (what `pointtrack select` names) starts from its validated weights
    from training.checkpoint import tracker_from_checkpoint
    from training.pretrain import train

    first = tiny_config(tmp_path / "first", batch_size=2, model_size="slim", ema_decay=0.5)
    train(first, train_data=data, val_fn=False)
    validated = tracker_from_checkpoint(tmp_path / "first" / "last.pt").state_dict()
    model = trainer(tmp_path / "first" / "last.pt").model
    for k, v in validated.items():
        assert torch.equal(model.state_dict()[k], v), k
    with pytest.raises(TrainingError, match="holds a 'p2b' checkpoint, not 'bat'"):
        trainer(tmp_path / "first" / "last.pt", tracker="bat")


def test_every_train_flag_reaches_the_config():
    """Each ``pointtrack train`` flag sets its config key (``--size-jitter`` was once parsed and
    then dropped, so runs that asked for resizing trained without it)."""
    import argparse

    from training.commands.train import add_arguments, build_config

    parser = argparse.ArgumentParser()
    add_arguments(parser)
    not_config = {
        "help",
        "config",
        "set",
        "resume",
        "no_progress",
        "export",
        "drct",
        "domain_randomize",
    }  # switches: tests/test_drct.py (mutually exclusive)
    # flag destination -> (value given on the command line, expected config key and value)
    given = {
        "tracker": ("gpt", "tracker", "gpt"),
        "setting": ("kitti-2", "setting", "kitti-2"),
        "category": ("Car", "category", "Car"),
        "model_size": ("slim", "model_size", "slim"),
        "weighting": ("sam", "weighting", "sam"),
        "dataset": ("kitti", "dataset", "kitti"),
        "preset": ("small", "preset", "small"),
        "sensor": ("hdl32", "sensor", "hdl32"),
        "data_root": ("/data/k", "data_root", "/data/k"),
        "world_seed": ("4", "world_seed", 4),
        "epochs": ("5", "epochs", 5),
        "batch_size": ("6", "batch_size", 6),
        "lr": ("0.002", "lr", 0.002),
        "iters_per_epoch": ("7", "iters_per_epoch", 7),
        "candidates_per_frame": ("2", "candidates_per_frame", 2),
        "size_jitter": ("0.3", "size_jitter", 0.3),
        "search_scale": ("1.5", "search_scale", 1.5),
        "search_offset_m": ("4", "search_offset_m", 4.0),
        "search_center": ("previous", "search_center", "previous"),
        "ema_decay": ("0.99", "ema_decay", 0.99),
        "seed": ("9", "seed", 9),
        "init_weights": ("p2b-kitti1-u", "init_weights", "p2b-kitti1-u"),
        "out": ("runs/z", "out", "runs/z"),
        "num_workers": ("1", "num_workers", 1),
        "threads": ("2", "num_threads", 2),
        "device": ("cuda:1", "device", "cuda:1"),
        "val_max_tracklets": ("3", "val_max_tracklets", 3),
        "val_max_frames": ("11", "val_max_frames", 11),
        "nuscenes_version": ("v1.0-mini", "nuscenes_version", "v1.0-mini"),
        "nuscenes_frame": ("lidar", "nuscenes_frame", "lidar"),  # scene: test_nuscenes_frames
        "drct_variant": ("siamese", "drct_variant", "siamese"),
        "logger": ("tensorboard,csv", "logger", "tensorboard,csv"),
    }
    flags = {a.dest: a.option_strings[0] for a in parser._actions if a.dest not in not_config}
    missing = set(flags) - set(given)
    assert not missing, f"give the new flags a value here: {missing}"
    argv = [part for dest, flag in flags.items() for part in (flag, given[dest][0])]
    cfg = build_config(parser.parse_args(argv))
    for dest in flags:
        _, key, expected = given[dest]
        assert getattr(cfg, key) == expected, dest


def test_weight_ema_matches_a_hand_computation():
    from training.averaging import WeightEMA

    model = torch.nn.BatchNorm1d(2)  # a parameter, float buffers and an integer buffer
    with torch.no_grad():
        model.weight.fill_(1.0)
    ema = WeightEMA(model, decay=0.9)
    expected = 1.0
    for n, value in enumerate([3.0, -1.0, 5.0, 2.0], start=1):
        with torch.no_grad():
            model.weight.fill_(value)
        model.num_batches_tracked.fill_(n)
        d = min(0.9, (1 + n) / (10 + n))  # warm-up: 2/11, 3/12, 4/13, 5/14 (all < 0.9)
        expected = d * expected + (1 - d) * value
        ema.update(model)
        assert torch.allclose(ema.shadow["weight"], torch.full((2,), expected)), n
        assert int(ema.shadow["num_batches_tracked"]) == n
    ema.decay, ema.updates = 0.5, 100  # past the warm-up: the configured decay
    ema.update(model)
    assert torch.allclose(ema.shadow["weight"], torch.full((2,), 0.5 * expected + 0.5 * 2.0))
    with pytest.raises(ValueError, match="decay"):
        WeightEMA(model, decay=1.0)


def test_ema_run_validates_and_exports_the_average_and_resumes_exactly(tmp_path):
    from training.checkpoint import load_weights

    seen = []

    def val_fn(model):
        seen.append({k: v.clone() for k, v in model.state_dict().items()})
        return {"success": float(len(seen)), "precision": 0.0}

    _run(tmp_path / "full", epochs=2, ema_decay=0.8, val_fn=val_fn)
    last = torch.load(tmp_path / "full" / "last.pt", weights_only=True)
    shadow, model = last["ema"]["shadow"], last["model"]
    assert any(not torch.equal(shadow[k], model[k]) for k in model)
    for k in model:  # validation saw the average, and export reads it
        assert torch.equal(seen[-1][k], shadow[k]), k
        assert torch.equal(load_weights(tmp_path / "full" / "last.pt")[0][k], shadow[k]), k
    _run(tmp_path / "cut", epochs=1, ema_decay=0.8)
    _run(tmp_path / "cut", epochs=2, ema_decay=0.8, resume=True)
    cut = torch.load(tmp_path / "cut" / "last.pt", weights_only=True)
    for k in model:
        assert torch.equal(cut["model"][k], model[k]), k
        assert torch.equal(cut["ema"]["shadow"][k], shadow[k]), k
    with pytest.raises(TrainingError, match="ema_decay: checkpoint 0.8 vs now 0.0"):
        _run(tmp_path / "cut", epochs=3, resume=True)
    with pytest.raises(ConfigError, match=r"ema_decay=1\.0: must be in \[0, 1\)"):
        config_from_dict({"ema_decay": 1.0})


# --------------------------------------------------------------------------- scalar logger
def _progress(run, drop=("samples_per_s", "epoch_wall_s")):
    """OUT/logs/progress.csv as rows, without the wall-clock columns (they differ per run)."""
    import csv

    with open(run / "logs" / "progress.csv") as f:
        rows = list(csv.DictReader(f))
    return [{k: v for k, v in r.items() if not k.endswith(drop)} for r in rows]


def test_scalars_go_to_csv_json_and_tensorboard(tmp_path):
    """Every number of log.jsonl reaches OUT/logs as KIND/NAME at its step, in each output."""
    import json

    val = lambda m: {"success": 1.0, "precision": 2.0}  # noqa: E731
    _run(tmp_path / "a", epochs=2, iters_per_epoch=6, val_fn=val)  # train records every 10 steps
    records = [json.loads(x) for x in (tmp_path / "a" / "log.jsonl").read_text().splitlines()]
    assert [r["kind"] for r in records] == ["data", "epoch", "train", "epoch"]
    dumps = [json.loads(x) for x in (tmp_path / "a" / "logs" / "progress.json").open()]
    assert dumps == [
        {
            f"{r['kind']}/{k}": v
            for k, v in r.items()
            if k not in ("kind", "step") and isinstance(v, int | float | str)
        }
        for r in records
    ]
    rows = _progress(tmp_path / "a")
    assert len(rows) == 4 and [r["epoch/val_success"] for r in rows] == ["", "1.0", "", "1.0"]
    assert not list((tmp_path / "a" / "logs").glob("events.out.tfevents.*"))

    pytest.importorskip("tensorboard", reason="the tensorboard extra is not installed")
    from tensorboard.backend.event_processing.event_accumulator import EventAccumulator

    _run(tmp_path / "b", epochs=2, iters_per_epoch=6, val_fn=val, logger="tensorboard")
    events = EventAccumulator(str(tmp_path / "b" / "logs"))
    events.Reload()
    success = events.Scalars("epoch/val_success")
    assert [(e.step, e.value) for e in success] == [(6, 1.0), (12, 1.0)]
    assert [e.step for e in events.Scalars("train/total")] == [10]
    assert not (tmp_path / "b" / "logs" / "progress.csv").exists()


def test_resumed_scalars_equal_an_uninterrupted_runs(tmp_path):
    """The outputs are rewritten from log.jsonl on resume: no rows of the killed attempt (the
    resumed attempt records its data once more, as log.jsonl does)."""
    _run(tmp_path / "full", epochs=3, iters_per_epoch=6)
    _run(tmp_path / "cut", epochs=1, iters_per_epoch=6)
    # the killed attempt had logged a step past the checkpoint: log.jsonl is cut back to it
    with open(tmp_path / "cut" / "log.jsonl", "a") as f:
        f.write('{"kind": "train", "step": 9, "total": 123.0}\n')
    _run(tmp_path / "cut", epochs=3, iters_per_epoch=6, resume=True)
    full, cut = _progress(tmp_path / "full"), _progress(tmp_path / "cut")
    assert "123.0" not in {v for r in cut for v in r.values()}
    assert [r for r in cut if not r["data/samples"]] == [r for r in full if not r["data/samples"]]
    assert len(cut) == len(full) + 1 and len(full) == 5  # data, 3 epochs, step 10


def test_logger_choice_is_checked_before_training(tmp_path, capsys, monkeypatch):
    import sys

    from training.cli import main

    with pytest.raises(ConfigError, match="logger='csv,wandb'"):
        config_from_dict({"logger": "csv,wandb"})
    monkeypatch.setitem(sys.modules, "tensorboard", None)
    out = tmp_path / "x"
    assert main(["train", "--tracker", "p2b", "--out", str(out), "--logger", "tensorboard"]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and 'pip install "pointtrack[tensorboard]"' in err
    assert not out.exists()


def test_loader_workers_train_the_same_bytes(tmp_path):
    """Samples depend on (seed, epoch, index) only, so building them in DataLoader worker
    processes (``--num-workers``, the cheap way to take sample building off the training
    thread) trains the same weights bit for bit as building them in the trainer's process."""
    from test_pretrain_support import train_slim_tracker

    for workers in (0, 1):
        train_slim_tracker(
            tmp_path / str(workers), "p2b", epochs=2, iters_per_epoch=2, num_workers=workers
        )
    a, b = _weights(tmp_path / "0" / "last.pt"), _weights(tmp_path / "1" / "last.pt")
    for k in a:
        assert torch.equal(a[k], b[k]), k
