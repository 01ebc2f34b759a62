"""The budget of a decision, and the lag from a decision to its display.

A decision's **budget** is how many training steps the reconstruction of its frames may take
(the carry's ``render_steps``: ``fresh`` trains that many steps from scratch, ``stream`` that
many from the previous decision's model). It is part of the decision: a policy spec may
carry one, ``mat:70@50`` (Γ = 70 ms, 50 steps), ``freshest:6@25``, ``all@100``
(:class:`aoi3d.policy.base.Budgeted`), and a policy may choose one per decision
(:meth:`Policy.budget_for`).
A decision without one is rendered at the caller's default (the experiments' config, the
live pool's ``render_steps``). The budget travels in the ``Decision`` message, the live pool
trains a job for it, and the virtual clock charges its compute
(:meth:`aoi3d.experiment.config.EpisodeConfig.compute_ms`).

The **display lag** L is the time from a decision to the moment its render is seen: the
queue before a worker takes the job, plus the compute of its budget
(:class:`DisplayLag`). Live, the pool measures both; on the virtual clock the cost model
gives them. A compute-aware policy reads L before it selects (:meth:`Policy.observe_lag`):
``dmat:<Γ>`` uses camera n iff its age *at display*, Δn + L, is under Γ.
"""

from __future__ import annotations

import math
from collections import deque
from dataclasses import dataclass, replace

import numpy as np

BUDGET_MAX_STEPS = 100_000
"""The largest budget a spec, a REST body or a decision may carry."""


def check_budget(steps: object, *, name: str = "budget") -> int:
    """``steps`` as a budget: an int in 1 … :data:`BUDGET_MAX_STEPS` (not a bool, not a
    float); ``ValueError`` saying what is wrong otherwise."""
    if isinstance(steps, bool) or not isinstance(steps, int | np.integer):
        raise ValueError(f"{name} must be a whole number of training steps, got {steps!r}")
    if not 1 <= int(steps) <= BUDGET_MAX_STEPS:
        raise ValueError(f"{name} must be 1 … {BUDGET_MAX_STEPS} steps, got {int(steps)}")
    return int(steps)


@dataclass(frozen=True)
class DisplayLag:
    """The expected time (ms of scene time) from a decision to its render being shown:
    ``queue_ms`` before a worker starts it, then ``fixed_ms`` + ``step_ms`` per training step.
    ``default_steps``: the budget of a decision that names none."""

    fixed_ms: float
    step_ms: float
    queue_ms: float = 0.0
    default_steps: int = 0

    def __post_init__(self) -> None:
        for name in ("fixed_ms", "step_ms", "queue_ms"):
            value = getattr(self, name)
            if isinstance(value, bool) or not isinstance(value, int | float) or not (
                    math.isfinite(value) and value >= 0):
                raise ValueError(f"{name} must be a finite number >= 0, got {value!r}")
        if isinstance(self.default_steps, bool) or self.default_steps < 0:
            raise ValueError(f"default_steps must be >= 0, got {self.default_steps!r}")

    def lag_ms(self, steps: int | None = None) -> float:
        """L for a render of ``steps`` training steps (None: the default budget)."""
        n = self.default_steps if steps is None else steps
        return self.queue_ms + self.fixed_ms + self.step_ms * n

    def at(self, steps: int) -> DisplayLag:
        """The same lag with ``steps`` as the budget of a decision that names none."""
        return replace(self, default_steps=int(steps))


def split_budget(text: str) -> tuple[str, str | None]:
    """``mat:70@50`` → (``mat:70``, ``50``); a spec without a budget → (spec, None). The
    budget is the part after the last ``@`` when it holds no ``:`` (``wsum:60@mat:130`` names
    a baseline over a policy, not a budget)."""
    head, sep, tail = text.rpartition("@")
    if not sep or ":" in tail:
        return text, None
    return head.strip(), tail.strip()


class LagEstimator:
    """The live :class:`DisplayLag`, learned from the renders seen so far: each scored render
    tells its training steps and its lag (ready − decision time, scene ms). Over the last
    ``window`` renders, L(steps) = a + b·steps by least squares when they used at least two
    budgets, else b = ``step_ms_prior`` and a from the mean (the pool's queue and fixed cost
    both sit in a). ``default_steps``: the budget of the newest render (the pool's, for a
    decision that names none). No estimate before ``min_renders``."""

    def __init__(self, step_ms_prior: float, *, window: int = 64, min_renders: int = 3) -> None:
        if not (math.isfinite(step_ms_prior) and step_ms_prior >= 0):
            raise ValueError(f"step_ms_prior must be a finite number >= 0, got {step_ms_prior}")
        if window < 2 or min_renders < 1:
            raise ValueError("window must be >= 2 and min_renders >= 1")
        self.step_ms_prior = float(step_ms_prior)
        self.min_renders = min_renders
        self._seen: deque[tuple[int, float]] = deque(maxlen=window)

    def observe(self, steps: int, lag_ms: float) -> bool:
        """One render: its steps and lag; False (ignored) for a negative or non-finite lag."""
        if steps < 0 or not math.isfinite(lag_ms) or lag_ms < 0:
            return False
        self._seen.append((int(steps), float(lag_ms)))
        return True

    def __len__(self) -> int:
        return len(self._seen)

    def estimate(self) -> DisplayLag | None:
        """The lag model now; None while fewer than ``min_renders`` renders were seen."""
        if len(self._seen) < self.min_renders:
            return None
        steps = np.array([s for s, _ in self._seen], dtype=np.float64)
        lags = np.array([lag for _, lag in self._seen], dtype=np.float64)
        slope = self.step_ms_prior
        if np.ptp(steps) > 0:
            fitted = float(np.polyfit(steps, lags, 1)[0])
            slope = max(0.0, fitted)
        intercept = max(0.0, float(lags.mean() - slope * steps.mean()))
        return DisplayLag(fixed_ms=intercept, step_ms=slope, default_steps=self._seen[-1][0])
