"""Record ``tracker_reference.npz``: ``act`` and B = 1 forward outputs of the six shipped
checkpoints on fixed observations (toy batches, padded clouds, env observations, an empty one).

The six -U / -W entries were recorded from main at commit cfcfd29 (before the tracker refactor
of issue 21); the entries of the checkpoints shipped since (``LATER``: the RL and DRCT
fine-tunes, session 16; the kitti-2 P2B checkpoints, session 20; ``p2b-kitti2-s``, a Table IV
pilot file, 2026-12-07) were added from the code of their time, and ``bat-kitti1-u`` was
re-recorded when its file was replaced (sessions 23 and 26), so that
``tests/test_trackers_reference.py`` can check every shipped matching tracker's outputs
stay what they were. Until session 26 the check was bit for bit and ``Z`` was kept as a
SHA-256; on another CPU (an Intel Xeon with AVX512, the entries having been recorded on
another kind) the same float32 forward rounds differently, by up to 7e-7 in the actions, so
the check has a tolerance and ``Z`` is kept as summaries (``z_summary``), recorded in session
26 from the code of that time after every recorded action, proposal and score had been matched
to the tolerance. Run: ``PYTHONPATH=$PWD OMP_NUM_THREADS=1 python
tests/data/record_tracker_reference.py [NAME ...]`` (names given: only their entries are
recorded, the file's other entries are kept).
"""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np
import torch

import trackers
from envs.tracking_env import TrackingEnv, make_toy_dataset
from trackers.decision import InferenceConfig
from trackers.toy import toy_batch

CHECKPOINTS = [f"{n}-kitti1-{w}" for n in ("p2b", "bat", "gpt") for w in "uw"]
LATER = [
    "p2b-kitti1-u-rl",
    "gpt-kitti1-u-rl",
    "p2b-kitti1-drct",
    "p2b-kitti2-u",
    "p2b-kitti2-w",
    "p2b-kitti2-s",
]
KEYS = ("template", "search", "size", "motion")


def observations() -> dict[str, np.ndarray]:
    batch, _ = toy_batch(3, seed=5)
    obs = [{k: batch[k][i].numpy() for k in KEYS} for i in range(3)]
    g = np.random.default_rng(0)
    for distinct_t, distinct_s in ((40, 150), (9, 60)):  # env-like padding: copies of points
        o = dict(obs[0])
        o["template"] = o["template"][g.integers(0, distinct_t, 512)]
        o["search"] = o["search"][g.integers(0, distinct_s, 1024)]
        o["motion"] = np.array([0.3, -0.1, 0.0, 0.05], np.float32)
        obs.append(o)
    env = TrackingEnv(make_toy_dataset(num_frames=3, seed=0))
    o, _ = env.reset(seed=1)
    obs.append(o)
    o, *_ = env.step(np.array([0.2, 0.0, 0.0, 0.0], np.float32))
    obs.append(o)
    empty = dict(obs[0])
    empty["template"] = np.zeros((512, 3), np.float32)
    obs.append(empty)
    return {k: np.stack([np.asarray(x[k], np.float32) for x in obs]) for k in KEYS}


def network_only(model):
    """``model`` with the inference-only still-target test and re-ranking off (added after the
    first recordings; their own tests are in test_trackers.py): ``act`` is the network's
    action."""
    model.inference = InferenceConfig()
    return model


def z_summary(name: str, z: np.ndarray) -> dict[str, np.ndarray]:
    """The fused features ``Z`` (B, C, N) are large: their mean and standard deviation over the
    last axis, (B, C) each, stand in for them."""
    return {f"{name}/Z_mean": z.mean(axis=-1), f"{name}/Z_std": z.std(axis=-1)}


def main(names: list[str]) -> None:
    torch.set_num_threads(1)
    path = Path(__file__).with_name("tracker_reference.npz")
    obs = observations()
    out: dict[str, np.ndarray] = {f"obs_{k}": v for k, v in obs.items()}
    if names:
        with np.load(path) as old:
            for key in old.files:
                np.testing.assert_array_equal(out.get(key, old[key]), old[key], err_msg=key)
                out[key] = old[key]
    n = len(obs["template"])
    for name in names or CHECKPOINTS + LATER:
        model = network_only(trackers.load(name))
        out[f"{name}/act_single"] = np.stack(
            [model.act({k: v[i] for k, v in obs.items()}) for i in range(n)]
        )
        out[f"{name}/act_batch"] = model.act(obs)
        with torch.no_grad():
            fw = [
                model({k: torch.from_numpy(v[i : i + 1]) for k, v in obs.items()}) for i in range(n)
            ]
        for key in ("proposals", "scores"):
            out[f"{name}/{key}"] = np.concatenate([f[key].numpy() for f in fw])
        out.update(z_summary(name, np.concatenate([f["Z"].numpy() for f in fw])))
    np.savez_compressed(path, **out)
    print(path, path.stat().st_size)


if __name__ == "__main__":
    main(sys.argv[1:])
