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

An agent trained with the lag to the display in its state (``aoi3d ppo train --observe-lag``,
issue 40) reads it from the decision step (:meth:`PPOPolicy.observe_lag`: L at the
decision's budget, ``ppo:<checkpoint>@<steps>`` for a budget); the checkpoint says whether it
does. The others ignore it.

This module is the torch-free acting side the registry loads: the network
(:class:`aoi3d.policy.ppo.actor.Actor`, torch) loads when a checkpoint is, so importing
:mod:`aoi3d.policy` (which registers the kind) stays light.
"""

from __future__ import annotations

from collections.abc import Mapping
from pathlib import Path
from typing import TYPE_CHECKING, Any, ClassVar

import numpy as np

from aoi3d.device import resolve_device
from aoi3d.policy.base import BasePolicy, PolicyKind, PolicySpecError, as_aoi_vector

if TYPE_CHECKING:
    from aoi3d.policy.budget import DisplayLag
    from aoi3d.policy.ppo.actor import Actor

__all__ = ["KIND", "PPOPolicy", "ppo_from_args", "ppo_from_json"]


class PPOPolicy(BasePolicy):
    """A trained single-step PPO agent's deterministic action over the AoI vector.

    ``actor``: the checkpoint's network (:class:`aoi3d.policy.ppo.actor.Actor`); ``checkpoint``:
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
        self._lag: DisplayLag | None = None

    @classmethod
    def from_checkpoint(cls, checkpoint: str | Path, *, learn: bool = False,
                        device: str = "cpu") -> PPOPolicy:
        """Load ``checkpoint`` onto ``device`` (a resolved torch device, ``cpu`` or
        ``cuda``); a missing or unreadable file raises ``PolicySpecError`` (a
        ``ValueError``) naming the file and the reason."""
        text = str(checkpoint)
        if not text.strip():
            raise PolicySpecError("ppo needs a checkpoint path (ppo:<checkpoint>)")
        from aoi3d.policy.ppo.actor import Actor  # torch loads here, with the first checkpoint

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

    def observe_lag(self, lag: DisplayLag) -> None:
        """The expected lag to the display of the coming decision (an agent trained with it
        observes it; the others do not)."""
        self._lag = lag

    def lag_ms(self) -> float | None:
        """L at the decision's budget, or None while no lag was told."""
        return None if self._lag is None else self._lag.lag_ms(None)

    def reset(self) -> None:
        self._lag = None

    def select(self, aoi_ms: np.ndarray) -> np.ndarray:
        """The deterministic action as a boolean mask; NaN AoI is never selected. A vector
        whose length differs from the checkpoint's N raises ``ValueError``."""
        aoi = as_aoi_vector(aoi_ms)
        if aoi.shape[0] != self.n_cameras:
            raise ValueError(f"PPO checkpoint {self.checkpoint} was trained for "
                             f"{self.n_cameras} cameras, but the AoI vector has "
                             f"{aoi.shape[0]}")
        mask: np.ndarray = self.actor.select(aoi, self.lag_ms()) & ~np.isnan(aoi)
        return mask

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


def ppo_short(spec: str) -> str:
    """``ppo:<folder>/<file>``, not the checkpoint's whole path (for tables and figures)."""
    path = Path(spec.strip().split(":", 1)[1] if ":" in spec else "")
    return f"ppo:{path.parent.name}/{path.name}" if path.parent.name else spec


KIND = PolicyKind("ppo", "ppo:<checkpoint>", ppo_from_args, ppo_from_json, family="learned",
                  short=ppo_short)
"""The ``ppo`` kind, registered by :mod:`aoi3d.policy`."""
