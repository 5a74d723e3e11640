"""The fault suite (issue 23): bad inputs give one clear error, killed processes leave nothing a
later run reads or trips over, and resumed work ends exactly where an uninterrupted run ends.

Each row test reproduces one row of the issue's table; the SIGKILL tests kill ``generate``,
``train`` and ``select`` at random points (seeded) and check what is left.
"""

from __future__ import annotations

import json
import os
import random
import shutil
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest
import torch

from envs.synthetic import ensure_world, verify_world
from training.cli import main

ROOT = Path(__file__).resolve().parents[1]
TESTS = Path(__file__).resolve().parent


def _env() -> dict[str, str]:
    env = dict(os.environ)
    env["PYTHONPATH"] = os.pathsep.join([str(ROOT), str(TESTS), env.get("PYTHONPATH", "")])
    env["OMP_NUM_THREADS"] = "1"
    return env


def _one_line_error(capsys, command: str, *needles: str) -> str:
    err = capsys.readouterr().err
    assert err.startswith(f"pointtrack {command}: "), err
    assert err.count("\n") == 1, err
    for needle in needles:
        assert needle in err, (needle, err)
    return err


def _leftovers(directory: Path) -> list[str]:
    return sorted(
        p.name
        for p in directory.rglob("*")
        if ".tmp" in p.name or ".trash-" in p.name or p.name.endswith(".lock")
    )


@pytest.fixture(scope="module")
def tiny() -> Path:
    return ensure_world("tiny", "hdl64", 0)


def _partial_root(tiny: Path, dest: Path, drop: str) -> Path:
    """A copy of the tiny world's labels and calibration (scans linked) without scene ``drop``."""
    for sub in ("label_02", "calib"):
        shutil.copytree(tiny / sub, dest / sub)
    (dest / "velodyne").symlink_to(tiny / "velodyne")
    shutil.copy(tiny / "manifest.json", dest / "manifest.json")
    (dest / "label_02" / f"{drop}.txt").unlink()
    return dest


# --------------------------------------------------------------------------- rows of the table


def test_row2_split_missing_a_scene_is_an_error_unless_allowed(tiny, tmp_path, capsys):
    from envs.data import KittiTracking
    from envs.data.kitti import MissingSceneWarning

    root = _partial_root(tiny, tmp_path / "k", "0019")
    with pytest.raises(FileNotFoundError, match=r"scenes 0019 .*label_02/0019\.txt"):
        KittiTracking(root, "test")
    with pytest.warns(MissingSceneWarning, match="0019"):
        assert KittiTracking(root, "all", allow_missing_scenes=True).scenes == ["0000", "0017"]
    assert main(["eval", "--root", str(root), "--split", "all", "--no-progress"]) == 2
    _one_line_error(capsys, "eval", "0019", "--allow-missing-scenes")
    with pytest.warns(MissingSceneWarning):
        assert (
            main(
                [
                    "eval",
                    "--root",
                    str(root),
                    "--split",
                    "all",
                    "--no-progress",
                    "--allow-missing-scenes",
                    "--max-tracklets",
                    "1",
                ]
            )
            == 0
        )
    # without a manifest the KITTI split itself names the scenes
    (root / "manifest.json").unlink()
    with pytest.raises(FileNotFoundError, match="0019, 0020"):
        KittiTracking(root, "test")
    # a root written with a subset on purpose declares it
    from envs.data.kitti import declare_scenes

    declare_scenes(root, ["0000"])
    declare_scenes(root, ["0017"])
    assert KittiTracking(root, "test").tracklets == []
    assert KittiTracking(root, "all").scenes == ["0000", "0017"]
    (root / "label_02" / "0017.txt").unlink()
    with pytest.raises(FileNotFoundError, match="0017"):
        KittiTracking(root, "val")


@pytest.mark.parametrize("count", ["0", "-1"])
def test_row3_max_tracklets_below_one_is_refused(count, capsys):
    assert main(["eval", "--preset", "tiny", "--max-tracklets", count]) == 2
    _one_line_error(capsys, "eval", f"--max-tracklets must be >= 1, got {count}")


def test_row5_untrained_learned_tracker_needs_the_flag_and_is_seeded(capsys):
    from training.loading import UntrainedTrackerError, load_tracker

    assert main(["eval", "--preset", "tiny", "--tracker", "p2b"]) == 2
    _one_line_error(capsys, "eval", "'p2b' has no weights", "--untrained")
    with pytest.raises(UntrainedTrackerError):
        load_tracker("bat")
    before = torch.get_rng_state()
    a, b = load_tracker("p2b", untrained=True, seed=3), load_tracker("p2b", untrained=True, seed=3)
    c = load_tracker("p2b", untrained=True, seed=4)
    assert torch.equal(torch.get_rng_state(), before)  # the caller's RNG is left alone
    sa, sb, sc = a.state_dict(), b.state_dict(), c.state_dict()
    assert all(torch.equal(sa[k], sb[k]) for k in sa)
    assert any(not torch.equal(sa[k], sc[k]) for k in sa if sa[k].is_floating_point())


def test_row6_every_tracker_is_validated_before_any_evaluation(tmp_path, capsys, monkeypatch):
    import training.commands.eval as eval_cmd

    def no_env(*a, **k):
        raise AssertionError("an env was built before every tracker was validated")

    monkeypatch.setattr(eval_cmd, "build_env", no_env)
    out = tmp_path / "x"
    assert main(["eval", "--tracker", "previous_box", "nosuch", "--out", str(out)]) == 2
    _one_line_error(capsys, "eval", "'nosuch'")
    assert not out.exists()


def _training_checkpoint(path: Path, ema: bool) -> dict[str, torch.Tensor]:
    """A best.pt as pretraining writes it (slim P2B; an EMA copy when ``ema``)."""
    import trackers
    from training.checkpoint import CHECKPOINT_FORMAT, atomic_save
    from training.config import TrainConfig

    cfg = TrainConfig(tracker="p2b", model_size="slim")
    torch.manual_seed(0)
    model = trackers.make("p2b", **cfg.make_kwargs())
    weights = {k: v.clone() for k, v in model.state_dict().items()}
    shadow = {k: v + 1 if v.is_floating_point() else v for k, v in weights.items()}
    atomic_save(
        {
            "format": CHECKPOINT_FORMAT,
            "tracker": "p2b",
            "config": cfg.to_dict(),
            "model": weights,
            "ema": {"shadow": shadow} if ema else {},
        },
        path,
    )
    return shadow if ema else weights


@pytest.mark.parametrize("ema", [False, True])
def test_row7_training_checkpoint_evaluates_directly(tiny, tmp_path, capsys, ema):
    from training.loading import load_tracker

    path = tmp_path / "run" / "best.pt"
    expected = _training_checkpoint(path, ema)
    got = load_tracker(str(path)).state_dict()
    assert all(torch.equal(got[k], expected[k]) for k in expected)
    if not ema:
        assert (
            main(
                [
                    "eval",
                    "--tracker",
                    str(path),
                    "--preset",
                    "tiny",
                    "--max-tracklets",
                    "1",
                    "--no-progress",
                ]
            )
            == 0
        )
        assert "best.pt" in capsys.readouterr().out


def test_row7_training_checkpoint_with_nan_weights_names_the_tensor(tmp_path):
    from training.checkpoint import CheckpointError, load_weights

    path = tmp_path / "best.pt"
    weights = _training_checkpoint(path, ema=False)
    ckpt = torch.load(path, weights_only=True)
    name = next(k for k, v in weights.items() if v.is_floating_point())
    ckpt["model"][name] = ckpt["model"][name].clone().fill_(float("nan"))
    torch.save(ckpt, path)
    with pytest.raises(CheckpointError, match=f"tensor '{name}' holds NaN"):
        load_weights(path)


def test_row8_resume_and_out_checks_come_before_any_data(tmp_path, capsys, monkeypatch):
    cache = tmp_path / "cache"
    monkeypatch.setenv("POINTTRACK_CACHE", str(cache))
    assert main(["train", "--resume", "--out", str(tmp_path / "typo"), "--no-progress"]) == 2
    _one_line_error(capsys, "train", "nothing to resume", "typo")
    run = tmp_path / "run"
    run.mkdir()
    (run / "config.yaml").write_text("tracker: bat\nmodel_size: slim\nepochs: 3\n")
    assert main(["train", "--out", str(run), "--no-progress"]) == 2
    _one_line_error(capsys, "train", "already holds a run", "--resume")
    assert not cache.exists()  # no world was generated for either refusal


def test_row8_resume_with_out_alone_reads_the_runs_config(tmp_path):
    import argparse

    from training.commands.train import add_arguments, build_config

    run = tmp_path / "run"
    run.mkdir()
    (run / "config.yaml").write_text("tracker: bat\nmodel_size: slim\nepochs: 3\nlr: 0.005\n")
    parser = argparse.ArgumentParser()
    add_arguments(parser)
    cfg = build_config(parser.parse_args(["--resume", "--out", str(run), "--epochs", "5"]))
    assert (cfg.tracker, cfg.model_size, cfg.lr, cfg.epochs) == ("bat", "slim", 0.005, 5)
    cfg = build_config(parser.parse_args(["--out", str(run)]))  # no --resume: not read
    assert cfg.tracker == "p2b"


def test_row11_non_positive_box_size_names_file_and_line(tiny, tmp_path):
    from envs.data import KittiTracking

    root = _partial_root(tiny, tmp_path / "k", "0017")
    label = root / "label_02" / "0019.txt"
    lines = label.read_text().splitlines()
    fields = lines[2].split()
    fields[11] = "-0.5"  # width
    lines[2] = " ".join(fields)
    label.write_text("\n".join(lines) + "\n")
    with pytest.raises(ValueError, match=r"0019\.txt, line 3: field 12 \(width\) is -0\.5"):
        KittiTracking(root, "test")


def test_row13_damaged_cached_world_is_regenerated_not_reused(tmp_path, capsys):
    root = ensure_world("tiny", "hdl64", 0, cache_dir=tmp_path)
    scan = sorted((root / "velodyne" / "0019").glob("*.bin"))[5]
    original = scan.read_bytes()
    scan.write_bytes(original[: len(original) // 2])  # truncated
    problems = verify_world(root, digests=False)
    assert len(problems) == 1 and scan.name in problems[0]
    assert main(["generate", "--verify", str(root)]) == 1
    assert scan.name in capsys.readouterr().err
    with pytest.warns(UserWarning, match="damaged.*regenerating"):
        again = ensure_world("tiny", "hdl64", 0, cache_dir=tmp_path)
    assert again == root and scan.read_bytes() == original
    assert verify_world(root) == []
    # same size, other bytes: only the digests see it
    scan.write_bytes(bytes(len(original)))
    assert verify_world(root, digests=False) == []
    assert any("SHA-256" in p for p in verify_world(root))
    assert main(["generate", "--verify", str(root)]) == 1
    assert main(["generate", "--verify", str(tmp_path / "nothing")]) == 1


def test_row15_evaluate_of_no_tracklets_is_refused(tiny):
    from envs.tracking_env import make_kitti_env
    from trackers.baselines import BASELINES
    from training.evaluate import evaluate

    env = make_kitti_env(root=str(tiny), split="test", setting="kitti-1")
    with pytest.raises(ValueError, match=r"tracklets=\[\] selects no tracklet"):
        evaluate(BASELINES["previous_box"](), env, tracklets=[])
    with pytest.raises(ValueError, match="out of range"):
        evaluate(BASELINES["previous_box"](), env, tracklets=[10_000])


def test_row16_two_generates_with_different_seeds_into_one_out(tmp_path):
    out = tmp_path / "w"
    cmd = [
        sys.executable,
        "-m",
        "training.cli",
        "generate",
        "--preset",
        "tiny",
        "--out",
        str(out),
        "--no-progress",
        "--seed",
    ]
    procs = [
        subprocess.Popen(cmd + [str(seed)], env=_env(), stderr=subprocess.PIPE, text=True)
        for seed in (1, 2)
    ]
    results = [(p.wait(timeout=300), p.stderr.read()) for p in procs]
    codes = sorted(rc for rc, _ in results)
    assert codes == [0, 2], results
    err = next(e for rc, e in results if rc == 2)
    assert err.startswith("pointtrack generate: ") and err.count("\n") == 1, err
    assert "not this world" in err
    assert verify_world(out) == [] and _leftovers(tmp_path) == []


def test_row18_missing_root_unwritable_out_and_cache_no_cuda(tmp_path, capsys, monkeypatch):
    assert main(["eval", "--dataset", "kitti", "--root", str(tmp_path / "nowhere")]) == 2
    _one_line_error(capsys, "eval", "nowhere")
    blocker = tmp_path / "file"
    blocker.write_text("")
    assert main(["eval", "--preset", "tiny", "--out", str(blocker / "sub")]) == 2
    _one_line_error(capsys, "eval", "cannot write to --out")
    assert main(["train", "--out", str(blocker / "sub"), "--no-progress"]) == 2
    _one_line_error(capsys, "train", "cannot write to the run directory")
    monkeypatch.setenv("POINTTRACK_CACHE", str(blocker))
    assert main(["eval", "--preset", "tiny", "--seed", "7"]) == 2
    _one_line_error(capsys, "eval", "POINTTRACK_CACHE")
    if not torch.cuda.is_available():
        assert main(["train", "--device", "cuda", "--out", str(tmp_path / "r")]) == 2
        _one_line_error(capsys, "train", "CUDA is not available")


def test_every_help_shows_every_flag_without_markup(capsys):
    from training.cli import COMMANDS

    for name in ("generate", "eval", "train", "select", "demo", "bench", "render"):
        assert name in COMMANDS
        with pytest.raises(SystemExit) as done:
            main([name, "--help"])
        assert done.value.code == 0
        text = capsys.readouterr().out
        assert "``" not in text and ":mod:" not in text and ":func:" not in text, name
    parser = __import__("training.cli", fromlist=["build_parser"]).build_parser()
    sub = next(a for a in parser._actions if a.dest == "command")
    for name in ("generate", "eval", "train", "select", "demo", "bench", "render"):
        for action in sub.choices[name]._actions:
            if action.dest == "help":
                continue
            assert action.help, f"pointtrack {name}: {action.option_strings or action.dest}"
    with pytest.raises(SystemExit):
        main(["eval", "--help"])
    text = " ".join(capsys.readouterr().out.split())
    assert "(default: small)" in text and "(default: 0)" in text


def test_table_columns_in_a_fixed_order():
    from training.evaluate import category_order, format_table

    def report(cats):
        entry = {"success": 1.0, "precision": 2.0, "frames": 3, "observed": True}
        return {
            "categories": {c: dict(entry) for c in cats},
            "observed": entry,
            "unseen": entry,
            "mean": entry,
            "tracker_fps": 1.0,
        }

    a = format_table({"a": report(["Pedestrian", "Car", "Zebra", "Cyclist"])})
    b = format_table({"b": report(["Cyclist", "Zebra", "Car", "Pedestrian"])})
    assert a.splitlines()[0] == b.splitlines()[0]
    assert category_order(["Zebra", "Cyclist", "Van", "Car"]) == ["Car", "Van", "Cyclist", "Zebra"]


# --------------------------------------------------------------------------- SIGKILL


def _kill_after(
    cmd: list[str], delay_s: float, cwd: Path | None = None, ready: str | None = None
) -> int | None:
    """Start ``cmd``; ``delay_s`` after it prints ``ready`` (or after the start) SIGKILL it.
    Returns its exit code when it finished first, else ``None``."""
    proc = subprocess.Popen(
        cmd, env=_env(), cwd=cwd, stdout=subprocess.PIPE, stderr=subprocess.DEVNULL, text=True
    )
    if ready is not None:
        for line in proc.stdout:
            if ready in line:
                break
    time.sleep(delay_s)
    if proc.poll() is not None:
        return proc.returncode
    proc.send_signal(signal.SIGKILL)
    proc.wait()
    return None


def _run_quietly(cmd: list[str], cwd: Path | None = None) -> None:
    subprocess.run(
        cmd,
        env=_env(),
        cwd=cwd,
        check=True,
        stdout=subprocess.DEVNULL,
        stderr=subprocess.DEVNULL,
        timeout=600,
    )


def _timed(cmd: list[str], cwd: Path | None = None) -> float:
    t0 = time.perf_counter()
    _run_quietly(cmd, cwd)
    return time.perf_counter() - t0


def test_sigkill_generate_leaves_nothing_and_regenerates_identically(tmp_path):
    gen = [
        sys.executable,
        "-m",
        "training.cli",
        "generate",
        "--preset",
        "tiny",
        "--seed",
        "3",
        "--no-progress",
        "--out",
    ]
    reference = tmp_path / "ref"
    full_s = _timed(gen + [str(reference)])
    files = json.loads((reference / "manifest.json").read_text())["files"]
    for seed in (0, 1):
        parent = tmp_path / f"kill{seed}"
        parent.mkdir()
        out = parent / "w"
        delay = random.Random(seed).uniform(0.3, 0.9) * full_s
        _kill_after(gen + [str(out)], delay)
        # never a partial world under the final name
        assert not out.exists() or verify_world(out) == []
        _run_quietly(gen + [str(out)])
        assert json.loads((out / "manifest.json").read_text())["files"] == files
        assert _leftovers(parent) == []


def test_sigkill_in_the_cache_is_cleaned_on_next_use(tmp_path):
    """A killed ``ensure_world`` leaves a temp directory; the next use of the cache, even of a
    world that exists, removes it."""
    script = (
        "import sys; from envs.synthetic import ensure_world; print('ready', flush=True); "
        "ensure_world('tiny', 'hdl64', 4, cache_dir=sys.argv[1])"
    )
    cache = tmp_path / "cache"
    ensure_world("tiny", "hdl64", 0, cache_dir=cache)
    # kill as soon as the writer's temp directory exists: a fixed delay is too early on a loaded
    # machine and too late on an idle one (the tiny world takes a few seconds)
    proc = subprocess.Popen(
        [sys.executable, "-c", script, str(cache)],
        env=_env(),
        stdout=subprocess.DEVNULL,
        stderr=subprocess.DEVNULL,
    )
    deadline = time.monotonic() + 300
    while not _leftovers(cache) and proc.poll() is None and time.monotonic() < deadline:
        time.sleep(0.01)
    proc.send_signal(signal.SIGKILL)
    proc.wait()
    assert _leftovers(cache), "the kill should have left a temp directory"
    ensure_world("tiny", "hdl64", 0, cache_dir=cache)  # exists: reused, and the cache cleaned
    assert _leftovers(cache) == []


TRAIN_SCRIPT = """
import sys
sys.modules["torch.utils.tensorboard"] = None  # optional logging: skip its slow import here
from test_pretrain_support import TinyTracker, small_dataset, tiny_config
from training.pretrain import train
print("ready", flush=True)
cfg = tiny_config(sys.argv[1], epochs=8, weighting=sys.argv[3])
train(cfg, resume=sys.argv[2] == "1", model_factory=lambda c: TinyTracker(),
      train_data=small_dataset(), val_fn=lambda m: {"success": float(m.head.weight.sum()),
                                                   "precision": 0.0})
"""


def _records(run: Path) -> list[dict]:
    out = []
    for line in (run / "log.jsonl").read_text().splitlines():
        r = json.loads(line)
        if r["kind"] in ("train", "epoch"):
            out.append({k: v for k, v in r.items() if k not in ("samples_per_s", "epoch_wall_s")})
    return out


@pytest.mark.parametrize("weighting", ["decorrelation"])  # the most state: memory, weights
def test_sigkill_train_resumes_exactly(tmp_path, weighting):
    script = tmp_path / "train_script.py"
    script.write_text(TRAIN_SCRIPT)
    full = tmp_path / "full"
    t0 = time.perf_counter()
    proc = subprocess.Popen(
        [sys.executable, str(script), str(full), "0", weighting],
        env=_env(),
        stdout=subprocess.PIPE,
        text=True,
    )
    for line in proc.stdout:
        if "ready" in line:
            t0 = time.perf_counter()
            break
    assert proc.wait(timeout=600) == 0
    train_s = time.perf_counter() - t0
    reference = torch.load(full / "last.pt", weights_only=True)
    for seed in range(2):
        run = tmp_path / f"cut{seed}"
        delay = random.Random(seed).uniform(0.05, 0.95) * train_s
        _kill_after([sys.executable, str(script), str(run), "0", weighting], delay, ready="ready")
        resume = "1" if (run / "config.yaml").exists() else "0"
        subprocess.run(
            [sys.executable, str(script), str(run), resume, weighting],
            env=_env(),
            check=True,
            timeout=600,
            stdout=subprocess.DEVNULL,
        )
        got = torch.load(run / "last.pt", weights_only=True)
        for key in reference["model"]:
            assert torch.equal(got["model"][key], reference["model"][key]), (seed, key)
        assert got["step"] == reference["step"]
        assert _records(run) == _records(full), seed  # no record twice, none missing
        best = torch.load(run / "best.pt", weights_only=True)
        assert best["epoch"] == torch.load(full / "best.pt", weights_only=True)["epoch"]
        assert _leftovers(run) == []


def test_sigkill_select_never_reads_a_partial_report(tiny, tmp_path):
    cmd = [
        sys.executable,
        "-m",
        "training.cli",
        "select",
        "previous_box",
        "constant_velocity",
        "--preset",
        "tiny",
        "--parts",
        "0:val",
        "--num-envs",
        "1",
        "--no-progress",
        "--out",
    ]
    reference = tmp_path / "ref"
    full_s = _timed(cmd + [str(reference)])
    expected = json.loads((reference / "selection.json").read_text())["ranking"]
    for seed in (0, 1):
        out = tmp_path / f"cut{seed}"
        _kill_after(cmd + [str(out)], random.Random(seed).uniform(0.3, 0.95) * full_s)
        for cached in (out / "parts").rglob("*.json") if out.exists() else []:
            json.loads(cached.read_text())  # every report on disk is complete
        _run_quietly(cmd + [str(out)])
        assert json.loads((out / "selection.json").read_text())["ranking"] == expected
        assert _leftovers(out) == []


def test_resume_truncates_the_log_to_the_checkpoint(tmp_path):
    from training.rundir import truncate_log

    log = tmp_path / "log.jsonl"
    records = [
        {"kind": "data", "step": 0},
        {"kind": "train", "step": 10},
        {"kind": "epoch", "step": 16},
        {"kind": "data", "step": 16},
        {"kind": "train", "step": 20},
    ]
    log.write_text("".join(json.dumps(r) + "\n" for r in records) + '{"kind": "tra')
    assert truncate_log(log, 16) == 3
    assert [json.loads(x) for x in log.read_text().splitlines()] == records[:3]


_SAVE_FOREVER = """
import sys, torch
from envs.files import atomic_save_safetensors
tensors = {"w": torch.zeros(16_000_000)}  # 64 MB: a kill falls inside a write most of the time
print("ready", flush=True)
while True:
    atomic_save_safetensors(sys.argv[1], tensors, {"format": "test"})
"""


def test_sigkill_during_a_safetensors_write_leaves_only_temps_we_clean(tmp_path):
    """safetensors' own ``save_file`` writes a ``.tmpXXXXXX`` sibling first, which a SIGKILL
    left behind where :func:`remove_stale_temps` cannot tie it to a process (a CI failure of
    the finetune resume test); every safetensors file of the project goes through
    :func:`envs.files.atomic_save_safetensors` instead."""
    from safetensors.torch import load_file

    from training.rundir import remove_stale_temps

    target = tmp_path / "state.safetensors"
    env = {**os.environ, "PYTHONPATH": str(Path(__file__).resolve().parents[1])}
    for delay in (0.05, 0.13, 0.29):
        child = subprocess.Popen(
            [sys.executable, "-c", _SAVE_FOREVER, str(target)], env=env, stdout=subprocess.PIPE
        )
        assert child.stdout.readline().strip() == b"ready"
        time.sleep(delay)
        child.send_signal(signal.SIGKILL)
        child.wait()
        remove_stale_temps(tmp_path)
        assert sorted(p.name for p in tmp_path.iterdir()) in ([], ["state.safetensors"])
        if target.exists():
            assert load_file(str(target))["w"].shape == (16_000_000,)
