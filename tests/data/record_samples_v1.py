"""Record SHA-256 hashes of training samples from ``training.samples`` as it was before recipe
v2 (run once, at commit a755674): ``recipe="v1"`` must reproduce them byte for byte.

    PYTHONPATH=$PWD python tests/data/record_samples_v1.py
"""

from __future__ import annotations

import hashlib
import json
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from test_pretrain_support import fake_tracklets  # noqa: E402

from training.samples import TrackingSamples  # noqa: E402

OUT = Path(__file__).with_name("samples_v1.json")
CASES = {  # name -> (TrackingSamples kwargs, epochs)
    "c3_s5": ({"candidates_per_frame": 3, "seed": 5}, (0, 2)),
    "c4_s0_jitter": ({"candidates_per_frame": 4, "seed": 0, "size_jitter": 0.2}, (0, 1)),
}


def sample_hash(sample: dict) -> str:
    """SHA-256 over every tensor of a sample (keys sorted; dtype, shape and bytes)."""
    h = hashlib.sha256()
    for key in sorted(sample):
        value = sample[key].numpy()
        h.update(f"{key}:{value.dtype}:{value.shape}".encode())
        h.update(value.tobytes())
    return h.hexdigest()


def build(kwargs: dict) -> TrackingSamples:
    return TrackingSamples(fake_tracklets(n=3, frames=6), **kwargs)


def record() -> dict:
    result = {}
    for name, (kwargs, epochs) in CASES.items():
        data = build(kwargs)
        for epoch in epochs:
            data.set_epoch(epoch)
            result[f"{name}/e{epoch}"] = [sample_hash(data[i]) for i in range(len(data))]
    return result


if __name__ == "__main__":
    OUT.write_text(json.dumps(record(), indent=1) + "\n")
    print(f"wrote {OUT}")
