"""The single-step PPO agent, in one home: the ``ppo`` policy kind and what it is made of.

The acting side (what the registry loads):

- :mod:`~aoi3d.policy.ppo.policy` — :class:`PPOPolicy`, the ``ppo:<checkpoint>`` kind: a
  trained agent's deterministic action as a frame-selection policy (torch-free until a
  checkpoint loads);
- :mod:`~aoi3d.policy.ppo.actor` — :class:`~aoi3d.policy.ppo.actor.Actor`: the network of
  a checkpoint, observing an AoI vector and selecting (torch);
- :mod:`~aoi3d.policy.ppo.network` — the actor–critic networks (torch);
- :mod:`~aoi3d.policy.ppo.obs` — the observation: the AoI vector encoded.

The learning side (what :mod:`aoi3d.rl` trains with, offline and online):

- :mod:`~aoi3d.policy.ppo.learner` — :class:`~aoi3d.policy.ppo.learner.PPOLearner`: an
  Actor that samples, runs the PPO update (the one place the loss is written) and saves
  checkpoints (torch);
- :mod:`~aoi3d.policy.ppo.batch` — the one-step episodes an update learns from.

Both: :mod:`~aoi3d.policy.ppo.config` (:class:`AgentConfig`, the acting part of the
hyper-parameters; :class:`PPOConfig`, the learner's, which adds the update's) and
:mod:`~aoi3d.policy.ppo.checkpoint` (the checkpoint file, read and written there only).

Importing this package loads no torch; the torch modules are imported by name.
"""

from aoi3d.policy.ppo.batch import Batch, Episode
from aoi3d.policy.ppo.config import ARCHS, AgentConfig, PPOConfig
from aoi3d.policy.ppo.obs import encode_aoi, obs_size
from aoi3d.policy.ppo.policy import KIND, PPOPolicy

__all__ = ["ARCHS", "KIND", "AgentConfig", "Batch", "Episode", "PPOConfig", "PPOPolicy",
           "encode_aoi", "obs_size"]
