"""`pointtrack sweep` (training.sweep) and the Ray weather backend: spec validation before any
trial, a tiny train sweep on a local Ray (killed, then finished with --resume), the Ray weather
backend against the local one, the one-line refusals. The Ray tests need the `sweep` extra
(scripts/test.sh installs it)."""

from __future__ import annotations

import importlib.util
import json
import os
import signal
import socket
import subprocess
import sys
import time
from pathlib import Path

import pytest
import yaml

from training.cli import main
from training.sweep.runner import SweepError, _resume_flags, _task, check_out, execute_trial
from training.sweep.spec import SpecError, load_spec, parse_spec

ROOT = Path(__file__).resolve().parents[1]
needs_ray = pytest.mark.skipif(
    importlib.util.find_spec("ray") is None,
    reason="Ray is not installed (pip install 'pointtrack[sweep]'; scripts/test.sh does)",
)

# 2 seeds x 2 weightings of `train` on the tiny world, one epoch of two batches
TINY = {
    "name": "tiny",
    "command": "train",
    "base": {
        "tracker": "p2b",
        "model-size": "slim",
        "preset": "tiny",
        "epochs": 1,
        "iters-per-epoch": 2,
        "batch-size": 4,
        "val-max-tracklets": 1,
        "val-max-frames": 5,
    },
    "grid": {"weighting": ["none", "decorrelation"], "seed": [0, 1]},
}


def write_spec(tmp_path: Path, spec: dict) -> Path:
    path = tmp_path / "spec.yaml"
    path.write_text(yaml.safe_dump(spec, sort_keys=False))
    return path


def test_spec_expands_the_grid_into_validated_command_lines():
    spec = parse_spec(TINY)
    assert [t.name for t in spec.trials] == [
        "weighting-none_seed-0",
        "weighting-none_seed-1",
        "weighting-decorrelation_seed-0",
        "weighting-decorrelation_seed-1",
    ]
    argv = spec.trials[1].argv
    assert argv[argv.index("--weighting") + 1] == "none"
    assert argv[argv.index("--seed") + 1] == "1"
    assert argv[argv.index("--threads") + 1] == "1"  # one torch thread per trial
    listed = parse_spec(
        {
            "command": "train",
            "base": {"set": {"decor_penalty": 0.2}},
            "trials": [{"weighting": "sam"}, {"drct": True}],
            "grid": {"seed": [0, 1, 2]},
        }
    )
    assert len(listed.trials) == 6
    assert "--drct" in listed.trials[1].argv
    assert listed.trials[0].argv[:2] == ["--set", "decor_penalty=0.2"]


@pytest.mark.parametrize(
    ("change", "words"),
    [
        ({"command": "trian"}, ["'trian'", "train, finetune, eval, eval --weather, select"]),
        ({"grid": {"sead": [0, 1]}}, ["grid", "'sead'", "valid:", "seed", "weighting"]),
        ({"base": {"out": "x"}}, ["'out'", "the sweep sets it"]),
        ({"epochs": 3}, ["unknown spec key", "'epochs'", "grid"]),
        ({"grid": {"weighting": ["none", "decorr"]}}, ["trial weighting-decorr", "'decorr'"]),
        ({"base": {"set": {"decor_penalti": 1}}}, ["decor_penalti"]),
        ({"grid": {"seed": []}}, ["'seed'", "non-empty list"]),
        ({"retries": -1}, ["retries", ">= 0"]),
        ({"command": "eval", "base": {"weather": "fog"}}, ["'eval --weather'"]),
    ],
)
def test_spec_errors_name_what_is_wrong_and_the_valid_choices(tmp_path, change, words):
    raw = {**TINY, **change}
    if "base" in change and "command" not in change:
        raw["base"] = {**TINY["base"], **change["base"]}
    if "command" in change:
        raw.pop("grid")
    path = write_spec(tmp_path, raw)
    with pytest.raises(SpecError) as info:
        load_spec(path)
    message = str(info.value)
    assert str(path) in message
    for word in words:
        assert word in message


def test_cli_refuses_a_bad_spec_in_one_line_before_any_trial(tmp_path, capsys):
    path = write_spec(tmp_path, {**TINY, "grid": {"lr": ["fast"]}})
    assert main(["sweep", str(path), "--out", str(tmp_path / "out")]) == 2
    err = capsys.readouterr().err.strip()
    assert err.startswith("pointtrack sweep: ") and "--lr" in err and len(err.splitlines()) == 1
    assert not (tmp_path / "out").exists()


def test_without_ray_the_cli_names_the_extra(tmp_path, capsys, monkeypatch):
    monkeypatch.setitem(sys.modules, "ray", None)  # import ray -> ImportError
    path = write_spec(tmp_path, TINY)
    assert main(["sweep", str(path), "--out", str(tmp_path / "out")]) == 2
    err = capsys.readouterr().err.strip()
    assert err == (
        "pointtrack sweep: Ray is not installed: pip install 'pointtrack[sweep]' (ray[tune]>=2.9)"
    )
    assert not (tmp_path / "out").exists()


def test_results_directory_rules(tmp_path):
    spec = parse_spec(TINY)
    out = tmp_path / "out"
    with pytest.raises(SweepError, match="nothing to resume"):
        check_out(spec, out, resume=True)
    assert len(check_out(spec, out, resume=False)) == 4
    out.mkdir()
    (out / "sweep.json").write_text(json.dumps({"command": "train", "trials": {}}))
    with pytest.raises(SweepError, match="already holds a sweep"):
        check_out(spec, out, resume=False)
    with pytest.raises(SweepError, match="another spec"):
        check_out(spec, out, resume=True)


def test_a_trial_runs_its_command_and_records_its_metrics(tmp_path):
    spec = parse_spec(
        {
            "command": "eval",
            "base": {"tracker": "previous_box", "preset": "tiny", "max-tracklets": 1},
            "grid": {"eval-seed": [3]},
        }
    )
    (trial,) = spec.trials
    task = _task(spec, trial, tmp_path, gpus=0.0)
    metrics = execute_trial(task)
    record = json.loads((tmp_path / "trials" / trial.name / "trial.json").read_text())
    assert record["metrics"] == metrics and set(metrics) == {"success", "precision"}
    report = json.loads((tmp_path / "trials" / trial.name / "report.json").read_text())
    assert metrics["success"] == report["previous_box"]["mean"]["success"]
    assert record["argv"][-3:] == ["--out", task["dir"], "--no-progress"]
    assert "--eval-seed" in record["argv"]
    bad = {**task, "name": "bad", "dir": str(tmp_path / "bad"), "argv": task["argv"] + ["--x"]}
    with pytest.raises(RuntimeError, match=r"bad: exit status 2; see .*bad/trial.log"):
        execute_trial(bad)
    assert not (tmp_path / "bad" / "trial.json").exists()
    assert "unrecognized arguments: --x" in (tmp_path / "bad" / "trial.log").read_text()


def test_a_retried_trial_resumes_what_the_killed_try_left(tmp_path):
    run = tmp_path / "run"
    run.mkdir()
    (run / "trial.log").write_text("$ first try\n")
    assert _resume_flags("train", run) == [] and _resume_flags("finetune", run) == []
    (run / "config.yaml").write_text("seed: 0\n")  # killed in its first epoch
    assert _resume_flags("train", run) == ["--resume"]
    assert _resume_flags("finetune", run) == ["--overwrite"]  # nothing resumable yet
    (run / "state.safetensors").write_bytes(b"")
    assert _resume_flags("finetune", run) == ["--resume"]
    assert _resume_flags("eval", run) == [] and _resume_flags("select", run) == []


def test_dry_run_prints_each_trial_command(tmp_path, capsys):
    path = write_spec(tmp_path, TINY)
    assert main(["sweep", str(path), "--out", str(tmp_path / "out"), "--dry-run"]) == 0
    lines = capsys.readouterr().out.strip().splitlines()
    assert len(lines) == 4 and all(" -m training.cli train " in line for line in lines)
    assert lines[0].endswith(
        f"{tmp_path / 'out' / 'trials' / 'weighting-none_seed-0'} --no-progress"
    )


@needs_ray
def test_unreachable_address_is_one_line_and_writes_nothing(tmp_path, capsys):
    with socket.socket() as s:  # a port on this machine that nothing listens on
        s.bind(("127.0.0.1", 0))
        port = s.getsockname()[1]
    path = write_spec(tmp_path, TINY)
    out = tmp_path / "out"
    code = main(["sweep", str(path), "--out", str(out), "--address", f"ray://127.0.0.1:{port}"])
    assert code == 2
    err = capsys.readouterr().err.strip()
    assert err.startswith(f"pointtrack sweep: cannot reach Ray at ray://127.0.0.1:{port}")
    assert len(err.splitlines()) == 1
    assert not out.exists()


@pytest.mark.slow  # ~40-80 s on 2 cores: two Ray start-ups and five tiny trainings
@needs_ray
def test_tiny_sweep_killed_then_resumed_runs_only_what_was_left(tmp_path, capsys):
    path = write_spec(tmp_path, TINY)
    out = tmp_path / "out"
    trials = out / "trials"
    command = [sys.executable, "-m", "training.cli", "sweep", str(path), "--out", str(out)]
    log = open(tmp_path / "killed.log", "w")  # noqa: SIM115 - closed below
    proc = subprocess.Popen(
        [*command, "--num-cpus", "2"],
        cwd=ROOT,
        stdout=log,
        stderr=subprocess.STDOUT,
        start_new_session=True,  # its own process group: Ray's processes die with it
        env=dict(os.environ, PYTHONPATH=str(ROOT)),
    )
    try:
        deadline = time.monotonic() + 240
        while not list(trials.glob("*/trial.json")):
            assert proc.poll() is None, (tmp_path / "killed.log").read_text()[-3000:]
            assert time.monotonic() < deadline, "no trial finished in 240 s"
            time.sleep(0.2)
    finally:
        os.killpg(proc.pid, signal.SIGKILL)
        proc.wait()
        log.close()
    # Ray's workers run in their own process groups and end when they notice their raylet is
    # gone; each trial's command dies with its worker (PR_SET_PDEATHSIG): none may outlive it
    deadline = time.monotonic() + 30
    while _processes_naming(out):
        assert time.monotonic() < deadline, f"trial commands outlived the sweep: {out}"
        time.sleep(0.2)
    time.sleep(1.0)  # a worker whose command had just ended writes its trial.json now
    done_before = {p.parent.name: p.stat().st_mtime_ns for p in trials.glob("*/trial.json")}
    assert 1 <= len(done_before) < 4
    assert not (out / "summary.md").exists()

    assert main(["sweep", str(path), "--out", str(out), "--resume", "--num-cpus", "2"]) == 0
    printed = capsys.readouterr().out
    names = [t.name for t in parse_spec(TINY).trials]
    assert sorted(p.name for p in trials.iterdir()) == sorted(names)  # four run directories
    for name in names:
        assert (trials / name / "best.pt").is_file()
        record = json.loads((trials / name / "trial.json").read_text())
        log_lines = (trials / name / "trial.log").read_text().splitlines()
        attempts = sum(line.startswith("$ ") for line in log_lines)
        if name in done_before:  # not run again
            assert (trials / name / "trial.json").stat().st_mtime_ns == done_before[name]
            assert "--resume" not in record["argv"]
        else:  # run once more; a killed try that had written its config is continued
            assert attempts in (1, 2) and ("--resume" not in record["argv"] or attempts == 2)
    rerun = len(names) - len(done_before)
    assert f"{rerun} trials run, {len(done_before)} skipped" in printed
    table = (out / "summary.md").read_text().splitlines()
    assert table[0].startswith("| group | trials | seed |") and "val_success" in table[0]
    assert [row.split(" | ")[0] for row in table[2:]] == [
        "| weighting=none",
        "| weighting=decorrelation",
    ]
    assert all(" ± " in row and "| 2 | 0,1 |" in row for row in table[2:])
    assert "| weighting=none | 2 | 0,1 |" in printed
    csv_rows = (out / "summary.csv").read_text().splitlines()
    assert csv_rows[0].startswith("group,trials,seeds,") and len(csv_rows) == 3


@needs_ray
def test_ray_weather_backend_equals_local(one_torch_thread):
    import torch

    import trackers
    from envs.tracking_env import make_synthetic_env
    from training.robustness import run_weather_benchmark

    torch.manual_seed(0)
    tracker = trackers.make("p2b", **trackers.size_config("p2b", "slim"))
    env = make_synthetic_env(preset="tiny", split="test", setting="kitti-1")

    def run(backend: str, workers: int | None) -> tuple[str, dict]:
        result = run_weather_benchmark(
            tracker,
            env.clone,
            ["fog"],
            [1, 3],
            tracklets=[0, 1],
            workers=workers,
            backend=backend,
        )
        return json.dumps(_untimed(result), sort_keys=True, default=str), result

    local, result = run("local", None)
    assert run("ray", 2)[0] == local
    assert result["weather"]["fog"][3]["frames"] > 0 and result["analysis"]["fog"][1]


def _processes_naming(path: Path) -> list[int]:
    """Process ids whose command line mentions ``path``."""
    pids = []
    for cmdline in Path("/proc").glob("[0-9]*/cmdline"):
        try:
            if str(path).encode() in cmdline.read_bytes():
                pids.append(int(cmdline.parent.name))
        except OSError:  # ended meanwhile
            continue
    return pids


def _untimed(value):
    """The result without its speed fields (wall_s, tracker_fps): the rest must match bit for
    bit."""
    if isinstance(value, dict):
        return {k: _untimed(v) for k, v in value.items() if k not in ("wall_s", "tracker_fps")}
    if isinstance(value, list):
        return [_untimed(v) for v in value]
    return value


@pytest.mark.parametrize("path", sorted((ROOT / "configs" / "sweeps").glob("*.yaml")), ids=str)
def test_shipped_specs_are_valid(path):
    spec = load_spec(path)
    assert spec.trials and spec.name == path.stem
