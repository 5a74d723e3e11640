"""The env's contract module (``envs.spec``: ``EnvOptions`` and its one validation), the one
factory (``make_tracking_env``) and the versioned ids (``-v1``; ``-v0`` an alias that warns)."""

from __future__ import annotations

import ast
import dataclasses
import math
import warnings
from pathlib import Path

import gymnasium as gym
import numpy as np
import pytest

import envs
from envs.spec import OBS_SHAPES, EnvOptions
from envs.tracking_env import TrackingEnv, make_kitti_env, make_toy_dataset, make_tracking_env


@pytest.fixture(scope="module")
def toy():
    return make_toy_dataset(num_frames=[6, 7, 5, 6], seed=4, num_clutter=500)


@pytest.fixture(scope="module")
def kitti_root(tmp_path_factory):
    ds = make_toy_dataset(num_frames=[6, 7, 5, 6], seed=2, num_clutter=2000)
    return ds.write_kitti(tmp_path_factory.mktemp("toy-kitti"), scene="0019")


def rollout(env, seed: int, steps: int = 4):
    """Observations, rewards and infos of ``steps`` steps of a fixed action sequence."""
    actions = np.random.default_rng(seed).uniform(-1.0, 1.0, (steps, 4))
    obs, info = env.reset(seed=seed)
    out = [(obs, 0.0, info["tracklet"])]
    for a in actions:
        obs, reward, term, trunc, info = env.step(a.astype(np.float32))
        out.append((obs, reward, info["iou"]))
        if term or trunc:
            break
    return out


def assert_same_rollout(a, b) -> None:
    assert len(a) == len(b)
    for (obs_a, r_a, x_a), (obs_b, r_b, x_b) in zip(a, b, strict=True):
        assert obs_a.keys() == obs_b.keys()
        for key in obs_a:
            np.testing.assert_array_equal(obs_a[key], obs_b[key])
        assert (r_a, x_a) == (r_b, x_b)


# --------------------------------------------------------------------------- EnvOptions


@pytest.mark.parametrize(
    ("field", "value", "error"),
    [
        ("sampling", "shuffle", ValueError),
        ("template_mode", "both", ValueError),
        ("reference", "gt", ValueError),
        ("render_mode", "human", ValueError),
        ("reward", 3, TypeError),
        ("reward_kwargs", ["threshold"], TypeError),
        ("scan_transform", 3, TypeError),
        ("max_action", (1.0, 1.0, 1.0), ValueError),
        ("max_action", (1.0, 1.0, -1.0, 1.0), ValueError),
        ("max_action", (1.0, 1.0, math.nan, 1.0), ValueError),
        ("max_action", "wide", ValueError),
        ("corridor_m", -1.0, ValueError),
        ("cell_m", 0.0, ValueError),
        ("cache_mb", -5.0, ValueError),
        ("episode_seed", 1.5, TypeError),
        ("episode_seed", -1, ValueError),
        ("start_frame", -1, ValueError),
        ("start_frame", "last", ValueError),
        ("max_steps", 0, ValueError),
        ("observation_keys", ("template", "search"), ValueError),
        ("observation_keys", (*OBS_SHAPES, "previous_points"), ValueError),
        ("search_enlargement", (0.0, 2.0), ValueError),
        ("search_enlargement", (1.25, -1.0), ValueError),
        ("search_enlargement", (1.25,), ValueError),
        ("search_enlargement", (1.25, math.inf), ValueError),
    ],
)
def test_bad_option_names_the_field_and_value(field, value, error):
    with pytest.raises(error) as err:
        EnvOptions(**{field: value})
    message = str(err.value)
    shown = list(value) if field == "observation_keys" else value
    assert field in message and repr(shown) in message, message
    # the env and the factory validate through it: the same error
    with pytest.raises(error, match=field):
        TrackingEnv(make_toy_dataset(num_frames=3, seed=0), **{field: value})


def test_reward_kwargs_with_a_callable_is_refused():
    with pytest.raises(ValueError, match="reward_kwargs apply to a reward name"):
        EnvOptions(reward=lambda *args: 0.0, reward_kwargs={"threshold": 0.3})


def test_unknown_option_is_a_type_error_naming_it(toy):
    with pytest.raises(TypeError, match="colour"):
        EnvOptions(colour="red")
    with pytest.raises(TypeError, match="colour"):
        TrackingEnv(toy, colour="red")
    with pytest.raises(TypeError, match="colour"):
        EnvOptions().replace(colour="red")


def test_options_are_normalised_and_frozen():
    opts = EnvOptions(
        max_action=np.array([1, 2, 3, 4], np.int64),
        search_enlargement=[np.float32(1.0), 4],
        observation_keys=list(OBS_SHAPES),
        episode_seed=np.int64(7),
    )
    assert opts.max_action == (1.0, 2.0, 3.0, 4.0)
    assert opts.search_enlargement == (1.0, 4.0)
    assert all(type(v) is float for v in (*opts.max_action, *opts.search_enlargement))
    assert opts.observation_keys == tuple(OBS_SHAPES)
    assert opts.episode_seed == 7 and type(opts.episode_seed) is int
    with pytest.raises(dataclasses.FrozenInstanceError):
        opts.template_mode = "first"
    # replace validates the new values too
    with pytest.raises(ValueError, match="template_mode"):
        opts.replace(template_mode="both")
    assert opts.replace(template_mode="first").template_mode == "first"
    assert EnvOptions().tracker_options() == {
        "template_mode": "first_and_previous",
        "search_enlargement": (1.25, 2.0),
    }
    assert set(EnvOptions().to_kwargs()) == set(EnvOptions.names())


def test_options_object_and_keywords_build_the_same_env(toy):
    opts = EnvOptions(template_mode="all", reference="previous_gt", episode_seed=3)
    by_object = TrackingEnv(toy, options=opts)
    by_keywords = TrackingEnv(toy, template_mode="all", reference="previous_gt", episode_seed=3)
    assert_same_rollout(rollout(by_object, 5), rollout(by_keywords, 5))
    # keywords override the object's fields
    env = TrackingEnv(toy, options=opts, template_mode="first")
    assert env.template_mode == "first" and env.reference == "previous_gt"


def test_spec_is_a_leaf():
    """``envs.spec`` imports nothing of the project (everyone reads it, so it may not read
    anyone back)."""
    tree = ast.parse(Path(envs.spec.__file__).read_text())
    project = ("envs", "trackers", "training")
    for node in ast.walk(tree):
        names = []
        if isinstance(node, ast.Import):
            names = [a.name for a in node.names]
        elif isinstance(node, ast.ImportFrom):
            names = [node.module or ""]
        assert not any(n.split(".")[0] in project for n in names), ast.dump(node)


def test_trackers_read_the_env_contract():
    import trackers.base
    import trackers.registry
    from envs import spec

    assert trackers.base.OBS_SHAPES is spec.OBS_SHAPES
    assert trackers.base.DEFAULT_MAX_ACTION is spec.DEFAULT_MAX_ACTION
    assert trackers.registry.default_env_options() == EnvOptions().tracker_options()
    env = TrackingEnv(make_toy_dataset(num_frames=3, seed=0))
    for key, shape in spec.OBS_SHAPES.items():
        assert env.observation_space[key].shape == shape
    np.testing.assert_array_equal(env.action_space.high, np.float32(spec.DEFAULT_MAX_ACTION))


# --------------------------------------------------------------------------- the factory


def test_factory_of_a_dataset_is_the_env(toy):
    kwargs = {"template_mode": "first_and_previous_merged", "episode_seed": 2}
    assert_same_rollout(
        rollout(make_tracking_env(toy, **kwargs), 1), rollout(TrackingEnv(toy, **kwargs), 1)
    )
    with pytest.raises(ValueError, match=r"\['preset'\] apply to a named source"):
        make_tracking_env(toy, preset="tiny")


def test_factory_of_a_kitti_root(kitti_root):
    env = make_tracking_env("kitti", root=kitti_root, setting="kitti-1", categories="Van")
    assert env.split == "test" and [t.category for t in env.tracklets] == ["Van"]
    same = make_kitti_env(root=kitti_root, setting="kitti-1", categories=["Van"])
    assert_same_rollout(rollout(env, 3), rollout(same, 3))
    with pytest.raises(ValueError, match="root"):
        make_tracking_env("kitti")
    with pytest.raises(ValueError, match="unknown source 'kitty'"):
        make_tracking_env("kitty", root=kitti_root)


# --------------------------------------------------------------------------- ids


def test_current_ids_and_their_aliases():
    envs.register_envs()
    assert envs.ENV_IDS == (
        "pointtrack/Synthetic-v1",
        "pointtrack/KITTI-v1",
        "pointtrack/NuScenes-v1",
    )
    for old, new in envs.DEPRECATED_ENV_IDS.items():
        assert old.endswith("-v0") and new.endswith("-v1")
        a, b = gym.spec(old), gym.spec(new)
        assert (a.entry_point, a.kwargs) == (b.entry_point, b.kwargs)


def test_v0_warns_once_and_builds_the_v1_env(kitti_root):
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        old = gym.make("pointtrack/KITTI-v0", root=kitti_root, setting="kitti-1")
    deprecations = [w for w in caught if issubclass(w.category, DeprecationWarning)]
    assert len(deprecations) == 1, [str(w.message) for w in caught]
    message = str(deprecations[0].message)
    assert "pointtrack/KITTI-v0" in message and "v1" in message
    with warnings.catch_warnings():
        warnings.simplefilter("error", DeprecationWarning)  # the current id: silent
        new = gym.make("pointtrack/KITTI-v1", root=kitti_root, setting="kitti-1")
    assert old.spec.id == "pointtrack/KITTI-v0" and new.spec.id == "pointtrack/KITTI-v1"
    assert type(old.unwrapped) is type(new.unwrapped) is TrackingEnv
    for seed in (0, 1):
        assert_same_rollout(rollout(old, seed, steps=6), rollout(new, seed, steps=6))
