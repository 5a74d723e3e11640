"""Episode scheduling: which tracklet, which frames and which resampling generator the env's
next episode gets (sequential or random sampling, the tracklet order, the reset options).

Draws come from the generator the caller passes (the env's ``np_random``), in a fixed order —
the tracklet, then a random start frame — so a seeded reset repeats its episode.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

import numpy as np

from envs.data.tracklet import Tracklet
from envs.spec import (
    RESET_OPTIONS,
    EnvOptions,
    check_max_steps,
    check_seed,
    check_start_frame,
)

__all__ = ["EpisodeSchedule"]


class EpisodeSchedule:
    """The episodes of a list of tracklets.

    Args:
        tracklets: the env's tracklets (shared, not copied).
        options: the env's options: ``sampling`` (``"sequential"``: visit
            :attr:`tracklet_order`, wrapping around; ``"random"``: draw one uniformly), and
            ``start_frame``, ``max_steps``, ``episode_seed``: the defaults of the reset options
            of the same names.
    """

    def __init__(self, tracklets: list[Tracklet], options: EnvOptions) -> None:
        self.tracklets = tracklets
        self.sampling = options.sampling
        self.default_start = options.start_frame
        self.default_max_steps = options.max_steps
        self.episode_seed = options.episode_seed
        self._order: list[int] | None = None
        self.cursor = 0

    @property
    def episode_seed(self) -> int | None:
        """Seed of the per-episode resampling generators (``None``: the env's ``np_random``)."""
        return self._episode_seed

    @episode_seed.setter
    def episode_seed(self, seed: int | None) -> None:
        self._episode_seed = check_seed(seed, "episode_seed")

    @property
    def tracklet_order(self) -> list[int]:
        """Indices visited by sequential sampling (settable; setting restarts the visit)."""
        if self._order is None:
            return list(range(len(self.tracklets)))
        return list(self._order)

    @tracklet_order.setter
    def tracklet_order(self, order: Sequence[int] | None) -> None:
        if order is None:
            self._order = None
            return
        order = [int(i) for i in order]
        bad = [i for i in order if not 0 <= i < len(self.tracklets)]
        if bad:
            raise ValueError(
                f"tracklet_order indices {bad} out of range 0..{len(self.tracklets) - 1}"
            )
        self._order = order
        self.cursor = 0

    def options(self, options: dict[str, Any] | None) -> dict[str, Any]:
        """The reset options validated, with the defaults for missing ones; ``category`` as a
        tuple of names. Any other key raises ``ValueError`` naming the valid ones; ``None``
        values mean "not given".

        - ``tracklet``: an index into the tracklets or a tracklet id;
        - ``category``: a category name or a list of them: the next tracklet (sequential: in
          ``tracklet_order`` from the cursor on; random: uniformly among them) of those;
        - ``start_frame``: an index in the tracklet (``0 .. T-2``) or ``"random"`` (uniform
          over them, drawn with the env's ``np_random``);
        - ``max_steps``: the clip length, at least 1;
        - ``episode_seed``: this episode's resampling seed (overrides the env's).

        The env's ``start_frame``, ``max_steps`` and ``episode_seed`` are the defaults;
        ``categories`` and ``sampling`` / ``tracklet_order`` play that part for ``category``
        and ``tracklet``.
        """
        options = dict(options or {})
        unknown = sorted(set(options) - set(RESET_OPTIONS))
        if unknown:
            raise ValueError(f"unknown reset options {unknown}; valid: {list(RESET_OPTIONS)}")
        opts = {k: options.get(k) for k in RESET_OPTIONS}
        if opts["start_frame"] is None:
            opts["start_frame"] = self.default_start
        else:
            check_start_frame(opts["start_frame"], "options['start_frame']")
        if opts["max_steps"] is None:
            opts["max_steps"] = self.default_max_steps
        else:
            check_max_steps(opts["max_steps"], "options['max_steps']")
        if opts["episode_seed"] is None:
            opts["episode_seed"] = self._episode_seed
        else:
            opts["episode_seed"] = check_seed(opts["episode_seed"], "options['episode_seed']")
        category = opts["category"]
        if category is not None:
            wanted = (category,) if isinstance(category, str) else tuple(category)
            served = sorted({tr.category for tr in self.tracklets})
            bad = [c for c in wanted if c not in served]
            if bad or not wanted:
                raise ValueError(
                    f"options['category']={category!r}: no tracklets of {bad or 'no category'} "
                    f"in this env; valid: {served}"
                )
            opts["category"] = wanted
        return opts

    def choose(
        self, tracklet: Any, category: tuple[str, ...] | None, rng: np.random.Generator
    ) -> int:
        """The index of the episode's tracklet (draws from ``rng`` when random)."""
        if tracklet is not None:
            index = self.index_of(tracklet)
            found = self.tracklets[index].category
            if category is not None and found not in category:
                raise ValueError(
                    f"options['tracklet']={tracklet!r} is a {found}, not of "
                    f"options['category']={list(category)}"
                )
            return index
        if self.sampling == "random":
            if category is None:
                return int(rng.integers(len(self.tracklets)))
            pool = [i for i, tr in enumerate(self.tracklets) if tr.category in category]
            return pool[int(rng.integers(len(pool)))]
        order = self.tracklet_order
        if not order:
            raise RuntimeError("tracklet_order is empty; nothing to visit")
        for k in range(len(order)):
            index = order[(self.cursor + k) % len(order)]
            if category is None or self.tracklets[index].category in category:
                self.cursor += k + 1
                return index
        raise ValueError(f"tracklet_order visits no tracklet of options['category']={category}")

    def index_of(self, value: Any) -> int:
        """The index of tracklet ``value``: an index or a tracklet id."""
        if isinstance(value, str):
            for i, tr in enumerate(self.tracklets):
                if tr.tracklet_id == value:
                    return i
            raise ValueError(f"unknown tracklet id {value!r}; {len(self.tracklets)} tracklets")
        if isinstance(value, bool) or not isinstance(value, int | np.integer):
            raise ValueError(
                f"options['tracklet'] must be an int index or a tracklet id; got {value!r}"
            )
        if not 0 <= int(value) < len(self.tracklets):
            raise ValueError(
                f"options['tracklet']={value} out of range 0..{len(self.tracklets) - 1}"
            )
        return int(value)

    @staticmethod
    def first_frame(tr: Tracklet, start: int | str, rng: np.random.Generator) -> int:
        """The episode's first frame in ``tr``: ``start``, or one drawn from ``rng`` for
        ``"random"`` (any frame but the last)."""
        if start == "random":
            return int(rng.integers(len(tr) - 1))
        if start > len(tr) - 2:
            raise ValueError(
                f"start_frame={start} leaves no step in tracklet {tr.tracklet_id} of {len(tr)} "
                f"frames (valid: 0..{len(tr) - 2} or 'random')"
            )
        return start

    @staticmethod
    def resample_rng(
        seed: int | None, tr: Tracklet, start: int, fallback: np.random.Generator
    ) -> np.random.Generator:
        """The episode's resampling generator: ``fallback`` (the env's ``np_random``) without
        a seed, else one seeded by ``(seed, tracklet id)`` (and the start frame when not 0)."""
        if seed is None:
            return fallback
        # the id's bytes, not the index: indices change with the category filter
        key = [seed, *tr.tracklet_id.encode()]
        if start:  # other start frames draw other samples (256 + start: never an id byte)
            key.append(256 + start)
        return np.random.default_rng(key)
