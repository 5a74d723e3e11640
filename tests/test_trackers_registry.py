"""The tracker registry and base classes: plug-in trackers, name errors, checkpoint integrity,
the fast_eval switch, empty batches and no input mutation."""

from __future__ import annotations

import copy
import json
import shutil
from dataclasses import dataclass

import numpy as np
import pytest
import torch
from torch import nn

import trackers
from trackers import registry
from trackers.base import SLIM_BACKBONE, MatchingConfig, MatchingTracker
from trackers.layers import MLP, grouped_max
from trackers.toy import toy_batch

pytestmark = pytest.mark.usefixtures("one_torch_thread")

SMALL = {
    "backbone": {"channels": [[16, 16, 32], [32, 32, 64], [64, 64, 64]], "out_channels": 64},
    "head": {"vote_channels": 32},
}


# ------------------------------------------------- a fourth matching tracker (docs/trackers.md)
@dataclass
class XCorrConfig(MatchingConfig):
    """Cross-correlation fusion: one hidden width."""

    hidden_channels: int = 64


class XCorrFusion(nn.Module):
    """``Z_j = MLP([f_S,j; max_i f_T,i * f_S,j])``: search features modulated by the template."""

    def __init__(self, d: int, hidden: int) -> None:
        super().__init__()
        self.mlp = MLP([2 * d, hidden, hidden])

    def forward(self, t_feat: torch.Tensor, s_feat: torch.Tensor) -> torch.Tensor:
        corr = (t_feat[:, :, None, :] * s_feat[:, None, :, :]).amax(dim=1)  # (B, M_S, D)
        return self.mlp(torch.cat([s_feat, corr], dim=-1))


class XCorr(MatchingTracker):
    config_class = XCorrConfig
    default_loss_weights = {"vote": 1.0, "seed": 0.2, "objectness": 1.5, "box": 0.2}
    sizes = {"default": {}, "slim": {"backbone": SLIM_BACKBONE, "head": {"vote_channels": 64}}}

    def build_fusion(self, in_channels: int) -> tuple[nn.Module, int]:
        return XCorrFusion(in_channels, self.config.hidden_channels), self.config.hidden_channels

    def fuse(self, t_xyz, t_feat, s_xyz, s_feat, batch):
        return self.fusion(t_feat, s_feat), {}


# ------------------------------------------------------------------------------------------------


@pytest.fixture
def xcorr():
    cls = trackers.register("xcorr")(XCorr)
    yield cls
    trackers.unregister("xcorr")


def test_a_fourth_tracker_plugs_in(xcorr, tmp_path):
    from training.config import TrainConfig, tracker_config

    assert "xcorr" in trackers.available("learned") and "xcorr" in trackers.available()
    model = trackers.make("xcorr", **tracker_config("xcorr", "slim")).train()
    batch, targets = toy_batch(2, seed=0)
    optimiser = torch.optim.Adam(model.parameters(), lr=1e-3)
    before = {k: v.clone() for k, v in model.state_dict().items()}
    out = model(batch, generator=torch.Generator().manual_seed(0))
    model.loss(out, targets)["total"].mean().backward()
    optimiser.step()
    assert any(not torch.equal(before[k], v) for k, v in model.state_dict().items())
    action = model.act({k: v[0].numpy() for k, v in batch.items()})
    assert action.shape == (4,) and np.isfinite(action).all() and model.training
    path = trackers.save(model, tmp_path / "xcorr.safetensors")
    loaded = trackers.load(path, expect="xcorr")
    assert type(loaded) is XCorr and loaded.config == model.config
    np.testing.assert_array_equal(loaded.act({k: v[0].numpy() for k, v in batch.items()}), action)
    cfg = TrainConfig(tracker="xcorr", model_size="slim", out=str(tmp_path / "run")).validate()
    assert cfg.tracker == "xcorr"


def test_trackers_outside_the_registry_are_refused(tmp_path):
    from training.config import ConfigError, TrainConfig

    with pytest.raises(ConfigError, match=r"tracker='xcorr'.*p2b, bat, gpt"):
        TrainConfig(tracker="xcorr", out=str(tmp_path / "run")).validate()
    with pytest.raises(ConfigError, match=r"model_size='huge'.*default, slim"):
        TrainConfig(tracker="p2b", model_size="huge", out=str(tmp_path / "run")).validate()
    with pytest.raises(ValueError, match=r"not registered as 'xcorr'"):
        unregistered = XCorr(**SMALL)
        trackers.save(unregistered, tmp_path / "x.safetensors")


def test_registry_errors_name_the_valid_names(xcorr):
    with pytest.raises(ValueError, match=r"unknown tracker 'p3b'; registered: .*'p2b'.*'xcorr'"):
        trackers.make("p3b")
    with pytest.raises(ValueError, match=r"'xcorr' is already registered .*registered: .*'gpt'"):
        trackers.register("xcorr")(XCorr)
    with pytest.raises(ValueError, match="lower-case"):
        trackers.register("XCorr")
    with pytest.raises(TypeError, match="no act"):
        trackers.register("noact")(object)
    with pytest.raises(ValueError, match=r"no model size 'huge'; valid: \['default', 'slim'\]"):
        trackers.size_config("p2b", "huge")
    with pytest.raises(ValueError, match="valid"):
        trackers.available("nonsense")


def test_available_lists_kinds_in_order():
    assert trackers.available("learned") == ["p2b", "bat", "gpt", "m2track", "mbptrack"]
    assert trackers.available("baseline") == ["previous_box", "constant_velocity"]
    shipped = trackers.available("checkpoint")
    assert trackers.available() == [
        "p2b",
        "bat",
        "gpt",
        "m2track",
        "mbptrack",
        "previous_box",
        "constant_velocity",
        *shipped,
    ]
    matching = {f"{n}-kitti1-{w}" for n in ("p2b", "bat", "gpt") for w in "uw"}
    others = {"p2b-kitti1-drct", "m2track-kitti1-u", "m2track-kitti1-w"}
    others |= {"p2b-kitti1-u-rl", "gpt-kitti1-u-rl", "p2b-kitti2-u", "p2b-kitti2-w"}
    others |= {"p2b-kitti2-s"}  # a Table IV pilot file (docs/checkpoints.md)
    others |= {"mbptrack-kitti1-u", "mbptrack-kitti1-w", "mbptrack-kitti1-u-light"}  # mbptrack.md
    assert set(shipped) == matching | others
    for name in ("p2b", "bat", "gpt"):  # the matching trackers (m2track: tests/test_m2track.py)
        assert trackers.size_config(name, "default") == {}
        slim = trackers.make(name, **trackers.size_config(name, "slim"))
        assert slim.config.backbone.out_channels == 128


# ---------------------------------------------------------------------------- integrity


def test_manifest_lists_every_shipped_checkpoint_with_its_digest():
    manifest = json.loads(registry.MANIFEST.read_text())
    files = {p.name for p in registry.CHECKPOINT_DIR.glob("*.safetensors")}
    assert set(manifest["files"]) == files
    for name, digest in manifest["files"].items():
        assert registry._sha256(registry.CHECKPOINT_DIR / name) == digest


@pytest.fixture
def shipped_copy(tmp_path, monkeypatch):
    """A copy of the shipped checkpoint directory standing in for it."""
    directory = tmp_path / "checkpoints"
    shutil.copytree(registry.CHECKPOINT_DIR, directory)
    monkeypatch.setattr(registry, "CHECKPOINT_DIR", directory.resolve())
    return directory


def test_modified_shipped_checkpoint_is_refused(shipped_copy):
    path = shipped_copy / "p2b-kitti1-u.safetensors"
    data = bytearray(path.read_bytes())
    digest = registry._sha256(path)
    data[-100] ^= 0x01  # one bit inside the last tensor's weights: still a valid file
    path.write_bytes(bytes(data))
    bad = registry._sha256(path)
    with pytest.raises(
        ValueError,
        match=rf"p2b-kitti1-u.safetensors: SHA-256 {bad} does not "
        rf"match the manifest's {digest}",
    ):
        trackers.load("p2b-kitti1-u")
    extra = shipped_copy / "extra.safetensors"
    shutil.copy(shipped_copy / "bat-kitti1-u.safetensors", extra)
    with pytest.raises(ValueError, match="extra.safetensors is in the shipped.*not in its"):
        trackers.load("extra")
    registry.write_manifest(shipped_copy)
    assert trackers.load("extra").name == "bat"
    assert trackers.load(path).name == "p2b"  # re-recorded: the modified file is now the one


@pytest.mark.parametrize("value", [float("nan"), float("inf")])
def test_non_finite_weights_refuse_to_load_naming_the_tensor(value, tmp_path):
    from safetensors import safe_open
    from safetensors.torch import load_file, save_file

    source = registry.CHECKPOINT_DIR / "gpt-kitti1-u.safetensors"
    state = load_file(str(source))
    with safe_open(str(source), framework="pt") as f:  # the metadata as shipped
        meta = f.metadata()
    state["head.proposal.linears.1.weight"][3, 2] = value
    path = tmp_path / "broken.safetensors"
    save_file(state, str(path), metadata=meta)
    with pytest.raises(
        ValueError,
        match=r"broken.safetensors: tensor "
        r"'head.proposal.linears.1.weight' has 1 NaN or inf",
    ):
        trackers.load(path)


def test_old_checkpoint_config_keys_still_load(tmp_path):
    model = trackers.make("p2b", **SMALL)
    path = trackers.save(model, tmp_path / "old.pt")
    blob = torch.load(path, weights_only=True)
    config = json.loads(blob["config"])
    config["backbone"]["ragged_eval"] = True  # written by versions before fast_eval
    blob["config"] = json.dumps(config)
    torch.save(blob, path)
    assert trackers.load(path).config == model.config


# ------------------------------------------------------------- act, fast_eval, mutation


@pytest.mark.parametrize("name", ["p2b", "previous_box", "constant_velocity"])
def test_act_on_an_empty_batch_is_an_empty_array(name):
    tracker = trackers.make(name, **(SMALL if name == "p2b" else {}))
    obs = {
        "template": np.zeros((0, 512, 3), np.float32),
        "search": np.zeros((0, 1024, 3), np.float32),
        "size": np.zeros((0, 3), np.float32),
        "motion": np.zeros((0, 4), np.float32),
    }
    action = tracker.act(obs)
    assert action.shape == (0, 4) and action.dtype == np.float32


def test_fast_eval_is_one_switch_for_every_submodule():
    model = trackers.make("p2b", **SMALL)
    flags = [m for m in model.modules() if hasattr(m, "fast_eval") and m is not model]
    assert len(flags) > 10 and all(m.fast_eval for m in flags)
    model.fast_eval = False
    assert not model.fast_eval and not any(m.fast_eval for m in flags)
    model.fast_eval = True
    assert all(m.fast_eval for m in flags)


def test_fast_eval_leaves_training_unchanged():
    batch, targets = toy_batch(2, seed=1)
    torch.manual_seed(0)
    fast = trackers.make("bat", **SMALL).train()
    plain = copy.deepcopy(fast)
    plain.fast_eval = False
    a = fast(batch, generator=torch.Generator().manual_seed(2))
    b = plain(batch, generator=torch.Generator().manual_seed(2))
    for key in ("Z", "proposals", "scores"):
        assert torch.equal(a[key], b[key]), key


@pytest.mark.parametrize("fast", [True, False])
@pytest.mark.parametrize("training", [True, False])
@pytest.mark.parametrize("grad", [True, False])
def test_mlp_methods_do_not_modify_their_input(fast, training, grad):
    torch.manual_seed(3)
    mlp = MLP([8, 16, 16, 12]).train(training)
    mlp.fast_eval = fast
    x = torch.randn(5, 7, 8)
    w, b = mlp.linear_params(0)
    with torch.set_grad_enabled(grad):
        pre = torch.nn.functional.linear(x, w, b).detach()
        for call in (
            lambda: mlp.finish(0, pre),
            lambda: mlp.forward_from(0, pre),
            lambda: mlp.hidden_from(0, pre, 2),
            lambda: mlp(x),
        ):
            kept_pre, kept_x = pre.clone(), x.clone()
            call()
            assert torch.equal(pre, kept_pre) and torch.equal(x, kept_x)
        per_point, per_centre = torch.randn(1, 6, 16), torch.randn(1, 3, 16)
        group, point = torch.tensor([0, 0, 1, 2, 2]), torch.tensor([0, 1, 2, 3, 5])
        kept = per_point.clone(), per_centre.clone()
        grouped_max(mlp, per_point, per_centre, group, point)
        assert torch.equal(per_point, kept[0]) and torch.equal(per_centre, kept[1])


@pytest.mark.parametrize("name", ["p2b", "bat", "gpt"])
@pytest.mark.parametrize("fast", [True, False])
def test_forward_does_not_modify_the_batch(name, fast):
    model = trackers.make(name, **trackers.size_config(name, "slim")).eval()
    model.fast_eval = fast
    batch, _ = toy_batch(2, seed=4)
    kept = {k: v.clone() for k, v in batch.items()}
    with torch.no_grad():
        model(batch)
    assert all(torch.equal(batch[k], kept[k]) for k in batch)


@pytest.mark.parametrize("name", trackers.available("checkpoint"))
def test_every_shipped_checkpoint_tracks_in_the_env(name, one_torch_thread):
    """Each shipped checkpoint loads (digest checked), gets the observation keys it reads from
    the env, and acts with finite actions for a few steps."""
    from envs.tracking_env import TrackingEnv, make_toy_dataset
    from training.evaluate import observation_keys_for

    tracker = trackers.load(name)
    toy = make_toy_dataset(categories=("Car", "Pedestrian"), num_frames=(4, 4), num_clutter=500)
    env = TrackingEnv(toy, observation_keys=observation_keys_for([tracker]))
    obs, _ = env.reset(seed=0)
    for _ in range(3):
        action = np.asarray(tracker.act(obs))
        assert action.shape == (4,) and np.isfinite(action).all()
        obs, _, terminated, truncated, _ = env.step(action.astype(np.float32))
        if terminated or truncated:
            break
