"""Keep freed large CPU blocks in the process instead of returning them to the kernel.

glibc's ``malloc`` serves every block above its mmap threshold (at most 32 MiB) with a fresh
``mmap`` and unmaps it on ``free``, so each such tensor costs page faults and zeroing by the
kernel on every allocation. A CPU training step allocates dozens of them: P2B's feature
augmentation alone holds ``(B, 64, 128, 64)`` float32 activations, 100 MiB at the default batch
48, and a fresh one costs ~10 ms more than a reused one. :func:`retain_freed_memory` has malloc
take every block from its heap and keep up to ``trim_bytes`` of freed memory there. P2B slim
training, one thread, on this project's 2-core VM: 1.40x samples/s at batch 48 for a peak RSS
of 4,574 against 3,618 MiB (the heap fragments before it settles), 1.08x at batch 16 (1,966
against 1,806 MiB), nothing at batch 8, whose blocks stay below the threshold
(``benchmarks/bench_training.py --batch 48``).
"""

from __future__ import annotations

import ctypes
import functools
import sys

__all__ = ["retain_freed_memory"]

# mallopt parameters (glibc's malloc.h)
_M_TRIM_THRESHOLD = -1
_M_MMAP_MAX = -4


@functools.cache
def retain_freed_memory(trim_bytes: int = 1 << 30) -> bool:
    """Ask glibc's malloc to serve large blocks from its heap (no ``mmap`` per block) and to
    keep up to ``trim_bytes`` of freed memory. Once per process (cached); ``True`` when
    applied, ``False`` off Linux or without glibc (nothing changes: only speed is at stake).
    Process-wide, as ``torch.set_num_threads``: the trainer and the RL loop call it on CPU
    (GroupPPO fine-tuning of gpt-kitti1-u: ~1.07x steps/s)."""
    if not sys.platform.startswith("linux"):
        return False
    try:  # the process's own symbols (libc among them): no library search, no subprocess
        mallopt = ctypes.CDLL(None).mallopt
    except (OSError, AttributeError):  # musl and other libcs: no mallopt
        return False
    mallopt.argtypes, mallopt.restype = [ctypes.c_int, ctypes.c_int], ctypes.c_int
    trim = min(int(trim_bytes), 2**31 - 1)
    return mallopt(_M_MMAP_MAX, 0) == 1 and mallopt(_M_TRIM_THRESHOLD, trim) == 1
