"""RL fine-tuning of a pretrained tracker with stable-baselines3: ``pointtrack finetune``.

Three algorithms (:data:`training.rl.config.ALGOS`):

* ``"ppo"`` (default): PPO on :class:`training.rl.policy.TrackerPolicy`, whose actor *is* the
  tracker (its weights are what trains). ``K`` sub-envs (``DummyVecEnv``) step together, so
  every rollout step is one batch-``K`` tracker forward. Episodes are clips of ``clip_length``
  steps from a random observed-category tracklet of the train split (a ``TimeLimit``:
  truncation, so PPO bootstraps from the value of the clip's last observation). The first
  ``warmup_rollouts`` updates train the critic alone (actor frozen), then PPO with
  ``target_kl``, gradient clipping and two learning rates (``tracker_lr`` for the tracker,
  ``lr`` for the value head and log-std).
* ``"group"``: :class:`training.rl.group_ppo.GroupPPO` on the same policy and envs:
  ``group_size`` sampled actions per visited state, scored by the env without stepping, each
  one's advantage its reward minus the group's mean; the env steps with the mean action.
  One-step rewards: no critic, so ``gamma``, ``gae_lambda``, ``critic``, ``baseline`` and
  ``warmup_rollouts`` do not apply (a ``baseline`` other than ``critic`` is refused).
* ``"residual"``: the earlier variant: the tracker is frozen and a small Gaussian MLP learns a
  residual on 23 hand-made features (:class:`training.rl.wrappers.ResidualTrackingEnv`).

Run directory (``out``, :data:`training.rundir.FINETUNE_LAYOUT`)::

    config.json            the run's FinetuneConfig (+ the base checkpoint's SHA-256)
    state.safetensors      resume state: policy and optimizer tensors, JSON metadata
    log.jsonl              one record per PPO update (rewards, IoU, approx_kl, losses, steps/s)
    sb3/from-<step>/       (``logger``) SB3's logger outputs of the attempt that started at
                           <step>: tensorboard events, progress.csv, progress.json
    snapshots/             tracker-<step>.safetensors every ``snapshot_every`` updates
    tracker.safetensors    the result, an ordinary tracker checkpoint (``trackers.load``)
    residual.safetensors   (``--algo residual``) the residual policy with its base tracker
    val.json               a quick check on the val split (base vs fine-tuned)

Every field, the base tracker and the run directory are checked before anything is built or
written. Nothing is unpickled (:mod:`training.rl.state`). Resuming continues from the last saved
update: weights, optimizer moments, step and update counters and log are restored; the episodes
in flight at the kill are lost and new ones are drawn from a seed derived from ``(seed,
update)``, so a resumed run is a valid continuation, not a bit-exact replay. A directory holding
only the config and log of a run killed before its first checkpoint starts from the beginning.
"""

from __future__ import annotations

import dataclasses
import functools
import json
import math
import time
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import gymnasium as gym
import numpy as np
import torch
from stable_baselines3 import PPO
from stable_baselines3.common.callbacks import BaseCallback
from stable_baselines3.common.logger import configure
from tqdm import tqdm

import trackers
from envs.data import KittiTracking, get_setting
from envs.synthetic import ensure_world
from envs.tracking_env import make_tracking_env
from trackers.registry import find_checkpoint
from training.allocator import retain_freed_memory
from training.checkpoint import parent_entry
from training.evaluate import env_options_for, evaluate, observation_keys_for
from training.loading import load_kernels, load_tracker
from training.parallel import torch_threads, usable_cores
from training.provenance import check_finetune_categories, finetune_provenance
from training.rl.config import RESUMABLE, FinetuneConfig, FinetuneError, NonFiniteError
from training.rl.group_ppo import GroupPPO
from training.rl.policy import TrackerPolicy, resolve_tracker
from training.rl.state import load_state, read_state_meta, save_state
from training.rl.wrappers import (
    DEFAULT_SCALE,
    RESIDUAL_NET_ARCH,
    ResidualTracker,
    ResidualTrackingEnv,
    SelfCriticalReward,
    make_vec_env,
)
from training.rundir import (
    FINETUNE_LAYOUT,
    RunDirError,
    atomic_write_text,
    file_sha256,
    prepare_run_dir,
    remove_stale_temps,
    truncate_log,
)

__all__ = [
    "FinetuneResult",
    "PPORun",
    "check_out_dir",
    "finetune",
    "load_base",
    "load_result",
    "train_env_factory",
    "val_check",
]


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


# --------------------------------------------------------------------------- checks


def tracker_digest(spec: str) -> str | None:
    """SHA-256 of the checkpoint file ``trackers.load(spec)`` reads (None for a bare name)."""
    path = find_checkpoint(spec)
    return None if path is None else file_sha256(path)


def _identity(cfg: FinetuneConfig) -> dict[str, Any]:
    return {**cfg.to_dict(), "tracker_sha256": tracker_digest(cfg.tracker)}


def load_base(cfg: FinetuneConfig) -> torch.nn.Module:
    """The base tracker of ``cfg`` (:func:`training.loading.load_tracker`: a shipped name, a
    tracker file or a training run's ``best.pt`` / ``last.pt``), checked for ``cfg.algo``.

    A learned tracker's bare name (``"p2b"``, a random initialisation, seeded by ``cfg.seed``)
    is refused unless ``cfg.untrained``; a tracker without weights (a baseline) is refused; the
    residual variant refuses a tracker that reads observation keys beyond the default ones
    (M2-Track's ``previous_search``: :class:`~training.rl.wrappers.ResidualTracker` does not
    carry them, so its result could not be evaluated). Raises :class:`FinetuneError` naming
    the field."""
    try:
        base = resolve_tracker(load_tracker(cfg.tracker, untrained=cfg.untrained, seed=cfg.seed))
    except (TypeError, ValueError, FileNotFoundError) as exc:
        raise FinetuneError(f"tracker {cfg.tracker!r}: {exc}", ["tracker"]) from None
    extra = tuple(getattr(base, "observation_keys", ()))
    if cfg.algo == "residual" and extra:
        raise FinetuneError(
            f"algo 'residual' cannot fine-tune tracker {cfg.tracker!r}: it reads the "
            f"observation key(s) {list(extra)}, which the residual tracker does not serve; "
            f"use algo 'ppo' or 'group'",
            ["algo", "tracker"],
        )
    return base


def _root(cfg: FinetuneConfig) -> str:
    if cfg.data_root:
        if not Path(cfg.data_root).is_dir():
            raise FinetuneError(f"data_root {cfg.data_root} is not a directory", ["data_root"])
        return cfg.data_root
    return str(ensure_world(preset=cfg.preset, sensor=cfg.sensor, seed=cfg.world_seed))


def _setting(cfg: FinetuneConfig):
    try:
        return get_setting(cfg.setting)
    except ValueError as exc:
        raise FinetuneError(str(exc), ["setting"]) from None


def check_out_dir(
    out: str | Path, cfg: FinetuneConfig, *, resume: bool = False, overwrite: bool = False
) -> dict[str, Any] | None:
    """Refuse what would silently lose or mix results (:func:`training.rundir.prepare_run_dir`
    with :data:`~training.rundir.FINETUNE_LAYOUT`), after validating ``cfg``.

    Returns the saved state's metadata when resuming (None for a run from the beginning: a
    fresh one, or a resume of a directory killed before its first checkpoint). ``resume``
    needs a saved state whose config equals ``cfg`` except :data:`RESUMABLE` fields."""
    cfg.validate()
    if resume and cfg.algo == "residual":
        raise FinetuneError("--resume is only available for algo ppo and group", ["algo"])
    try:
        state = prepare_run_dir(out, FINETUNE_LAYOUT, resume=resume, overwrite=overwrite)
    except RunDirError as exc:
        raise FinetuneError(str(exc)) from None
    if state is None:
        return None
    meta = read_state_meta(state)
    # a field added since the run was saved had its default then
    saved = {**FinetuneConfig().to_dict(), **meta["identity"]}
    given = _identity(cfg)
    keys = sorted(k for k in set(saved) | set(given) if k not in RESUMABLE)
    diffs = [k for k in keys if saved.get(k) != given.get(k)]
    if diffs:
        listed = "; ".join(f"{k}: saved {saved.get(k)!r}, given {given.get(k)!r}" for k in diffs)
        raise FinetuneError(
            f"--resume refused: {out} holds a run with another tracker or config ({listed})",
            [k for k in diffs if k in given and k != "tracker_sha256"],
        )
    return meta


# --------------------------------------------------------------------------- data and envs


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


# --------------------------------------------------------------------------- PPO


def _finite_params(module: torch.nn.Module) -> str | None:
    for name, p in module.named_parameters():
        if not torch.isfinite(p).all():
            return name
    return None


class _RunCallback(BaseCallback):
    """Progress bar, ``log.jsonl``, resume checkpoints, snapshots and NaN checks of a
    :class:`PPORun`, as an SB3 callback."""

    def __init__(self, run: PPORun) -> None:
        super().__init__()
        self.run = run

    def _on_step(self) -> bool:
        return self.run.on_step(self.locals)

    def _on_rollout_start(self) -> None:
        self.run.after_update()

    def _on_rollout_end(self) -> None:
        self.run.check_rollout()


class PPORun:
    """One PPO / GroupPPO fine-tuning run (see :func:`finetune`); ``base``: the base tracker
    (default: :func:`load_base` of ``cfg``); ``resume_meta``: the saved state's metadata
    (:func:`check_out_dir`) to continue from."""

    def __init__(
        self,
        cfg: FinetuneConfig,
        out: Path,
        make_env: Callable[[], gym.Env],
        *,
        base: torch.nn.Module | None = None,
        resume_meta: dict[str, Any] | None = None,
        progress: bool = False,
        log: Callable[[str], Any] = print,
    ) -> None:
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
                "tracker": load_base(cfg) if base is None else base,
                "train_parts": cfg.train_parts,
                "log_std_init": cfg.log_std_init,
                "action_mode": cfg.action_mode,
                "critic": cfg.critic,
                "tracker_lr_scale": cfg.tracker_lr / cfg.lr if cfg.lr else 0.0,
            },
        )
        if cfg.logger_formats:
            # SB3's own logger (TensorBoard, CSV, JSON), one folder per attempt: its CSV and
            # JSON writers start their files afresh, so a resume must not reuse the folder
            folder = out / "sb3" / f"from-{steps0:08d}"
            self.model.set_logger(configure(str(folder), cfg.logger_formats))
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
        # start-up, like the imports and the model build: the first reset would load them
        load_kernels(self.policy.tracker)
        self.t0 = time.perf_counter()
        self.steps_at_start = steps0
        self.ious: list[float] = []
        self.bar: tqdm | None = None
        self.log_file: Any = None

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
        self._log_scalars(record)
        if self.bar is not None:
            kl = record.get("approx_kl")
            self.bar.set_postfix_str(
                f"ep_reward {record['ep_reward'] or float('nan'):.2f} iou "
                f"{record['iou'] or float('nan'):.3f} kl "
                f"{float('nan') if kl is None else kl:.4f} {record['steps_per_s']:.1f} steps/s"
            )

    def _log_scalars(self, record: dict[str, Any]) -> None:
        """The update's record through SB3's logger (``rollout/``, ``train/``, ``time/``
        scalars; the ``train/`` ones SB3's update recorded), one row per update at its step."""
        logger = self.model.logger
        for key, name in (("ep_reward", "rollout/ep_rew_mean"), ("ep_len", "rollout/ep_len_mean"),
                          ("iou", "rollout/iou"), ("steps_per_s", "time/steps_per_s"),
                          ("update", "time/updates")):  # fmt: skip
            if record[key] is not None:
                logger.record(name, record[key])
        logger.dump(step=record["step"])

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
    def run(self) -> FinetuneResult:
        cfg = self.cfg
        truncate_log(self.out / "log.jsonl", self.steps_at_start)
        self.log_file = open(self.out / "log.jsonl", "a")  # noqa: SIM115 - closed below
        if self.progress:
            self.bar = tqdm(
                total=cfg.timesteps,
                initial=min(self.steps_at_start, cfg.timesteps),
                unit="step",
                desc=f"finetune {cfg.algo}",
                dynamic_ncols=True,
            )
        callback = _RunCallback(self)
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
                    # log_interval=None: one logger row per update, written by _log_update
                    self.model.learn(
                        remaining,
                        callback=callback,
                        reset_num_timesteps=False,
                        progress_bar=False,
                        log_interval=None,
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


# --------------------------------------------------------------------------- the driver


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

    ``make_env`` (tests, custom data): a factory of unwrapped ``TrackingEnv`` s
    to train on, instead of the train split of ``cfg``'s world; the val check is then skipped.
    Raises :class:`FinetuneError` (bad config, bad base tracker, refused run directory, resume
    mismatch) before anything is built or written, and :class:`NonFiniteError` when a NaN
    appears (naming the step)."""
    out = Path(out)
    cfg.validate()
    base = load_base(cfg)
    if make_env is None:
        if cfg.data_root:
            _root(cfg)  # a missing data root is refused before the run directory is touched
        check_finetune_categories(base, cfg.setting, cfg.allow_held_out)
    resume_meta = check_out_dir(out, cfg, resume=resume, overwrite=overwrite)
    if resume_meta and resume_meta.get("finished") and resume_meta["timesteps"] >= cfg.timesteps:
        log(
            f"{out} already finished at step {resume_meta['timesteps']} (>= timesteps "
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
    if cfg.threads is None:  # recorded in config.json as the count that ran
        cfg = dataclasses.replace(cfg, threads=usable_cores())
    if not str(cfg.device).startswith("cuda"):  # the update's big activations (allocator doc)
        retain_freed_memory()
    factory = make_env or train_env_factory(cfg, base.env_options, observation_keys_for([base]))
    out.mkdir(parents=True, exist_ok=True)
    remove_stale_temps(out)
    atomic_write_text(out / "config.json", json.dumps(_identity(cfg), indent=2) + "\n")
    with torch_threads(cfg.threads):
        if cfg.algo == "residual":
            result = _finetune_residual(cfg, base, out, factory)
        else:
            run = PPORun(
                cfg, out, factory, base=base, resume_meta=resume_meta, progress=progress, log=log
            )
            result = run.run()
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
    return trackers.load(out / "tracker.safetensors")


def val_check(cfg: FinetuneConfig, base: Any, tuned: Any, out: Path) -> dict[str, Any]:
    """Base and fine-tuned tracker on the first ``val_max_tracklets`` observed-category val
    tracklets, eval seed 0 (a quick check only: too few tracklets to tell a gain from noise;
    the protocol in docs/notes/rl-runs.md is what measures one); each with its ``env_options``."""
    setting = _setting(cfg)
    data = KittiTracking(_root(cfg), "val", list(setting.observed))
    result: dict[str, Any] = {}
    for name, tracker in (("base", base), ("finetuned", tuned)):
        env = make_tracking_env(
            data,
            setting=setting,
            categories=setting.observed,
            observation_keys=observation_keys_for([tracker]),
            **env_options_for([tracker]),
        )
        subset = list(range(min(cfg.val_max_tracklets, env.num_tracklets)))
        rep = evaluate(tracker, env, tracklets=subset, seed=0)
        result[name] = {k: rep["mean"][k] for k in ("success", "precision")}
        result["frames"], result["tracklets"] = rep["frames"], rep["tracklets"]
    atomic_write_text(out / "val.json", json.dumps(result, indent=2) + "\n")
    return result


def _finetune_residual(
    cfg: FinetuneConfig, base: Any, out: Path, make_env: Callable[[], gym.Env]
) -> FinetuneResult:
    """PPO on :class:`ResidualTrackingEnv` (one env; the base tracker frozen)."""
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
