"""training.rl.run / `pointtrack finetune`: the PPO run, its run directory, resume, NaN stops,
the residual variant without unpickling (issue 22 items 2, 5; issue 23 rows 1, 17)."""

from __future__ import annotations

import base64
import dataclasses
import json
import os
import pickle
import signal
import subprocess
import sys
import time
import zipfile
from pathlib import Path

import gymnasium as gym
import numpy as np
import pytest
import torch

import trackers
from envs.tracking_env import TrackingEnv, make_toy_dataset
from training.cli import main
from training.parallel import usable_cores
from training.rl import config as ftc
from training.rl import run as ft
from training.rl import state as fts
from training.rl.wrappers import ResidualTracker

pytestmark = pytest.mark.usefixtures("one_torch_thread")
REPO = Path(__file__).resolve().parents[1]


@pytest.fixture(scope="module")
def data():
    return make_toy_dataset(num_frames=8)


def tiny_cfg(**kwargs) -> ftc.FinetuneConfig:
    base = {
        "tracker": "p2b-kitti1-u",
        "timesteps": 32,
        "num_envs": 2,
        "n_steps": 4,
        "batch_size": 8,
        "n_epochs": 1,
        "clip_length": 4,
        "warmup_rollouts": 1,
    }
    return ftc.FinetuneConfig(**{**base, **kwargs})


def run(cfg, out, data, **kwargs):
    return ft.finetune(
        cfg,
        out,
        make_env=lambda: TrackingEnv(data, sampling="random"),
        progress=False,
        log=lambda *_: None,
        **kwargs,
    )


def log_steps(out: Path) -> list[int]:
    return [json.loads(line)["step"] for line in (out / "log.jsonl").read_text().splitlines()]


def test_ppo_run_writes_an_ordinary_tracker_checkpoint(tmp_path, data):
    out = tmp_path / "run"
    threads = torch.get_num_threads()
    result = run(tiny_cfg(snapshot_every=2), out, data)
    assert result.timesteps == 32 and result.updates == 4
    # every usable core by default, recorded as the count that ran; the caller's count restored
    assert json.loads((out / "config.json").read_text())["threads"] == usable_cores()
    assert torch.get_num_threads() == threads
    tuned, base = trackers.load(out / "tracker.safetensors"), trackers.load("p2b-kitti1-u")
    changed = [k for k, v in tuned.state_dict().items() if not torch.equal(v, base.state_dict()[k])]
    assert changed and all(k.startswith("head.") for k in changed)  # train_parts="head"
    provenance = tuned.provenance  # its own, not the base's (training.provenance)
    assert (provenance.written_by, provenance.steps, provenance.parent["name"]) == (
        "finetune",
        32,
        "p2b-kitti1-u",
    )
    assert provenance.parent["provenance"] == base.provenance
    snapshot = trackers.load(out / "snapshots/tracker-00000016.safetensors")
    assert snapshot.provenance.steps == 16
    assert log_steps(out) == [8, 16, 24, 32]
    records = [json.loads(line) for line in (out / "log.jsonl").read_text().splitlines()]
    assert records[0]["actor_frozen"] and not records[1]["actor_frozen"]
    assert records[0]["approx_kl"] == 0.0  # warm-up: the actor did not move
    assert all(0.0 <= r["iou"] <= 1.0 and r["steps_per_s"] > 0 for r in records)
    assert sorted(p.name for p in (out / "snapshots").iterdir()) == [
        "tracker-00000016.safetensors",
        "tracker-00000032.safetensors",
    ]
    torch.testing.assert_close(
        trackers.load(out / "snapshots/tracker-00000032.safetensors").state_dict(),
        tuned.state_dict(),
    )
    _, _, _, meta = fts.load_state(out / "state.safetensors")
    assert meta["finished"] and meta["timesteps"] == 32


def test_out_dir_refusals_name_the_problem(tmp_path, data):
    out = tmp_path / "run"
    run(tiny_cfg(timesteps=8), out, data)
    with pytest.raises(ftc.FinetuneError, match="already holds a run.*--resume.*--overwrite"):
        run(tiny_cfg(timesteps=8), out, data)
    with pytest.raises(
        ftc.FinetuneError,
        match=r"another tracker or config \(gamma: saved 0.9, "
        r"given 0.5; tracker: saved 'p2b-kitti1-u', "
        r"given 'bat-kitti1-u'",
    ):
        run(tiny_cfg(timesteps=16, gamma=0.5, tracker="bat-kitti1-u"), out, data, resume=True)
    with pytest.raises(ftc.FinetuneError, match="nothing to resume"):
        run(tiny_cfg(), tmp_path / "empty", data, resume=True)
    with pytest.raises(
        ftc.FinetuneError, match="algo must be one of \\['ppo', 'group', 'residual'\\]"
    ):
        run(tiny_cfg(algo="sac"), tmp_path / "x", data)
    if not torch.cuda.is_available():
        with pytest.raises(ftc.FinetuneError, match="device 'cuda': CUDA is not available"):
            run(tiny_cfg(device="cuda"), tmp_path / "y", data)
    run(tiny_cfg(timesteps=8), out, data, overwrite=True)
    assert log_steps(out) == [8]


def test_self_critical_run_trains_and_needs_one_step_returns(tmp_path, data):
    with pytest.raises(ftc.FinetuneError, match="self_critical.*set gamma=0 \\(got gamma=0.9\\)"):
        run(tiny_cfg(baseline="self_critical"), tmp_path / "bad", data)
    with pytest.raises(ftc.FinetuneError, match="baseline must be one of \\['critic'"):
        run(tiny_cfg(baseline="greedy"), tmp_path / "bad", data)
    out = tmp_path / "run"
    result = run(tiny_cfg(baseline="self_critical", gamma=0.0), out, data)
    assert result.timesteps == 32
    tuned, base = trackers.load(out / "tracker.safetensors"), trackers.load("p2b-kitti1-u")
    assert any(not torch.equal(v, base.state_dict()[k]) for k, v in tuned.state_dict().items())
    # the logged episode reward is the env's own (IoU), not the baseline-subtracted one
    records = [json.loads(line) for line in (out / "log.jsonl").read_text().splitlines()]
    assert any(r["ep_reward"] is not None for r in records)
    assert all(r["ep_reward"] is None or r["ep_reward"] >= 0 for r in records)


def test_group_run_trains_resumes_and_refuses_what_does_not_apply(tmp_path, data):
    with pytest.raises(ftc.FinetuneError, match="group_size must be >= 2, got 1"):
        run(tiny_cfg(algo="group", group_size=1), tmp_path / "bad", data)
    with pytest.raises(ftc.FinetuneError, match="baseline 'self_critical' does not apply"):
        run(tiny_cfg(algo="group", baseline="self_critical", gamma=0.0), tmp_path / "bad", data)
    out = tmp_path / "run"
    cfg = tiny_cfg(algo="group", group_size=4, timesteps=16, snapshot_every=2)
    assert run(cfg, out, data).timesteps == 16
    result = run(dataclasses.replace(cfg, timesteps=32), out, data, resume=True)
    assert result.timesteps == 32 and log_steps(out) == [8, 16, 24, 32]
    records = [json.loads(line) for line in (out / "log.jsonl").read_text().splitlines()]
    # no critic warm-up: the actor trains from the first update
    assert not any(r["actor_frozen"] for r in records)
    assert all(r["group_reward_std"] >= 0 and 0 <= r["iou"] <= 1 for r in records)
    tuned, base = trackers.load(out / "tracker.safetensors"), trackers.load("p2b-kitti1-u")
    changed = [k for k, v in tuned.state_dict().items() if not torch.equal(v, base.state_dict()[k])]
    assert changed and all(k.startswith("head.") for k in changed)
    with pytest.raises(ftc.FinetuneError, match="group_size: saved 4, given 8"):
        run(dataclasses.replace(cfg, timesteps=48, group_size=8), out, data, resume=True)


def test_interrupted_run_resumes_from_its_checkpoint(tmp_path, data, monkeypatch):
    out = tmp_path / "run"
    original = ft.PPORun.after_update

    def stop_after_two(self):
        original(self)
        if self.updates == 2:
            raise KeyboardInterrupt  # a kill right after the second checkpoint

    monkeypatch.setattr(ft.PPORun, "after_update", stop_after_two)
    with pytest.raises(KeyboardInterrupt):
        run(tiny_cfg(), out, data)
    monkeypatch.setattr(ft.PPORun, "after_update", original)
    policy_sd, optim_sd, _, meta = fts.load_state(out / "state.safetensors")
    assert meta["timesteps"] == 16 and not meta["finished"]
    assert not (out / "tracker.safetensors").exists()
    # the state restores into a fresh policy exactly (optimizer moments included)
    with pytest.raises(ftc.FinetuneError, match="already holds a run"):
        run(tiny_cfg(), out, data)
    result = run(tiny_cfg(), out, data, resume=True)
    assert result.timesteps == 32 and result.updates == 4
    assert log_steps(out) == [8, 16, 24, 32]
    assert optim_sd["state"] and all(
        torch.isfinite(t).all() for e in optim_sd["state"].values() for t in e.values()
    )
    assert set(policy_sd) == set(fts.load_state(out / "state.safetensors")[0])
    trackers.load(out / "tracker.safetensors")


def test_ppo_run_loads_the_compiled_kernels_before_its_clock(monkeypatch, tmp_path, data):
    # steps/s measures the loop: numba's start (~0.8 s) belongs to the set-up, not the first reset
    loaded: list[tuple[object, float]] = []
    monkeypatch.setattr(ft, "load_kernels", lambda t: loaded.append((t, time.perf_counter())))
    r = ft.PPORun(tiny_cfg(timesteps=16), tmp_path / "run", lambda: TrackingEnv(data))
    assert [t for t, _ in loaded] == [r.policy.tracker] and loaded[0][1] <= r.t0


def test_state_round_trips_policy_and_optimizer(tmp_path, data):
    out = tmp_path / "run"
    run(tiny_cfg(timesteps=16), out, data)
    cfg = tiny_cfg(timesteps=16)
    r = ft.PPORun(
        cfg,
        out,
        lambda: TrackingEnv(data, sampling="random"),
        resume_meta=fts.read_state_meta(out / "state.safetensors"),
    )
    policy_sd, optim_sd, _, _ = fts.load_state(out / "state.safetensors")
    for k, v in r.policy.state_dict().items():
        assert torch.equal(v, policy_sd[k]), k
    restored = r.policy.optimizer.state_dict()
    assert [g["lr_scale"] for g in restored["param_groups"]] == [1.0, cfg.tracker_lr / cfg.lr]
    for idx, entry in optim_sd["state"].items():
        for key, value in entry.items():
            assert torch.equal(torch.as_tensor(restored["state"][idx][key]), value)
    r.env.close()


class NanAfter(gym.Wrapper):
    """Rewards become NaN after ``k`` steps (a numerical fault inside a rollout)."""

    def __init__(self, env, k):
        super().__init__(env)
        self.k, self.n = k, 0

    def step(self, action):
        obs, reward, term, trunc, info = self.env.step(action)
        self.n += 1
        return obs, (float("nan") if self.n > self.k else reward), term, trunc, info


def test_nan_in_a_rollout_stops_naming_the_step_and_keeps_the_last_good_checkpoint(tmp_path, data):
    out = tmp_path / "run"
    with pytest.raises(
        ftc.NonFiniteError,
        match=r"non-finite rewards of the rollout at step 24 "
        r"\(update 2\).*last good checkpoint \(step 16\)",
    ):
        ft.finetune(
            tiny_cfg(),
            out,
            progress=False,
            make_env=lambda: NanAfter(TrackingEnv(data, sampling="random"), 10),
        )
    _, _, _, meta = fts.load_state(out / "state.safetensors")
    assert meta["timesteps"] == 16 and not meta["finished"]
    assert not (out / "tracker.safetensors").exists()


def test_residual_variant_saves_safetensors_and_loads_in_eval(tmp_path, data):
    from training.evaluate import evaluate
    from training.loading import load_tracker

    out = tmp_path / "res"
    run(tiny_cfg(algo="residual", timesteps=16, n_steps=8), out, data)
    assert not (out / "ppo.zip").exists()
    tuned = ResidualTracker.load(out)
    again = load_tracker(str(out / "residual.safetensors"))  # what `pointtrack eval` calls
    assert isinstance(again, ResidualTracker)
    obs, _ = TrackingEnv(data).reset(seed=0)
    np.testing.assert_allclose(again.act(obs), tuned.act(obs), atol=1e-6)
    batch = {k: np.stack([v, v]) for k, v in obs.items()}
    np.testing.assert_allclose(tuned.act(batch), np.stack([tuned.act(obs)] * 2), atol=1e-5)
    assert 0.0 <= evaluate(again, TrackingEnv(data))["mean"]["success"] <= 100.0


class _Payload:
    """Unpickling this creates ``path`` (stands for arbitrary code)."""

    def __init__(self, path):
        self.path = str(path)

    def __reduce__(self):
        return (open, (self.path, "w"))


def _crafted_sb3_zip(path: Path, marker: Path) -> None:
    blob = base64.b64encode(pickle.dumps(_Payload(marker))).decode()
    data = {"policy_class": {":type:": "<class 'abc.ABCMeta'>", ":serialized:": blob}}
    with zipfile.ZipFile(path, "w") as z:
        z.writestr("data", json.dumps(data))
        z.writestr("_stable_baselines3_version", "2.0.0")


def test_a_crafted_ppo_zip_is_never_unpickled(tmp_path):
    run_dir, marker = tmp_path / "ft", tmp_path / "pwned"
    run_dir.mkdir()
    _crafted_sb3_zip(run_dir / "ppo.zip", marker)
    (run_dir / "finetune.json").write_text(json.dumps({"tracker": "p2b-kitti1-u"}))
    with pytest.raises(ValueError, match="ppo.zip.*refused.*unpickles"):
        ResidualTracker.load(run_dir)
    with pytest.raises(ValueError, match="SB3 zips are refused"):
        ResidualTracker.load(run_dir / "ppo.zip")
    from training.loading import load_tracker

    with pytest.raises((ValueError, FileNotFoundError)):
        load_tracker(str(run_dir / "ppo.zip"))
    assert not marker.exists()
    # the payload is live: SB3's own loader runs it (why nothing of ours calls PPO.load)
    from stable_baselines3 import PPO

    with pytest.raises(Exception):  # noqa: B017 - whatever fails after the payload ran
        PPO.load(run_dir / "ppo.zip")
    assert marker.exists()


def test_cli_bad_flags_are_one_line_errors(tmp_path, capsys):
    with pytest.raises(SystemExit) as exc:
        main(["finetune", "--val-max-tracklets", "0", "--out", str(tmp_path / "x")])
    assert exc.value.code == 2
    err = capsys.readouterr().err.strip()
    assert err == (
        "pointtrack finetune: --val-max-tracklets must be >= 1, got 0 (use --no-val "
        "to skip the val check)"
    )
    with pytest.raises(SystemExit) as exc:
        main(["finetune", "--algo", "sac", "--out", str(tmp_path / "x")])
    assert exc.value.code == 2
    err = capsys.readouterr().err
    assert "--algo: invalid choice: 'sac'" in err and "ppo" in err and "residual" in err
    with pytest.raises(SystemExit) as exc:
        main(["finetune", "--tracker", "previous_box", "--out", str(tmp_path / "x")])
    assert exc.value.code == 2
    assert "no parameters to train" in capsys.readouterr().err
    assert not (tmp_path / "x").exists()


TINY_RUN = [
    "finetune",
    "--tracker",
    "p2b-kitti1-u",
    "--preset",
    "tiny",
    "--num-envs",
    "2",
    "--n-steps",
    "4",
    "--batch-size",
    "8",
    "--n-epochs",
    "1",
    "--clip-length",
    "4",
    "--no-progress",
]


def test_cli_end_to_end_result_loads_and_evaluates(tmp_path, capsys):
    out = tmp_path / "ft"
    assert (
        main([*TINY_RUN, "--timesteps", "16", "--val-max-tracklets", "1", "--out", str(out)]) == 0
    )
    text = capsys.readouterr().out
    assert "base: val success" in text and "finetuned: val success" in text
    assert json.loads((out / "val.json").read_text())["tracklets"] == 1
    trackers.load(out / "tracker.safetensors")
    assert (
        main(
            [
                "eval",
                "--tracker",
                str(out / "tracker.safetensors"),
                "--preset",
                "tiny",
                "--max-tracklets",
                "1",
                "--no-progress",
            ]
        )
        == 0
    )
    assert "tracker.safetensors" in capsys.readouterr().out
    # --resume --out DIR alone takes DIR's config; a flag that changes it is refused by name
    with pytest.raises(SystemExit) as exc:
        main(["finetune", "--resume", "--out", str(out), "--gamma", "0.5", "--timesteps", "24"])
    assert exc.value.code == 2
    assert "(--gamma: saved 0.9, given 0.5)" in capsys.readouterr().err
    assert (
        main(
            [
                "finetune",
                "--resume",
                "--out",
                str(out),
                "--timesteps",
                "24",
                "--no-val",
                "--no-progress",
            ]
        )
        == 0
    )
    assert log_steps(out) == [8, 16, 24]


@pytest.mark.slow
def test_sigkill_and_resume_through_the_cli(tmp_path):
    from envs.synthetic import ensure_world

    ensure_world(preset="tiny")  # in this run's cache, shared with the child through the env
    out = tmp_path / "ft"
    args = [
        sys.executable,
        "-m",
        "training.cli",
        *TINY_RUN,
        "--timesteps",
        "64",
        "--no-val",
        "--out",
        str(out),
    ]
    env = {**os.environ, "PYTHONPATH": str(REPO), "OMP_NUM_THREADS": "1"}
    child = subprocess.Popen(
        args, cwd=REPO, env=env, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE
    )
    deadline = time.monotonic() + 240
    while time.monotonic() < deadline and child.poll() is None:
        state = out / "state.safetensors"
        if state.exists() and fts.read_state_meta(state)["timesteps"] >= 16:
            break
        time.sleep(0.2)
    assert child.poll() is None, child.stderr.read().decode()
    child.send_signal(signal.SIGKILL)
    child.wait()
    killed_at = fts.read_state_meta(out / "state.safetensors")["timesteps"]
    assert killed_at < 64 and not (out / "tracker.safetensors").exists()
    done = subprocess.run([*args, "--resume"], cwd=REPO, env=env, capture_output=True, timeout=300)
    assert done.returncode == 0, done.stderr.decode()
    steps = log_steps(out)
    assert steps == sorted(set(steps)) and steps[-1] == 64 and steps[0] == 8
    assert fts.read_state_meta(out / "state.safetensors")["finished"]
    trackers.load(out / "tracker.safetensors")
    assert not list(out.glob(".*tmp*"))


def test_every_finetune_flag_reaches_the_config():
    """Each config field has its flag, and a value given on the command line arrives in the
    config with the field's type (a float flag parsed as int, or a dropped flag, would change
    a run silently)."""
    import argparse
    import dataclasses

    from training.commands.finetune import add_arguments, build_config

    parser = argparse.ArgumentParser()
    add_arguments(parser)
    dests = {a.dest for a in parser._actions}
    fields = {f.name: f for f in dataclasses.fields(ftc.FinetuneConfig)}
    assert set(fields) <= dests
    given = {
        "tracker": ("bat-kitti1-u", "bat-kitti1-u"),
        "algo": ("residual", "residual"),
        "setting": ("kitti-2", "kitti-2"),
        "preset": ("small", "small"),
        "sensor": ("hdl32", "hdl32"),
        "world_seed": ("3", 3),
        "data_root": ("/data/k", "/data/k"),
        "reward": ("iou_bev", "iou_bev"),
        "clip_length": ("16", 16),
        "timesteps": ("512", 512),
        "num_envs": ("2", 2),
        "n_steps": ("32", 32),
        "batch_size": ("16", 16),
        "n_epochs": ("3", 3),
        "lr": ("0.001", 1e-3),
        "tracker_lr": ("2e-5", 2e-5),
        "train_parts": ("all", "all"),
        "action_mode": ("soft", "soft"),
        "critic": ("separate", "separate"),
        "baseline": ("self_critical", "self_critical"),
        "log_std_init": ("-3", -3.0),
        "warmup_rollouts": ("2", 2),
        "target_kl": ("0.05", 0.05),
        "clip_range": ("0.2", 0.2),
        "max_grad_norm": ("1", 1.0),
        "gamma": ("0", 0.0),
        "group_size": ("4", 4),
        "gae_lambda": ("0.9", 0.9),
        "ent_coef": ("0.01", 0.01),
        "seed": ("7", 7),
        "device": ("cpu", "cpu"),
        "threads": ("2", 2),
        "save_every": ("3", 3),
        "snapshot_every": ("4", 4),
        "val_max_tracklets": ("5", 5),
        "logger": ("csv,json", "csv,json"),
        "untrained": (None, True),  # switches
        "allow_held_out": (None, True),
    }
    assert set(given) == set(fields)
    argv = []
    for dest, (text, _) in given.items():
        argv += ["--" + dest.replace("_", "-"), *([] if text is None else [text])]
    cfg = build_config(parser.parse_args(argv))
    for dest, (_, expected) in given.items():
        value = getattr(cfg, dest)
        assert value == expected and type(value) is type(expected), dest


# ---------------------------------------------------------------- issue 42's bad inputs 1-6


def test_a_run_directory_of_another_command_is_refused(tmp_path, data):
    """42.1: ``--overwrite`` never deletes another command's run (here a ``pointtrack train``
    one), and ``train`` refuses a finetune directory."""
    from training.pretrain import TrainingError, check_run_dir

    train_dir = tmp_path / "train-run"
    train_dir.mkdir()
    for name in ("config.yaml", "last.pt", "log.jsonl"):
        (train_dir / name).write_text("x")
    for overwrite in (False, True):
        with pytest.raises(ftc.FinetuneError, match="holds a `pointtrack train` run"):
            run(tiny_cfg(), train_dir, data, overwrite=overwrite)
    assert sorted(p.name for p in train_dir.iterdir()) == ["config.yaml", "last.pt", "log.jsonl"]
    ft_dir = tmp_path / "ft-run"
    run(tiny_cfg(timesteps=8), ft_dir, data)
    with pytest.raises(TrainingError, match="holds a `pointtrack finetune` run"):
        check_run_dir(ft_dir, resume=False)


def _cli_config(argv: list[str]) -> ftc.FinetuneConfig:
    import argparse

    from training.commands.finetune import add_arguments, build_config

    parser = argparse.ArgumentParser()
    add_arguments(parser)
    return build_config(parser.parse_args(argv))


def test_resume_compares_what_the_user_passed_even_a_default(tmp_path, data):
    """42.2: ``--resume --algo ppo`` on a group run is refused although ppo is the default;
    ``--resume --out DIR`` alone continues DIR's run as configured."""
    out = tmp_path / "run"
    run(tiny_cfg(algo="group", group_size=4, timesteps=8), out, data)
    alone = _cli_config(["--resume", "--out", str(out), "--timesteps", "16"])
    assert (alone.algo, alone.group_size, alone.timesteps) == ("group", 4, 16)
    changed = _cli_config(["--resume", "--out", str(out), "--algo", "ppo"])
    with pytest.raises(ftc.FinetuneError, match="algo: saved 'group', given 'ppo'"):
        ft.check_out_dir(out, changed, resume=True)


def test_a_bare_learned_name_needs_untrained(tmp_path, data):
    """42.3: ``p2b`` (no weights) is refused naming the flag; with ``untrained`` it trains the
    random initialisation seeded by ``seed`` (two such runs start from the same weights)."""
    from training.commands.finetune import flag_message

    with pytest.raises(ftc.FinetuneError, match="has no weights") as exc:
        run(tiny_cfg(tracker="p2b"), tmp_path / "x", data)
    assert "--untrained" in flag_message(exc.value) and exc.value.fields == ("tracker",)
    assert not (tmp_path / "x").exists()
    cfg = tiny_cfg(tracker="p2b", untrained=True, timesteps=8)
    assert ft.load_base(cfg).state_dict().keys() == trackers.load("p2b").state_dict().keys()
    a, b = ft.load_base(cfg), ft.load_base(cfg)
    assert all(torch.equal(v, b.state_dict()[k]) for k, v in a.state_dict().items())
    assert run(cfg, tmp_path / "u", data).timesteps == 8


def test_every_field_is_checked_before_anything_is_written_and_a_stateless_dir_starts_fresh(
    tmp_path, data, monkeypatch
):
    """42.4: a bad value writes nothing; a run killed inside its first rollout (config and
    log, no state) blocks neither a rerun nor ``--resume``: both start from the beginning."""
    out = tmp_path / "run"
    with pytest.raises(ftc.FinetuneError, match="log_std_init must be finite, got nan"):
        run(tiny_cfg(log_std_init=float("nan")), out, data)
    assert not out.exists()

    def killed(self, local):
        raise KeyboardInterrupt

    monkeypatch.setattr(ft.PPORun, "on_step", killed)
    with pytest.raises(KeyboardInterrupt):
        run(tiny_cfg(), out, data)
    monkeypatch.undo()
    assert (out / "config.json").exists() and not (out / "state.safetensors").exists()
    assert run(tiny_cfg(timesteps=8), out, data).timesteps == 8
    (out / "state.safetensors").unlink()
    (out / "tracker.safetensors").unlink()
    assert run(tiny_cfg(timesteps=8), out, data, resume=True).timesteps == 8
    assert log_steps(out) == [8]


def test_residual_on_a_tracker_with_extra_observation_keys_is_refused_before_training(
    tmp_path, data
):
    """42.5: M2-Track reads ``previous_search``, which the residual tracker does not serve."""
    out = tmp_path / "run"
    with pytest.raises(ftc.FinetuneError, match="algo 'residual' cannot fine-tune.*previous"):
        run(tiny_cfg(algo="residual", tracker="m2track-kitti1-u"), out, data)
    assert not out.exists()


def test_group_size_is_bounded(tmp_path, data):
    """42.6: a huge group is one line, not an allocator traceback."""
    with pytest.raises(ftc.FinetuneError, match=r"group_size must be <= 1024, got 1000000000"):
        run(tiny_cfg(algo="group", group_size=10**9), tmp_path / "x", data)
    assert not (tmp_path / "x").exists()


# ---------------------------------------------------------------- issue 43: logger and config


def test_sb3_logger_writes_the_update_scalars(tmp_path, data, monkeypatch):
    import csv

    out = tmp_path / "run"
    run(tiny_cfg(algo="group", group_size=4, timesteps=16, logger="csv,json"), out, data)
    rows = list(csv.DictReader((out / "sb3/from-00000000/progress.csv").open()))
    assert [int(r["time/updates"]) for r in rows] == [1, 2]
    for key in ("rollout/iou", "train/approx_kl", "train/clip_fraction", "time/steps_per_s"):
        assert all(r[key] != "" and np.isfinite(float(r[key])) for r in rows), key
    assert len((out / "sb3/from-00000000/progress.json").read_text().splitlines()) == 2
    monkeypatch.setattr(ftc.importlib.util, "find_spec", lambda name: None)
    with pytest.raises(ftc.FinetuneError, match=r"pip install 'pointtrack\[tensorboard\]'"):
        tiny_cfg(logger="tensorboard").validate()
    with pytest.raises(ftc.FinetuneError, match="logger must list some of"):
        tiny_cfg(logger="csv,wandb").validate()


def test_config_file_then_flags_then_set(tmp_path):
    """43.5: an RL Zoo-style file < the flags given < ``--set``; bad keys and values name the
    file or the key before any work."""
    path = tmp_path / "group_ppo.yml"
    path.write_text("algo: group\ngroup_size: 4\nn_timesteps: 64\nlearning_rate: 1e-3\n")
    cfg = _cli_config(["--config", str(path)])
    assert (cfg.algo, cfg.group_size, cfg.timesteps, cfg.lr) == ("group", 4, 64, 1e-3)
    assert _cli_config(["--config", str(path), "--group-size", "6"]).group_size == 6
    top = _cli_config(["--config", str(path), "--group-size", "6", "--set", "group_size=7"])
    assert top.group_size == 7 and top.timesteps == 64
    path.write_text("algo: group\ngroup_sise: 4\n")
    with pytest.raises(ftc.FinetuneError, match=f"{path}.*unknown key 'group_sise'"):
        _cli_config(["--config", str(path)])
    with pytest.raises(ftc.FinetuneError, match="n_steps='many': must be an integer"):
        _cli_config(["--set", "n_steps=many"])
    with pytest.raises(ftc.FinetuneError, match="expected KEY=VALUE"):
        _cli_config(["--set", "n_steps"])
