"""The pretraining loop (training.pretrain) with a stand-in tracker and fake tracklets."""

from __future__ import annotations

import pytest
import torch
from test_pretrain_support import TinyTracker, small_dataset, tiny_config

from training.config import ConfigError, TrainConfig, config_from_dict, load_config
from training.pretrain import TrainingError, train


def _run(out, *, resume=False, nan_at=None, val_fn=False, **kw):
    cfg = tiny_config(out, **kw)
    return train(cfg, resume=resume, model_factory=lambda c: TinyTracker(nan_at_step=nan_at),
                 train_data=small_dataset(), val_fn=val_fn)


def _weights(path):
    return torch.load(path, weights_only=True)["model"]


def test_two_epoch_run_lowers_the_loss(tmp_path):
    res = _run(tmp_path / "a", epochs=2, iters_per_epoch=8, val_fn=lambda m: {"success": 1.0,
                                                                              "precision": 2.0})
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
    with pytest.raises(TrainingError, match="already exists"):
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
        train(cfg, resume=True, model_factory=lambda c: model, train_data=small_dataset(),
              val_fn=False)
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

    with pytest.raises(SystemExit) as err:
        main(["train", "--tracker", "p2b", "--out", str(tmp_path / "x"), "--set", "nope=1"])
    assert "nope" in str(err.value)
    assert not (tmp_path / "x").exists()


def test_resume_exact_with_a_real_tracker(tmp_path):
    """The same kill-and-resume equality with P2B (slim widths), whose backbone samples points
    with its own generator."""
    trackers = pytest.importorskip("trackers")
    from test_pretrain_support import fake_tracklets

    from training.config import tracker_config
    from training.samples import TrackingSamples

    def run(out, epochs, resume=False):
        cfg = tiny_config(out, epochs=epochs, batch_size=2, iters_per_epoch=1,
                          weighting="decorrelation", model_size="slim")
        data = TrackingSamples(fake_tracklets(n=2, frames=4), candidates_per_frame=1)
        return train(cfg, resume=resume, train_data=data, val_fn=False,
                     model_factory=lambda c: trackers.make("p2b", **tracker_config("p2b", "slim")))

    run(tmp_path / "full", 2)
    run(tmp_path / "cut", 1)
    run(tmp_path / "cut", 2, resume=True)
    a, b = _weights(tmp_path / "full" / "last.pt"), _weights(tmp_path / "cut" / "last.pt")
    for k in a:
        assert torch.equal(a[k], b[k]), k


def test_init_weights_starts_from_a_checkpoint_and_checks_it(tmp_path):
    """``init_weights`` copies a saved tracker's weights into the run's model before step 1 (so
    zero epochs of training would return them unchanged) and refuses another tracker or config."""
    trackers = pytest.importorskip("trackers")
    from test_pretrain_support import fake_tracklets

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
        cfg = tiny_config(tmp_path / "run", batch_size=2, model_size="slim",
                          init_weights=str(init), **extra)
        return Trainer(cfg, train_data=data, val_fn=False)

    model = trainer(path).model
    for k, v in source.state_dict().items():
        assert torch.equal(model.state_dict()[k], v), k
    with pytest.raises(TrainingError, match="holds a 'p2b' checkpoint, not 'bat'"):
        trainer(path, tracker="bat")
    with pytest.raises(TrainingError, match="another tracker config"):
        trainer(path, tracker_config={"hidden_channels": 32})
    with pytest.raises(TrainingError, match="no such checkpoint"):
        trainer(tmp_path / "missing.safetensors")
    with pytest.raises(ConfigError, match="init_weights"):
        config_from_dict({"init_weights": " "})
