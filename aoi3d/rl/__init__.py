"""Reinforcement learning of the frame selection: the environment and the training loops of
the paper's single-step PPO agent.

The agent itself — its config, network, observation, checkpoints, sampling and the PPO
update — lives in one home, :mod:`aoi3d.policy.ppo` (the ``ppo`` policy is its acting side);
this package trains it:

- :mod:`~aoi3d.rl.env` — the gymnasium environment ``aoi3d/FrameSelection-v0`` over the
  experiment engine's virtual-clock episode (imported lazily: it pulls in the radiance
  field);
- :mod:`~aoi3d.rl.train` — batched offline training, resume; :mod:`~aoi3d.rl.runner` (env
  workers), :mod:`~aoi3d.rl.presets` (budgets, seeds, the training config),
  :mod:`~aoi3d.rl.record` (episode CSV, reward plot);
- :mod:`~aoi3d.rl.online` — :class:`~aoi3d.rl.online.OnlineLearner`: learning from the live
  scheduler's rewarded decisions (pending episodes, reward matching, batches, checkpoints);
- :mod:`~aoi3d.rl.evaluate` — scoring on held-out seeds.

Importing this package registers the environment id with gymnasium (by entry point, so the
environment module loads only when ``gymnasium.make`` builds one).
"""

import gymnasium

ENV_ID = "aoi3d/FrameSelection-v0"

if ENV_ID not in gymnasium.registry:
    gymnasium.register(id=ENV_ID, entry_point="aoi3d.rl.env:FrameSelectionEnv")

__all__ = ["ENV_ID"]
