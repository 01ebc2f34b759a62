"""Reinforcement learning of the frame selection: the paper's single-step PPO agent.

- :mod:`~aoi3d.rl.agent` — :class:`SingleStepPPO`, the learning agent (the network of
  :mod:`aoi3d.policy.actor` with sampled actions, an optimizer, checkpoints);
- :mod:`~aoi3d.rl.ppo` — the PPO update, top to bottom (offline and online alike);
- :mod:`~aoi3d.rl.online` — :class:`~aoi3d.rl.online.OnlineLearner`: learning from the live
  scheduler's rewarded decisions (pending episodes, reward matching, batches, checkpoints);
- :mod:`~aoi3d.rl.env` — the gymnasium environment ``aoi3d/FrameSelection-v0`` over the
  experiment engine's virtual-clock episode (imported lazily: it pulls in the radiance
  field);
- :mod:`~aoi3d.rl.presets` (budgets, seeds, the training config), :mod:`~aoi3d.rl.pool`
  (env workers), :mod:`~aoi3d.rl.train` (batched training, resume),
  :mod:`~aoi3d.rl.record` (episode CSV, reward plot), :mod:`~aoi3d.rl.evaluate`
  (held-out seeds).

The ``ppo`` policy, its config and the observation live in :mod:`aoi3d.policy` (re-exported
here). Importing this package registers the environment id with gymnasium (by entry point,
so the environment module loads only when ``gymnasium.make`` builds one); torch loads with
the first name that needs it (:class:`SingleStepPPO`, :class:`Act`).
"""

from typing import Any

import gymnasium

from aoi3d.policy.obs import encode_aoi, obs_size
from aoi3d.policy.ppo import PPOConfig, PPOPolicy

ENV_ID = "aoi3d/FrameSelection-v0"

if ENV_ID not in gymnasium.registry:
    gymnasium.register(id=ENV_ID, entry_point="aoi3d.rl.env:FrameSelectionEnv")

_TORCH_NAMES = ("Act", "SingleStepPPO")


def __getattr__(name: str) -> Any:
    if name in _TORCH_NAMES:
        from aoi3d.rl import agent

        return getattr(agent, name)
    raise AttributeError(f"module 'aoi3d.rl' has no attribute {name!r}")


__all__ = ["ENV_ID", "Act", "PPOConfig", "PPOPolicy", "SingleStepPPO", "encode_aoi", "obs_size"]
