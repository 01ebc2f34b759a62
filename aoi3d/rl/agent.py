"""The learning agent: the paper's single-step PPO over N independent Bernoulli bits.

The frame-selection problem is a contextual bandit: the agent sees the AoI vector once
(:func:`aoi3d.policy.obs.encode_aoi`), picks a subset of the N cameras, and the episode ends
with one reward (the quality of the novel view). :class:`SingleStepPPO` is the network of
:class:`aoi3d.policy.actor.Actor` (what a ``ppo`` policy acts with) plus what learning
needs: actions sampled from one ``torch.Generator``, an Adam optimizer, the PPO update
(:func:`aoi3d.rl.ppo.update`, the one place the loss is written) and checkpoints that hold
all of it.

Everything random — the initial weights, the sampled actions, the minibatch order — comes
from the one generator seeded from ``PPOConfig.seed``, so a run is reproducible and a
checkpoint (which stores the generator's state) resumes the same stream.
"""

from __future__ import annotations

import os
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import torch

from aoi3d.policy.actor import CHECKPOINT_FORMAT, CHECKPOINT_VERSION, Actor
from aoi3d.policy.ppo import PPOConfig
from aoi3d.rl import ppo
from aoi3d.rl.batch import Batch

__all__ = ["CHECKPOINT_FORMAT", "CHECKPOINT_VERSION", "Act", "PPOConfig", "SingleStepPPO"]


@dataclass(frozen=True)
class Act:
    """One action of the agent and what PPO needs to learn from it.

    ``action``: int8 0/1 per camera; ``logp``: log π(action|obs); ``value``: V(obs);
    ``entropy``: the policy's entropy at obs (nats, summed over the N bits); ``probs``: the
    per-camera selection probabilities.
    """

    action: np.ndarray
    logp: float
    value: float
    entropy: float
    probs: np.ndarray


class SingleStepPPO(Actor):
    """The agent: act on an AoI observation, learn from batches of one-step episodes.

    ``episodes`` counts the episodes learned so far (the sum of the batch sizes given to
    :meth:`update`), ``updates`` the calls to it. Not thread-safe: a caller that acts and
    learns from several threads holds a lock around both.
    """

    def __init__(self, config: PPOConfig, device: str = "cpu") -> None:
        super().__init__(config, device)
        self.optimizer = torch.optim.Adam(self.net.parameters(), lr=config.lr, eps=1e-5)

    @torch.no_grad()
    def act(self, obs: np.ndarray, *, deterministic: bool = False) -> Act:
        """Select cameras for one observation: sample the N bits (from the agent's generator),
        or with ``deterministic`` take bit n = (p_n ≥ 0.5)."""
        x = self.obs_tensor(obs, batch=False)
        logits = self.net.logits(x)
        probs = torch.sigmoid(logits).cpu()
        if deterministic:
            bits = (probs >= 0.5).to(torch.float32)
        else:
            bits = torch.bernoulli(probs, generator=self.generator)
        dist = torch.distributions.Bernoulli(logits=logits.cpu())
        return Act(
            action=bits.numpy().astype(np.int8),
            logp=float(dist.log_prob(bits).sum()),
            value=float(self.net.value(x)),
            entropy=float(dist.entropy().sum()),
            probs=probs.numpy().astype(np.float64),
        )

    def update(self, obs: np.ndarray, actions: np.ndarray, logp: np.ndarray,
               rewards: np.ndarray) -> dict[str, float]:
        """One PPO update on a batch of B one-step episodes (:func:`aoi3d.rl.ppo.update`):
        ``obs`` (B, 2N), ``actions`` (B, N) of 0/1, ``logp`` (B,) the log-probabilities under
        the policy that acted, ``rewards`` (B,). Returns the update's statistics."""
        return ppo.update(self, Batch(obs, actions, logp, rewards))

    # --- checkpoints ---------------------------------------------------------------------
    def state(self, extra: dict[str, Any] | None = None) -> dict[str, Any]:
        """Everything :meth:`save` writes (tensors on the CPU)."""
        return {
            "format": CHECKPOINT_FORMAT,
            "version": CHECKPOINT_VERSION,
            "config": self.config.to_dict(),
            "episodes": self.episodes,
            "updates": self.updates,
            "model": {k: v.detach().cpu() for k, v in self.net.state_dict().items()},
            "optimizer": _to_cpu(self.optimizer.state_dict()),
            "generator": self.generator.get_state(),
            "extra": dict(extra or {}),
        }

    def save(self, path: str | Path, *, extra: dict[str, Any] | None = None) -> None:
        """Write a checkpoint atomically (temporary file, then rename): weights, optimizer
        state, config, episodes learned, the generator's state and the format version.
        ``extra``: plain data (numbers, strings, lists, dicts, tensors) kept alongside, e.g. a
        training loop's position."""
        path = Path(path)
        path.parent.mkdir(parents=True, exist_ok=True)
        tmp = path.with_name(f".{path.name}.{os.getpid()}.tmp")
        try:
            torch.save(self.state(extra), tmp)
            os.replace(tmp, path)
        finally:
            tmp.unlink(missing_ok=True)

    def restore(self, doc: dict[str, Any]) -> None:
        """Weights, counts, optimizer state and the generator's position of a checkpoint."""
        super().restore(doc)
        self.optimizer.load_state_dict(doc["optimizer"])
        self.generator.set_state(doc["generator"])

    def copy(self) -> SingleStepPPO:
        """A second agent with this one's config, weights and generator state (not its
        optimizer state): e.g. one that acts while this one learns."""
        twin = SingleStepPPO(self.config, device=str(self.device))
        twin.net.load_state_dict(self.net.state_dict())
        twin.generator.set_state(self.generator.get_state())
        twin.net.eval()
        return twin


def _to_cpu(obj: Any) -> Any:
    """A copy of a (nested) optimizer state with every tensor on the CPU."""
    if isinstance(obj, torch.Tensor):
        return obj.detach().cpu()
    if isinstance(obj, dict):
        return {k: _to_cpu(v) for k, v in obj.items()}
    if isinstance(obj, list | tuple):
        return type(obj)(_to_cpu(v) for v in obj)
    return obj
