"""Reinforcement learning of the frame selection: the paper's single-step PPO agent.

- :mod:`~aoi3d.rl.obs` — the observation (normalised AoI vector, unknowns flagged);
- :mod:`~aoi3d.rl.agent` — :class:`SingleStepPPO` (N Bernoulli bits, γ = 1, clipped
  surrogate) and its checkpoints;
- :mod:`~aoi3d.rl.policy` — ``ppo:<checkpoint>`` as a :class:`aoi3d.policy.Policy`;
- :mod:`~aoi3d.rl.env` — the gymnasium environment ``aoi3d/FrameSelection-v0`` over the
  experiment engine's virtual-clock episode (imported lazily: it pulls in the radiance
  field);
- :mod:`~aoi3d.rl.train` — the PPO presets, batched training on a pool of env workers,
  evaluation on held-out seeds.

Importing this package registers the environment id with gymnasium (by entry point, so the
environment module loads only when ``gymnasium.make`` builds one).
"""

import gymnasium

from aoi3d.rl.agent import Act, PPOConfig, SingleStepPPO
from aoi3d.rl.obs import encode_aoi, obs_size
from aoi3d.rl.policy import PPOPolicy

ENV_ID = "aoi3d/FrameSelection-v0"

if ENV_ID not in gymnasium.registry:
    gymnasium.register(id=ENV_ID, entry_point="aoi3d.rl.env:FrameSelectionEnv")

__all__ = ["ENV_ID", "Act", "PPOConfig", "PPOPolicy", "SingleStepPPO", "encode_aoi", "obs_size"]
