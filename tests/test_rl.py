"""training.rl.TrackerPolicy: the tracker as an SB3 PPO policy (issue 22 item 1)."""

from __future__ import annotations

import copy
from pathlib import Path

import gymnasium as gym
import numpy as np
import pytest
import torch
from stable_baselines3 import PPO

import trackers
from envs.tracking_env import TrackingEnv, make_toy_dataset
from trackers.base import prepare_observation
from trackers.decision import InferenceConfig, keeps_box
from training.rl import GroupPPO, ScaledAdam, SelfCriticalReward, TrackerPolicy
from training.rl.features import PerState

pytestmark = pytest.mark.usefixtures("one_torch_thread")
ONE = np.ones(4, dtype=np.float32)


@pytest.fixture(scope="module")
def data():
    return make_toy_dataset(num_frames=8)


def rescaled(data, **kwargs) -> gym.Env:
    return gym.wrappers.RescaleAction(TrackingEnv(data, sampling="random", **kwargs), -ONE, ONE)


def observations(tracker, data, n: int = 6, **env_kwargs) -> list[dict[str, np.ndarray]]:
    """Observations along the tracker's own closed loop over two tracklets."""
    env, out = TrackingEnv(data, **env_kwargs), []
    for i in range(2):
        obs, _ = env.reset(seed=0, options={"tracklet": i})
        for _ in range(n // 2):
            out.append(obs)
            obs, *_ = env.step(tracker.act(obs))
    return out


def stack(obs: list[dict[str, np.ndarray]]) -> dict[str, np.ndarray]:
    return {k: np.stack([o[k] for o in obs]) for k in obs[0]}


def assert_predict_equals_act(model: PPO, base, obs: list[dict[str, np.ndarray]]) -> None:
    """Deterministic predictions, one at a time and batched, equal ``act / max_action``."""
    for o in obs:
        action, _ = model.predict(o, deterministic=True)
        np.testing.assert_allclose(action, base.act(o) / base.max_action, atol=1e-5)
    batched, _ = model.predict(stack(obs), deterministic=True)
    np.testing.assert_allclose(batched, base.act(stack(obs)) / base.max_action, atol=1e-5)


def ppo(data, tracker, env=None, **kwargs) -> PPO:
    """PPO on ``env`` (default: one rescaled env of ``data``)."""
    policy_kwargs = {"tracker": tracker, **kwargs.pop("policy_kwargs", {})}
    defaults = {"n_steps": 16, "batch_size": 16, "n_epochs": 1, "seed": 0, "device": "cpu"}
    env = rescaled(data) if env is None else env
    return PPO(TrackerPolicy, env, policy_kwargs=policy_kwargs, **{**defaults, **kwargs})


@pytest.mark.parametrize("name", ["p2b-kitti1-u", "bat-kitti1-u", "gpt-kitti1-u"])
def test_predict_equals_rescaled_tracker_act_at_init(data, name):
    base = trackers.load(name)
    model = ppo(data, name)
    obs = observations(base, data)
    assert_predict_equals_act(model, base, obs)


def test_predict_keeps_the_box_where_the_tracker_holds_it(data):
    base = trackers.load("bat-kitti1-u")
    base.inference = InferenceConfig(hold_chamfer_m=100.0)  # enough points: still
    model = ppo(data, base)
    obs = observations(base, data)
    assert all((base.act(o) == 0).all() for o in obs)
    assert_predict_equals_act(model, base, obs)


def test_predict_executes_the_re_ranked_box(data):
    base = trackers.load("bat-kitti1-u")
    base.inference = InferenceConfig(rerank_top_k=8)
    model = ppo(data, base)
    obs = observations(base, data)
    # the shipped file re-ranks (session 25)
    plain = trackers.load("bat-kitti1-u", inference=InferenceConfig())
    # the re-ranking changes some of these actions, and predict follows it
    assert any(not np.array_equal(base.act(o), plain.act(o)) for o in obs)
    assert_predict_equals_act(model, base, obs)


def test_batched_and_single_predictions_agree(data):
    base = trackers.load("p2b-kitti1-u")
    model = ppo(data, base)
    obs = observations(base, data)
    single = np.stack([model.predict(o, deterministic=True)[0] for o in obs])
    batched, _ = model.predict(stack(obs), deterministic=True)
    np.testing.assert_allclose(batched, single, atol=1e-5)


def test_building_the_policy_changes_no_weight_and_copies_the_tracker(data):
    base = trackers.load("p2b-kitti1-u")
    before = {k: v.clone() for k, v in base.state_dict().items()}
    policy = ppo(data, base).policy
    assert policy.tracker is not base
    for key, value in policy.tracker.state_dict().items():
        assert torch.equal(value, before[key]), key
        assert torch.equal(base.state_dict()[key], before[key]), key
    # SB3 flips the policy to training mode for updates; the tracker must stay in eval mode
    policy.set_training_mode(True)
    assert policy.training and not any(m.training for m in policy.tracker.modules())
    # the frozen stages' no_grad forward follows a copy (it must not call the original)
    clone = copy.deepcopy(policy.tracker)
    assert clone.backbone.forward.__self__ is clone.backbone
    assert torch.allclose(policy.log_std, torch.full((4,), -2.0))


def test_log_prob_does_not_depend_on_training_mode(data):
    base = trackers.load("p2b-kitti1-u")
    policy = ppo(data, base).policy
    obs = {k: torch.as_tensor(v) for k, v in stack(observations(base, data)).items()}
    with torch.no_grad():
        actions, _, rollout_logp = policy(obs)  # as collect_rollouts does
    policy.set_training_mode(True)
    _, logp_train, _ = policy.evaluate_actions(obs, actions)  # as PPO.train does (grad on)
    policy.set_training_mode(False)
    _, logp_eval, _ = policy.evaluate_actions(obs, actions)
    torch.testing.assert_close(logp_train, logp_eval)
    torch.testing.assert_close(logp_train.detach(), rollout_logp, atol=1e-3, rtol=0)


def test_first_update_sees_ratio_one_and_changes_only_trained_parts(data):
    base = trackers.load("p2b-kitti1-u")
    model = ppo(data, base, learning_rate=1e-3, policy_kwargs={"tracker_lr_scale": 1.0})
    policy = model.policy
    before = {k: v.clone() for k, v in policy.tracker.state_dict().items()}
    value_before = [p.clone() for p in policy.value_head.parameters()]
    model.learn(16)  # one rollout, one epoch of one minibatch: approx_kl is the pre-update KL
    assert abs(model.logger.name_to_value["train/approx_kl"]) < 1e-5
    after = policy.tracker.state_dict()
    changed = {k for k in before if not torch.equal(before[k], after[k])}
    assert changed and all(k.startswith("head.") for k in changed)
    assert not any(k.startswith(("backbone.", "fusion.")) for k in changed)
    assert any(
        not torch.equal(a, b)
        for a, b in zip(value_before, policy.value_head.parameters(), strict=True)
    )


def test_train_parts_select_the_tracker_modules(data):
    base = trackers.load("p2b-kitti1-u")
    ids = {
        name: {id(p) for p in getattr(base, name).parameters()}
        for name in ("backbone", "fusion", "head")
    }
    for parts, expected in (
        ("head", {"head"}),
        ("fusion+head", {"fusion", "head"}),
        ("all", {"backbone", "fusion", "head"}),
    ):
        policy = ppo(data, base, policy_kwargs={"train_parts": parts}).policy
        got = {id(p) for p in policy.trainable_tracker_parameters}
        own = {name: {id(p) for p in getattr(policy.tracker, name).parameters()} for name in ids}
        assert got == set().union(*(own[n] for n in expected))
        assert all(p.requires_grad == (id(p) in got) for p in policy.tracker.parameters())


def test_frozen_actor_trains_the_critic_only(data):
    base = trackers.load("p2b-kitti1-u")
    model = ppo(data, base, learning_rate=1e-3, policy_kwargs={"tracker_lr_scale": 1.0})
    policy = model.policy
    policy.freeze_actor(True)
    tracker_before = {k: v.clone() for k, v in policy.tracker.state_dict().items()}
    std_before = policy.log_std.detach().clone()
    value_before = [p.clone() for p in policy.value_head.parameters()]
    model.learn(16)
    assert all(torch.equal(v, tracker_before[k]) for k, v in policy.tracker.state_dict().items())
    assert torch.equal(policy.log_std.detach(), std_before)
    assert any(
        not torch.equal(a, b)
        for a, b in zip(value_before, policy.value_head.parameters(), strict=True)
    )


def test_scaled_adam_steps_each_group_with_its_scaled_rate():
    a, b = torch.nn.Parameter(torch.zeros(3)), torch.nn.Parameter(torch.zeros(3))
    opt = ScaledAdam([{"params": [a], "lr_scale": 1.0}, {"params": [b], "lr_scale": 0.01}], lr=0.1)
    a.grad, b.grad = torch.ones(3), torch.ones(3)
    opt.step()
    # Adam's first step moves by lr * g / (|g| + eps) = lr for unit gradients
    torch.testing.assert_close(a.detach(), torch.full((3,), -0.1))
    torch.testing.assert_close(b.detach(), torch.full((3,), -0.001))
    assert [g["lr"] for g in opt.param_groups] == [0.1, 0.1]  # SB3's rate is left as set


def test_a2c_drives_the_same_policy_with_its_rmsprop(data):
    from stable_baselines3 import A2C

    base = trackers.load("p2b-kitti1-u")
    model = A2C(
        TrackerPolicy,
        rescaled(data),
        n_steps=8,
        seed=0,
        device="cpu",
        policy_kwargs={"tracker": base, "tracker_lr_scale": 1.0},
    )
    opt = model.policy.optimizer
    assert isinstance(opt, torch.optim.RMSprop) and opt.param_groups[1]["lr_scale"] == 1.0
    before = {k: v.clone() for k, v in model.policy.tracker.state_dict().items()}
    model.learn(8)
    after = model.policy.tracker.state_dict()
    assert any(not torch.equal(before[k], after[k]) for k in before if k.startswith("head."))
    assert all(torch.equal(before[k], after[k]) for k in before if not k.startswith("head."))


def test_soft_mode_mean_is_the_score_weighted_proposal_mean(data):
    base = trackers.load("p2b-kitti1-u")
    policy = ppo(data, base, policy_kwargs={"action_mode": "soft", "temperature": 0.5}).policy
    obs = stack(observations(base, data))
    with torch.no_grad():
        out = base({k: torch.as_tensor(v) for k, v in obs.items()})
        w = torch.softmax(out["scores"] / 0.5, dim=1).numpy()
        expected = (w[..., None] * out["proposals"].numpy()).sum(1)
        mean, _ = policy.mean_and_value({k: torch.as_tensor(v) for k, v in obs.items()})
        held = keeps_box(base, prepare_observation(obs)[0], base.inference).numpy()  # it holds
    expected = np.where(held[:, None], 0.0, expected)
    expected = np.clip(expected, -base.max_action, base.max_action) / base.max_action
    np.testing.assert_allclose(mean.numpy(), expected, atol=1e-5)


def test_separate_critic_and_value_shapes(data):
    base = trackers.load("p2b-kitti1-u")
    obs = {k: torch.as_tensor(v) for k, v in stack(observations(base, data)).items()}
    for critic in ("fused", "separate"):
        policy = ppo(data, base, policy_kwargs={"critic": critic}).policy
        with torch.no_grad():
            assert policy.predict_values(obs).shape == (len(obs["search"]), 1)


def test_bad_inputs_give_clear_errors(data):
    with pytest.raises(TypeError, match="no parameters to train"):
        ppo(data, "previous_box")
    with pytest.raises(ValueError, match=r"train_parts must be one of \['head', 'fusion\+head'"):
        ppo(data, "p2b-kitti1-u", policy_kwargs={"train_parts": "backbone"})
    with pytest.raises(ValueError, match="action_mode must be one of"):
        ppo(data, "p2b-kitti1-u", policy_kwargs={"action_mode": "mean"})
    with pytest.raises(ValueError, match="RescaleAction"):
        PPO(TrackerPolicy, TrackingEnv(data), policy_kwargs={"tracker": "p2b-kitti1-u"})


def test_nan_weights_raise_instead_of_acting(data):
    base = trackers.load("p2b-kitti1-u")
    policy = ppo(data, base).policy
    with torch.no_grad():
        next(policy.tracker.head.proposal.parameters()).fill_(float("nan"))
    obs = {k: torch.as_tensor(v) for k, v in stack(observations(base, data)).items()}
    with pytest.raises(FloatingPointError, match="NaN"), torch.no_grad():
        policy(obs)


def self_critical_ppo(data, tracker, num_envs: int = 2) -> tuple[PPO, SelfCriticalReward]:
    from stable_baselines3.common.vec_env import DummyVecEnv

    venv = SelfCriticalReward(DummyVecEnv([lambda: rescaled(data)] * num_envs))
    model = ppo(data, tracker, venv, n_steps=8, gamma=0.0, policy_kwargs={"log_std_init": -1.0})
    venv.policy = model.policy
    return model, venv


def test_self_critical_reward_subtracts_the_mean_actions_own_reward(data):
    """Each reward is the sampled action's minus what the *mean* action would have earned at
    the same state, the latter checked on a pickled copy of each sub-env stepped with it."""
    import pickle

    base = trackers.load("p2b-kitti1-u")
    model, venv = self_critical_ppo(data, base)
    policy, inner = model.policy, venv.venv
    obs = venv.reset()
    nonzero = 0
    for _ in range(6):
        with torch.no_grad():
            actions, _, _ = policy({k: torch.as_tensor(v) for k, v in obs.items()})
        mean = policy.last_mean.numpy() * base.max_action
        twins = [pickle.loads(pickle.dumps(e.unwrapped)) for e in inner.envs]
        expected_baseline = [twin.step(m)[1] for twin, m in zip(twins, mean, strict=True)]
        obs, rewards, _, infos = venv.step(actions.numpy())
        for i, info in enumerate(infos):
            assert info["baseline_reward"] == pytest.approx(expected_baseline[i], abs=1e-12)
            assert rewards[i] == pytest.approx(info["iou"] - expected_baseline[i], abs=1e-6)
            nonzero += abs(rewards[i]) > 1e-6
    assert nonzero  # the noise (std 0.37) moves the boxes: the advantages are not all 0
    # the mean action itself has no advantage
    with torch.no_grad():
        policy({k: torch.as_tensor(v) for k, v in obs.items()})
    _, rewards, _, _ = venv.step(policy.last_mean.numpy())
    np.testing.assert_allclose(rewards, 0.0, atol=1e-6)
    with pytest.raises(RuntimeError, match="policy's forward"):
        venv.step(np.zeros((2, 4), np.float32))  # no forward since the last step
    model.learn(16)  # PPO drives it end to end
    assert np.isfinite(model.logger.name_to_value["train/loss"])


def test_the_docs_example_runs(tmp_path, monkeypatch):
    """docs/rl.md's SB3 example, on the tiny world with fewer steps."""
    text = (Path(__file__).resolve().parents[1] / "docs" / "rl.md").read_text()
    code = text.split("```python\n", 1)[1].split("```", 1)[0]
    assert len(code.strip().splitlines()) <= 16  # the "at most 15 lines" (+ a blank)
    for old, new in (
        ('preset="small"', 'preset="tiny"'),
        ("n_steps=128", "n_steps=8"),
        ("batch_size=64", "batch_size=8"),
        ("learn(2048)", "learn(8)"),
    ):
        assert old in code
        code = code.replace(old, new)
    monkeypatch.chdir(tmp_path)
    exec(compile(code, "docs/rl.md", "exec"), {})
    tuned = trackers.load(tmp_path / "p2b-rl.safetensors")
    assert tuned.name == "p2b"


# ---------------------------------------------------------------- M2-Track as the policy

M2_KEYS = ("template", "search", "size", "motion", "previous_search")


def m2_ppo(data, **kwargs) -> PPO:
    env = TrackingEnv(data, sampling="random", observation_keys=M2_KEYS)
    defaults = {"n_steps": 16, "batch_size": 16, "n_epochs": 1, "seed": 0, "device": "cpu"}
    policy_kwargs = {"tracker": "m2track-kitti1-u", **kwargs.pop("policy_kwargs", {})}
    return PPO(
        TrackerPolicy,
        gym.wrappers.RescaleAction(env, -ONE, ONE),
        policy_kwargs=policy_kwargs,
        **{**defaults, **kwargs},
    )


def m2_observations(tracker, data) -> list[dict[str, np.ndarray]]:
    return observations(tracker, data, observation_keys=M2_KEYS)


def test_m2track_policy_starts_as_the_tracker(data):
    """M2-Track serves as the actor too: its final box is the mean, before any update equal to
    the rescaled ``act`` (single and batched), and ``"head"`` trains its four heads."""
    base = trackers.load("m2track-kitti1-u")
    model = m2_ppo(data)
    obs = m2_observations(base, data)
    assert_predict_equals_act(model, base, obs)
    policy = model.policy
    heads = ("motion_head", "state_head", "prev_head", "box_head")
    expected = {id(p) for h in heads for p in getattr(policy.tracker, h).parameters()}
    assert {id(p) for p in policy.trainable_tracker_parameters} == expected


def test_m2track_gradient_reaches_heads_through_the_frozen_second_stage(data):
    """The second PointNet (frozen under ``"head"``) sits between trained heads: it keeps its
    graph, so the first-stage box head gets the gradient that flows through it. The frozen
    stages before the first trained one run without a graph."""
    policy = m2_ppo(data).policy
    obs = {k: torch.as_tensor(v) for k, v in stack(m2_observations(policy.tracker, data)).items()}
    assert policy.tracker.seg.forward.__func__.__name__ == "frozen_forward"
    assert policy.tracker.motion_net.forward.__func__.__name__ == "frozen_forward"
    assert "forward" not in vars(policy.tracker.box_net)  # its class's forward, with a graph
    mean, value = policy.mean_and_value(obs)
    mean.sum().backward()
    for head in ("prev_head", "box_head"):
        grads = [p.grad for p in getattr(policy.tracker, head).parameters()]
        assert any(g is not None and g.abs().sum() > 0 for g in grads), head
    assert value.shape == (len(mean),)
    separate = m2_ppo(data, policy_kwargs={"critic": "separate"}).policy
    mean_s, value_s = separate.mean_and_value(obs)
    torch.testing.assert_close(mean_s, mean)
    assert value_s.shape == (len(mean),) and torch.isfinite(value_s).all()


def test_m2track_policy_refuses_an_env_without_previous_search_and_fusion_parts(data):
    with pytest.raises(ValueError, match=r"reads the observation key\(s\) \['previous_search'\]"):
        ppo(data, "m2track-kitti1-u")
    with pytest.raises(ValueError, match=r"m2track.*no such part.*\['head', 'all'\]"):
        m2_ppo(data, policy_kwargs={"train_parts": "fusion+head"})


# ---------------------------------------------------------------- GroupPPO


def group_ppo(data, tracker, num_envs: int = 2, env_kwargs=None, **kwargs) -> GroupPPO:
    from stable_baselines3.common.vec_env import DummyVecEnv

    venv = DummyVecEnv([lambda: rescaled(data, **(env_kwargs or {}))] * num_envs)
    defaults = {"n_steps": 4, "batch_size": 8, "n_epochs": 1, "seed": 0, "device": "cpu"}
    policy_kwargs = {"tracker": tracker, "log_std_init": -1.0, **kwargs.pop("policy_kwargs", {})}
    return GroupPPO(TrackerPolicy, venv, policy_kwargs=policy_kwargs, **{**defaults, **kwargs})


def collect(model: GroupPPO, callback=None) -> None:
    """One rollout through SB3's own entry points (what ``learn`` does before ``train``);
    ``callback``: that of an earlier ``_setup_learn`` (which reset the sub-envs)."""
    if callback is None:
        _, callback = model._setup_learn(model.n_steps * model.n_envs, callback=None)
    callback.on_training_start(locals(), globals())
    assert model.collect_rollouts(model.env, callback, model.rollout_buffer, model.n_steps)


def test_group_ppo_scores_every_sample_and_steps_with_the_mean(data):
    """Each of the K samples' rewards is what the env would give for it at that state, and the
    env moves with the policy's mean action: both checked on pickled twins of the sub-envs,
    stepped alongside with the policy's deterministic action."""
    import pickle

    base = trackers.load("p2b-kitti1-u")
    model = group_ppo(data, base, group_size=5)
    _, callback = model._setup_learn(8, callback=None)  # resets (and seeds) the sub-envs
    wrappers = model.env.envs  # RescaleAction: its .action() maps [-1, 1] to env units
    twins = [pickle.loads(pickle.dumps(e.unwrapped)) for e in wrappers]
    obs = {k: v.copy() for k, v in model._last_obs.items()}
    collect(model, callback)
    buf = model.rollout_buffer
    assert buf.actions.shape == (8, 5, 4) and buf.rewards.shape == (8, 5) == buf.log_probs.shape
    np.testing.assert_allclose(buf.advantages.sum(axis=1), 0.0, atol=1e-12)
    assert np.ptp(buf.actions, axis=1).min() > 0  # distinct samples per state
    for t in range(4):
        rows = slice(2 * t, 2 * t + 2)  # each step's sub-envs, stacked
        for key, value in obs.items():
            np.testing.assert_array_equal(buf.observations[key][rows], value)
        for i, twin in enumerate(twins):
            for k, action in enumerate(buf.actions[rows][i]):
                a = np.clip(action, -1, 1) * base.max_action
                assert buf.rewards[2 * t + i, k] == twin.reward_for_action(a)
        mean, _ = model.policy.predict(obs, deterministic=True)  # the weights have not moved
        steps = [twin.step(w.action(m)) for twin, w, m in zip(twins, wrappers, mean, strict=True)]
        obs = stack([step[0] for step in steps])
    # stored log-probabilities are the sampling policy's: the first update sees ratio 1
    model.train()
    assert model.logger.name_to_value["train/approx_kl"] == pytest.approx(0.0, abs=1e-6)


def test_group_ppo_moves_the_mean_toward_the_better_samples(data):
    """With rewards that grow with a sample's dx, one update raises the mean dx on every state
    of the rollout (the sign of the group-relative gradient; the soft mean, because a best
    proposal can switch under any step)."""
    # held states keep mean 0: every state must be able to move
    base = trackers.load("p2b-kitti1-u", inference={"hold_chamfer_m": 0.0})
    model = group_ppo(
        data, base, group_size=8, learning_rate=1e-3,
        policy_kwargs={"tracker_lr_scale": 1.0, "action_mode": "soft"},
    )  # fmt: skip
    collect(model)
    buf = model.rollout_buffer
    buf.rewards = buf.actions[..., 0].astype(np.float64)
    buf.advantages = buf.rewards - buf.rewards.mean(axis=1, keepdims=True)
    obs = {k: torch.as_tensor(v) for k, v in buf.observations.items()}
    with torch.no_grad():
        before = model.policy.mean_and_value(obs, value=False)[0]
    model.train()
    with torch.no_grad():
        after = model.policy.mean_and_value(obs, value=False)[0]
    assert (after[:, 0] > before[:, 0]).all()


def test_group_ppo_bad_inputs(data):
    with pytest.raises(ValueError, match="group_size must be >= 2"):
        group_ppo(data, "p2b-kitti1-u", group_size=1)
    with pytest.raises(TypeError, match="GroupPPO needs TrackerPolicy"):
        GroupPPO("MultiInputPolicy", rescaled(data), n_steps=4, batch_size=4)


@pytest.mark.parametrize("train_parts", ["head", "fusion+head"])
def test_group_ppo_cached_features_update_equals_uncached(data, train_parts):
    """The update epochs reuse the rollout's frozen-stage outputs (issue 41 item 4): the same
    means and log-probabilities as running those stages again (to 1e-6), after a real update
    moved the trained parts; and the cached outputs are what the forward used (another state's
    features give another mean)."""
    base = trackers.load("gpt-kitti1-u")
    runs = {}
    for cache in (True, False):
        model = group_ppo(
            data, base, group_size=4, learning_rate=1e-3, cache_features=cache,
            n_epochs=2, batch_size=4,
            policy_kwargs={"tracker_lr_scale": 1.0, "train_parts": train_parts},
        )  # fmt: skip
        collect(model)
        assert (model.rollout_buffer.features is not None) == cache
        model.train()
        runs[cache] = model
    cached, plain = runs[True], runs[False]
    buf = cached.rollout_buffer
    # the decision step's scenes are kept too, one per state, with the still-target test
    kept = [call for call in buf.features.calls if isinstance(call, PerState)]
    assert len(kept) == 1 and len(kept[0]) == buf.size
    base_state = base.state_dict()
    assert any(  # the update trained something: the head below is not the base's
        not torch.equal(v, base_state[k]) for k, v in cached.policy.tracker.state_dict().items()
    )
    for p, q in zip(
        cached.policy.trainable_tracker_parameters,
        plain.policy.trainable_tracker_parameters,
        strict=True,
    ):
        torch.testing.assert_close(p, q, atol=1e-6, rtol=0)
    obs = {k: torch.as_tensor(v) for k, v in buf.observations.items()}
    rows = torch.arange(buf.size)
    with torch.no_grad():
        replayed = cached.policy.mean_and_value(obs, False, buf.features.select(rows))[0]
        fresh = cached.policy.mean_and_value(obs, False)[0]
        shifted = cached.policy.mean_and_value(obs, False, buf.features.select(rows.roll(1)))[0]
    torch.testing.assert_close(replayed, fresh, atol=1e-6, rtol=0)
    assert not torch.allclose(shifted, fresh, atol=1e-3)


def test_mbptrack_policy_starts_as_the_tracker_and_its_cached_update_equals_uncached(data):
    """MBPTrack as the actor (issue 46 item 5): the env serves its memory keys, before any
    update the deterministic prediction is the rescaled ``act``, ``"head"`` trains BPLocNet,
    and a group PPO update on the rollout's cached backbone and transformer outputs equals the
    uncached one (to 1e-6)."""
    from envs.spec import MEMORY_KEYS, OBSERVATION_KEYS

    torch.manual_seed(0)
    base = trackers.make("mbptrack", **trackers.size_config("mbptrack", "slim")).eval()
    # the untrained tracker loses the toy targets (IoU 0 everywhere): a dense reward
    env_kwargs = {
        "observation_keys": (*OBSERVATION_KEYS, *MEMORY_KEYS),
        "reward": "neg_center_error",
    }
    model = ppo(data, base, env=rescaled(data, **env_kwargs))
    assert_predict_equals_act(model, base, observations(base, data, **env_kwargs))
    loc = {id(p) for p in model.policy.tracker.loc.parameters()}
    assert {id(p) for p in model.policy.trainable_tracker_parameters} == loc
    runs = {}
    for cache in (True, False):
        group = group_ppo(
            data, base, env_kwargs=env_kwargs, group_size=4, learning_rate=1e-3, n_epochs=2,
            cache_features=cache, batch_size=4, policy_kwargs={"tracker_lr_scale": 1.0},
        )  # fmt: skip
        collect(group)
        group.train()
        runs[cache] = group.policy.trainable_tracker_parameters
    moved = [not torch.equal(p, q) for p, q in zip(runs[True], base.loc.parameters(), strict=True)]
    assert any(moved)
    for p, q in zip(runs[True], runs[False], strict=True):
        torch.testing.assert_close(p, q, atol=1e-6, rtol=0)


@pytest.mark.parametrize("name", ["p2b-kitti1-u", "bat-kitti1-u", "gpt-kitti1-u"])
def test_executed_proposal_gradient_equals_the_whole_heads(data, name):
    """With ``train_parts="head"`` the update differentiates only the executed proposal's
    cluster (``executed_gradient_only``): the same means and the same gradient in every head
    weight as differentiating the whole head (to float rounding), on the tracker's own closed
    loop (held boxes, best-scored and re-ranked proposals; the hold off for a second pass so
    that every state moves)."""
    for inference in ({}, {"hold_chamfer_m": 0.0}):
        base = trackers.load(name, inference=inference)
        obs = stack(observations(base, data, n=8))
        grads, means = {}, {}
        for executed in (True, False):
            model = ppo(data, base, policy_kwargs={"executed_gradient_only": executed})
            policy = model.policy
            assert policy._executed_gradient == executed
            mean, _ = policy.mean_and_value({k: torch.as_tensor(v) for k, v in obs.items()})
            weights = torch.linspace(-1.0, 1.0, mean.numel()).reshape(mean.shape)
            (mean * weights).sum().backward()
            means[executed] = mean.detach()
            grads[executed] = [p.grad for p in policy.trainable_tracker_parameters]
        torch.testing.assert_close(means[True], means[False], atol=1e-6, rtol=0)
        assert any(g is not None and g.abs().sum() > 0 for g in grads[False])
        for fast, full in zip(grads[True], grads[False], strict=True):
            if full is None:  # a weight no executed proposal depends on (the seed scores)
                assert fast is None or not fast.any()
            else:
                torch.testing.assert_close(fast, full, atol=1e-5, rtol=1e-4)


def test_executed_gradient_is_off_where_it_would_change_the_gradient(data):
    """The soft mean weighs every proposal, ``fusion+head`` needs the forward's graph up to the
    fused features, and a frozen actor needs no gradient: the plain path there."""
    for kwargs in ({"action_mode": "soft"}, {"train_parts": "fusion+head"}):
        assert not ppo(data, "p2b-kitti1-u", policy_kwargs=kwargs).policy._executed_gradient
    policy = ppo(data, "p2b-kitti1-u").policy
    policy.freeze_actor()
    assert not policy._executed_gradient
