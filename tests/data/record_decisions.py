"""Record ``decisions.npz``: the actions the shipped kitti-1 matching checkpoints execute (the
still-target test and the re-ranking as shipped) on observations of the tiny synthetic world,
with the network outputs they were chosen from.

Recorded from main at commit 265311c, before the decision step moved out of ``trackers/base.py``
into ``trackers/decision.py`` (issue 40 item 2) and was vectorised (issue 41 item 2), so that
``tests/test_decision.py`` checks ``decide`` and ``act`` still choose what they chose. The
script reads only ``trackers.load``, ``act`` and the forward, so it runs on either side of that
change.

The observations: every frame of a closed-loop ``p2b-kitti1-u`` run over the tiny world's test
split (world seed 0, kitti-1, eval seed 3); of them, for each checkpoint, the first
``PER_KIND`` where it executes no move, the best-scored proposal, or another proposal (the
re-ranking overruled the scores), then one observation with an empty search and one with an
empty template. Run: ``PYTHONPATH=$PWD OMP_NUM_THREADS=1 python tests/data/record_decisions.py``.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import torch

import trackers

CHECKPOINTS = [
    *(f"{n}-kitti1-{w}" for n in ("p2b", "bat", "gpt") for w in "uw"),
    "p2b-kitti1-u-rl",
    "gpt-kitti1-u-rl",
    "p2b-kitti1-drct",
]
KEYS = ("template", "search", "size", "motion")
#: observations kept per checkpoint and kind of decision (no move, best, another proposal)
PER_KIND = 2
#: the kinds of decision, as recorded in ``<name>/kind``
KINDS = ("zero", "best", "other")


def pool() -> list[dict[str, np.ndarray]]:
    """Every observation of a closed-loop p2b-kitti1-u run over the tiny world's test split."""
    from envs.tracking_env import make_synthetic_env

    env = make_synthetic_env(preset="tiny", seed=0, split="test", setting="kitti-1")
    model = trackers.load("p2b-kitti1-u")
    out = []
    for episode in range(len(env.tracklet_lengths)):
        obs, _ = env.reset(seed=3 if episode == 0 else None)
        done = False
        while not done:
            out.append({k: np.array(obs[k], np.float32) for k in KEYS})
            obs, _, terminated, truncated, _ = env.step(model.act(obs))
            done = terminated or truncated
    return out


def decisions(model, observations: list[dict[str, np.ndarray]]) -> dict[str, np.ndarray]:
    """Batch-1 ``act`` of every observation, its forward's proposals and scores, and the kind
    of decision (an index into :data:`KINDS`)."""
    acts, proposals, scores, kinds = [], [], [], []
    a_max = torch.as_tensor(model.max_action)
    for obs in observations:
        acts.append(model.act(obs))
        with torch.no_grad():
            out = model({k: torch.from_numpy(v[None]) for k, v in obs.items()})
        proposals.append(out["proposals"][0].numpy())
        scores.append(out["scores"][0].numpy())
        best = out["proposals"][0, out["scores"][0].argmax()]
        best = torch.maximum(torch.minimum(best, a_max), -a_max).numpy()
        kind = 0 if not acts[-1].any() else 1 if np.array_equal(acts[-1], best) else 2
        kinds.append(kind)
    return {
        "act": np.stack(acts),
        "proposals": np.stack(proposals),
        "scores": np.stack(scores),
        "kind": np.asarray(kinds, np.int8),
    }


def main() -> None:
    torch.set_num_threads(1)
    candidates = pool()
    chosen: set[int] = set()
    for name in CHECKPOINTS:
        kinds = decisions(trackers.load(name), candidates)["kind"]
        for kind in range(len(KINDS)):
            chosen.update(np.flatnonzero(kinds == kind)[:PER_KIND].tolist())
    observations = [candidates[i] for i in sorted(chosen)]
    empty_search = dict(observations[0], search=np.zeros((1024, 3), np.float32))
    empty_template = dict(observations[0], template=np.zeros((512, 3), np.float32))
    observations += [empty_search, empty_template]
    out = {f"obs_{k}": np.stack([o[k] for o in observations]) for k in KEYS}
    for name in CHECKPOINTS:
        recorded = decisions(trackers.load(name), observations)
        out.update({f"{name}/{k}": v for k, v in recorded.items()})
        print(name, "kinds", np.bincount(recorded["kind"], minlength=len(KINDS)).tolist())
    path = Path(__file__).with_name("decisions.npz")
    np.savez_compressed(path, **out)
    print(path, len(observations), "observations", path.stat().st_size, "bytes")


if __name__ == "__main__":
    main()
