"""The one process pool of the project: independent items over forked workers.

:func:`map_forked` runs ``fn(item)`` for every item in ``workers`` forked processes (one torch
thread each) and returns the results in the items' order. Nothing is pickled but the items and
the results: the children inherit ``fn`` (a closure over a tracker and an env is fine). Items are
handed out one at a time over each worker's own pipe (the next free worker gets the next item), so a
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

import contextlib
import os
import warnings
from collections.abc import Callable, Iterator, Sequence
from dataclasses import dataclass
from typing import Any

__all__ = [
    "WorkerDiedError",
    "map_forked",
    "one_torch_thread",
    "resolve_workers",
    "torch_threads",
    "usable_cores",
]


class WorkerDiedError(ChildProcessError):
    """A worker process ended without returning the items it was running (an ``OSError``, so
    the CLI reports it in one line)."""


@contextlib.contextmanager
def torch_threads(count: int) -> Iterator[None]:
    """Torch on ``count`` intra-op threads for the block (restored after)."""
    import torch

    before = torch.get_num_threads()
    torch.set_num_threads(count)
    try:
        yield
    finally:
        torch.set_num_threads(before)


def one_torch_thread() -> contextlib.AbstractContextManager[None]:
    """Torch on one intra-op thread for the block (restored after). Evaluations run so in
    every process: a closed tracking loop amplifies the last-bit differences that another
    thread count gives a forward (tracklet 0019/21 of the small test split: P2B Success 63.6
    with two threads, 58.7 with one), so results depend on neither the machine's cores nor
    the number of workers."""
    return torch_threads(1)


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
    warm_up: Callable[[], Any] | None = None,
) -> list[Any]:
    """``[fn(item) for item in items]``, in ``workers`` forked processes when ``workers > 1``.

    Args:
        fn: called once per item (in a child: one torch thread); its result is pickled back.
        items: the work, handed out in this order (put long items first for balance).
        workers: number of processes (``None`` or ``<= 1``: in this process, no fork).
        done: ``done(item, result)`` in the parent as each result arrives (a progress bar).
        label: how an item is named in an error (default ``repr``).
        warm_up: work of the caller's next step (e.g. importing a library for its report),
            run once in a thread of this process while the workers run, on the core the
            waiting parent leaves idle (started after the last fork, joined before returning;
            its exception is raised then). Not run without workers: nothing would overlap.

    Raises:
        WorkerDiedError: a worker ended without the result of the item it was given.
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
    pool = _Pool([], [], {}, iter(range(len(items))))
    try:
        for _ in range(min(int(workers), len(items))):
            # one pipe per worker, written synchronously: nothing sent is lost if it is killed
            parent_end, child_end = ctx.Pipe()
            proc = ctx.Process(target=_work, args=(fn, items, child_end), daemon=True)
            proc.start()
            child_end.close()
            pool.conns.append(parent_end)
            pool.procs.append(proc)
        for w in range(len(pool.procs)):
            pool.hand_out(w, items, label)
        with _alongside(warm_up):
            return pool.collect(items, done, label)
    finally:
        for proc in pool.procs:
            if proc.is_alive():
                proc.terminate()
            proc.join()
        for conn in pool.conns:
            conn.close()


@contextlib.contextmanager
def _alongside(task: Callable[[], Any] | None) -> Iterator[None]:
    """Run ``task`` in a thread during the block; join it after, raising what it raised (unless
    the block itself raises: that error wins)."""
    if task is None:
        yield
        return
    import threading

    failure: list[BaseException] = []

    def run() -> None:
        try:
            task()
        except BaseException as exc:  # noqa: BLE001 - re-raised in the caller's thread
            failure.append(exc)

    thread = threading.Thread(target=run, name="map_forked-warm-up", daemon=True)
    thread.start()
    try:
        yield
    finally:
        thread.join()
    if failure:
        raise failure[0]


def _work(fn: Callable[[Any], Any], items: Sequence[Any], conn: Any) -> None:
    """A worker's loop: receive an item index (``None``: stop), run it, send the outcome."""
    import traceback

    import torch

    torch.set_num_threads(1)  # the workers are the parallelism
    while (i := conn.recv()) is not None:
        try:
            conn.send(("done", i, fn(items[i])))
        except BaseException:  # noqa: BLE001 - reported to the parent, which raises
            conn.send(("error", i, traceback.format_exc()))


@dataclass
class _Pool:
    """The parent's view: each worker's pipe and process, the item each one runs."""

    conns: list[Any]
    procs: list[Any]
    running: dict[int, int]  # worker -> item index it was given
    pending: Iterator[int]

    def hand_out(self, w: int, items: Sequence[Any], label: Callable[[Any], str]) -> None:
        """Give worker ``w`` the next item, or tell it to stop."""
        i = next(self.pending, None)
        try:
            self.conns[w].send(i)
        except OSError:  # it died between two items
            if i is None:
                return
            raise WorkerDiedError(
                f"worker process {self.procs[w].pid} died before taking {label(items[i])}; "
                "nothing written"
            ) from None
        if i is not None:
            self.running[w] = i

    def _receive(self, w: int) -> tuple[str, int, Any] | None:
        """Worker ``w``'s next message, or ``None`` (none waiting, or its pipe closed: then
        the process is ending, and it is waited for)."""
        conn = self.conns[w]
        try:
            return conn.recv() if conn.poll() else None
        except EOFError:
            self.procs[w].join()
            return None

    def collect(
        self,
        items: Sequence[Any],
        done: Callable[[Any, Any], None] | None,
        label: Callable[[Any], str],
    ) -> list[Any]:
        """Gather every result; fail fast on an error or a worker that died."""
        from multiprocessing.connection import wait

        results: dict[int, Any] = {}
        alive = set(range(len(self.procs)))
        while len(results) < len(items):
            if not alive:
                missing = [label(items[i]) for i in range(len(items)) if i not in results]
                raise WorkerDiedError(f"worker processes ended without results for {missing}")
            owner = {id(self.conns[w]): w for w in alive}
            owner |= {id(self.procs[w].sentinel): w for w in alive}
            ready = wait([self.conns[w] for w in alive] + [self.procs[w].sentinel for w in alive])
            for obj in ready:
                w = owner[id(obj)]
                message = self._receive(w)  # a message first, even from a worker that ended
                if message is not None:
                    kind, i, value = message
                    del self.running[w]
                    if kind == "error":
                        raise RuntimeError(
                            f"{label(items[i])} failed in a worker process:\n{value}"
                        )
                    results[i] = value
                    if done is not None:
                        done(items[i], value)
                    self.hand_out(w, items, label)
                elif w in alive and not self.procs[w].is_alive():
                    self._ended(w, items, results, label)
                    alive.discard(w)
        return [results[i] for i in range(len(items))]

    def _ended(self, w: int, items: Sequence[Any], results: dict[int, Any], label) -> None:
        """Worker ``w`` ended: fine after its stop mark, :class:`WorkerDiedError` while it
        still had an item."""
        if w not in self.running:
            return
        proc = self.procs[w]
        proc.join()
        missing = sum(1 for i in range(len(items)) if i not in results)
        raise WorkerDiedError(
            f"worker process {proc.pid} died (exit code {proc.exitcode}) while running "
            f"{label(items[self.running[w]])}; {missing} item(s) without a result, "
            "nothing written"
        )
