"""The tracker's frozen leading stages, run under ``no_grad`` and cached between a rollout and
its update epochs (issue 41 item 4).

With ``train_parts="head"`` (or ``"fusion+head"``) the stages before the first trained one
(the backbone, and the fusion for ``"head"``) compute the same features for a state in the
rollout and in every update epoch: their weights do not change within an update and the
tracker always runs in eval mode. :class:`FrozenStages` wraps those stages' entry points
(``forward``, and ``forward_many`` where a stage has one): while :meth:`FrozenStages.recording`
is on it keeps each call's outputs, and under :meth:`FrozenStages.replaying` the calls return
the kept outputs of the minibatch's rows instead of running, so an update epoch runs only the
trained stages and the decision step. :meth:`FrozenStages.call` does the same for any other
computation that depends on the observation alone (the policy's decision-step scenes, kept as
:class:`PerState` objects, its still-target test, a matching tracker's sampling orders).
Outputs must have the batch as their leading dimension (every tensor leaf); a stage whose
outputs do not is simply not cached (the update then runs it).
"""

from __future__ import annotations

import contextlib
import types
from collections.abc import Callable, Iterator, Sequence
from typing import Any

import torch
from torch import nn

__all__ = ["FrozenStages", "PerState", "StageFeatures"]

#: the entry points of a stage the tracker calls (the backbone's ``forward_many`` runs the
#: template and the search region together)
_ENTRY_POINTS = ("forward", "forward_many")


class PerState(tuple):
    """Python objects, one per state of a forward (not tensors: the decision step's
    :class:`trackers.decision.Scene` s): a leaf of a frozen call's outputs that is kept,
    concatenated and selected by rows as its tensors are."""


def _detach(leaf: Any) -> Any:
    return leaf.detach() if isinstance(leaf, torch.Tensor) else leaf


def _cat(*parts: Any) -> Any:
    if isinstance(parts[0], PerState):
        return PerState(item for part in parts for item in part)
    return torch.cat(parts)


def _take(leaf: Any, rows: torch.Tensor) -> Any:
    return PerState(leaf[i] for i in rows.tolist()) if isinstance(leaf, PerState) else leaf[rows]


def _rows(leaf: torch.Tensor | PerState) -> int | None:
    """The leading (state) dimension of a leaf; None for a 0-dim tensor."""
    if isinstance(leaf, PerState):
        return len(leaf)
    return leaf.shape[0] if leaf.dim() else None


def _tree_map(fn: Callable[..., Any], *trees: Any) -> Any:
    """``fn`` on the tensor (and :class:`PerState`) leaves of nested tuples / lists / dicts
    (``None`` kept)."""
    first = trees[0]
    if isinstance(first, torch.Tensor | PerState):
        return fn(*trees)
    if isinstance(first, tuple | list):
        return type(first)(_tree_map(fn, *parts) for parts in zip(*trees, strict=True))
    if isinstance(first, dict):
        return {k: _tree_map(fn, *(t[k] for t in trees)) for k in first}
    return first


def _leaves(tree: Any) -> list[torch.Tensor | PerState]:
    found: list[torch.Tensor | PerState] = []
    _tree_map(lambda t: found.append(t), tree)
    return found


class StageFeatures:
    """The frozen stages' outputs for ``S`` states: one entry per stage call of a forward (in
    call order), each a tree of ``(S, ...)`` tensors; :meth:`select` takes rows."""

    def __init__(self, calls: list[Any]) -> None:
        self.calls = calls

    def select(self, rows: torch.Tensor) -> StageFeatures:
        """The outputs of the states ``rows (b,)`` (indices into ``S``)."""
        return StageFeatures([_tree_map(lambda t: _take(t, rows), call) for call in self.calls])


class FrozenStages:
    """Runs a tracker's frozen leading children under ``no_grad`` and caches their outputs
    (see the module docstring). ``stages``: the children, in execution order."""

    def __init__(self, stages: Sequence[nn.Module]) -> None:
        self._forwards: list[list[Any]] | None = None  # recording: each forward's calls
        self._replay: list[Any] | None = None  # replaying: the calls left to return
        self._depth = 0  # a stage's entry point calling another one records once
        self.cacheable = True
        for stage in stages:
            for name in _ENTRY_POINTS:
                if hasattr(type(stage), name):
                    self.wrap(stage, name)

    def wrap(self, owner: Any, name: str) -> None:
        """Make ``owner.name`` a frozen call (:meth:`call`): a stage's entry point, or a method
        whose outputs only frozen stages read (a matching tracker's backbone sampling orders)."""
        # a bound method on the instance: a deepcopy of the tracker rebinds it
        setattr(owner, name, types.MethodType(self._wrapped(name), owner))

    def _wrapped(self, name: str) -> Callable[..., Any]:
        frozen = self

        def entry(owner: Any, *args: Any, **kwargs: Any) -> Any:
            return frozen.call(getattr(type(owner), name), owner, *args, **kwargs)

        entry.__name__ = f"frozen_{name}"
        return entry

    def call(self, fn: Callable[..., Any], *args: Any, **kwargs: Any) -> Any:
        """``fn(*args, **kwargs)`` as a frozen stage: under ``no_grad``, its outputs kept while
        recording and returned from the cache while replaying. The stages' entry points go
        through here, and so can any other computation that depends on the observation alone
        (the policy's decision-step scenes and still-target test)."""
        if self._depth == 0 and self._replay is not None:
            return self._replay.pop(0)
        self._depth += 1
        try:
            with torch.no_grad():
                out = fn(*args, **kwargs)
        finally:
            self._depth -= 1
        if self._depth == 0 and self._forwards is not None:
            self._forwards[-1].append(_tree_map(_detach, out))
        return out

    def start_forward(self, batch_size: int) -> None:
        """Called by the policy before each tracker forward of ``batch_size`` states."""
        if self._forwards is not None:
            self._check_last()
            self._forwards.append([])
            self._batch_sizes.append(batch_size)

    def _check_last(self) -> None:
        if self._forwards and any(
            _rows(leaf) != self._batch_sizes[-1]
            for call in self._forwards[-1]
            for leaf in _leaves(call)
        ):
            self.cacheable = False

    @contextlib.contextmanager
    def recording(self) -> Iterator[list[StageFeatures | None]]:
        """Keep the outputs of the forwards inside; the yielded list then holds one
        :class:`StageFeatures` for all their states, in order (``None`` when a stage's outputs
        are not batch-leading, or no forward ran)."""
        self._forwards, self._batch_sizes, self.cacheable = [], [], True
        result: list[StageFeatures | None] = [None]
        try:
            yield result
            self._check_last()
            forwards = self._forwards
            if self.cacheable and forwards and all(len(f) == len(forwards[0]) for f in forwards):
                calls = [
                    _tree_map(_cat, *(f[i] for f in forwards)) for i in range(len(forwards[0]))
                ]
                result[0] = StageFeatures(calls)
        finally:
            self._forwards = None

    @contextlib.contextmanager
    def replaying(self, features: StageFeatures | None) -> Iterator[None]:
        """The forward inside returns ``features``' outputs from the frozen stages (``None``:
        they run)."""
        if features is None:
            yield
            return
        self._replay = list(features.calls)
        try:
            yield
            if self._replay:
                raise RuntimeError(
                    f"cached frozen-stage features: {len(self._replay)} call(s) left unused"
                )
        finally:
            self._replay = None
