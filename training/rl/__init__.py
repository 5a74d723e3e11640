"""RL fine-tuning of pretrained trackers with stable-baselines3 (docs/rl.md).

* :mod:`training.rl.policy`: :class:`TrackerPolicy`, the tracker as an SB3 actor-critic policy.
* :mod:`training.rl.group_ppo`: :class:`GroupPPO` (several sampled actions per state) and its
  buffer :class:`GroupRollout`.
* :mod:`training.rl.wrappers`: the env / ``VecEnv`` wrappers (:class:`SelfCriticalReward`) and
  the residual variant (:class:`ResidualTracker`).
* :mod:`training.rl.config`: :class:`FinetuneConfig` and its validation.
* :mod:`training.rl.run`: the ``pointtrack finetune`` driver (run directory, resume, val
  check); :mod:`training.rl.state` its resume state.

The algorithm pieces are importable from here (``from training.rl import TrackerPolicy``).
"""

from training.rl.group_ppo import GroupPPO, GroupRollout
from training.rl.policy import (
    ACTION_MODES,
    CRITICS,
    TRAIN_PARTS,
    ScaledAdam,
    TrackerPolicy,
    lr_scaled,
    resolve_tracker,
)
from training.rl.wrappers import ResidualTracker, SelfCriticalReward

__all__ = [
    "ACTION_MODES",
    "CRITICS",
    "TRAIN_PARTS",
    "GroupPPO",
    "GroupRollout",
    "ResidualTracker",
    "ScaledAdam",
    "SelfCriticalReward",
    "TrackerPolicy",
    "lr_scaled",
    "resolve_tracker",
]
