"""Serving weather to the tracking env: the ``scan_transform`` hook and a Gymnasium wrapper.

Two ways, the same result:

- ``TrackingEnv(dataset, scan_transform=WeatherTransform("fog", 3, seed=0))`` — the env option.
- ``WeatherWrapper(env, "fog", 3, seed=0)`` — wraps an already-built env (e.g. from
  ``gymnasium.make("pointtrack/Synthetic-v0")``); it installs the same transform on
  ``env.unwrapped`` and drops the env's scan cache so no clean scan is served afterwards.

Why both: the transform has to sit inside the env (it must act on whole scans before the env
crops them, and its results are cached with the env's per-tracklet corridor cache), so the env
option is the mechanism; the wrapper is the Gymnasium-idiomatic front end for code that gets an
env from a factory (the benchmark runner's ``make_env()``), and it reports ``info["weather"]``
even through other wrappers. Clean runs use neither and are untouched.
"""

from __future__ import annotations

import zlib
from collections import OrderedDict
from typing import Any

import gymnasium as gym
import numpy as np

from envs.weather.corruptions import corrupt
from envs.weather.fog import check_fog_mode
from envs.weather.levels import KINDS, UNITS, check_kind, check_level, parameter


class WeatherTransform:
    """``scan_transform(points (N, 4), tracklet_id, frame) -> (N', 4)`` float32 applying
    ``kind`` at ``level`` to the whole scan.

    The generator of each frame is ``default_rng(SeedSequence([seed, kind, level, crc32(scene),
    frame]))`` — keyed by the scene (the part of ``tracklet_id`` before ``"/"``) and the frame,
    not the tracklet, so every tracklet of a frame sees the same weather, and the same seed gives
    the same corruption in any process. Picklable; keeps the last few corrupted scans (shared by
    the tracklets of a scene).
    """

    def __init__(
        self, kind: str, level: int, seed: int = 0, cache_size: int = 4, fog_mode: str = "reference"
    ) -> None:
        self.kind = check_kind(kind)
        self.level = check_level(level)
        self.seed = int(seed)
        self.fog_mode = check_fog_mode(fog_mode)
        self.cache_size = int(cache_size)
        self._cache: OrderedDict[tuple[str, int], np.ndarray] = OrderedDict()

    @property
    def info(self) -> dict[str, Any]:
        """What the env reports as ``info["weather"]``."""
        return {
            "kind": self.kind,
            "level": self.level,
            "parameter": parameter(self.kind, self.level),
            "unit": UNITS[self.kind],
            "seed": self.seed,
            **({"fog_mode": self.fog_mode} if self.kind == "fog" else {}),
        }

    def rng(self, scene: str, frame: int) -> np.random.Generator:
        """The generator of one frame of one scene."""
        scene_key = zlib.crc32(scene.encode())
        key = [self.seed, KINDS.index(self.kind), self.level, scene_key, int(frame)]
        return np.random.default_rng(np.random.SeedSequence(key))

    def __call__(self, points: np.ndarray, tracklet_id: str, frame: int) -> np.ndarray:
        scene = str(tracklet_id).split("/", 1)[0]
        key = (scene, int(frame))
        hit = self._cache.get(key)
        if hit is not None:
            self._cache.move_to_end(key)
            return hit.copy()
        pts = np.asarray(points, dtype=np.float32)
        if pts.ndim != 2 or pts.shape[1] < 4:
            raise ValueError(
                f"WeatherTransform needs (N, 4) scans (x, y, z, intensity); got shape {pts.shape}"
            )
        xyz, inten = corrupt(
            self.kind,
            pts[:, :3],
            pts[:, 3],
            self.rng(scene, frame),
            self.level,
            fog_mode=self.fog_mode,
        )
        out = np.empty((len(xyz), pts.shape[1]), np.float32)
        out[:, :3] = xyz
        out[:, 3] = inten
        if pts.shape[1] > 4:  # extra columns (e.g. ring) cannot be carried through; zero them
            out[:, 4:] = 0.0
        if self.cache_size > 0:
            self._cache[key] = out
            if len(self._cache) > self.cache_size:
                self._cache.popitem(last=False)
            return out.copy()
        return out

    def __repr__(self) -> str:
        return (
            f"WeatherTransform({self.kind!r}, {self.level}, seed={self.seed}, "
            f"fog_mode={self.fog_mode!r})"
        )

    def _key(self) -> tuple[str, int, int, str]:
        return (self.kind, self.level, self.seed, self.fog_mode)

    def __eq__(self, other: object) -> bool:
        return isinstance(other, WeatherTransform) and self._key() == other._key()

    def __hash__(self) -> int:
        return hash(self._key())

    def __getstate__(self) -> dict[str, Any]:
        state = self.__dict__.copy()
        state["_cache"] = OrderedDict()
        return state


class WeatherWrapper(gym.Wrapper):
    """Serve ``kind`` at ``level`` (seeded by ``seed``; ``fog_mode`` as in
    :func:`envs.weather.corrupt`) to a built ``TrackingEnv``.

    Installs a :class:`WeatherTransform` as the unwrapped env's ``scan_transform`` (the env must
    have that attribute), clears its scan cache, and sets ``info["weather"]`` on reset and step.
    ``close()`` restores the previous transform. Observation and action spaces are unchanged.
    """

    def __init__(
        self, env: gym.Env, kind: str, level: int, seed: int = 0, fog_mode: str = "reference"
    ) -> None:
        super().__init__(env)
        base = env.unwrapped
        if not hasattr(base, "scan_transform"):
            raise TypeError(
                f"{type(base).__name__} has no scan_transform hook; WeatherWrapper needs a "
                "pointtrack TrackingEnv"
            )
        self.transform = WeatherTransform(kind, level, seed, fog_mode=fog_mode)
        self._previous = base.scan_transform
        self._install(self.transform)

    def _install(self, transform) -> None:
        base = self.env.unwrapped
        setter = getattr(base, "set_scan_transform", None)
        if not callable(setter):
            raise TypeError(
                f"WeatherWrapper needs an env with set_scan_transform (a TrackingEnv); "
                f"got {type(base).__name__}"
            )
        setter(transform)  # installs it and drops scans cached without it

    @property
    def weather(self) -> dict[str, Any]:
        return self.transform.info

    def reset(self, *, seed: int | None = None, options: dict[str, Any] | None = None):
        obs, info = self.env.reset(seed=seed, options=options)
        info.setdefault("weather", self.transform.info)
        return obs, info

    def step(self, action):
        obs, reward, terminated, truncated, info = self.env.step(action)
        info.setdefault("weather", self.transform.info)
        return obs, reward, terminated, truncated, info

    def close(self) -> None:
        self._install(self._previous)
        super().close()
