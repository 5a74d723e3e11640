"""Running a sweep: every trial of a :class:`~training.sweep.spec.SweepSpec` as a Ray Tune trial.

Layout of a sweep's results directory ``OUT`` (docs/cluster.md)::

    OUT/sweep.json              the spec and every trial's command line (checked on --resume)
    OUT/trials/NAME/            one trial's run directory (the command's --out)
    OUT/trials/NAME/trial.log   the command's output, one block per attempt
    OUT/trials/NAME/trial.json  written last, atomically: the trial finished (its metrics)
    OUT/summary.csv, .md        mean +- sd over the seeds of each group (training.sweep.summary)
    OUT/_ray/                   Ray Tune's own bookkeeping (not needed to resume)

A trial is a subprocess ``python -m training.cli COMMAND ... --out OUT/trials/NAME`` rather
than an in-process call: it is exactly the command a user (or the shell loops of
``experiments/``) runs, with the same bytes out; a trial that Ray kills or retries leaves no
torch state, threads or open files behind in a long-lived Ray worker; and resuming is the
command's own (``train --resume`` continues ``last.pt`` to the same weights, ``finetune
--resume`` its PPO state; ``eval`` and ``select`` are deterministic and simply run again). The
child dies with the Ray worker that runs it (``PR_SET_PDEATHSIG``), so a killed sweep leaves
no orphans. A failed trial is retried ``retries`` times (Tune's ``FailureConfig``), each try
resuming what the previous one left; ``--resume`` skips the trials that wrote ``trial.json``.
"""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from training.rundir import atomic_write_text
from training.sweep.spec import SweepSpec, Trial, command_parser
from training.sweep.summary import GroupRow, summarize, trial_metrics, write_summary

__all__ = ["SweepError", "SweepResult", "check_out", "run_sweep", "trial_command"]

SWEEP_FILE = "sweep.json"
DONE_FILE = "trial.json"
LOG_FILE = "trial.log"


class SweepError(ValueError):
    """A sweep that cannot start or did not finish (one line; the CLI's exit status 2)."""


@dataclass
class SweepResult:
    """What a sweep run did: trials run now, skipped (finished before), failed (name -> why),
    and the summary rows."""

    out: Path
    ran: list[str] = field(default_factory=list)
    skipped: list[str] = field(default_factory=list)
    failed: dict[str, str] = field(default_factory=dict)
    rows: list[GroupRow] = field(default_factory=list)
    metrics: list[str] = field(default_factory=list)
    wall_s: float = 0.0


def trial_dir(out: Path, trial: Trial) -> Path:
    return out / "trials" / trial.name


def trial_command(spec: SweepSpec, trial: Trial, out: Path, gpus: float = 0.0) -> list[str]:
    """The full command line of ``trial`` (without the resume flags the trial adds itself)."""
    argv = list(trial.argv)
    if gpus > 0 and "device" in {a.dest for a in command_parser(spec.command)._actions}:
        if "device" not in {**spec.base, **trial.overrides}:
            argv += ["--device", "cuda"]  # Ray sets CUDA_VISIBLE_DEVICES to the trial's GPU
    words = spec.command.split()[:1]  # "eval --weather" runs `eval` (its --weather is in argv)
    run_dir = trial_dir(out, trial).resolve()
    command = [sys.executable, "-m", "training.cli", *words, *argv, "--out", str(run_dir)]
    return command + ["--no-progress"]  # trial.log gets lines, not a redrawn progress bar


def check_out(spec: SweepSpec, out: Path, resume: bool) -> list[Trial]:
    """The trials still to run in ``out``; refuses (``SweepError``) a fresh sweep into a
    directory holding one, ``--resume`` of nothing, and ``--resume`` with another spec.
    Creates nothing."""
    stored = out / SWEEP_FILE
    if not resume:
        if stored.exists():
            raise SweepError(
                f"{out} already holds a sweep ({SWEEP_FILE}): pass --resume to finish it, or "
                "choose another --out"
            )
        return list(spec.trials)
    if not stored.is_file():
        raise SweepError(f"nothing to resume in {out}: no {SWEEP_FILE} (check --out)")
    before = json.loads(stored.read_text())
    now = _identity(spec)
    if before.get("trials") != now["trials"] or before.get("command") != now["command"]:
        raise SweepError(
            f"--resume refused: {stored} was written for another spec (command or trials "
            "differ); choose another --out for the new spec"
        )
    return [t for t in spec.trials if not (trial_dir(out, t) / DONE_FILE).is_file()]


def _identity(spec: SweepSpec) -> dict[str, Any]:
    return {
        "name": spec.name,
        "command": spec.command,
        "spec": spec.source,
        "seed_key": spec.seed_key,
        "trials": {t.name: t.argv for t in spec.trials},
    }


def run_sweep(
    spec: SweepSpec,
    out: str | Path,
    *,
    address: str | None = None,
    resume: bool = False,
    num_cpus: int | None = None,
    retries: int | None = None,
    log: Callable[[str], None] = print,
) -> SweepResult:
    """Run the trials of ``spec`` not yet finished in ``out`` on Ray Tune and write the summary.

    ``address`` ``None``: a local Ray with ``num_cpus`` (default the usable cores); ``"auto"`` /
    ``HOST:PORT`` / ``ray://HOST:PORT``: a running cluster, whose nodes must see ``out`` (a
    shared file system) and have the project installed. Raises :class:`SweepError` (nothing
    written) for a refused ``out`` and :class:`~training.sweep.ray_backend.RayUnavailable` for
    a missing extra or an unreachable address; returns the result, failed trials included."""
    from training.sweep.ray_backend import connect, require_ray

    start = time.perf_counter()
    out = Path(out)
    pending = check_out(spec, out, resume)
    ray = require_ray(tune=True)
    started = connect(address, num_cpus=num_cpus)  # before any file: an unreachable address
    try:  # leaves no partial results directory
        gpus = spec.gpus
        if gpus is None:
            gpus = 1.0 if ray.cluster_resources().get("GPU", 0) > 0 else 0.0
        (out / "trials").mkdir(parents=True, exist_ok=True)
        if not (out / SWEEP_FILE).exists():
            atomic_write_text(out / SWEEP_FILE, json.dumps(_identity(spec), indent=1) + "\n")
        result = SweepResult(out=out, skipped=[t.name for t in spec.trials if t not in pending])
        if result.skipped:
            log(f"{len(result.skipped)} of {len(spec.trials)} trials finished before: skipped")
        if pending:
            tasks = [_task(spec, t, out, gpus) for t in pending]
            errors = _fit(spec, tasks, out, gpus, spec.retries if retries is None else retries, log)
            for trial in pending:
                if (trial_dir(out, trial) / DONE_FILE).is_file():
                    result.ran.append(trial.name)
                else:
                    result.failed[trial.name] = errors.get(trial.name, "no result")
    finally:
        if started:
            ray.shutdown()
    finished = [
        json.loads((trial_dir(out, t) / DONE_FILE).read_text())
        for t in spec.trials
        if (trial_dir(out, t) / DONE_FILE).is_file()
    ]
    result.rows, result.metrics = summarize(finished, spec.seed_key)
    if finished:
        write_summary(out, result.rows, result.metrics, spec.seed_key)
    result.wall_s = time.perf_counter() - start
    return result


def _task(spec: SweepSpec, trial: Trial, out: Path, gpus: float) -> dict[str, Any]:
    """A trial as the plain dict Tune passes to :func:`run_trial` (JSON-able: Tune logs it)."""
    return {
        "name": trial.name,
        "command": spec.command,
        "argv": trial_command(spec, trial, out, gpus),
        "dir": str(trial_dir(out, trial).resolve()),
        "overrides": trial.overrides,
        "threads": spec.threads,
    }


def _fit(
    spec: SweepSpec,
    tasks: list[dict[str, Any]],
    out: Path,
    gpus: float,
    retries: int,
    log: Callable[[str], None],
) -> dict[str, str]:
    """Run ``tasks`` as Tune trials; returns ``{trial name: error}`` of those that failed."""
    from ray import tune

    errors: dict[str, str] = {}
    finished: list[str] = []

    class Progress(tune.Callback):
        """One line per finished or failed trial, in the driver."""

        def on_trial_complete(self, iteration, trials, trial, **info):
            finished.append(trial.config["task"]["name"])
            log(f"trial {finished[-1]}: done ({len(finished)} of {len(tasks)})")

        def on_trial_error(self, iteration, trials, trial, **info):
            name = trial.config["task"]["name"]
            errors[name] = f"failed; see {Path(trial.config['task']['dir']) / LOG_FILE}"
            log(f"trial {name}: {errors[name]}")

    root = (out / "_ray").resolve()
    attempt = len(list(root.glob("attempt-*"))) if root.is_dir() else 0
    trainable = tune.with_resources(run_trial, {"cpu": spec.cpus, "gpu": gpus})
    tuner = tune.Tuner(
        trainable,
        param_space={"task": tune.grid_search(tasks)},
        tune_config=tune.TuneConfig(reuse_actors=True),  # a trial is a subprocess: no state
        run_config=tune.RunConfig(
            name=f"attempt-{attempt}",
            storage_path=str(root),
            failure_config=tune.FailureConfig(max_failures=retries),
            callbacks=[Progress()],
            verbose=0,
        ),
    )
    tuner.fit()
    return errors


def run_trial(config: dict[str, Any]) -> None:
    """Tune's trainable: run one trial's command in its run directory, resuming what an earlier
    try left, then write ``trial.json`` and report its metrics (raises when the command fails,
    so Tune retries it)."""
    from ray import tune

    tune.report(execute_trial(config["task"]))


def execute_trial(task: dict[str, Any]) -> dict[str, float]:
    """Run a :func:`_task` dict's command (appending its output to ``trial.log``), write
    ``trial.json`` atomically and return the metrics. ``RuntimeError`` when the command fails."""
    run_dir = Path(task["dir"])
    run_dir.mkdir(parents=True, exist_ok=True)
    argv = task["argv"] + _resume_flags(task["command"], run_dir)
    threads = str(task["threads"])
    env = dict(os.environ, OMP_NUM_THREADS=threads, MKL_NUM_THREADS=threads)
    root = Path(__file__).resolve().parents[2]  # the checkout of this module, when it is one
    if (root / "training" / "cli.py").is_file():
        env["PYTHONPATH"] = os.pathsep.join(filter(None, [str(root), env.get("PYTHONPATH")]))
    start = time.perf_counter()
    with open(run_dir / LOG_FILE, "a") as stream:
        stream.write(f"$ {' '.join(argv)}\n")
        stream.flush()
        code = subprocess.run(
            argv, stdout=stream, stderr=subprocess.STDOUT, env=env, preexec_fn=_die_with_parent
        ).returncode
    if code != 0:
        raise RuntimeError(f"{task['name']}: exit status {code}; see {run_dir / LOG_FILE}")
    metrics = trial_metrics(task["command"], run_dir)
    record = {
        "name": task["name"],
        "overrides": task["overrides"],
        "argv": argv,
        "metrics": metrics,
        "wall_s": time.perf_counter() - start,
    }
    atomic_write_text(run_dir / DONE_FILE, json.dumps(record, indent=1) + "\n")
    return metrics


def _resume_flags(command: str, run_dir: Path) -> list[str]:
    """What a try adds to continue an earlier, killed one in ``run_dir`` (see module doc)."""
    if command == "train" and any((run_dir / n).exists() for n in ("last.pt", "config.yaml")):
        return ["--resume"]
    if command == "finetune":
        if (run_dir / "state.safetensors").is_file():
            return ["--resume"]
        if any(p.name != LOG_FILE for p in run_dir.iterdir()):
            return ["--overwrite"]  # killed before its first resumable state
    return []


def _die_with_parent() -> None:
    """In the child, before exec: ask Linux for SIGKILL when the Ray worker thread that started
    it ends (a killed or cancelled trial must not leave its command running)."""
    if sys.platform.startswith("linux"):
        import ctypes

        pr_set_pdeathsig = 1
        ctypes.CDLL(None).prctl(pr_set_pdeathsig, signal.SIGKILL)
