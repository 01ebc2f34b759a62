"""ω-wait (``wait:<ms>``): wait ω after the decision epoch, then use the frames that arrived.

At the decision epoch t the agent does not decide at once: it waits ω ms and then trains on
the frames *captured since t* that have been delivered by t + ω, i.e. camera n is used iff
its newest delivered frame at t + ω was generated at or after t:

    U_n(t + ω) ≥ t   ⇔   Δ_n(t + ω) ≤ ω.

The render made from them is used at t + ω, so it is scored against the truth at t + ω (as in
the authors' follow-up work, where waiting buys fresher and more frames at the price of
latency). ω = 0 selects nothing (no frame arrives in the slot it is captured).

A policy has no clock, so the time shift is declared, not performed: :attr:`WaitPolicy.wait_ms`
tells the caller to evaluate the AoI vector — and render, and score — at t + ω, and
:meth:`WaitPolicy.select` then applies ``Δ ≤ ω`` to that vector. The caller is always
:func:`aoi3d.policy.decide.decide`, which reads the shift from the policy's ``wait_ms`` (0,
:class:`~aoi3d.policy.base.BasePolicy`'s, for the policies that decide at once): the experiment
engine and the live scheduler alike decide at t + ω and stamp the decision with that time.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass, field
from typing import Any, ClassVar

import numpy as np

from aoi3d.policy.base import (
    BasePolicy,
    PolicyKind,
    PolicySpecError,
    as_aoi_vector,
    expect_fields,
    expect_keys,
    integer,
)

__all__ = ["KIND", "WaitPolicy"]


@dataclass(frozen=True)
class WaitPolicy(BasePolicy):
    """ω-wait: given the AoI vector at t + ω, use camera n iff Δ_n(t + ω) ≤ ω (``wait_ms``).

    ``wait_ms`` is a whole number of slots (ms) ≥ 0.
    """

    wait_ms: int = field()  # required: not BasePolicy's default 0
    kind: ClassVar[str] = "wait"

    def __post_init__(self) -> None:
        object.__setattr__(self, "wait_ms", integer("wait_ms", self.wait_ms, minimum=0))

    @property
    def spec(self) -> str:
        return f"wait:{self.wait_ms}"

    def select(self, aoi_ms: np.ndarray) -> np.ndarray:
        """Cameras whose frame was captured within the wait (``aoi_ms`` taken at t + ω)."""
        return as_aoi_vector(aoi_ms) <= self.wait_ms  # NaN compares False: never selected

    def to_json(self) -> dict[str, Any]:
        return {"kind": self.kind, "wait_ms": self.wait_ms}



def _wait_from_args(fields: list[str]) -> WaitPolicy:
    (value,) = expect_fields("wait", fields, ("ms",))
    return WaitPolicy(integer("wait_ms", value, minimum=0))


def _wait_from_json(params: Mapping[str, Any]) -> WaitPolicy:
    expect_keys("wait", params, ("wait_ms",))
    if isinstance(params["wait_ms"], str):
        raise PolicySpecError(f"wait_ms must be a JSON number, got {params['wait_ms']!r}")
    return WaitPolicy(params["wait_ms"])


KIND = PolicyKind("wait", "wait:<ms>", _wait_from_args, _wait_from_json, family="rule")
"""The ``wait`` kind, registered by :mod:`aoi3d.policy`."""
