"""Synthetic training batches for tests and benchmarks (no dataset needed).

``toy_batch(B, seed)`` -> ``(batch, targets)`` in the trackers' contract: a box-shaped target
(points on its surface) on a ground plane; the template in the target's own box frame, the
search region in a reference frame the target is slightly offset and rotated from.
"""

from __future__ import annotations

import torch

from envs.geometry import box_to_world_torch, world_to_box_torch

__all__ = ["toy_batch"]


def _surface(n: int, size: torch.Tensor, g: torch.Generator) -> torch.Tensor:
    """``n`` points on the faces (not the bottom) of boxes ``size (B, 3)`` -> ``(B, n, 3)``."""
    b = size.shape[0]
    u = torch.rand(b, n, 3, generator=g) - 0.5
    face = torch.randint(0, 5, (b, n), generator=g)  # +-x, +-y, +z
    axis = torch.tensor([0, 0, 1, 1, 2])[face]
    sign = torch.tensor([0.5, -0.5, 0.5, -0.5, 0.5])[face]
    u.scatter_(2, axis[..., None], sign[..., None])
    return u * size[:, None, :]


def toy_batch(
    batch_size: int = 2,
    seed: int = 0,
    template_points: int = 512,
    search_points: int = 1024,
    target_fraction: float = 0.4,
) -> tuple[dict[str, torch.Tensor], dict[str, torch.Tensor]]:
    """A synthetic batch and its targets (float32 CPU tensors), deterministic in ``seed``."""
    g = torch.Generator().manual_seed(seed)
    b = batch_size
    size = torch.stack(
        [
            3.5 + torch.rand(b, generator=g),
            1.5 + 0.4 * torch.rand(b, generator=g),
            1.4 + 0.3 * torch.rand(b, generator=g),
        ],
        dim=-1,
    )
    zeros = torch.zeros(b, 1)
    # ground-truth box in the search (reference) frame
    centre = torch.cat(
        [0.4 * torch.randn(b, 2, generator=g), 0.1 * torch.randn(b, 1, generator=g)], -1
    )
    yaw = 0.1 * torch.randn(b, 1, generator=g)
    gt = torch.cat([centre, size, yaw], dim=-1)
    # search: target surface points + ground plane + a few clutter points
    n_t = int(search_points * target_fraction)
    target = box_to_world_torch(_surface(n_t, size, g), gt)
    half = size[:, None, :2] * 0.625 + 2.0
    n_g = search_points - n_t
    ground_xy = (torch.rand(b, n_g, 2, generator=g) * 2 - 1) * half
    ground_z = (centre[:, None, 2:3] - size[:, None, 2:3] / 2).expand(b, n_g, 1)
    ground = torch.cat([ground_xy, ground_z + 0.02 * torch.randn(b, n_g, 1, generator=g)], -1)
    search = torch.cat([target, ground], dim=1)
    shuffle = torch.argsort(torch.rand(b, search_points, generator=g), 1)
    search = search[torch.arange(b)[:, None], shuffle]
    local = world_to_box_torch(search, gt)
    labels = (local.abs() <= size[:, None, :] / 2 + 1e-4).all(-1).float()
    # template: target points in its own (canonical) box frame + a little ground
    n_tt = int(template_points * 0.9)
    canon = torch.cat([zeros.expand(b, 3), size, zeros], dim=-1)
    t_target = _surface(n_tt, size, g)
    n_tg = template_points - n_tt
    t_ground_xy = (torch.rand(b, n_tg, 2, generator=g) * 2 - 1) * size[:, None, :2] * 0.625
    t_ground = torch.cat([t_ground_xy, (-size[:, None, 2:3] / 2).expand(-1, n_tg, 1)], -1)
    template = torch.cat([t_target, t_ground], dim=1)
    t_local = world_to_box_torch(template, canon)
    t_labels = (t_local.abs() <= size[:, None, :] / 2 + 1e-4).all(-1).float()
    batch = {
        "template": template.float(),
        "search": search.float(),
        "size": size.float(),
        "motion": torch.zeros(b, 4),
    }
    targets = {
        "search_box": gt.float(),
        "search_labels": labels,
        "template_centers": torch.zeros(b, template_points, 3),
        "template_labels": t_labels,
    }
    return batch, targets
