"""PPO checkpoints whose choice is known in advance (the scheduler's PPO tests, the live one)."""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path

import torch

from aoi3d.policy.ppo import PPOConfig
from aoi3d.policy.ppo.learner import PPOLearner


def make_subset_checkpoint(path: Path, *, n_cameras: int, subset: Sequence[int],
                           seed: int = 0, logit: float = 8.0) -> Path:
    """A checkpoint whose policy selects exactly the camera ids in ``subset`` whatever the
    AoI: the actor's last layer is zeroed and its bias set to ±``logit`` (p ≈ 0.9997 at 8).

    Reaches into the agent's network (``net.actor``, an ``nn.Sequential`` ending in the
    logits layer), which is what makes the selection known in advance."""
    agent = PPOLearner(PPOConfig(n_cameras=n_cameras, seed=seed))
    head = agent.net.actor[-1]
    with torch.no_grad():
        head.weight.zero_()
        head.bias.copy_(torch.tensor([logit if cam in subset else -logit
                                      for cam in range(1, n_cameras + 1)]))
    agent.save(path)
    return path
