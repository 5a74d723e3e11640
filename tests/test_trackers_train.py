"""One synthetic batch overfits: the loss falls by an order of magnitude (tiny configs)."""

from __future__ import annotations

import pytest
import torch

import trackers
from trackers.toy import toy_batch

TINY = {
    "backbone": {"channels": [[16, 16, 32], [32, 32, 64], [64, 64, 64]], "out_channels": 64},
    "head": {"vote_channels": 64},
    "out_channels": 64,
}
EXTRA = {
    "p2b": {"hidden_channels": 64},
    "bat": {"hidden_channels": 64},
    "gpt": {"node_channels": 32, "itc_channels": 32},
}


SLOW = pytest.mark.slow


@pytest.mark.parametrize(
    "name", ["p2b", pytest.param("bat", marks=SLOW), pytest.param("gpt", marks=SLOW)]
)
def test_one_batch_overfits(name, one_torch_thread):
    torch.manual_seed(0)
    model = trackers.make(name, **TINY, **EXTRA[name]).train()
    batch, targets = toy_batch(2, seed=0, template_points=128, search_points=256)
    opt = torch.optim.Adam(model.parameters(), lr=3e-3)
    first = None
    for _ in range(150):
        # a fixed sampling generator makes the objective a fixed function of the weights
        out = model(batch, generator=torch.Generator().manual_seed(0))
        total = model.loss(out, targets)["total"].mean()
        first = total.item() if first is None else first
        if total.item() < first / 10:
            break
        opt.zero_grad()
        total.backward()
        opt.step()
    assert total.item() < first / 10, (first, total.item())
