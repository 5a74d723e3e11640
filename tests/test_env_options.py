"""Eval env options travel with a tracker (issue 24): ``tracker.env_options`` is set from the
training config, written by ``trackers.save``, restored by ``trackers.load``, and every eval
path builds its env with it (``pointtrack eval``, selection, the residual tracker)."""

from __future__ import annotations

import json
import warnings
from pathlib import Path

import numpy as np
import pytest
import torch
from safetensors import safe_open
from safetensors.torch import save_file

import trackers
from envs.tracking_env import TrackingEnv, make_toy_dataset
from trackers.baselines import PreviousBox
from trackers.registry import CHECKPOINT_DIR, ENV_OPTION_KEYS, default_env_options
from training.config import GPT_SEARCH_ENLARGEMENT, TrainConfig
from training.provenance import ProvenanceWarning

MERGED = "first_and_previous_merged"
V2_P2B = {"template_mode": MERGED, "search_enlargement": (1.25, 2.0)}


@pytest.fixture(scope="module", autouse=True)
def _one_thread(one_torch_thread):
    yield


@pytest.fixture(scope="module")
def toy():
    return make_toy_dataset(num_frames=4, seed=3, num_clutter=300)


def _slim(name: str = "p2b", options: dict | None = None) -> trackers.base.Tracker:
    torch.manual_seed(0)
    model = trackers.make(name, **trackers.size_config(name, "slim")).eval()
    if options is not None:
        model.env_options = dict(options)
    return model


def _metadata(path: Path) -> dict[str, str]:
    with safe_open(str(path), framework="pt", device="cpu") as f:
        return dict(f.metadata() or {})


# --------------------------------------------------------------------------- file format


@pytest.mark.parametrize("suffix", [".safetensors", ".pt"])
def test_saved_options_load_back(tmp_path, suffix):
    options = {"template_mode": MERGED, "search_enlargement": GPT_SEARCH_ENLARGEMENT}
    model = _slim("p2b", options)
    path = trackers.save(model, tmp_path / f"v2{suffix}")
    loaded = trackers.load(path)
    assert loaded.env_options == options
    assert isinstance(loaded.env_options["search_enlargement"], tuple)
    state = model.state_dict()
    assert all(torch.equal(loaded.state_dict()[k], state[k]) for k in state)
    if suffix == ".safetensors":
        assert json.loads(_metadata(path)["env_options"]) == {
            "search_enlargement": [1.0, 4.0],
            "template_mode": MERGED,
        }


def _old_format(model, path: Path) -> Path:
    """``model`` written as ``trackers.save`` wrote every file before ``env_options`` existed."""
    meta = {
        "format": "pointtrack-tracker",
        "version": "1",
        "tracker": model.name,
        "config": json.dumps(trackers.config.config_to_dict(model.config), sort_keys=True),
    }
    save_file({k: v.contiguous() for k, v in model.state_dict().items()}, str(path), meta)
    return path


def _parts(path: Path) -> tuple[dict, bytes]:
    """A safetensors file -> (its JSON header, its tensor bytes)."""
    blob = path.read_bytes()
    size = int.from_bytes(blob[:8], "little")
    return json.loads(blob[8 : 8 + size]), blob[8 + size :]


def test_no_options_write_the_file_as_before(tmp_path):
    """``{}`` (env defaults) writes no key: the header (as JSON: safetensors orders metadata
    keys at random) and the tensor bytes of the former writer's file, and the shipped
    checkpoints (manifest digests checked on load) load with ``{}``."""
    model = _slim("p2b", {})
    now = _parts(trackers.save(model, tmp_path / "now.safetensors"))
    assert now == _parts(_old_format(model, tmp_path / "before.safetensors"))
    assert set(now[0]["__metadata__"]) == {"format", "version", "tracker", "config"}
    for name in trackers.available("checkpoint"):
        assert "env_options" not in _metadata(CHECKPOINT_DIR / f"{name}.safetensors")
        assert trackers.load(name).env_options == {}


def test_old_file_without_the_key_loads_with_env_defaults(tmp_path):
    path = _old_format(_slim("gpt"), tmp_path / "old.safetensors")
    assert trackers.load(path).env_options == {}
    assert all(k in ENV_OPTION_KEYS for k in default_env_options())
    assert default_env_options() == {
        "template_mode": "first_and_previous",
        "search_enlargement": (1.25, 2.0),
    }


@pytest.mark.parametrize(
    ("raw", "message"),
    [
        ('{"template_mode": "both"}', "template_mode 'both' is not one of"),
        ('{"search_enlargement": [0, 2]}', "search_enlargement [0, 2] must be"),
        ('{"search_enlargement": [1.25]}', "search_enlargement [1.25] must be"),
        ('{"search_enlargement": [1.25, -1]}', "search_enlargement [1.25, -1] must be"),
        ('{"search_enlargement": "wide"}', "search_enlargement 'wide' must be"),
        ('{"colour": "red"}', "unknown env_options key(s) ['colour']"),
        ('["first"]', "env_options must be a JSON object"),
        ("{not json", "env_options metadata is not valid JSON"),
    ],
)
def test_bad_metadata_is_a_clear_error(tmp_path, raw, message):
    model = _slim()
    good = trackers.save(model, tmp_path / "good.safetensors")
    meta = _metadata(good) | {"env_options": raw}
    path = tmp_path / "bad.safetensors"
    save_file({k: v.contiguous() for k, v in model.state_dict().items()}, str(path), meta)
    with pytest.raises(ValueError) as err:
        trackers.load(path)
    assert str(path) in str(err.value) and message in str(err.value)


def test_bad_options_are_refused_before_writing(tmp_path):
    model = _slim("p2b", {"template_mode": "sideways"})
    with pytest.raises(ValueError, match="p2b tracker: env_options template_mode 'sideways'"):
        trackers.save(model, tmp_path / "x.safetensors")
    assert not list(tmp_path.iterdir())


# --------------------------------------------------------------------------- training configs


def test_config_env_options():
    assert TrainConfig(tracker="p2b", recipe="v1").env_options() == {}
    assert TrainConfig(tracker="gpt", recipe="v1").env_options() == {}
    assert TrainConfig(tracker="p2b", recipe="v2").env_options() == V2_P2B
    gpt = TrainConfig(tracker="gpt", recipe="v2")
    assert (
        gpt.env_options()
        == gpt.env_kwargs()
        == {
            "template_mode": MERGED,
            "search_enlargement": GPT_SEARCH_ENLARGEMENT,
        }
    )
    # one recipe item off: only GPT's search region differs from the env's defaults
    only_region = TrainConfig(tracker="gpt", recipe="v2", template_union=False)
    assert only_region.env_options()["search_enlargement"] == GPT_SEARCH_ENLARGEMENT


def _training_checkpoint(path: Path, config: dict) -> None:
    """A ``best.pt`` as pretraining writes it, trained with ``config`` (a ``TrainConfig`` dict,
    possibly without the keys an older version lacked)."""
    from training.checkpoint import CHECKPOINT_FORMAT, atomic_save
    from training.config import checkpoint_tracker_kwargs

    torch.manual_seed(1)
    model = trackers.make(config["tracker"], **checkpoint_tracker_kwargs(config))
    atomic_save(
        {
            "format": CHECKPOINT_FORMAT,
            "tracker": config["tracker"],
            "config": config,
            "model": model.state_dict(),
        },
        path,
    )


@pytest.mark.parametrize(
    ("tracker", "recipe"), [("p2b", "v2"), ("gpt", "v2"), ("p2b", "v1"), ("gpt", "legacy")]
)
def test_export_records_the_training_env_options(tmp_path, capsys, tracker, recipe):
    """``pointtrack train --export``: a v2 run's file records ``env_kwargs()``, a v1 run's (and
    a checkpoint older than the recipes, read as v1) records nothing."""
    from training.commands.train import export

    cfg = TrainConfig(
        tracker=tracker, model_size="slim", recipe="v1" if recipe == "legacy" else recipe
    )
    config = cfg.to_dict()
    if recipe == "legacy":  # written before the recipe fields existed
        for key in ("recipe", "template_union", "gpt_search_region"):
            config.pop(key)
    _training_checkpoint(tmp_path / "run" / "best.pt", config)
    out = tmp_path / "exported.safetensors"
    export(tmp_path / "run", str(out))
    loaded = trackers.load(out)
    if recipe == "v2":
        assert loaded.env_options == cfg.env_kwargs()
        assert json.loads(_metadata(out)["env_options"])["template_mode"] == MERGED
    else:
        assert loaded.env_options == {}
        assert "env_options" not in _metadata(out)
    assert "exported" in capsys.readouterr().out


# --------------------------------------------------------------------------- eval envs


def test_env_options_for_and_groups():
    from training.evaluate import env_option_groups, env_options_for

    v1, v2, base = _slim("p2b", {}), _slim("p2b", V2_P2B), PreviousBox()
    assert env_options_for([v1, base]) == {}
    assert env_options_for([v2]) == V2_P2B
    # the default values spelled out are the same option set as {}
    spelled = _slim("p2b", {"template_mode": "first_and_previous"})
    assert env_options_for([v1, spelled, base]) == {}
    with pytest.raises(ValueError) as err:
        env_options_for([v1, v2])
    assert "different options" in str(err.value) and MERGED in str(err.value)
    assert "p2b: env defaults" in str(err.value)
    named = {"a": v1, "b": v2, "c": base, "d": _slim("p2b", V2_P2B)}
    assert env_option_groups(named) == [({}, ["a", "c"]), (V2_P2B, ["b", "d"])]
    # an explicit choice wins over every tracker's option; None is no choice
    assert env_option_groups(named, {"template_mode": None}) == env_option_groups(named)
    forced = env_option_groups(named, {"template_mode": "first"})
    # (V2_P2B differs from the defaults in the template mode only: one env serves them all)
    assert [names for _, names in forced] == [["a", "b", "c", "d"]]
    assert forced[0][0] == {"template_mode": "first"}
    gpt = {"b": _slim("gpt", {"search_enlargement": GPT_SEARCH_ENLARGEMENT}), "a": v1}
    assert env_option_groups(gpt, {"template_mode": "first"}) == [
        ({"search_enlargement": GPT_SEARCH_ENLARGEMENT, "template_mode": "first"}, ["b"]),
        ({"template_mode": "first"}, ["a"]),
    ]


def test_evaluate_warns_when_the_env_contradicts_the_tracker(toy):
    from training.evaluate import evaluate

    v2 = _slim("p2b", V2_P2B)
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # the matching env, and a baseline anywhere: silent
        report = evaluate(v2, TrackingEnv(toy, template_mode=MERGED), tracklets=[0])
        evaluate(PreviousBox(), TrackingEnv(toy, template_mode="first"), tracklets=[0])
    assert report["env"]["template_mode"] == MERGED
    assert report["env"]["search_enlargement"] == [1.25, 2.0]
    with pytest.warns(UserWarning, match=r"'p2b' was trained with template_mode='first_and_pre"):
        evaluate(v2, TrackingEnv(toy), tracklets=[0])
    gpt = _slim("gpt", {"search_enlargement": GPT_SEARCH_ENLARGEMENT})
    with pytest.warns(UserWarning, match=r"search_enlargement=\(1.0, 4.0\) but the env uses"):
        evaluate(gpt, TrackingEnv(toy), tracklets=[0])


def _eval(tmp_path: Path, *extra: str) -> dict:
    from training.cli import main

    out = tmp_path / "eval"
    argv = ["eval", "--preset", "tiny", "--max-tracklets", "1", "--no-progress"]
    assert main([*argv, "--out", str(out), *extra]) == 0
    return json.loads((out / "report.json").read_text())


def test_cli_eval_builds_each_trackers_env(tmp_path, monkeypatch):
    """``pointtrack eval --tracker A B``: one env per distinct option set, in --tracker order."""
    import training.commands.eval as eval_cmd

    v2 = trackers.save(_slim("p2b", V2_P2B), tmp_path / "v2.safetensors")
    built = []
    real = eval_cmd.build_env

    def spy(args, **overrides):
        env = real(args, **overrides)
        built.append(env.template_mode)
        return env

    monkeypatch.setattr(eval_cmd, "build_env", spy)
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # no tracker runs on options it was not trained with
        # a file saved here records no provenance: that note is not what this test is about
        warnings.filterwarnings("ignore", category=ProvenanceWarning)
        report = _eval(tmp_path, "--tracker", "previous_box", str(v2), "constant_velocity")
    assert built == ["first_and_previous", MERGED]
    assert list(report) == ["previous_box", str(v2), "constant_velocity"]
    assert report[str(v2)]["env"]["template_mode"] == MERGED
    assert report["previous_box"]["env"]["template_mode"] == "first_and_previous"
    assert report["constant_velocity"]["env"]["template_mode"] == "first_and_previous"


def test_cli_explicit_template_mode_wins_with_a_warning(tmp_path):
    v2 = trackers.save(_slim("p2b", V2_P2B), tmp_path / "v2.safetensors")
    with pytest.warns(UserWarning, match="trained with template_mode='first_and_previous_merged'"):
        report = _eval(tmp_path, "--tracker", str(v2), "--template-mode", "first_and_previous")
    assert report[str(v2)]["env"]["template_mode"] == "first_and_previous"


def test_selection_scores_a_candidate_with_its_options(tmp_path, monkeypatch, toy):
    """``pointtrack select``: each candidate's env has its options; the cache key names them
    (so a report scored before the options travelled is not reused)."""
    import envs.tracking_env as tracking_env
    from training.selection import SelectionConfig, ValPart, score_candidates

    made = []

    def toy_env(**kwargs):
        made.append(kwargs.get("template_mode", "first_and_previous"))
        return TrackingEnv(toy, template_mode=made[-1])

    monkeypatch.setattr(tracking_env, "make_synthetic_env", toy_env)
    v2 = str(trackers.save(_slim("p2b", V2_P2B), tmp_path / "v2.safetensors"))
    config = SelectionConfig(parts=(ValPart(0, "val"),))
    cache = tmp_path / "cache"
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        rows = score_candidates([v2, "previous_box"], config, cache_dir=cache)
    assert made == [MERGED, "first_and_previous"] and len(rows) == 2
    keys = [json.loads(p.read_text())["selection_key"] for p in sorted(cache.rglob("*.json"))]
    by_candidate = {k["candidate"]: k for k in keys}
    assert by_candidate[v2]["env_options"] == {
        "search_enlargement": [1.25, 2.0],
        "template_mode": MERGED,
    }
    assert "env_options" not in by_candidate["previous_box"]  # earlier caches still match


def test_residual_tracker_keeps_its_base_options(tmp_path):
    from training.rl.wrappers import ResidualTracker, residual_policy

    base = _slim("p2b", V2_P2B)
    tuned = ResidualTracker(base, residual_policy(-2.0), name="p2b-residual")
    assert tuned.env_options == V2_P2B
    path = tuned.save(tmp_path / "residual.safetensors")
    again = ResidualTracker.load(path)
    assert again.env_options == again.base.env_options == V2_P2B
    plain = ResidualTracker(_slim(), residual_policy(-2.0)).save(tmp_path / "plain.safetensors")
    assert "env_options" not in _metadata(plain)
    assert ResidualTracker.load(plain).env_options == {}
    assert np.allclose(again.scale, tuned.scale)


def test_finetune_envs_use_the_base_trackers_options():
    """``pointtrack finetune`` trains (and val-checks) on the base tracker's options."""
    from training.rl.config import FinetuneConfig
    from training.rl.run import train_env_factory

    cfg = FinetuneConfig(preset="tiny", clip_length=4)
    env = train_env_factory(cfg, V2_P2B)()
    assert env.template_mode == MERGED and env.search_enlargement == (1.25, 2.0)
    gpt = train_env_factory(cfg, {"search_enlargement": GPT_SEARCH_ENLARGEMENT})()
    assert gpt.template_mode == "first_and_previous"
    assert gpt.search_enlargement == GPT_SEARCH_ENLARGEMENT
    assert train_env_factory(cfg)().template_mode == "first_and_previous"


def test_cli_weather_runs_each_tracker_on_its_options(tmp_path, monkeypatch):
    """``pointtrack eval --weather``: the clean env of each tracker (and so every corrupted
    clone of it) has the tracker's options."""
    import training.commands.eval as eval_cmd
    import training.robustness as robustness

    v2 = str(trackers.save(_slim("p2b", V2_P2B), tmp_path / "v2.safetensors"))
    seen = {}

    def spy(tracker, make_env, *args, name, **kwargs):
        seen[name] = make_env().template_mode
        return {}

    monkeypatch.setattr(robustness, "run_weather_eval", spy)
    monkeypatch.setattr(
        eval_cmd,
        "load_trackers",
        lambda args, plan: {"previous_box": PreviousBox(), v2: trackers.load(v2)},
    )
    from training.cli import main

    argv = ["eval", "--preset", "tiny", "--weather", "rain", "--no-progress"]
    assert main([*argv, "--tracker", "previous_box", v2]) == 0
    assert seen == {"previous_box": "first_and_previous", v2: MERGED}


def test_cli_demo_runs_a_tracker_on_its_options(tmp_path):
    from training.cli import main

    v2 = str(trackers.save(_slim("p2b", V2_P2B), tmp_path / "v2.safetensors"))
    out = tmp_path / "demo"
    argv = ["demo", "--preset", "tiny", "--out", str(out), "--no-progress", "--num-envs", "2"]
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        assert main([*argv, "--max-tracklets", "1", "--tracker", "previous_box", v2]) == 0
    report = json.loads((out / "report.json").read_text())
    assert report[v2]["env"]["template_mode"] == MERGED
    assert report[v2]["env"]["num_envs"] == 2
    assert report["previous_box"]["env"]["template_mode"] == "first_and_previous"


def test_numpy_numbers_are_valid_options():
    from trackers.registry import check_env_options

    got = check_env_options({"search_enlargement": [np.float32(1.0), np.float64(4.0)]}, "x")
    assert got == {"search_enlargement": (1.0, 4.0)}
    assert all(type(v) is float for v in got["search_enlargement"])
    with pytest.raises(ValueError, match="x: env_options search_enlargement"):
        check_env_options({"search_enlargement": [True, 2.0]}, "x")
