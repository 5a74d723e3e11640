"""``evaluate(..., workers=N)`` and ``pointtrack eval --workers``: tracklets sharded over forked
processes give per-tracklet results bit-identical to one process, for every tracker kind; a
killed worker fails the run naming its tracklets and writes no report."""

from __future__ import annotations

import json
import os
import signal
import threading

import pytest

from training.cli import main
from training.evaluate import evaluate
from training.parallel import WorkerDiedError, map_forked, resolve_workers, usable_cores

needs_two_cores = pytest.mark.skipif(usable_cores() < 2, reason="needs 2 usable cores")


@pytest.fixture(scope="module")
def tiny_env():
    from envs.tracking_env import make_synthetic_env

    return make_synthetic_env(preset="tiny", split="test", setting="kitti-1")


def _per_tracklet(report):
    return {r["tracklet"]: r for r in report["per_tracklet"]}


@needs_two_cores
@pytest.mark.parametrize("name", ["p2b-kitti1-u", "m2track-kitti1-u", "constant_velocity"])
def test_two_workers_bit_identical_to_one(name):
    """A matching tracker, M2-Track (its own observation key) and a baseline: the same
    per-tracklet numbers and the same pooled report, to the last bit."""
    import trackers
    from envs.tracking_env import make_synthetic_env
    from training.evaluate import observation_keys_for

    tracker = trackers.load(name)
    env = make_synthetic_env(
        preset="tiny",
        split="test",
        setting="kitti-1",
        observation_keys=observation_keys_for([tracker]),
        **getattr(tracker, "env_options", {}),
    )
    subset = list(range(min(6, env.num_tracklets)))
    one = evaluate(tracker, env, seed=3, tracklets=subset, workers=1, record_boxes=True)
    two = evaluate(tracker, env, seed=3, tracklets=subset, workers=2, record_boxes=True)
    assert two["env"]["workers"] == 2 and "workers" not in one["env"]
    assert one["per_tracklet"] == two["per_tracklet"] and len(one["per_tracklet"]) == len(subset)
    assert one["boxes"] == two["boxes"]  # every frame's predicted box, bit for bit
    for key in ("categories", "observed", "unseen", "mean", "frames", "tracklets"):
        assert one[key] == two[key], key


class _ThreadSpy:
    """Records torch's intra-op thread count at every ``act``."""

    name = "spy"

    def __init__(self) -> None:
        self.threads: set[int] = set()

    def act(self, obs):
        import numpy as np
        import torch

        self.threads.add(torch.get_num_threads())
        return np.zeros((*np.shape(obs["size"])[:-1], 4), np.float32)


def test_every_path_acts_on_one_torch_thread(tiny_env):
    """The thread count changes a learned forward's last bits, which the closed loop amplifies
    (P2B on tracklet 0019/21 of the small test split: 63.6 on two threads, 58.7 on one), so
    evaluate pins one thread in-process too, and restores the caller's count."""
    import torch

    before = torch.get_num_threads()
    torch.set_num_threads(2)
    try:
        for kwargs in ({}, {"num_envs": 2}):
            spy = _ThreadSpy()
            evaluate(spy, tiny_env, tracklets=[0, 1], **kwargs)
            assert spy.threads == {1}, kwargs
            assert torch.get_num_threads() == 2
    finally:
        torch.set_num_threads(before)


class _KillsItsWorker:
    """A tracker that SIGKILLs the worker process it runs in at its 3rd ``act`` (not in the
    parent, which must survive to report)."""

    name = "killer"

    def __init__(self) -> None:
        self.parent = os.getpid()
        self.calls = 0

    def act(self, obs):
        import numpy as np

        self.calls += 1
        if os.getpid() != self.parent and self.calls == 3:
            os.kill(os.getpid(), signal.SIGKILL)
        return np.zeros(4, np.float32)


@needs_two_cores
def test_a_killed_worker_fails_the_run_naming_its_tracklet(tiny_env):
    ids = [t.tracklet_id for t in tiny_env.tracklets]
    with pytest.raises(
        WorkerDiedError, match=r"died \(exit code -9\) while running tracklet "
    ) as e:
        evaluate(_KillsItsWorker(), tiny_env, workers=2)
    named = str(e.value).split("while running ", 1)[1].split(";")[0]
    assert named.startswith("tracklet ") and named.split(", ")[0][len("tracklet ") :] in ids


@needs_two_cores
def test_cli_killed_worker_writes_no_report(tmp_path, capsys, monkeypatch):
    """The eval command fails in one line naming the tracklet; ``--out`` gets no report."""
    import trackers.baselines as baselines

    killer = _KillsItsWorker()
    monkeypatch.setattr(baselines.PreviousBox, "act", lambda self, obs: killer.act(obs))
    out = tmp_path / "out"
    rc = main(["eval", "--preset", "tiny", "--workers", "2", "--no-progress", "--out", str(out)])
    assert rc == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "while running tracklet" in err[0] and "nothing written" in err[0]
    assert not (out / "report.json").exists()


def test_workers_bad_values():
    with pytest.raises(ValueError, match="workers must be an integer >= 1; got 0"):
        resolve_workers(0)
    with pytest.raises(ValueError, match="got 1.5"):
        resolve_workers(1.5)
    assert resolve_workers(None) == usable_cores()
    with pytest.warns(UserWarning, match=f"more than the {usable_cores()} usable core"):
        assert resolve_workers(usable_cores() + 3) == usable_cores()


def test_cli_workers_zero_is_one_line(capsys):
    assert main(["eval", "--preset", "tiny", "--workers", "0"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert err == ["pointtrack eval: --workers must be an integer >= 1; got 0"]


def test_workers_with_a_vector_env_is_refused(tiny_env):
    from trackers.baselines import PreviousBox

    with pytest.raises(ValueError, match="cannot be combined with a vector env or num_envs"):
        evaluate(PreviousBox(), tiny_env, num_envs=2, workers=2)


def test_map_forked_hands_out_items_dynamically():
    """Results in the items' order whatever worker ran them; ``done`` sees each once."""
    seen = []
    assert map_forked(lambda x: (x, os.getpid()), list(range(7)), 2, lambda i, r: seen.append(i))
    assert sorted(seen) == list(range(7))
    out = map_forked(lambda x: x * 2, list(range(7)), 2)
    assert out == [0, 2, 4, 6, 8, 10, 12]


def test_map_forked_warm_up_runs_beside_the_workers():
    """The caller's warm-up runs once, in a thread of the parent while the workers run (its
    exception raised after them), and not at all without workers."""
    calls = []

    def warm_up():
        calls.append((os.getpid(), threading.current_thread() is threading.main_thread()))

    assert map_forked(lambda x: x + 1, [1, 2, 3], 2, warm_up=warm_up) == [2, 3, 4]
    assert calls == [(os.getpid(), False)]
    assert map_forked(lambda x: x + 1, [1, 2, 3], 1, warm_up=warm_up) == [2, 3, 4]
    assert len(calls) == 1

    def broken():
        raise ImportError("no plotting library")

    with pytest.raises(ImportError, match="no plotting library"):
        map_forked(lambda x: x, [1, 2], 2, warm_up=broken)


def test_cli_device_cuda_without_cuda_is_one_line(capsys):
    import torch

    if torch.cuda.is_available():
        pytest.skip("this machine has CUDA: the refusal cannot happen here")
    assert main(["eval", "--preset", "tiny", "--device", "cuda"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "CUDA is not available" in err[0]


def test_report_says_how_it_ran(tmp_path):
    assert main(["eval", "--preset", "tiny", "--no-progress", "--out", str(tmp_path)]) == 0
    report = json.loads((tmp_path / "report.json").read_text())["previous_box"]
    assert report["eval"]["workers"] == resolve_workers(None)
    assert report["eval"]["device"] == "cpu" and report["eval"]["batch_invariant"] is True
