"""Ray as an optional engine: the one-line refusal without the ``sweep`` extra, connecting to a
local or remote Ray, and :func:`map_ray`, the Ray counterpart of the local process pool that
``pointtrack eval --weather --backend ray`` uses.

Only this module (and :mod:`training.sweep.runner`) imports ``ray``, and only inside functions,
so the CLI and the tests run without the extra.
"""

from __future__ import annotations

import os
import socket
from collections.abc import Callable, Sequence
from typing import Any
from urllib.parse import urlsplit

__all__ = ["RayUnavailable", "connect", "map_ray", "require_ray", "usable_cpus"]

INSTALL_HINT = "Ray is not installed: pip install 'pointtrack[sweep]' (ray[tune]>=2.9)"


class RayUnavailable(OSError):
    """Ray is not installed, or the cluster at ``--address`` cannot be reached (one line)."""


def require_ray(tune: bool = False) -> Any:
    """The ``ray`` module (with ``ray.tune`` imported when ``tune``), or :class:`RayUnavailable`
    naming the extra to install."""
    try:
        import ray

        if tune:
            import ray.tune  # noqa: F401 - the sweep needs Tune, not only the core
    except ImportError:
        raise RayUnavailable(INSTALL_HINT) from None
    return ray


def usable_cpus() -> int:
    """The cores this process may run on (its CPU affinity, not the machine's count)."""
    return len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else os.cpu_count() or 1


def connect(address: str | None, num_cpus: int | None = None) -> bool:
    """Connect this process to Ray: ``None`` starts a local Ray with ``num_cpus`` (default: the
    usable cores); ``"auto"``, ``HOST:PORT`` or ``ray://HOST:PORT`` joins a running cluster.

    Returns whether this call started the connection (the caller then shuts it down). A cluster
    that cannot be reached raises :class:`RayUnavailable` in one line, after a TCP check of a
    few seconds (Ray's own client would wait 30 s and print pages)."""
    ray = require_ray()
    if ray.is_initialized():
        return False
    if address not in (None, "auto", "local"):
        _check_reachable(address)
    quiet = {"include_dashboard": False, "logging_level": "WARNING", "log_to_driver": False}
    try:
        if address in (None, "local"):
            ray.init(num_cpus=num_cpus or usable_cpus(), **quiet)
        else:
            ray.init(address=address, **quiet)
    except ConnectionError as exc:
        raise RayUnavailable(f"cannot reach Ray at {address}: {exc}") from None
    return True


def _check_reachable(address: str, timeout_s: float = 5.0) -> None:
    parts = urlsplit(address if "://" in address else f"tcp://{address}")
    try:
        host, port = parts.hostname, parts.port
    except ValueError:
        host, port = None, None
    if not host or port is None:
        raise RayUnavailable(f"--address {address!r}: expected auto, HOST:PORT or ray://HOST:PORT")
    try:
        with socket.create_connection((host, port), timeout=timeout_s):
            pass
    except OSError as exc:
        raise RayUnavailable(f"cannot reach Ray at {address}: {exc.strerror or exc}") from None


def map_ray(
    fn: Callable[[Any], Any],
    items: Sequence[Any],
    workers: int | None = None,
    done: Callable[[Any, Any], None] | None = None,
) -> list[Any]:
    """``[fn(item) for item in items]`` as Ray tasks, one torch thread and one CPU each; the
    same signature as the local pool (``training.parallel.map_forked``).

    ``fn`` may be a closure (Ray pickles it with cloudpickle, once). Connects to ``RAY_ADDRESS``
    when set, else starts a local Ray with ``workers`` CPUs (default: the usable cores), and
    shuts down what it started. ``done(item, result)`` is called as each result arrives. A
    failing item raises ``RuntimeError`` naming it, with the task's error."""
    ray = require_ray()
    started = connect(os.environ.get("RAY_ADDRESS"), num_cpus=workers)
    try:

        def task(item: Any) -> Any:
            import torch

            torch.set_num_threads(1)  # as the local pool: one thread per condition
            return fn(item)

        remote = ray.remote(num_cpus=1, max_retries=0)(task)
        pending = {remote.remote(item): i for i, item in enumerate(items)}
        results: dict[int, Any] = {}
        while pending:
            ready, _ = ray.wait(list(pending), num_returns=1)
            i = pending.pop(ready[0])
            try:
                results[i] = ray.get(ready[0])
            except ray.exceptions.RayError as exc:
                for ref in pending:
                    ray.cancel(ref, force=True)
                raise RuntimeError(f"{items[i]!r} failed in a Ray task:\n{exc}") from None
            if done is not None:
                done(items[i], results[i])
        return [results[i] for i in range(len(items))]
    finally:
        if started:
            ray.shutdown()
