"""The agent's network (imports torch): an actor and a critic, as in CleanRL's ``ppo.py``.

:class:`ActorCritic` maps the observation (:func:`aoi3d.policy.ppo.obs.encode_aoi`) to N
logits — one Bernoulli bit per camera — and to V, with separate tanh MLPs; the actor is a
plain MLP (``arch="mlp"``) or :class:`SharedCameraActor` (``arch="shared"``). The last actor
layer's bias starts at logit(``init_select_p``) and its weights near zero, so the untrained
policy picks each camera with an even chance. Every initial weight is drawn from the
``torch.Generator`` passed in.
"""

from __future__ import annotations

import math

import torch
from torch import nn

from aoi3d.policy.ppo.config import AgentConfig

__all__ = ["ActorCritic", "SharedCameraActor"]


def _layer(n_in: int, n_out: int, gain: float, gen: torch.Generator, bias: float = 0.0
           ) -> nn.Linear:
    """A linear layer with orthogonal weights (CleanRL's ``layer_init``), drawn from ``gen``."""
    layer = nn.Linear(n_in, n_out)
    with torch.no_grad():
        nn.init.orthogonal_(layer.weight, gain, generator=gen)
        layer.bias.fill_(bias)
    return layer


class SharedCameraActor(nn.Module):
    """Logits from one small MLP shared by all cameras (permutation-equivariant).

    Camera n's logit is ``g([x_n, c, e_n]) + b_n``: ``x_n`` = (scaled AoI, unknown flag, and
    the camera's fixed features when the agent observes any, the lag to the display when it
    observes it) of camera n, ``c`` = the mean of
    ``x`` over the cameras (the context: how fresh the others
    are), ``e_n`` a learned embedding of the camera (its place in the rig), ``b_n`` its bias.
    Every episode then teaches the one function g with N samples — what the rule "use camera
    n iff its frame is fresh enough, given the others" needs — instead of N separate ones.
    """

    def __init__(self, cfg: AgentConfig, gen: torch.Generator, bias: float) -> None:
        super().__init__()
        n, h, e = cfg.n_cameras, cfg.hidden, 4
        self.n = n
        self.channels = cfg.channels
        self.embedding = nn.Parameter(0.1 * torch.randn(n, e, generator=gen))
        self.bias = nn.Parameter(torch.full((n,), bias))
        self.g = nn.Sequential(
            _layer(2 * self.channels + e, h, math.sqrt(2), gen), nn.Tanh(),
            _layer(h, h, math.sqrt(2), gen), nn.Tanh(),
            _layer(h, 1, 0.01, gen),
        )

    def forward(self, obs: torch.Tensor) -> torch.Tensor:
        # (..., C·N) value-major → (..., N, C)
        x = obs.unflatten(-1, (self.channels, self.n)).transpose(-1, -2)
        ctx = x.mean(dim=-2, keepdim=True).expand_as(x)
        emb = self.embedding.expand(*x.shape[:-1], self.embedding.shape[-1])
        scores: torch.Tensor = self.g(torch.cat([x, ctx, emb], dim=-1)).squeeze(-1) + self.bias
        return scores


class ActorCritic(nn.Module):
    """Actor (obs → N logits) and critic (obs → V): separate networks, tanh MLPs.

    The actor is a plain MLP over the whole observation (``arch="mlp"``, CleanRL's) or the
    camera-shared :class:`SharedCameraActor` (``arch="shared"``).
    """

    def __init__(self, cfg: AgentConfig, gen: torch.Generator) -> None:
        super().__init__()
        h = cfg.hidden
        bias = math.log(cfg.init_select_p / (1.0 - cfg.init_select_p))
        if cfg.arch == "shared":
            self.actor: nn.Module = SharedCameraActor(cfg, gen, bias)
        else:
            self.actor = nn.Sequential(
                _layer(cfg.obs_dim, h, math.sqrt(2), gen), nn.Tanh(),
                _layer(h, h, math.sqrt(2), gen), nn.Tanh(),
                _layer(h, cfg.n_cameras, 0.01, gen, bias=bias),
            )
        self.critic = nn.Sequential(
            _layer(cfg.obs_dim, h, math.sqrt(2), gen), nn.Tanh(),
            _layer(h, h, math.sqrt(2), gen), nn.Tanh(),
            _layer(h, 1, 1.0, gen),
        )

    def logits(self, obs: torch.Tensor) -> torch.Tensor:
        logits: torch.Tensor = self.actor(obs)
        return logits

    def value(self, obs: torch.Tensor) -> torch.Tensor:
        value: torch.Tensor = self.critic(obs).squeeze(-1)
        return value

    def evaluate(self, obs: torch.Tensor, actions: torch.Tensor
                 ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """log π(actions|obs), entropy (both summed over the bits) and V(obs), per row."""
        dist = torch.distributions.Bernoulli(logits=self.logits(obs))
        return (dist.log_prob(actions).sum(-1), dist.entropy().sum(-1), self.value(obs))
