"""RL fine-tuning of a pretrained tracker with stable-baselines3: ``pointtrack finetune``.

Three algorithms (:data:`ALGOS`):

* ``"ppo"`` (default): PPO on :class:`training.rl.TrackerPolicy`, whose actor *is* the tracker
  (its weights are what trains). ``K`` sub-envs (``DummyVecEnv``) step together, so every
  rollout step is one batch-``K`` tracker forward. Episodes are clips of ``clip_length`` steps
  from a random observed-category tracklet of the train split (a ``TimeLimit``: truncation, so
  PPO bootstraps from the value of the clip's last observation). The first ``warmup_rollouts``
  updates train the critic alone (actor frozen), then PPO with ``target_kl``, gradient clipping
  and two learning rates (``tracker_lr`` for the tracker, ``lr`` for the value head and log-std).
* ``"group"``: :class:`training.rl.GroupPPO` on the same policy and envs: ``group_size``
  sampled actions per visited state, scored by the env without stepping, each one's advantage
  its reward minus the group's mean; the env steps with the mean action. One-step rewards: no
  critic, so ``gamma``, ``gae_lambda``, ``critic``, ``baseline`` and ``warmup_rollouts`` do not
  apply (a ``baseline`` other than ``critic`` is refused).
* ``"residual"``: the earlier variant: the tracker is frozen and a small Gaussian MLP learns a
  residual on 23 hand-made features (:class:`ResidualTrackingEnv`).

Run directory (``out``)::

    config.json            the run's FinetuneConfig (+ the base checkpoint's SHA-256)
    state.safetensors      resume state: policy and optimizer tensors, JSON metadata
    log.jsonl              one record per PPO update (rewards, IoU, approx_kl, losses, speed)
    snapshots/             tracker-<step>.safetensors every ``snapshot_every`` updates
    tracker.safetensors    the result, an ordinary tracker checkpoint (``trackers.load``)
    residual.safetensors   (``--algo residual``) the residual policy with its base tracker
    val.json               a quick check on the val split (base vs fine-tuned)

Nothing is unpickled: SB3's ``PPO.load`` runs cloudpickle (a crafted zip can execute code), so
the result and the resume state are safetensors (tensors + string metadata holding JSON) and the
optimizer state goes through its ``state_dict`` tensors. Resuming continues from the last saved
update: weights, optimizer moments, step and update counters and log are restored; the
episodes in flight at the kill are lost and new ones are drawn from a seed derived from
``(seed, update)``, so a resumed run is a valid continuation, not a bit-exact replay.
"""

from __future__ import annotations

import dataclasses
import functools
import hashlib
import json
import math
import os
import shutil
import time
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import gymnasium as gym
import numpy as np
import torch
from gymnasium import spaces

from training.checkpoint import parent_entry
from training.provenance import check_finetune_categories, finetune_provenance

__all__ = [
    "ALGOS",
    "FinetuneConfig",
    "FinetuneError",
    "FinetuneResult",
    "NonFiniteError",
    "ResidualTracker",
    "ResidualTrackingEnv",
    "check_out_dir",
    "features",
    "finetune",
    "load_state",
]

ALGOS = ("ppo", "group", "residual")
BASELINES = ("critic", "self_critical")
STATE_FORMAT = "pointtrack-finetune-state"
RESIDUAL_FORMAT = "pointtrack-residual"
FORMAT_VERSION = "1"
#: Config fields that may change on ``--resume`` (how long and where it runs, not what).
RESUMABLE = ("timesteps", "device", "threads", "save_every", "snapshot_every", "val_max_tracklets")


class FinetuneError(ValueError):
    """An expected failure (bad config, refused run directory): the CLI prints one line."""


class NonFiniteError(FinetuneError):
    """A NaN or inf in a rollout, a loss or the weights; the last good checkpoint is kept."""


@dataclass
class FinetuneConfig:
    """Everything a fine-tuning run depends on (``pointtrack finetune`` flags)."""

    tracker: str = "p2b-kitti1-u"
    algo: str = "ppo"
    # data: the synthetic world (preset, sensor, world_seed) or a KITTI-layout root
    setting: str = "kitti-1"
    preset: str = "default"
    sensor: str = "hdl64"
    world_seed: int = 0
    data_root: str | None = None
    reward: str = "iou_3d"
    clip_length: int = 32  # steps per episode (0: whole tracklets)
    # PPO
    timesteps: int = 4096
    num_envs: int = 4
    n_steps: int = 64  # per sub-env and update
    batch_size: int = 64
    n_epochs: int = 4
    lr: float = 3e-4  # value head and log-std
    tracker_lr: float = 1e-5
    train_parts: str = "head"
    action_mode: str = "best"
    critic: str = "fused"
    baseline: str = "critic"  # or "self_critical" (needs gamma=0): training.rl.SelfCriticalReward
    log_std_init: float = -2.0
    warmup_rollouts: int = 1
    target_kl: float | None = 0.02
    clip_range: float = 0.1
    max_grad_norm: float = 0.5
    gamma: float = 0.9
    group_size: int = 8  # --algo group: sampled actions per state
    gae_lambda: float = 0.95
    ent_coef: float = 0.0
    seed: int = 0
    device: str = "cpu"
    threads: int = 1
    save_every: int = 1  # updates between resume checkpoints
    snapshot_every: int = 0  # updates between tracker snapshots (0: none)
    val_max_tracklets: int = 8
    # train in an env serving a category the base file holds out (training.provenance)
    allow_held_out: bool = False

    def validate(self) -> None:
        """Raise :class:`FinetuneError` naming every offending field."""
        from envs.tracking_env import REWARDS
        from training.rl import ACTION_MODES, CRITICS, TRAIN_PARTS

        errors = []
        for name, value, valid in (
            ("algo", self.algo, ALGOS),
            ("train_parts", self.train_parts, TRAIN_PARTS),
            ("action_mode", self.action_mode, ACTION_MODES),
            ("critic", self.critic, CRITICS),
            ("baseline", self.baseline, BASELINES),
            ("reward", self.reward, REWARDS),
        ):
            if value not in valid:
                errors.append(f"{name} must be one of {list(valid)}, got {value!r}")
        if self.group_size < 2:
            errors.append(f"group_size must be >= 2, got {self.group_size}")
        if self.algo == "group" and self.baseline != "critic":
            errors.append(
                f"baseline {self.baseline!r} does not apply to algo 'group' (its baseline is "
                f"the group's mean reward)"
            )
        for name in ("timesteps", "num_envs", "n_epochs", "threads", "save_every"):
            if getattr(self, name) < 1:
                errors.append(f"{name} must be >= 1, got {getattr(self, name)}")
        if self.n_steps < 2 or self.batch_size < 2:
            errors.append(
                f"n_steps and batch_size must be >= 2, got {self.n_steps}, {self.batch_size}"
            )
        for name in ("clip_length", "warmup_rollouts", "snapshot_every"):
            if getattr(self, name) < 0:
                errors.append(f"{name} must be >= 0, got {getattr(self, name)}")
        if self.val_max_tracklets < 0:
            errors.append(
                f"val_max_tracklets must be >= 1 (or 0 for no val check), got "
                f"{self.val_max_tracklets}"
            )
        for name in ("lr", "tracker_lr", "clip_range", "max_grad_norm"):
            v = getattr(self, name)
            if not (math.isfinite(v) and v >= 0):
                errors.append(f"{name} must be a finite number >= 0, got {v}")
        for name in ("gamma", "gae_lambda"):
            if not 0 <= getattr(self, name) <= 1:
                errors.append(f"{name} must be in [0, 1], got {getattr(self, name)}")
        if self.baseline == "self_critical" and self.gamma != 0:
            errors.append(
                f"baseline 'self_critical' is unbiased for one-step returns only: set gamma=0 "
                f"(got gamma={self.gamma})"
            )
        if str(self.device).startswith("cuda") and not torch.cuda.is_available():
            errors.append(f"device {self.device!r}: CUDA is not available here (use cpu)")
        elif not str(self.device).startswith(("cpu", "cuda")):
            errors.append(f"device must be cpu or cuda[:N], got {self.device!r}")
        if self.target_kl is not None and not self.target_kl > 0:
            errors.append(f"target_kl must be > 0 (or None), got {self.target_kl}")
        if errors:
            raise FinetuneError("; ".join(errors))

    def to_dict(self) -> dict[str, Any]:
        return dataclasses.asdict(self)


@dataclass
class FinetuneResult:
    """What :func:`finetune` returns."""

    out: Path
    tracker_path: Path
    timesteps: int
    updates: int
    wall_s: float
    steps_per_s: float
    val: dict[str, Any] | None


# --------------------------------------------------------------------------- run directory


def tracker_digest(spec: str) -> str | None:
    """SHA-256 of the checkpoint file ``trackers.load(spec)`` reads (None for a bare name)."""
    from trackers.registry import find_checkpoint

    path = find_checkpoint(spec)
    if path is None:
        return None
    h = hashlib.sha256()
    with open(path, "rb") as f:
        for block in iter(lambda: f.read(1 << 20), b""):
            h.update(block)
    return h.hexdigest()


def _identity(cfg: FinetuneConfig) -> dict[str, Any]:
    return {**cfg.to_dict(), "tracker_sha256": tracker_digest(cfg.tracker)}


def _read_meta(path: Path) -> dict[str, Any]:
    from safetensors import safe_open

    try:
        with safe_open(str(path), framework="pt", device="cpu") as f:
            meta = dict(f.metadata() or {})
    except Exception as exc:
        raise FinetuneError(
            f"cannot read {path}: not a safetensors file ({type(exc).__name__}: {exc})"
        ) from exc
    if meta.get("format") != STATE_FORMAT:
        raise FinetuneError(
            f"{path} is not a pointtrack finetune state (format={meta.get('format')!r})"
        )
    return json.loads(meta["state"])


def check_out_dir(
    out: str | Path, cfg: FinetuneConfig, *, resume: bool = False, overwrite: bool = False
) -> dict[str, Any] | None:
    """Refuse what would silently lose or mix results, before any data is built.

    Returns the saved state's metadata when resuming (None for a fresh run). A fresh run into
    a directory holding a run needs ``overwrite`` (its run files are then removed); ``resume``
    needs a saved state whose config equals ``cfg`` except :data:`RESUMABLE` fields.
    """
    cfg.validate()
    if resume and overwrite:
        raise FinetuneError("--resume and --overwrite exclude each other")
    out = Path(out)
    if out.exists() and not out.is_dir():
        raise FinetuneError(f"--out {out} exists and is not a directory")
    state = out / "state.safetensors"
    held = [
        name
        for name in (
            "state.safetensors",
            "tracker.safetensors",
            "residual.safetensors",
            "log.jsonl",
            "config.json",
        )
        if (out / name).exists()
    ]
    if resume:
        if cfg.algo == "residual":
            raise FinetuneError("--resume is only available for --algo ppo and group")
        if not state.is_file():
            raise FinetuneError(f"nothing to resume: {state} does not exist")
        meta = _read_meta(state)
        # a field added since the run was saved had its default then
        saved = {**FinetuneConfig().to_dict(), **meta["identity"]}
        given = _identity(cfg)
        diffs = [
            f"{k}: saved {saved.get(k)!r}, given {given.get(k)!r}"
            for k in sorted(set(saved) | set(given))
            if k not in RESUMABLE and saved.get(k) != given.get(k)
        ]
        if diffs:
            raise FinetuneError(
                f"--resume refused: {out} holds a run with another tracker or "
                f"config ({'; '.join(diffs)})"
            )
        return meta
    if held and not overwrite:
        finished = False
        if state.is_file():
            finished = bool(_read_meta(state).get("finished"))
        what = (
            "a finished run"
            if finished or (out / "residual.safetensors").exists()
            else "an unfinished run"
        )
        raise FinetuneError(
            f"--out {out} holds {what} ({', '.join(held)}); pass --resume to "
            f"continue it or --overwrite to replace it"
        )
    if held:
        for name in held:
            (out / name).unlink()
        for name in ("snapshots", "val.json"):
            p = out / name
            if p.is_dir():
                shutil.rmtree(p)
            elif p.exists():
                p.unlink()
    return None


def _atomic_write_text(path: Path, text: str) -> None:
    tmp = path.with_name(f".{path.name}.tmp{os.getpid()}")
    tmp.write_text(text)
    tmp.replace(path)


def save_state(
    path: Path, policy: torch.nn.Module, optimizer: torch.optim.Optimizer, meta: dict[str, Any]
) -> None:
    """Policy and optimizer tensors plus JSON ``meta`` into one safetensors file (atomic)."""
    from safetensors.torch import save_file

    tensors = {f"policy.{k}": v.detach().cpu().contiguous() for k, v in policy.state_dict().items()}
    opt = optimizer.state_dict()
    for idx, entry in opt["state"].items():
        for key, value in entry.items():
            tensors[f"optim.{idx}.{key}"] = torch.as_tensor(value).detach().cpu().contiguous()
    tensors["rng.torch"] = torch.get_rng_state()
    groups = [{k: v for k, v in g.items()} for g in opt["param_groups"]]
    meta = {**meta, "optimizer_groups": groups}
    tmp = path.with_name(f".{path.name}.tmp{os.getpid()}")
    save_file(
        tensors,
        str(tmp),
        metadata={"format": STATE_FORMAT, "version": FORMAT_VERSION, "state": json.dumps(meta)},
    )
    tmp.replace(path)


def load_state(
    path: str | Path,
) -> tuple[dict[str, torch.Tensor], dict[str, Any], torch.Tensor, dict[str, Any]]:
    """-> (policy state dict, optimizer state dict, torch RNG state, metadata); safetensors
    only (no unpickling)."""
    from safetensors import safe_open

    path = Path(path)
    meta = _read_meta(path)
    policy, state = {}, {}
    with safe_open(str(path), framework="pt", device="cpu") as f:
        for key in f.keys():  # noqa: SIM118 - safe_open API
            tensor = f.get_tensor(key)
            if key.startswith("policy."):
                policy[key[len("policy.") :]] = tensor
            elif key.startswith("optim."):
                _, idx, name = key.split(".", 2)
                state.setdefault(int(idx), {})[name] = tensor
        rng = f.get_tensor("rng.torch")
    optim = {"state": state, "param_groups": meta["optimizer_groups"]}
    return policy, optim, rng, meta


# --------------------------------------------------------------------------- data and envs


def _setting(cfg: FinetuneConfig):
    from envs.data import get_setting

    try:
        return get_setting(cfg.setting)
    except ValueError as exc:
        raise FinetuneError(str(exc)) from None


def _root(cfg: FinetuneConfig) -> str:
    if cfg.data_root:
        if not Path(cfg.data_root).is_dir():
            raise FinetuneError(f"--data-root {cfg.data_root} is not a directory")
        return cfg.data_root
    from envs.synthetic import ensure_world

    return str(ensure_world(preset=cfg.preset, sensor=cfg.sensor, seed=cfg.world_seed))


def train_env_factory(
    cfg: FinetuneConfig,
    env_options: Mapping[str, Any] | None = None,
    observation_keys: Sequence[str] | None = None,
) -> Callable[[], gym.Env]:
    """A factory of training envs on the train split, the setting's *observed* categories only
    (never the unseen ones), random tracklets; the sub-envs share the loaded data.
    ``env_options``: the base tracker's ``env_options`` (its template mode, search region);
    ``observation_keys``: the env's observation (``None``: its default; M2-Track needs
    ``previous_search``, see ``training.evaluate.observation_keys_for``)."""
    from envs.tracking_env import make_tracking_env

    setting = _setting(cfg)
    # clips start anywhere in a tracklet (the env's start_frame / max_steps episode options)
    base = make_tracking_env(
        "kitti",
        root=_root(cfg),
        split="train",
        setting=setting,
        categories=setting.observed,
        sampling="random",
        reward=cfg.reward,
        start_frame="random",
        max_steps=cfg.clip_length if cfg.clip_length > 0 else None,
        **({} if observation_keys is None else {"observation_keys": tuple(observation_keys)}),
        **(env_options or {}),
    )
    return base.clone


def _wrap(env: gym.Env, clip_length: int) -> gym.Env:
    # a TimeLimit for envs that do not clip themselves; on one that does (max_steps) it ends
    # the episode at the same step
    if clip_length > 0:
        env = gym.wrappers.TimeLimit(env, max_episode_steps=clip_length)
    one = np.ones(4, dtype=np.float32)
    return gym.wrappers.RescaleAction(env, -one, one)


def make_vec_env(make_env: Callable[[], gym.Env], num_envs: int, clip_length: int):
    """``VecMonitor(DummyVecEnv)`` of ``num_envs`` wrapped envs (``RescaleAction`` to [-1, 1],
    ``TimeLimit`` clips): the policy acts on one batch of ``num_envs`` per step."""
    from stable_baselines3.common.vec_env import DummyVecEnv, VecMonitor

    return VecMonitor(
        DummyVecEnv([lambda: _wrap(make_env(), clip_length) for _ in range(num_envs)])
    )


# --------------------------------------------------------------------------- PPO


def _finite_params(module: torch.nn.Module) -> str | None:
    for name, p in module.named_parameters():
        if not torch.isfinite(p).all():
            return name
    return None


class _RunCallback:
    """Progress bar, ``log.jsonl``, resume checkpoints, snapshots and NaN checks, as an SB3
    callback (built lazily so SB3 is imported only when a run starts)."""

    @staticmethod
    def make(run: _PPORun):
        from stable_baselines3.common.callbacks import BaseCallback

        class Callback(BaseCallback):
            def _on_step(self) -> bool:
                return run.on_step(self.locals)

            def _on_rollout_start(self) -> None:
                run.after_update()

            def _on_rollout_end(self) -> None:
                run.check_rollout()

        return Callback()


class _PPORun:
    """One PPO fine-tuning run (see :func:`finetune`)."""

    def __init__(
        self,
        cfg: FinetuneConfig,
        out: Path,
        make_env: Callable[[], gym.Env],
        resume_meta: dict[str, Any] | None,
        progress: bool,
        log: Callable,
    ) -> None:
        from stable_baselines3 import PPO

        from training.rl import GroupPPO, SelfCriticalReward, TrackerPolicy

        self.cfg, self.out, self.log = cfg, out, log
        self.progress = progress
        state = load_state(out / "state.safetensors") if resume_meta else None
        self.updates = int(resume_meta["updates"]) if resume_meta else 0
        steps0 = int(resume_meta["timesteps"]) if resume_meta else 0
        self.rollout_steps = cfg.n_steps * cfg.num_envs
        self.env = make_vec_env(make_env, cfg.num_envs, cfg.clip_length)
        if cfg.baseline == "self_critical":
            self.env = SelfCriticalReward(self.env)
        algorithm: Any = PPO
        if cfg.algo == "group":
            algorithm = functools.partial(GroupPPO, group_size=cfg.group_size)
        self.model = algorithm(
            TrackerPolicy,
            self.env,
            learning_rate=cfg.lr,
            n_steps=cfg.n_steps,
            batch_size=cfg.batch_size,
            n_epochs=cfg.n_epochs,
            gamma=cfg.gamma,
            gae_lambda=cfg.gae_lambda,
            clip_range=cfg.clip_range,
            ent_coef=cfg.ent_coef,
            max_grad_norm=cfg.max_grad_norm,
            target_kl=cfg.target_kl,
            device=cfg.device,
            seed=cfg.seed + 7919 * self.updates,
            verbose=0,
            policy_kwargs={
                "tracker": cfg.tracker,
                "train_parts": cfg.train_parts,
                "log_std_init": cfg.log_std_init,
                "action_mode": cfg.action_mode,
                "critic": cfg.critic,
                "tracker_lr_scale": cfg.tracker_lr / cfg.lr if cfg.lr else 0.0,
            },
        )
        self.policy = self.model.policy
        if isinstance(self.env, SelfCriticalReward):
            self.env.policy = self.policy
        if state is not None:
            policy_sd, optim_sd, rng, _ = state
            self.policy.load_state_dict(policy_sd, strict=True)
            self.policy.optimizer.load_state_dict(optim_sd)
            torch.set_rng_state(rng)
            self.model.num_timesteps = steps0
            self.model._n_updates = int(resume_meta["n_updates"])
        self.last_good = steps0 if state is not None else None
        self.counted_at = steps0  # num_timesteps of the last update counted by after_update
        self.t0 = time.perf_counter()
        self.steps_at_start = steps0
        self.ious: list[float] = []
        self.bar = None
        self.log_file = None

    # -------------------------------------------------------------- callback hooks
    def on_step(self, local: dict[str, Any]) -> bool:
        for info in local.get("infos", ()):
            if "iou" in info:
                self.ious.append(float(info["iou"]))
        if self.bar is not None:
            self.bar.update(self.cfg.num_envs)
        return True

    def check_rollout(self) -> None:
        buf = self.model.rollout_buffer
        for name in ("rewards", "values", "log_probs", "actions"):
            if not np.all(np.isfinite(getattr(buf, name, 0.0))):
                self._non_finite(f"{name} of the rollout")

    def after_update(self) -> None:
        """Called before each rollout: the previous update (if any) is complete."""
        if self.model.num_timesteps <= self.counted_at:
            return
        self.counted_at = self.model.num_timesteps
        self.updates += 1
        values = dict(self.model.logger.name_to_value)
        for key in ("train/loss", "train/value_loss", "train/approx_kl"):
            if key in values and not math.isfinite(float(values[key])):
                self._non_finite(key)
        bad = _finite_params(self.policy)
        if bad is not None:
            self._non_finite(f"weight {bad}")
        self._log_update(values)
        if self.updates % self.cfg.save_every == 0:
            self.checkpoint()
        if self.cfg.snapshot_every and self.updates % self.cfg.snapshot_every == 0:
            import trackers

            trackers.save(
                self.policy.tracker,
                self.out / "snapshots" / f"tracker-{self.model.num_timesteps:08d}.safetensors",
                provenance=finetune_provenance(
                    self.cfg, self.model.num_timesteps, parent_entry(self.cfg.tracker)
                ),
            )

    def _non_finite(self, what: str) -> None:
        kept = (
            f"the last good checkpoint (step {self.last_good}) is kept in "
            f"{self.out / 'state.safetensors'}"
            if self.last_good is not None
            else "no checkpoint was saved yet"
        )
        raise NonFiniteError(
            f"non-finite {what} at step {self.model.num_timesteps} "
            f"(update {self.updates}); stopped; {kept}"
        )

    def _log_update(self, values: dict[str, Any]) -> None:
        eps = list(self.model.ep_info_buffer)
        wall = time.perf_counter() - self.t0
        steps = self.model.num_timesteps
        record = {
            "kind": "train",
            "step": steps,
            "update": self.updates,
            "ep_reward": float(np.mean([e["r"] for e in eps])) if eps else None,
            "ep_len": float(np.mean([e["l"] for e in eps])) if eps else None,
            "iou": float(np.mean(self.ious)) if self.ious else None,
            "actor_frozen": self.policy.actor_frozen,
            "wall_s": round(wall, 2),
            "steps_per_s": round((steps - self.steps_at_start) / max(wall, 1e-9), 3),
        }
        for key, value in values.items():
            if key.startswith("train/") and key not in ("train/learning_rate",):
                record[key[len("train/") :]] = float(value)
        self.ious = []
        self.log_file.write(json.dumps(record) + "\n")
        self.log_file.flush()
        if self.bar is not None:
            kl = record.get("approx_kl")
            self.bar.set_postfix_str(
                f"ep_reward {record['ep_reward'] or float('nan'):.2f} iou "
                f"{record['iou'] or float('nan'):.3f} kl "
                f"{float('nan') if kl is None else kl:.4f}"
            )

    def checkpoint(self, finished: bool = False) -> None:
        meta = {
            "identity": _identity(self.cfg),
            "timesteps": self.model.num_timesteps,
            "updates": self.updates,
            "n_updates": self.model._n_updates,
            "finished": finished,
        }
        save_state(self.out / "state.safetensors", self.policy, self.policy.optimizer, meta)
        self.last_good = self.model.num_timesteps

    # -------------------------------------------------------------- the run
    def _truncate_log(self) -> None:
        path = self.out / "log.jsonl"
        if not path.exists():
            return
        keep = [
            line
            for line in path.read_text().splitlines()
            if line.strip() and json.loads(line).get("step", 0) <= self.steps_at_start
        ]
        _atomic_write_text(path, "".join(line + "\n" for line in keep))

    def run(self) -> FinetuneResult:
        import trackers

        cfg = self.cfg
        self._truncate_log()
        self.log_file = open(self.out / "log.jsonl", "a")  # noqa: SIM115 - closed below
        if self.progress:
            from tqdm import tqdm

            self.bar = tqdm(
                total=cfg.timesteps,
                initial=min(self.steps_at_start, cfg.timesteps),
                unit="step",
                desc=f"finetune {cfg.algo}",
                dynamic_ncols=True,
            )
        callback = _RunCallback.make(self)
        try:
            # GroupPPO has no critic to warm up
            warmup = 0 if cfg.algo == "group" else cfg.warmup_rollouts
            warmup_steps = warmup * self.rollout_steps
            for frozen, until in ((True, min(warmup_steps, cfg.timesteps)), (False, cfg.timesteps)):
                remaining = until - self.model.num_timesteps
                if remaining <= 0:
                    continue
                self.policy.freeze_actor(frozen)
                try:
                    self.model.learn(
                        remaining, callback=callback, reset_num_timesteps=False, progress_bar=False
                    )
                except FloatingPointError as exc:
                    self._non_finite(f"policy output ({exc})")
                self.after_update()
            self.policy.freeze_actor(False)
        finally:
            if self.bar is not None:
                self.bar.close()
            self.log_file.close()
            self.env.close()
        path = trackers.save(
            self.policy.tracker,
            self.out / "tracker.safetensors",
            provenance=finetune_provenance(
                cfg, self.model.num_timesteps, parent_entry(cfg.tracker)
            ),
        )
        self.checkpoint(finished=True)
        wall = time.perf_counter() - self.t0
        done = self.model.num_timesteps - self.steps_at_start
        return FinetuneResult(
            self.out,
            path,
            self.model.num_timesteps,
            self.updates,
            wall,
            done / max(wall, 1e-9),
            None,
        )


def finetune(
    cfg: FinetuneConfig,
    out: str | Path,
    *,
    resume: bool = False,
    overwrite: bool = False,
    make_env: Callable[[], gym.Env] | None = None,
    progress: bool = True,
    log: Callable[[str], Any] = print,
) -> FinetuneResult:
    """Fine-tune ``cfg.tracker`` with ``cfg.algo`` into ``out`` (see the module docstring).

    ``make_env`` (tests, custom data): a factory of unwrapped ``TrackingEnv`` s to train on,
    instead of the train split of ``cfg``'s world; the val check is then skipped. Raises
    :class:`FinetuneError` (refused run directory, bad config, resume mismatch) before any data
    is built, and :class:`NonFiniteError` when a NaN appears (naming the step).
    """
    out = Path(out)
    resume_meta = check_out_dir(out, cfg, resume=resume, overwrite=overwrite)
    from training.rl import resolve_tracker

    try:
        base = resolve_tracker(cfg.tracker)
    except (TypeError, ValueError, FileNotFoundError) as exc:
        raise FinetuneError(str(exc)) from None
    if resume_meta and resume_meta.get("finished") and resume_meta["timesteps"] >= cfg.timesteps:
        log(
            f"{out} already finished at step {resume_meta['timesteps']} (>= --timesteps "
            f"{cfg.timesteps}); nothing to do"
        )
        return FinetuneResult(
            out,
            out / "tracker.safetensors",
            int(resume_meta["timesteps"]),
            int(resume_meta["updates"]),
            0.0,
            0.0,
            None,
        )
    torch.set_num_threads(cfg.threads)
    if make_env is not None:
        factory = make_env
    else:
        from training.evaluate import observation_keys_for

        check_finetune_categories(base, cfg.setting, cfg.allow_held_out)
        factory = train_env_factory(cfg, base.env_options, observation_keys_for([base]))
    out.mkdir(parents=True, exist_ok=True)
    _atomic_write_text(out / "config.json", json.dumps(_identity(cfg), indent=2) + "\n")
    if cfg.algo == "residual":
        result = _finetune_residual(cfg, base, out, factory)
    else:
        result = _PPORun(cfg, out, factory, resume_meta, progress, log).run()
    if make_env is None and cfg.val_max_tracklets > 0:
        result.val = val_check(cfg, base, load_result(out), out)
        for name in ("base", "finetuned"):
            rep = result.val[name]
            log(
                f"{name}: val success {rep['success']:.2f} precision {rep['precision']:.2f} "
                f"({result.val['frames']} frames, {result.val['tracklets']} tracklets)"
            )
    return result


def load_result(out: str | Path) -> Any:
    """The fine-tuned tracker of a run directory (PPO: ``tracker.safetensors``; residual:
    ``residual.safetensors``)."""
    out = Path(out)
    if (out / "residual.safetensors").is_file():
        return ResidualTracker.load(out / "residual.safetensors")
    import trackers

    return trackers.load(out / "tracker.safetensors")


def val_check(cfg: FinetuneConfig, base: Any, tuned: Any, out: Path) -> dict[str, Any]:
    """Base and fine-tuned tracker on the first ``val_max_tracklets`` observed-category val
    tracklets, eval seed 0 (a quick check only: too few tracklets to tell a gain from noise;
    the protocol in docs/rl.md is what measures one); each with its ``env_options``."""
    from envs.data import KittiTracking
    from envs.tracking_env import make_tracking_env
    from training.evaluate import env_options_for, evaluate, observation_keys_for

    setting = _setting(cfg)
    data = KittiTracking(_root(cfg), "val", list(setting.observed))
    result: dict[str, Any] = {}
    for name, tracker in (("base", base), ("finetuned", tuned)):
        options = env_options_for([tracker])
        env = make_tracking_env(
            data,
            setting=setting,
            categories=setting.observed,
            observation_keys=observation_keys_for([tracker]),
            **options,
        )
        subset = list(range(min(cfg.val_max_tracklets, env.num_tracklets)))
        rep = evaluate(tracker, env, tracklets=subset, seed=0)
        result[name] = {k: rep["mean"][k] for k in ("success", "precision")}
        result["frames"], result["tracklets"] = rep["frames"], rep["tracklets"]
    _atomic_write_text(out / "val.json", json.dumps(result, indent=2) + "\n")
    return result


# --------------------------------------------------------------------------- residual variant

FEATURE_DIM = 4 + 4 + 3 + 3 * 4
DEFAULT_SCALE = (0.5, 0.5, 0.2, 0.2)
RESIDUAL_NET_ARCH = (64, 64)


def features(obs: dict[str, np.ndarray], base: np.ndarray) -> np.ndarray:
    """The residual policy's observation ``(23,)``: the base action, the last motion, the target
    size, and for radii 0.5 / 1 / 2 m around the proposed centre the log point count and the
    mean offset of the search points."""
    search = np.asarray(obs["search"], dtype=np.float32)
    d = np.linalg.norm(search[:, :2] - base[None, :2], axis=1)
    nonzero = np.any(search != 0, axis=1)
    parts = [base, obs["motion"], obs["size"]]
    for radius in (0.5, 1.0, 2.0):
        near = (d <= radius) & nonzero
        count = near.sum()
        mean = (search[near, :3].mean(0) - base[:3]) if count else np.zeros(3, np.float32)
        parts.append(np.array([np.log1p(count)], np.float32))
        parts.append(mean.astype(np.float32))
    return np.concatenate([np.asarray(p, np.float32).ravel() for p in parts]).astype(np.float32)


class ResidualTrackingEnv(gym.Wrapper):
    """Wraps a :class:`~envs.tracking_env.TrackingEnv`: actions are residuals in ``[-1, 1]^4``
    added (times ``scale``) to the frozen tracker's action; observations are :func:`features`."""

    def __init__(self, env: gym.Env, tracker: Any, scale=DEFAULT_SCALE) -> None:
        super().__init__(env)
        self.tracker = tracker
        self.scale = np.asarray(scale, dtype=np.float32)
        self.action_space = spaces.Box(-1.0, 1.0, (4,), np.float32)
        self.observation_space = spaces.Box(-np.inf, np.inf, (FEATURE_DIM,), np.float32)
        self._base = np.zeros(4, np.float32)

    def _encode(self, obs: dict[str, np.ndarray]) -> np.ndarray:
        self._base = np.asarray(self.tracker.act(obs), dtype=np.float32)
        return features(obs, self._base)

    def reset(self, *, seed=None, options=None):
        obs, info = self.env.reset(seed=seed, options=options)
        return self._encode(obs), info

    def step(self, action):
        r = np.clip(np.asarray(action, dtype=np.float32), -1.0, 1.0)
        full = self._base + self.scale * r
        low, high = self.env.action_space.low, self.env.action_space.high
        obs, reward, terminated, truncated, info = self.env.step(np.clip(full, low, high))
        return self._encode(obs), reward, terminated, truncated, info


def _residual_policy(log_std_init: float):
    from stable_baselines3.common.policies import ActorCriticPolicy

    return ActorCriticPolicy(
        spaces.Box(-np.inf, np.inf, (FEATURE_DIM,), np.float32),
        spaces.Box(-1.0, 1.0, (4,), np.float32),
        lambda _: 0.0,
        net_arch=list(RESIDUAL_NET_ARCH),
        log_std_init=log_std_init,
    )


class ResidualTracker:
    """A fine-tuned tracker: the frozen base tracker plus the PPO residual (deterministic).

    Saved as one ``residual.safetensors`` (the residual policy's and the base tracker's
    tensors, config as JSON metadata); :meth:`load` reads only that file — an SB3 ``ppo.zip``
    is refused, never unpickled.
    """

    def __init__(
        self,
        base: Any,
        policy: Any,
        scale=DEFAULT_SCALE,
        name: str = "finetuned",
        log_std_init: float = -2.0,
    ) -> None:
        self.base = base
        self.policy = policy
        self.scale = np.asarray(scale, dtype=np.float32)
        self.name = name
        self.log_std_init = float(log_std_init)
        #: the base tracker's env options (it acts on the same observations)
        self.env_options = dict(getattr(base, "env_options", None) or {})

    def save(self, path: str | Path) -> Path:
        """Write ``path`` (safetensors, atomic)."""
        from safetensors.torch import save_file

        from trackers.registry import tracker_metadata

        path = Path(path)
        tensors = {
            f"policy.{k}": v.detach().cpu().contiguous()
            for k, v in self.policy.state_dict().items()
        }
        tensors.update(
            {f"base.{k}": v.detach().cpu().contiguous() for k, v in self.base.state_dict().items()}
        )
        meta = {
            "format": RESIDUAL_FORMAT,
            "version": FORMAT_VERSION,
            "base_tracker": self.base.name,
            "scale": json.dumps([float(s) for s in self.scale]),
            "name": self.name,
            "log_std_init": json.dumps(self.log_std_init),
        }
        # as trackers.save: the config, and env_options / inference where not the defaults
        base_meta = tracker_metadata(self.base)
        meta.update(base_config=base_meta.pop("config"), **base_meta)
        tmp = path.with_name(f".{path.name}.tmp{os.getpid()}")
        save_file(tensors, str(tmp), metadata=meta)
        tmp.replace(path)
        return path

    @staticmethod
    def is_residual_file(path: str | Path) -> bool:
        """True for a ``residual.safetensors`` (or a run directory holding one)."""
        path = Path(path)
        if path.is_dir():
            path = path / "residual.safetensors"
        if not path.is_file() or path.suffix != ".safetensors":
            return False
        from safetensors import safe_open

        try:
            with safe_open(str(path), framework="pt", device="cpu") as f:
                return (f.metadata() or {}).get("format") == RESIDUAL_FORMAT
        except Exception:  # noqa: BLE001 - not a safetensors file: not ours
            return False

    @classmethod
    def load(cls, path: str | Path) -> ResidualTracker:
        """From ``residual.safetensors`` or a run directory holding it (no unpickling)."""
        from trackers.registry import read_safetensors, tracker_from_metadata

        path = Path(path)
        if path.is_dir():
            if not (path / "residual.safetensors").is_file() and (path / "ppo.zip").exists():
                raise ValueError(
                    f"{path} holds an SB3 ppo.zip (older pointtrack): refused, "
                    f"because loading it unpickles (and can run code); re-run "
                    f"`pointtrack finetune --algo residual`"
                )
            path = path / "residual.safetensors"
        if path.suffix == ".zip":
            raise ValueError(
                f"{path}: SB3 zips are refused (loading one unpickles); pass the "
                f"run's residual.safetensors"
            )
        if not path.is_file():
            raise FileNotFoundError(f"no residual checkpoint at {path}")
        meta, state = read_safetensors(path, "residual checkpoint")
        if meta.get("format") != RESIDUAL_FORMAT:
            raise ValueError(
                f"{path} is not a pointtrack residual checkpoint (format={meta.get('format')!r})"
            )
        base_meta = {**meta, "config": meta["base_config"]}  # older files: inference inside
        base = tracker_from_metadata(meta["base_tracker"], base_meta, path)
        base.load_state_dict(
            {k[5:]: v for k, v in state.items() if k.startswith("base.")}, strict=True
        )
        log_std = float(json.loads(meta["log_std_init"]))
        policy = _residual_policy(log_std)
        policy.load_state_dict(
            {k[7:]: v for k, v in state.items() if k.startswith("policy.")}, strict=True
        )
        policy.set_training_mode(False)
        return cls(
            base.eval(), policy, json.loads(meta["scale"]), name=meta["name"], log_std_init=log_std
        )

    def act(self, obs: dict[str, np.ndarray]) -> np.ndarray:
        """One observation -> ``(4,)``; a batch -> ``(B, 4)``."""
        single = np.asarray(obs["search"]).ndim == 2
        base = np.asarray(self.base.act(obs), dtype=np.float32)
        if single:
            feats = features(obs, base)[None]
        else:
            feats = np.stack(
                [features({k: v[i] for k, v in obs.items()}, base[i]) for i in range(len(base))]
            )
        r, _ = self.policy.predict(feats, deterministic=True)
        action = base + self.scale * np.clip(r, -1, 1)
        return action[0] if single else action


def _finetune_residual(
    cfg: FinetuneConfig, base: Any, out: Path, make_env: Callable[[], gym.Env]
) -> FinetuneResult:
    """PPO on :class:`ResidualTrackingEnv` (one env; the base tracker frozen)."""
    from stable_baselines3 import PPO

    base.eval()
    for p in base.parameters():
        p.requires_grad_(False)
    t0 = time.perf_counter()
    env = ResidualTrackingEnv(make_env(), base, DEFAULT_SCALE)
    model = PPO(
        "MlpPolicy",
        env,
        n_steps=cfg.n_steps,
        batch_size=min(cfg.batch_size, cfg.n_steps),
        n_epochs=cfg.n_epochs,
        seed=cfg.seed,
        learning_rate=cfg.lr,
        verbose=0,
        device=cfg.device,
        policy_kwargs={"net_arch": list(RESIDUAL_NET_ARCH), "log_std_init": cfg.log_std_init},
    )
    model.learn(total_timesteps=cfg.timesteps)
    if _finite_params(model.policy) is not None:
        raise NonFiniteError(f"non-finite residual weights at step {model.num_timesteps}")
    tuned = ResidualTracker(
        base,
        model.policy,
        DEFAULT_SCALE,
        name=f"{cfg.tracker}-residual",
        log_std_init=cfg.log_std_init,
    )
    path = tuned.save(out / "residual.safetensors")
    wall = time.perf_counter() - t0
    return FinetuneResult(
        out,
        path,
        model.num_timesteps,
        model._n_updates,
        wall,
        model.num_timesteps / max(wall, 1e-9),
        None,
    )
