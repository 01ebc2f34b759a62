"""The learning side of the agent (imports torch): the paper's single-step PPO.

The frame-selection problem is a contextual bandit: the agent sees the AoI vector once
(:func:`aoi3d.policy.ppo.obs.encode_aoi`), picks a subset of the N cameras, and the episode
ends with one reward (the quality of the novel view). :class:`PPOLearner` is an
:class:`~aoi3d.policy.ppo.actor.Actor` (the network a ``ppo`` policy acts with) plus what
learning needs: actions sampled from one ``torch.Generator`` (:meth:`PPOLearner.sample`),
an Adam optimizer, the PPO update (:meth:`PPOLearner.update`, the one place the loss is
written) and checkpoints that hold all of it
(:class:`~aoi3d.policy.ppo.checkpoint.Checkpoint`).

Offline training (:func:`aoi3d.rl.train.train`: a batch of env episodes) and online learning
(:class:`aoi3d.rl.online.OnlineLearner`: a batch of the live scheduler's rewarded decisions)
both end in :meth:`PPOLearner.update` on a :class:`~aoi3d.policy.ppo.batch.Batch` of one-step
episodes. PPO with γ = 1 on one-step episodes reduces to:

- return  G = r (no bootstrapping, nothing after the single step);
- advantage  A = r − V(s), normalised within the batch when it holds more than one episode;
- the clipped surrogate  L = E[max(−A·ρ, −A·clip(ρ, 1 − ε, 1 + ε))], ρ = π(a|s) / π_old(a|s),
  over ``update_epochs`` passes of shuffled minibatches, plus ``vf_coef``·½(V(s) − r)² and
  minus ``ent_coef``·entropy, with the gradient norm clipped to ``max_grad_norm``.

π(a|s) = Π_n Bernoulli(a_n; σ(logit_n)): the log-probabilities and entropies are sums over
the N camera bits.

Everything random — the initial weights, the sampled actions, the minibatch order — comes
from the one generator seeded from ``PPOConfig.seed``, so a run is reproducible and a
checkpoint (which stores the generator's state) resumes the same stream.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import torch
from torch import nn

from aoi3d.policy.ppo.actor import Actor
from aoi3d.policy.ppo.batch import Batch
from aoi3d.policy.ppo.checkpoint import Checkpoint
from aoi3d.policy.ppo.config import AgentConfig, PPOConfig

__all__ = ["STATS", "PPOLearner", "Sample"]

STATS = ("policy_loss", "value_loss", "entropy", "approx_kl", "clip_frac")
"""The per-minibatch statistics :meth:`PPOLearner.update` averages (it adds
``mean_reward``)."""


@dataclass(frozen=True)
class Sample:
    """One sampled action of the learner and what PPO needs to learn from it.

    ``action``: int8 0/1 per camera; ``logp``: log π(action|obs); ``value``: V(obs);
    ``entropy``: the policy's entropy at obs (nats, summed over the N bits); ``probs``: the
    per-camera selection probabilities.
    """

    action: np.ndarray
    logp: float
    value: float
    entropy: float
    probs: np.ndarray


class PPOLearner(Actor):
    """The agent that learns: sample actions on AoI observations, update from batches of
    one-step episodes, checkpoint.

    ``episodes`` counts the episodes learned so far (the sum of the batch sizes given to
    :meth:`update`), ``updates`` the calls to it. Not thread-safe: a caller that samples and
    learns from several threads holds a lock around both.
    """

    config: PPOConfig

    def __init__(self, config: PPOConfig, device: str = "cpu") -> None:
        if not isinstance(config, PPOConfig):
            raise TypeError(f"config must be a PPOConfig, got {type(config).__name__}")
        super().__init__(config, device)
        self.optimizer = torch.optim.Adam(self.net.parameters(), lr=config.lr, eps=1e-5)

    @torch.no_grad()
    def sample(self, obs: np.ndarray) -> Sample:
        """Sample the N bits for one observation (from the learner's generator)."""
        x = self.obs_tensor(obs, batch=False)
        logits = self.net.logits(x)
        probs = torch.sigmoid(logits).cpu()
        bits = torch.bernoulli(probs, generator=self.generator)
        dist = torch.distributions.Bernoulli(logits=logits.cpu())
        return Sample(
            action=bits.numpy().astype(np.int8),
            logp=float(dist.log_prob(bits).sum()),
            value=float(self.net.value(x)),
            entropy=float(dist.entropy().sum()),
            probs=probs.numpy().astype(np.float64),
        )

    def update(self, batch: Batch) -> dict[str, float]:
        """One PPO update on ``batch`` (see the module docstring); counts the episodes and the
        update. Returns the mean over minibatches of :data:`STATS` and the batch's
        ``mean_reward``. A malformed batch raises ``ValueError`` before anything changes."""
        cfg = self.config
        # --- the batch, checked
        x = self.obs_tensor(batch.obs, batch=True)
        b = x.shape[0]
        a = np.asarray(batch.actions)
        if a.shape != (b, cfg.n_cameras) or not np.isin(a, (0, 1)).all():
            raise ValueError(f"actions must be 0/1 of shape ({b}, {cfg.n_cameras}), "
                             f"got shape {a.shape}")
        old_logp = np.asarray(batch.logp, dtype=np.float32)
        ret = np.asarray(batch.rewards, dtype=np.float32)
        for name, arr in (("logp", old_logp), ("rewards", ret)):
            if arr.shape != (b,) or not np.all(np.isfinite(arr)):
                raise ValueError(f"{name} must be {b} finite numbers, got shape {arr.shape}")
        act_t = torch.as_tensor(a, dtype=torch.float32, device=self.device)
        logp_t = torch.as_tensor(old_logp, device=self.device)
        ret_t = torch.as_tensor(ret, device=self.device)

        # --- advantages: γ = 1 and one step, so the return is the reward
        with torch.no_grad():
            adv = ret_t - self.net.value(x)
            if cfg.norm_adv and b > 1:
                adv = (adv - adv.mean()) / (adv.std() + 1e-8)

        # --- epochs of shuffled minibatches
        sums = dict.fromkeys(STATS, 0.0)
        count = 0
        mb = min(cfg.minibatch_size, b)
        self.net.train()
        for _ in range(cfg.update_epochs):
            order = torch.randperm(b, generator=self.generator).to(self.device)
            for start in range(0, b, mb):
                idx = order[start:start + mb]
                new_logp, entropy, new_value = self.net.evaluate(x[idx], act_t[idx])
                log_ratio = new_logp - logp_t[idx]
                ratio = log_ratio.exp()
                with torch.no_grad():
                    approx_kl = ((ratio - 1.0) - log_ratio).mean()
                    clip_frac = ((ratio - 1.0).abs() > cfg.clip_eps).float().mean()
                mb_adv = adv[idx]
                pg_loss = torch.max(
                    -mb_adv * ratio,
                    -mb_adv * torch.clamp(ratio, 1.0 - cfg.clip_eps, 1.0 + cfg.clip_eps),
                ).mean()
                v_loss = 0.5 * ((new_value - ret_t[idx]) ** 2).mean()
                ent = entropy.mean()
                loss = pg_loss - cfg.ent_coef * ent + cfg.vf_coef * v_loss
                self.optimizer.zero_grad(set_to_none=True)
                loss.backward()
                nn.utils.clip_grad_norm_(self.net.parameters(), cfg.max_grad_norm)
                self.optimizer.step()
                for key, val in zip(STATS, (pg_loss, v_loss, ent, approx_kl, clip_frac),
                                    strict=True):
                    sums[key] += float(val.detach())
                count += 1
        self.net.eval()

        # --- bookkeeping
        self.episodes += b
        self.updates += 1
        stats = {k: v / count for k, v in sums.items()}
        stats["mean_reward"] = float(ret.mean())
        return stats

    # --- checkpoints ---------------------------------------------------------------------
    def checkpoint(self, extra: dict[str, Any] | None = None) -> Checkpoint:
        """Everything :meth:`save` writes: config, counts, weights, optimizer state, the
        generator's state and ``extra``."""
        return Checkpoint(config=self.config.to_dict(), episodes=self.episodes,
                          updates=self.updates, model=self.net.state_dict(),
                          optimizer=self.optimizer.state_dict(),
                          generator=self.generator.get_state(), extra=dict(extra or {}))

    def save(self, path: str | Path, *, extra: dict[str, Any] | None = None) -> None:
        """Write a checkpoint atomically. ``extra``: plain data (numbers, strings, lists,
        dicts, tensors) kept alongside, e.g. a training loop's position."""
        self.checkpoint(extra).write(path)

    @staticmethod
    def _config_of(stored: PPOConfig) -> AgentConfig:
        return stored  # the learner keeps the update's hyper-parameters too

    def restore(self, ckpt: Checkpoint) -> None:
        """Weights, counts, optimizer state and the generator's position of a checkpoint."""
        super().restore(ckpt)
        self.optimizer.load_state_dict(ckpt.optimizer)
        self.generator.set_state(ckpt.generator)

    def copy(self) -> PPOLearner:
        """A second learner with this one's config, weights and generator state (not its
        optimizer state): e.g. one that samples while this one learns."""
        twin = PPOLearner(self.config, device=str(self.device))
        twin.net.load_state_dict(self.net.state_dict())
        twin.generator.set_state(self.generator.get_state())
        twin.net.eval()
        return twin
