"""The one-step episodes a PPO update learns from (plain data: no torch here).

An :class:`Episode` is one decision and its reward; a :class:`Batch` is B of them as arrays,
what :meth:`aoi3d.policy.ppo.learner.PPOLearner.update` takes. Offline training collects a
batch from the env workers, the online learner from the scheduler's rewarded decisions.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

__all__ = ["Batch", "Episode"]


@dataclass(frozen=True)
class Episode:
    """One finished one-step episode: the observation, the action taken, its log π under
    the policy that acted, and the reward."""

    obs: np.ndarray
    action: np.ndarray
    logp: float
    reward: float


@dataclass(frozen=True)
class Batch:
    """B episodes as arrays: ``obs`` (B, 2N), ``actions`` (B, N) of 0/1, ``logp`` (B,),
    ``rewards`` (B,)."""

    obs: np.ndarray
    actions: np.ndarray
    logp: np.ndarray
    rewards: np.ndarray

    @classmethod
    def of(cls, episodes: Sequence[Episode]) -> Batch:
        return cls(obs=np.stack([e.obs for e in episodes]),
                   actions=np.stack([e.action for e in episodes]),
                   logp=np.array([e.logp for e in episodes], dtype=np.float64),
                   rewards=np.array([e.reward for e in episodes], dtype=np.float64))
