"""``ppo:<checkpoint>``: a trained :class:`~aoi3d.rl.agent.SingleStepPPO` as a frame-selection
policy.

The policy applies the agent's deterministic action (camera n is used iff its selection
probability is ≥ 0.5) to the AoI vector at each decision; cameras with unknown (NaN) AoI are
never selected, whatever the network says. Its forms:

- spec ``ppo:<checkpoint path>`` (the path may itself contain ``:``);
- JSON ``{"kind": "ppo", "checkpoint": "<path>", "learn": false}`` — ``learn`` is optional
  (default false) and carried in :meth:`PPOPolicy.to_json`: it tells the live scheduler to
  keep learning online from the rewards of its decisions; the policy itself never learns.

The kind is registered by :mod:`aoi3d.policy` (lazily: this module, and torch, load only when
a ``ppo`` policy is built), so importing :mod:`aoi3d.policy` is enough for ``parse_policy`` and
``policy_from_json`` to know it.
"""

from __future__ import annotations

from collections.abc import Mapping
from pathlib import Path
from typing import Any, ClassVar

import numpy as np

from aoi3d.policy.base import PolicySpecError, as_aoi_vector
from aoi3d.rl.agent import SingleStepPPO

__all__ = ["PPOPolicy", "ppo_from_args", "ppo_from_json"]


class PPOPolicy:
    """A trained single-step PPO agent's deterministic action over the AoI vector.

    ``agent``: the loaded agent; ``checkpoint``: the path it came from, as given (the spec
    round-trips through it); ``learn``: whether the live scheduler should keep learning.
    """

    kind: ClassVar[str] = "ppo"

    def __init__(self, agent: SingleStepPPO, checkpoint: str | Path, learn: bool = False
                 ) -> None:
        if not isinstance(learn, bool):
            raise PolicySpecError(f"ppo learn must be true or false, got {learn!r}")
        self.agent = agent
        self.checkpoint = str(checkpoint)
        self.learn = learn

    @classmethod
    def from_checkpoint(cls, checkpoint: str | Path, *, learn: bool = False,
                        device: str = "cpu") -> PPOPolicy:
        """Load ``checkpoint``; a missing or unreadable file raises ``PolicySpecError`` (a
        ``ValueError``) naming the file and the reason."""
        text = str(checkpoint)
        if not text.strip():
            raise PolicySpecError("ppo needs a checkpoint path (ppo:<checkpoint>)")
        try:
            agent = SingleStepPPO.load(text, device=device)
        except (FileNotFoundError, ValueError) as err:
            raise PolicySpecError(f"cannot load the PPO checkpoint: {err}") from None
        return cls(agent, text, learn)

    @property
    def n_cameras(self) -> int:
        """N: the length of the AoI vector this agent was trained for."""
        return self.agent.config.n_cameras

    @property
    def spec(self) -> str:
        return f"ppo:{self.checkpoint}"

    def select(self, aoi_ms: np.ndarray) -> np.ndarray:
        """The deterministic action as a boolean mask; NaN AoI is never selected. A vector
        whose length differs from the checkpoint's N raises ``ValueError``."""
        aoi = as_aoi_vector(aoi_ms)
        if aoi.shape[0] != self.n_cameras:
            raise ValueError(f"PPO checkpoint {self.checkpoint} was trained for "
                             f"{self.n_cameras} cameras, but the AoI vector has "
                             f"{aoi.shape[0]}")
        act = self.agent.act(self.agent.observe(aoi), deterministic=True)
        return act.action.astype(bool) & ~np.isnan(aoi)

    def to_json(self) -> dict[str, Any]:
        return {"kind": self.kind, "checkpoint": self.checkpoint, "learn": self.learn}

    def reset(self) -> None:
        """Stateless between episodes (the agent does not change while it acts)."""

    def __repr__(self) -> str:
        return (f"PPOPolicy(checkpoint={self.checkpoint!r}, learn={self.learn}, "
                f"n_cameras={self.n_cameras}, episodes={self.agent.episodes})")


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
