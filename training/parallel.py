"""The one process pool of the project: independent items over forked workers.

:func:`map_forked` runs ``fn(item)`` for every item in ``workers`` forked processes (one torch
thread each) and returns the results in the items' order. Nothing is pickled but the items and
the results: the children inherit ``fn`` (a closure over a tracker and an env is fine). Items are
handed out one at a time from a shared queue (the next free worker takes the next item), so a
long item does not hold up a whole static shard; callers that want the results to be independent
of the assignment (``training.evaluate``: each tracklet seeds its own episode) get them so.

:func:`resolve_workers` is the one rule for a ``--workers`` value: ``None`` means every usable
core (``os.sched_getaffinity``), ``< 1`` is an error, more than the usable cores is clamped with
a warning (more processes than cores only adds switching).

A worker that dies without a result (killed, out of memory) raises :class:`WorkerDiedError`
naming the items it was running; an item that raises in a worker raises ``RuntimeError`` with
the worker's traceback. Either way the pool is torn down and nothing partial is returned.
"""

from __future__ import annotations

import os
import warnings
from collections.abc import Callable, Sequence
from typing import Any

__all__ = ["WorkerDiedError", "map_forked", "resolve_workers", "usable_cores"]

#: seconds between checks that every worker is still alive while waiting for results
_POLL_S = 0.2


class WorkerDiedError(ChildProcessError):
    """A worker process ended without returning the items it was running (an ``OSError``, so
    the CLI reports it in one line)."""


def usable_cores() -> int:
    """The cores this process may run on (its CPU affinity, not the machine's count)."""
    try:
        return len(os.sched_getaffinity(0))
    except AttributeError:  # not Linux
        return os.cpu_count() or 1


def resolve_workers(workers: int | None, what: str = "workers") -> int:
    """``workers`` checked: ``None`` -> :func:`usable_cores`; not an integer or ``< 1`` ->
    ``ValueError`` naming ``what``; more than the usable cores -> that many, with a warning."""
    cores = usable_cores()
    if workers is None:
        return cores
    if isinstance(workers, bool) or int(workers) != workers or workers < 1:
        raise ValueError(f"{what} must be an integer >= 1; got {workers!r}")
    if workers > cores:
        warnings.warn(
            f"{what}={workers} is more than the {cores} usable core(s): using {cores}",
            UserWarning,
            stacklevel=2,
        )
        return cores
    return int(workers)


def map_forked(
    fn: Callable[[Any], Any],
    items: Sequence[Any],
    workers: int | None,
    done: Callable[[Any, Any], None] | None = None,
    *,
    label: Callable[[Any], str] = repr,
) -> list[Any]:
    """``[fn(item) for item in items]``, in ``workers`` forked processes when ``workers > 1``.

    Args:
        fn: called once per item (in a child: one torch thread); its result is pickled back.
        items: the work, handed out in this order (put long items first for balance).
        workers: number of processes (``None`` or ``<= 1``: in this process, no fork).
        done: ``done(item, result)`` in the parent as each result arrives (a progress bar).
        label: how an item is named in an error (default ``repr``).

    Raises:
        WorkerDiedError: a worker ended without the results of the items it had taken.
        RuntimeError: ``fn`` raised in a worker (the message holds its traceback).
    """
    import multiprocessing as mp

    if workers is None or workers <= 1 or len(items) <= 1:
        results = []
        for item in items:
            results.append(fn(item))
            if done is not None:
                done(item, results[-1])
        return results
    if "fork" not in mp.get_all_start_methods():
        raise RuntimeError("workers > 1 needs the 'fork' start method (Linux); use workers=1")
    ctx = mp.get_context("fork")
    n = min(int(workers), len(items))
    tasks = ctx.Queue()
    for i in range(len(items)):
        tasks.put(i)
    for _ in range(n):
        tasks.put(None)  # one stop mark per worker
    messages = ctx.Queue()
    procs = [ctx.Process(target=_work, args=(fn, items, tasks, messages)) for _ in range(n)]
    for proc in procs:
        proc.start()
    try:
        return _collect(items, procs, messages, done, label)
    finally:
        for proc in procs:
            if proc.is_alive():
                proc.terminate()
            proc.join()
        for q in (tasks, messages):
            q.cancel_join_thread()  # a killed worker may leave items unread
            q.close()


def _work(fn: Callable[[Any], Any], items: Sequence[Any], tasks: Any, messages: Any) -> None:
    """A worker's loop: take an item index, say it started, run it, send the result."""
    import traceback

    import torch

    torch.set_num_threads(1)  # the workers are the parallelism
    pid = os.getpid()
    while (i := tasks.get()) is not None:
        messages.put(("start", i, pid, None))
        try:
            messages.put(("done", i, pid, fn(items[i])))
        except BaseException:  # noqa: BLE001 - reported to the parent, which raises
            messages.put(("error", i, pid, traceback.format_exc()))


def _collect(
    items: Sequence[Any],
    procs: list[Any],
    messages: Any,
    done: Callable[[Any, Any], None] | None,
    label: Callable[[Any], str],
) -> list[Any]:
    """The parent's loop: gather results, fail fast on an error or a dead worker."""
    import queue as queue_module

    results: dict[int, Any] = {}
    running: dict[int, set[int]] = {}  # pid -> indices started, not finished
    while len(results) < len(items):
        try:
            kind, i, pid, value = messages.get(timeout=_POLL_S)
        except queue_module.Empty:
            _check_alive(items, procs, running, results, label)
            continue
        if kind == "start":
            running.setdefault(pid, set()).add(i)
            continue
        running.get(pid, set()).discard(i)
        if kind == "error":
            raise RuntimeError(f"{label(items[i])} failed in a worker process:\n{value}")
        results[i] = value
        if done is not None:
            done(items[i], value)
    return [results[i] for i in range(len(items))]


def _check_alive(
    items: Sequence[Any],
    procs: list[Any],
    running: dict[int, set[int]],
    results: dict[int, Any],
    label: Callable[[Any], str],
) -> None:
    """Raise :class:`WorkerDiedError` when a worker ended abnormally, or when every worker
    ended with results missing (called when no message came for a while, so the dead
    worker's last messages have been read)."""
    for proc in procs:
        if proc.exitcode not in (None, 0):
            lost = sorted(running.get(proc.pid, set()))
            missing = [i for i in range(len(items)) if i not in results]
            raise WorkerDiedError(
                f"worker process {proc.pid} died (exit code {proc.exitcode}) while running "
                f"{', '.join(label(items[i]) for i in lost) or 'no item'}; "
                f"{len(missing)} item(s) without a result, nothing written"
            )
    if all(proc.exitcode is not None for proc in procs):
        missing = [label(items[i]) for i in range(len(items)) if i not in results]
        raise WorkerDiedError(f"worker processes ended without results for {missing}")
