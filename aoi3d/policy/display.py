"""Compute-aware policies: they know how long their decision takes to reach a screen.

A render is seen a lag L after its decision (:class:`~aoi3d.policy.budget.DisplayLag`: the
pool's queue, then the compute of the decision's budget), so a frame of age Δn at the
decision is Δn + L old when the viewer sees the render. Two kinds read L (the decision step
tells them before they select, :meth:`Policy.observe_lag`):

- ``dmat:<Γ>`` — MAT on the age at display: use camera n iff Δn + L < Γ, with L at the
  decision's budget (``dmat:100@50``: 50 steps; no budget: the caller's default). With no
  lag known (L = 0) it is ``mat:<Γ>``.
- ``deadline:<Γ>:<ms>`` — a budget from the lag: the largest budget in
  ``BUDGET_CHOICES`` whose decision is on screen within ``ms`` of it (queue + compute ≤
  ms; the smallest choice when none is), and ``dmat:<Γ>`` at that budget. Live, a longer
  queue buys fewer steps, so renders keep their age at display; on the virtual clock (no
  queue) the budget is a constant.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass, field
from typing import Any, ClassVar

import numpy as np

from aoi3d.numbers import format_number
from aoi3d.policy.base import (
    BasePolicy,
    PolicyKind,
    PolicySpecError,
    as_aoi_vector,
    expect_fields,
    expect_keys,
    number,
)
from aoi3d.policy.budget import DisplayLag

BUDGET_CHOICES = (10, 25, 50, 75, 100, 150, 200, 300)
"""The budgets ``deadline`` chooses from (training steps)."""


@dataclass(eq=False)
class DisplayMatPolicy(BasePolicy):
    """``dmat:<Γ>``: camera n iff its age at display, Δn + L, is under Γ (``mat_ms``)."""

    mat_ms: float
    kind: ClassVar[str] = "dmat"
    _lag: DisplayLag | None = field(default=None, init=False, repr=False)

    def __post_init__(self) -> None:
        self.mat_ms = number("mat_ms", self.mat_ms, minimum=0.0)

    def __eq__(self, other: object) -> bool:
        return type(other) is type(self) and other.spec == self.spec

    def __hash__(self) -> int:
        return hash(self.spec)

    @property
    def spec(self) -> str:
        return f"dmat:{format_number(self.mat_ms)}"

    @property
    def gamma_ms(self) -> float:
        """Γ: the threshold on the age at display."""
        return self.mat_ms

    def observe_lag(self, lag: DisplayLag) -> None:
        self._lag = lag

    def lag_ms(self) -> float:
        """L at the decision's budget (0 while no lag was told)."""
        return 0.0 if self._lag is None else self._lag.lag_ms(self.budget_for(np.empty(0)))

    def select(self, aoi_ms: np.ndarray) -> np.ndarray:
        selected: np.ndarray = as_aoi_vector(aoi_ms) + self.lag_ms() < self.mat_ms
        return selected  # NaN compares False: never selected

    def reset(self) -> None:
        self._lag = None

    def to_json(self) -> dict[str, Any]:
        value = int(self.mat_ms) if self.mat_ms.is_integer() else self.mat_ms
        return {"kind": self.kind, "mat_ms": value}


@dataclass(eq=False)
class DeadlinePolicy(DisplayMatPolicy):
    """``deadline:<Γ>:<ms>``: the largest budget whose render is on screen within
    ``deadline_ms`` (:data:`BUDGET_CHOICES`), and ``dmat:<Γ>`` at that budget."""

    deadline_ms: float = 100.0
    kind: ClassVar[str] = "deadline"
    chooses_budget: ClassVar[bool] = True
    """It picks each decision's budget: a fixed '@<steps>' would contradict it."""

    def __post_init__(self) -> None:
        super().__post_init__()
        self.deadline_ms = number("deadline_ms", self.deadline_ms, minimum=0.0)

    @property
    def spec(self) -> str:
        return f"deadline:{format_number(self.mat_ms)}:{format_number(self.deadline_ms)}"

    def budget_for(self, aoi_ms: np.ndarray) -> int | None:
        lag = self._lag
        if lag is None:
            return None  # no lag known: the caller's default budget
        fits = [b for b in BUDGET_CHOICES if lag.lag_ms(b) <= self.deadline_ms]
        return max(fits) if fits else min(BUDGET_CHOICES)

    def to_json(self) -> dict[str, Any]:
        doc = super().to_json()
        value = self.deadline_ms
        doc["deadline_ms"] = int(value) if value.is_integer() else value
        return doc


def _number_json(kind: str, params: Mapping[str, Any], key: str) -> float:
    value = params[key]
    if isinstance(value, str):
        raise PolicySpecError(f"{kind} {key} must be a JSON number, got {value!r}")
    return number(key, value, minimum=0.0)


def _dmat_from_args(fields: list[str]) -> DisplayMatPolicy:
    (value,) = expect_fields("dmat", fields, ("ms",))
    return DisplayMatPolicy(number("mat_ms", value, minimum=0.0))


def _dmat_from_json(params: Mapping[str, Any]) -> DisplayMatPolicy:
    expect_keys("dmat", params, ("mat_ms",))
    return DisplayMatPolicy(_number_json("dmat", params, "mat_ms"))


def _deadline_from_args(fields: list[str]) -> DeadlinePolicy:
    gamma, deadline = expect_fields("deadline", fields, ("ms", "deadline_ms"))
    return DeadlinePolicy(number("mat_ms", gamma, minimum=0.0),
                          number("deadline_ms", deadline, minimum=0.0))


def _deadline_from_json(params: Mapping[str, Any]) -> DeadlinePolicy:
    expect_keys("deadline", params, ("mat_ms", "deadline_ms"))
    return DeadlinePolicy(_number_json("deadline", params, "mat_ms"),
                          _number_json("deadline", params, "deadline_ms"))


KINDS = (
    PolicyKind("dmat", "dmat:<ms>", _dmat_from_args, _dmat_from_json, family="rule"),
    PolicyKind("deadline", "deadline:<ms>:<deadline_ms>", _deadline_from_args,
               _deadline_from_json, family="rule"),
)
"""The compute-aware kinds, registered by :mod:`aoi3d.policy`."""
