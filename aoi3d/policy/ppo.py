"""``ppo:<checkpoint>``: a trained single-step PPO agent as a frame-selection policy.

The policy applies the agent's deterministic action (camera n is used iff its selection
probability is ≥ 0.5) to the AoI vector at each decision; cameras with unknown (NaN) AoI are
never selected, whatever the network says. Its forms:

- spec ``ppo:<checkpoint path>`` (the path may itself contain ``:``);
- JSON ``{"kind": "ppo", "checkpoint": "<path>", "learn": false}`` — ``learn`` is optional
  (default false) and carried in :meth:`PPOPolicy.to_json`: the policy then answers
  :attr:`PPOPolicy.learns` with true, and a caller that can (the live scheduler) keeps
  learning online from the rewards of its decisions (:mod:`aoi3d.rl.online`); the policy
  itself never learns.

This module is torch-free: the network and the checkpoint reader (:mod:`aoi3d.policy.actor`)
load when a checkpoint is, so importing :mod:`aoi3d.policy` (which registers the kind) stays
light. :class:`PPOConfig` is here because a checkpoint stores it: everything needed to
rebuild the agent, its learning hyper-parameters included.
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import asdict, dataclass, fields
from pathlib import Path
from typing import TYPE_CHECKING, Any, ClassVar

import numpy as np

from aoi3d.device import resolve_device
from aoi3d.policy.base import PolicyKind, PolicySpecError, as_aoi_vector
from aoi3d.policy.obs import obs_size

if TYPE_CHECKING:
    from aoi3d.policy.actor import Actor

__all__ = ["ARCHS", "KIND", "PPOConfig", "PPOPolicy", "ppo_from_args", "ppo_from_json"]

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
    (:class:`aoi3d.policy.actor.SharedCameraActor`: one small MLP applied to every camera's
    AoI with the mean over the cameras as context, plus a learned per-camera embedding and
    bias; it learns a per-camera rule from N samples per episode — see docs/ppo.md for the
    measured gain).
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


class PPOPolicy:
    """A trained single-step PPO agent's deterministic action over the AoI vector.

    ``actor``: the checkpoint's network (:class:`aoi3d.policy.actor.Actor`); ``checkpoint``:
    the path it came from, as given (the spec round-trips through it); ``learn``: whether the
    caller should keep learning online (:attr:`learns`).
    """

    kind: ClassVar[str] = "ppo"

    def __init__(self, actor: Actor, checkpoint: str | Path, learn: bool = False) -> None:
        if not isinstance(learn, bool):
            raise PolicySpecError(f"ppo learn must be true or false, got {learn!r}")
        self.actor = actor
        self.checkpoint = str(checkpoint)
        self.learn = learn

    @classmethod
    def from_checkpoint(cls, checkpoint: str | Path, *, learn: bool = False,
                        device: str = "cpu") -> PPOPolicy:
        """Load ``checkpoint`` onto ``device`` (a resolved torch device, ``cpu`` or
        ``cuda``); a missing or unreadable file raises ``PolicySpecError`` (a
        ``ValueError``) naming the file and the reason."""
        text = str(checkpoint)
        if not text.strip():
            raise PolicySpecError("ppo needs a checkpoint path (ppo:<checkpoint>)")
        from aoi3d.policy.actor import Actor  # torch loads here, with the first checkpoint

        try:
            actor = Actor.load(text, device=device)
        except (FileNotFoundError, ValueError) as err:
            raise PolicySpecError(f"cannot load the PPO checkpoint: {err}") from None
        return cls(actor, text, learn)

    @property
    def n_cameras(self) -> int:
        """N: the length of the AoI vector this agent was trained for."""
        return self.actor.config.n_cameras

    @property
    def device(self) -> str:
        """The torch device type the network is on (``cpu`` or ``cuda``)."""
        return self.actor.device.type

    @property
    def spec(self) -> str:
        return f"ppo:{self.checkpoint}"

    @property
    def learns(self) -> bool:
        """Whether the caller should keep learning online from this policy's decisions."""
        return self.learn

    def select(self, aoi_ms: np.ndarray) -> np.ndarray:
        """The deterministic action as a boolean mask; NaN AoI is never selected. A vector
        whose length differs from the checkpoint's N raises ``ValueError``."""
        aoi = as_aoi_vector(aoi_ms)
        if aoi.shape[0] != self.n_cameras:
            raise ValueError(f"PPO checkpoint {self.checkpoint} was trained for "
                             f"{self.n_cameras} cameras, but the AoI vector has "
                             f"{aoi.shape[0]}")
        return self.actor.select(aoi) & ~np.isnan(aoi)

    def check_fits(self, n_cameras: int) -> None:
        """The checkpoint must have been trained for the rig's N cameras."""
        if self.n_cameras != n_cameras:
            raise PolicySpecError(
                f"PPO checkpoint {self.checkpoint} was trained for {self.n_cameras} cameras, "
                f"but there are N = {n_cameras}", self.to_json())

    def on_device(self, device: str) -> PPOPolicy:
        """This policy with its network on ``device`` (``auto``, ``cpu``, ``cuda``): itself
        when it is there already, else loaded again from its checkpoint."""
        try:
            dev = resolve_device(device)
        except ValueError as err:
            raise PolicySpecError(str(err), self.to_json()) from None
        if self.device == dev:
            return self
        return PPOPolicy.from_checkpoint(self.checkpoint, learn=self.learn, device=dev)

    def to_json(self) -> dict[str, Any]:
        return {"kind": self.kind, "checkpoint": self.checkpoint, "learn": self.learn}

    def reset(self) -> None:
        """Stateless between episodes (the network does not change while it acts)."""

    def __repr__(self) -> str:
        return (f"PPOPolicy(checkpoint={self.checkpoint!r}, learn={self.learn}, "
                f"n_cameras={self.n_cameras}, episodes={self.actor.episodes})")


def ppo_from_args(fields: list[str]) -> PPOPolicy:
    """``ppo:<checkpoint>``: the fields after ``ppo:`` joined back with ``:``."""
    path = ":".join(fields).strip()
    if not path:
        raise PolicySpecError("ppo takes a checkpoint path (ppo:<checkpoint>)")
    return PPOPolicy.from_checkpoint(path)


def ppo_from_json(params: Mapping[str, Any]) -> PPOPolicy:
    """``{"checkpoint": "<path>", "learn": false}`` (``learn`` optional)."""
    extra = sorted(k for k in params if k not in ("checkpoint", "learn"))
    if extra:
        raise PolicySpecError(f"ppo does not take key(s) {extra}")
    path = params.get("checkpoint")
    if not isinstance(path, str) or not path.strip():
        raise PolicySpecError(f'ppo needs "checkpoint", a non-empty path string, got {path!r}')
    learn = params.get("learn", False)
    if not isinstance(learn, bool):
        raise PolicySpecError(f"ppo learn must be true or false, got {learn!r}")
    return PPOPolicy.from_checkpoint(path, learn=learn)


KIND = PolicyKind("ppo", "ppo:<checkpoint>", ppo_from_args, ppo_from_json)
"""The ``ppo`` kind, registered by :mod:`aoi3d.policy`."""
