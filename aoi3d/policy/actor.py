"""The PPO agent's network and checkpoints, as far as acting needs them (imports torch).

:class:`ActorCritic` is the agent's network: an actor (observation → N logits, one Bernoulli
bit per camera) and a critic (observation → V), separate tanh MLPs as in CleanRL's
``ppo.py``; the actor is a plain MLP (``arch="mlp"``) or :class:`SharedCameraActor`
(``arch="shared"``). The last actor layer's bias starts at logit(``init_select_p``) and its
weights near zero, so the untrained policy picks each camera with an even chance.

:class:`Actor` holds one network with its config: it observes an AoI vector
(:func:`aoi3d.policy.obs.encode_aoi`) and takes the deterministic action (camera n iff
p_n ≥ 0.5) — what the ``ppo`` policy does. It reads checkpoints (:func:`read_checkpoint`
checks their format and version). The learning agent,
:class:`aoi3d.rl.agent.SingleStepPPO`, is an :class:`Actor` with an optimizer and a random
generator that samples; it writes the checkpoints this module reads.

Imported only when a ``ppo`` policy or the agent is built: :mod:`aoi3d.policy.ppo` stays
torch-free.
"""

from __future__ import annotations

import math
from pathlib import Path
from typing import Any, Self

import numpy as np
import torch
from torch import nn

from aoi3d.policy.obs import encode_aoi
from aoi3d.policy.ppo import PPOConfig

__all__ = ["CHECKPOINT_FORMAT", "CHECKPOINT_VERSION", "Actor", "ActorCritic",
           "SharedCameraActor", "read_checkpoint"]

CHECKPOINT_FORMAT = "aoi3d-ppo"
CHECKPOINT_VERSION = 1


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

    Camera n's logit is ``g([x_n, c, e_n]) + b_n``: ``x_n`` = (scaled AoI, unknown flag) of
    camera n, ``c`` = the mean of ``x`` over the cameras (the context: how fresh the others
    are), ``e_n`` a learned embedding of the camera (its place in the rig), ``b_n`` its bias.
    Every episode then teaches the one function g with N samples — what the rule "use camera
    n iff its frame is fresh enough, given the others" needs — instead of N separate ones.
    """

    def __init__(self, cfg: PPOConfig, gen: torch.Generator, bias: float) -> None:
        super().__init__()
        n, h, e = cfg.n_cameras, cfg.hidden, 4
        self.n = n
        self.embedding = nn.Parameter(0.1 * torch.randn(n, e, generator=gen))
        self.bias = nn.Parameter(torch.full((n,), bias))
        self.g = nn.Sequential(
            _layer(2 + 2 + e, h, math.sqrt(2), gen), nn.Tanh(),
            _layer(h, h, math.sqrt(2), gen), nn.Tanh(),
            _layer(h, 1, 0.01, gen),
        )

    def forward(self, obs: torch.Tensor) -> torch.Tensor:
        x = torch.stack([obs[..., : self.n], obs[..., self.n:]], dim=-1)  # (..., N, 2)
        ctx = x.mean(dim=-2, keepdim=True).expand_as(x)
        emb = self.embedding.expand(*x.shape[:-1], self.embedding.shape[-1])
        return self.g(torch.cat([x, ctx, emb], dim=-1)).squeeze(-1) + self.bias


class ActorCritic(nn.Module):
    """Actor (obs → N logits) and critic (obs → V): separate networks, tanh MLPs.

    The actor is a plain MLP over the whole observation (``arch="mlp"``, CleanRL's) or the
    camera-shared :class:`SharedCameraActor` (``arch="shared"``).
    """

    def __init__(self, cfg: PPOConfig, gen: torch.Generator) -> None:
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
        return self.actor(obs)

    def value(self, obs: torch.Tensor) -> torch.Tensor:
        return self.critic(obs).squeeze(-1)

    def evaluate(self, obs: torch.Tensor, actions: torch.Tensor
                 ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """log π(actions|obs), entropy (both summed over the bits) and V(obs), per row."""
        dist = torch.distributions.Bernoulli(logits=self.logits(obs))
        return (dist.log_prob(actions).sum(-1), dist.entropy().sum(-1), self.value(obs))


def read_checkpoint(path: str | Path) -> dict[str, Any]:
    """The document of an agent checkpoint (tensors on the CPU), its format and version
    checked. A missing file raises ``FileNotFoundError``; anything that is not a readable
    checkpoint of this format and version raises ``ValueError`` saying why."""
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"no PPO checkpoint at {path}")
    try:
        doc = torch.load(path, map_location="cpu", weights_only=True)
    except Exception as err:  # torch raises many kinds for a file that is not its own
        raise ValueError(f"{path} is not a readable PPO checkpoint: "
                         f"{type(err).__name__}: {str(err).splitlines()[0][:200]}") from None
    if not isinstance(doc, dict) or doc.get("format") != CHECKPOINT_FORMAT:
        raise ValueError(f"{path} is not an aoi3d PPO checkpoint (format "
                         f"{doc.get('format') if isinstance(doc, dict) else None!r})")
    if doc.get("version") != CHECKPOINT_VERSION:
        raise ValueError(f"{path}: checkpoint version {doc.get('version')!r}, this code "
                         f"reads version {CHECKPOINT_VERSION}")
    return doc


class Actor:
    """A network with its config, acting on AoI vectors.

    ``generator``: the ``torch.Generator`` (seeded from ``config.seed``) the initial weights
    are drawn from — and, in the learning agent, the sampled actions and minibatch orders.
    ``episodes`` / ``updates``: what the network has learned from (as its checkpoint says).
    """

    def __init__(self, config: PPOConfig, device: str = "cpu") -> None:
        if not isinstance(config, PPOConfig):
            raise TypeError(f"config must be a PPOConfig, got {type(config).__name__}")
        self.config = config
        self.device = torch.device(device)
        if self.device.type == "cuda" and not torch.cuda.is_available():
            raise ValueError("device cuda asked for, but CUDA is not available here")
        self.generator = torch.Generator(device="cpu").manual_seed(config.seed)
        self.net = ActorCritic(config, self.generator).to(self.device)
        self.episodes = 0
        self.updates = 0

    # --- acting --------------------------------------------------------------------------
    def observe(self, aoi_ms: np.ndarray) -> np.ndarray:
        """The observation of an AoI vector (ms, NaN = unknown), with the config's scale."""
        aoi = np.asarray(aoi_ms, dtype=np.float64)
        if aoi.ndim != 1 or aoi.shape[0] != self.config.n_cameras:
            raise ValueError(f"this agent was trained for {self.config.n_cameras} cameras; "
                             f"got an AoI vector of shape {aoi.shape}")
        return encode_aoi(aoi, self.config.aoi_scale_ms)

    def obs_tensor(self, obs: np.ndarray, batch: bool) -> torch.Tensor:
        """Observations (2N,) or, with ``batch``, (B, 2N) as a tensor on the device."""
        arr = np.asarray(obs, dtype=np.float32)
        ndim = 2 if batch else 1
        if arr.ndim != ndim or arr.shape[-1] != self.config.obs_dim or arr.shape[0] < 1:
            shape = "(B, 2N)" if batch else "(2N,)"
            raise ValueError(f"observation must have shape {shape} with 2N = "
                             f"{self.config.obs_dim}, got {arr.shape}")
        if not np.all(np.isfinite(arr)):
            raise ValueError("observation holds non-finite values")
        return torch.as_tensor(arr, device=self.device)

    @torch.no_grad()
    def select(self, aoi_ms: np.ndarray) -> np.ndarray:
        """The deterministic action on an AoI vector: bit n = (p_n ≥ 0.5), as booleans."""
        logits = self.net.logits(self.obs_tensor(self.observe(aoi_ms), batch=False))
        return (torch.sigmoid(logits).cpu() >= 0.5).numpy()

    @torch.no_grad()
    def value(self, obs: np.ndarray) -> float:
        """V(obs): the critic's estimate of the reward at this observation."""
        return float(self.net.value(self.obs_tensor(obs, batch=False)))

    # --- checkpoints ---------------------------------------------------------------------
    @classmethod
    def load(cls, path: str | Path, device: str = "cpu") -> Self:
        """Rebuild from a checkpoint. A missing file raises ``FileNotFoundError``; anything
        that is not a readable checkpoint of this format and version raises ``ValueError``
        saying why."""
        obj, _ = cls.load_with_extra(path, device)
        return obj

    @classmethod
    def load_with_extra(cls, path: str | Path, device: str = "cpu"
                        ) -> tuple[Self, dict[str, Any]]:
        """:meth:`load`, and the ``extra`` data saved with the checkpoint."""
        doc = read_checkpoint(path)
        try:
            obj = cls(PPOConfig.from_dict(dict(doc["config"])), device=device)
            obj.restore(doc)
        except (KeyError, TypeError, RuntimeError, ValueError) as err:
            raise ValueError(f"{path}: damaged PPO checkpoint: {type(err).__name__}: "
                             f"{str(err).splitlines()[0][:200]}") from None
        obj.net.eval()
        return obj, dict(doc.get("extra") or {})

    def restore(self, doc: dict[str, Any]) -> None:
        """Take the weights and counts of a checkpoint document (:func:`read_checkpoint`)."""
        self.net.load_state_dict(doc["model"])
        self.episodes = int(doc["episodes"])
        self.updates = int(doc["updates"])
