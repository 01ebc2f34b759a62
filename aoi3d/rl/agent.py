"""Single-step PPO over N independent Bernoulli bits (the paper's agent), CleanRL style.

The frame-selection problem is a contextual bandit: the agent sees the AoI vector once
(:func:`aoi3d.rl.obs.encode_aoi`), picks a subset of the N cameras, and the episode ends with
one reward (the quality of the novel view). PPO with γ = 1 on such one-step episodes reduces
to:

- return  G = r (no bootstrapping, nothing after the single step);
- advantage  A = r − V(s), normalised within the batch when it holds more than one episode;
- the clipped surrogate  L = E[max(−A·ρ, −A·clip(ρ, 1 − ε, 1 + ε))], ρ = π(a|s) / π_old(a|s),
  over ``update_epochs`` passes of shuffled minibatches, plus ``vf_coef``·½(V(s) − r)² and
  minus ``ent_coef``·entropy, with the gradient norm clipped to ``max_grad_norm``.

The policy is N independent Bernoulli variables: an MLP maps the observation to N logits,
log π(a|s) = Σ_n log Bernoulli(a_n; σ(logit_n)). The last layer's bias starts at
logit(``init_select_p``) (0.5 by default: the untrained policy picks each camera with an even
chance) and its weights near zero, so the first actions are close to uniform over subsets.
The critic is a separate MLP (no shared trunk, as CleanRL's ``ppo.py``).

Everything random — the initial weights, the sampled actions, the minibatch order — comes
from one ``torch.Generator`` seeded from ``PPOConfig.seed``, so a run is reproducible and a
checkpoint (which stores the generator's state) resumes the same stream.
"""

from __future__ import annotations

import math
import os
from dataclasses import asdict, dataclass, fields
from pathlib import Path
from typing import Any

import numpy as np
import torch
from torch import nn

from aoi3d.rl.obs import encode_aoi, obs_size

__all__ = ["CHECKPOINT_FORMAT", "CHECKPOINT_VERSION", "Act", "PPOConfig", "SingleStepPPO"]

CHECKPOINT_FORMAT = "aoi3d-ppo"
CHECKPOINT_VERSION = 1
ARCHS = ("mlp", "shared")
"""Actor networks: a plain MLP over the observation, or one MLP shared by the cameras."""


def _check_int(name: str, value: Any, minimum: int) -> None:
    if isinstance(value, bool) or not isinstance(value, int) or value < minimum:
        raise ValueError(f"{name} must be an int >= {minimum}, got {value!r}")


def _check_float(name: str, value: Any, low: float, high: float = math.inf, *,
                 open_low: bool = False, open_high: bool = False) -> None:
    ok = (isinstance(value, int | float) and not isinstance(value, bool)
          and math.isfinite(value)
          and (value > low if open_low else value >= low)
          and (value < high if open_high else value <= high))
    if not ok:
        lo, hi = "(" if open_low else "[", ")" if open_high else "]"
        raise ValueError(f"{name} must be a number in {lo}{low:g}, {high:g}{hi}, got {value!r}")


@dataclass(frozen=True)
class PPOConfig:
    """The agent's hyper-parameters (everything a checkpoint needs to rebuild it).

    ``n_cameras``: N, the length of the AoI vector and of the action. ``hidden``: width of the
    two hidden tanh layers of actor and critic. ``lr``: Adam step size. ``clip_eps``: ε of
    the clipped surrogate. ``update_epochs`` passes over each batch in ``minibatch_size``
    chunks. ``vf_coef`` / ``ent_coef``: weights of the value loss and the entropy bonus.
    ``max_grad_norm``: gradient clipping. ``norm_adv``: normalise advantages within a batch
    (of more than one episode). ``init_select_p``: the untrained policy's probability of
    selecting a camera. ``aoi_scale_ms``: the AoI that maps to 1.0 in the observation.
    ``seed``: initial weights, sampled actions and minibatch order. ``arch``: the actor,
    ``mlp`` (CleanRL's: an MLP from the whole observation to the N logits) or ``shared``
    (:class:`SharedCameraActor`: one small MLP applied to every camera's AoI with the mean
    over the cameras as context, plus a learned per-camera embedding and bias; it learns a
    per-camera rule from N samples per episode — see docs/ppo.md for the measured gain).
    """

    n_cameras: int
    hidden: int = 64
    lr: float = 3e-4
    clip_eps: float = 0.2
    update_epochs: int = 10
    minibatch_size: int = 16
    vf_coef: float = 0.5
    ent_coef: float = 0.01
    max_grad_norm: float = 0.5
    norm_adv: bool = True
    init_select_p: float = 0.5
    aoi_scale_ms: float = 300.0
    seed: int = 0
    arch: str = "mlp"

    def __post_init__(self) -> None:
        if self.arch not in ARCHS:
            raise ValueError(f"arch must be one of {ARCHS}, got {self.arch!r}")
        _check_int("n_cameras", self.n_cameras, 1)
        _check_int("hidden", self.hidden, 1)
        _check_int("update_epochs", self.update_epochs, 1)
        _check_int("minibatch_size", self.minibatch_size, 1)
        _check_int("seed", self.seed, 0)
        _check_float("lr", self.lr, 0.0, open_low=True)
        _check_float("clip_eps", self.clip_eps, 0.0, open_low=True)
        _check_float("vf_coef", self.vf_coef, 0.0)
        _check_float("ent_coef", self.ent_coef, 0.0)
        _check_float("max_grad_norm", self.max_grad_norm, 0.0, open_low=True)
        _check_float("init_select_p", self.init_select_p, 0.0, 1.0, open_low=True,
                     open_high=True)
        _check_float("aoi_scale_ms", self.aoi_scale_ms, 0.0, open_low=True)
        if not isinstance(self.norm_adv, bool):
            raise ValueError(f"norm_adv must be a bool, got {self.norm_adv!r}")

    @property
    def obs_dim(self) -> int:
        """Length of the observation (2N)."""
        return obs_size(self.n_cameras)

    def to_dict(self) -> dict[str, Any]:
        return asdict(self)

    @classmethod
    def from_dict(cls, data: dict[str, Any]) -> PPOConfig:
        """Build from a dict; unknown keys or bad values raise ``ValueError``."""
        if not isinstance(data, dict):
            raise ValueError(f"PPO config must be a JSON object, got {type(data).__name__}")
        known = {f.name for f in fields(cls)}
        unknown = sorted(set(data) - known)
        if unknown:
            raise ValueError(f"unknown PPO config key(s) {unknown}; known: {sorted(known)}")
        if "n_cameras" not in data:
            raise ValueError("PPO config needs n_cameras")
        return cls(**data)


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


class SingleStepPPO:
    """The agent: act on an AoI observation, learn from batches of one-step episodes.

    ``episodes`` counts the episodes learned so far (the sum of the batch sizes given to
    :meth:`update`), ``updates`` the calls to it. Not thread-safe: a caller that acts and
    learns from several threads holds a lock around both.
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
        self.optimizer = torch.optim.Adam(self.net.parameters(), lr=config.lr, eps=1e-5)
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

    def _obs_tensor(self, obs: np.ndarray, batch: bool) -> torch.Tensor:
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
    def act(self, obs: np.ndarray, *, deterministic: bool = False) -> Act:
        """Select cameras for one observation: sample the N bits (from the agent's generator),
        or with ``deterministic`` take bit n = (p_n ≥ 0.5)."""
        x = self._obs_tensor(obs, batch=False)
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

    @torch.no_grad()
    def value(self, obs: np.ndarray) -> float:
        """V(obs): the critic's estimate of the reward at this observation."""
        return float(self.net.value(self._obs_tensor(obs, batch=False)))

    # --- learning ------------------------------------------------------------------------
    def update(self, obs: np.ndarray, actions: np.ndarray, logp: np.ndarray,
               rewards: np.ndarray) -> dict[str, float]:
        """One PPO update on a batch of B one-step episodes (γ = 1: return = reward,
        advantage = reward − V(s), normalised in the batch when B > 1).

        ``obs`` (B, 2N), ``actions`` (B, N) of 0/1, ``logp`` (B,) the log-probabilities under
        the policy that acted, ``rewards`` (B,). Returns the mean over minibatches of
        ``policy_loss``, ``value_loss``, ``entropy``, ``approx_kl``, ``clip_frac``, and the
        batch's ``mean_reward``.
        """
        cfg = self.config
        x = self._obs_tensor(obs, batch=True)
        b = x.shape[0]
        a = np.asarray(actions)
        if a.shape != (b, cfg.n_cameras) or not np.isin(a, (0, 1)).all():
            raise ValueError(f"actions must be 0/1 of shape ({b}, {cfg.n_cameras}), "
                             f"got shape {a.shape}")
        old_logp = np.asarray(logp, dtype=np.float32)
        ret = np.asarray(rewards, dtype=np.float32)
        for name, arr in (("logp", old_logp), ("rewards", ret)):
            if arr.shape != (b,) or not np.all(np.isfinite(arr)):
                raise ValueError(f"{name} must be {b} finite numbers, got shape {arr.shape}")
        act_t = torch.as_tensor(a, dtype=torch.float32, device=self.device)
        logp_t = torch.as_tensor(old_logp, device=self.device)
        ret_t = torch.as_tensor(ret, device=self.device)
        with torch.no_grad():
            adv = ret_t - self.net.value(x)
            if cfg.norm_adv and b > 1:
                adv = (adv - adv.mean()) / (adv.std() + 1e-8)

        sums = {"policy_loss": 0.0, "value_loss": 0.0, "entropy": 0.0, "approx_kl": 0.0,
                "clip_frac": 0.0}
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
                for key, val in (("policy_loss", pg_loss), ("value_loss", v_loss),
                                 ("entropy", ent), ("approx_kl", approx_kl),
                                 ("clip_frac", clip_frac)):
                    sums[key] += float(val.detach())
                count += 1
        self.net.eval()
        self.episodes += b
        self.updates += 1
        stats = {k: v / count for k, v in sums.items()}
        stats["mean_reward"] = float(ret.mean())
        return stats

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

    @classmethod
    def load(cls, path: str | Path, device: str = "cpu") -> SingleStepPPO:
        """Rebuild an agent from :meth:`save`'s file. A missing file raises
        ``FileNotFoundError``; anything that is not a readable checkpoint of this format and
        version raises ``ValueError`` saying why."""
        agent, _ = cls.load_with_extra(path, device)
        return agent

    @classmethod
    def load_with_extra(cls, path: str | Path, device: str = "cpu"
                        ) -> tuple[SingleStepPPO, dict[str, Any]]:
        """:meth:`load`, and the ``extra`` data saved with the checkpoint."""
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
        try:
            agent = cls(PPOConfig.from_dict(dict(doc["config"])), device=device)
            agent.net.load_state_dict(doc["model"])
            agent.optimizer.load_state_dict(doc["optimizer"])
            agent.generator.set_state(doc["generator"])
            agent.episodes = int(doc["episodes"])
            agent.updates = int(doc["updates"])
        except (KeyError, TypeError, RuntimeError, ValueError) as err:
            raise ValueError(f"{path}: damaged PPO checkpoint: {type(err).__name__}: "
                             f"{str(err).splitlines()[0][:200]}") from None
        agent.net.eval()
        return agent, dict(doc.get("extra") or {})


def _to_cpu(obj: Any) -> Any:
    """A copy of a (nested) optimizer state with every tensor on the CPU."""
    if isinstance(obj, torch.Tensor):
        return obj.detach().cpu()
    if isinstance(obj, dict):
        return {k: _to_cpu(v) for k, v in obj.items()}
    if isinstance(obj, list | tuple):
        return type(obj)(_to_cpu(v) for v in obj)
    return obj
