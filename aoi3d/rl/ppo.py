"""The PPO update of the single-step agent, top to bottom (CleanRL style).

Offline training (:func:`aoi3d.rl.train.train`: a batch of env episodes) and online learning
(:class:`aoi3d.rl.online.OnlineLearner`: a batch of the live scheduler's rewarded decisions)
both end in :func:`update` on a :class:`~aoi3d.rl.batch.Batch` of one-step episodes.

PPO with γ = 1 on one-step episodes reduces to:

- return  G = r (no bootstrapping, nothing after the single step);
- advantage  A = r − V(s), normalised within the batch when it holds more than one episode;
- the clipped surrogate  L = E[max(−A·ρ, −A·clip(ρ, 1 − ε, 1 + ε))], ρ = π(a|s) / π_old(a|s),
  over ``update_epochs`` passes of shuffled minibatches, plus ``vf_coef``·½(V(s) − r)² and
  minus ``ent_coef``·entropy, with the gradient norm clipped to ``max_grad_norm``.

π(a|s) = Π_n Bernoulli(a_n; σ(logit_n)): the log-probabilities and entropies are sums over
the N camera bits. The minibatch order comes from the agent's generator.
"""

from __future__ import annotations

from typing import TYPE_CHECKING

import numpy as np
import torch
from torch import nn

from aoi3d.rl.batch import Batch

if TYPE_CHECKING:
    from aoi3d.rl.agent import SingleStepPPO

__all__ = ["STATS", "update"]

STATS = ("policy_loss", "value_loss", "entropy", "approx_kl", "clip_frac")
"""The per-minibatch statistics :func:`update` averages (it adds ``mean_reward``)."""


def update(agent: SingleStepPPO, batch: Batch) -> dict[str, float]:
    """One PPO update of ``agent`` on ``batch``; counts the episodes and the update on the
    agent. Returns the mean over minibatches of :data:`STATS` and the batch's
    ``mean_reward``. A malformed batch raises ``ValueError`` before anything changes."""
    cfg = agent.config
    # --- the batch, checked
    x = agent.obs_tensor(batch.obs, batch=True)
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
    act_t = torch.as_tensor(a, dtype=torch.float32, device=agent.device)
    logp_t = torch.as_tensor(old_logp, device=agent.device)
    ret_t = torch.as_tensor(ret, device=agent.device)

    # --- advantages: γ = 1 and one step, so the return is the reward
    with torch.no_grad():
        adv = ret_t - agent.net.value(x)
        if cfg.norm_adv and b > 1:
            adv = (adv - adv.mean()) / (adv.std() + 1e-8)

    # --- epochs of shuffled minibatches
    sums = dict.fromkeys(STATS, 0.0)
    count = 0
    mb = min(cfg.minibatch_size, b)
    agent.net.train()
    for _ in range(cfg.update_epochs):
        order = torch.randperm(b, generator=agent.generator).to(agent.device)
        for start in range(0, b, mb):
            idx = order[start:start + mb]
            new_logp, entropy, new_value = agent.net.evaluate(x[idx], act_t[idx])
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
            agent.optimizer.zero_grad(set_to_none=True)
            loss.backward()
            nn.utils.clip_grad_norm_(agent.net.parameters(), cfg.max_grad_norm)
            agent.optimizer.step()
            for key, val in zip(STATS, (pg_loss, v_loss, ent, approx_kl, clip_frac),
                                strict=True):
                sums[key] += float(val.detach())
            count += 1
    agent.net.eval()

    # --- bookkeeping
    agent.episodes += b
    agent.updates += 1
    stats = {k: v / count for k, v in sums.items()}
    stats["mean_reward"] = float(ret.mean())
    return stats
