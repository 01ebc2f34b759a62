"""One decision: the AoI vector at the evaluation time → a policy → the selected cameras.

Every caller that selects frames goes through :func:`decide` — the experiment engine
(:func:`aoi3d.experiment.plan_episode`, on the simulated links), the live scheduler
(``services/scheduler``, on the frames the network delivered), the gymnasium environment
(:class:`aoi3d.rl.env.FrameSelectionEnv`, the agent's action) and the online learner
(:class:`aoi3d.rl.online.OnlineLearner`, a sampled action) — so a policy means the same in
all of them. A decision taken at epoch t:

1. asks the policy when it selects: at s = t + ``policy.wait_ms`` (0 for every policy but
   ``wait:<ω>``, which selects at t + ω);
2. reads U(s), the generation time of each camera's newest frame delivered by s (NaN: none
   yet), from the caller's ``newest_at`` — the only thing that differs between the settings;
3. forms the AoI vector Δ(s) = s − U(s) (NaN = unknown);
4. tells the policy the time s and the frames delivered since the previous decision
   (``policy.observe``; the caller's ``deliveries(s)``, none when the caller has no such
   record): what an adaptive policy (:mod:`aoi3d.policy.adaptive`) estimates the channel
   from;
5. tells the policy the expected lag from the decision to its display, when the caller
   knows it (``policy.observe_lag``; the caller's :class:`~aoi3d.policy.budget.DisplayLag`:
   the live pool's measured queue and compute, the virtual clock's cost model);
6. selects: ``policy.select(Δ(s))``, or the caller's ``act(Δ(s), s)`` when an agent acts
   in the policy's place (the env's action, the learner's sampled bits);
7. drops every camera whose AoI is unknown, whatever was selected;
8. asks the policy the decision's budget (``policy.budget_for(Δ(s))``: the training steps
   its render may take; None: the caller's default) — the budget travels with the decision.

The :class:`Selection` holds s (the time the selection is for: the render made from it is
scored against the truth at s), the whole AoI and U vectors, the mask, the budget and the
expected lag; callers read the selected cameras, their generation times and their AoIs from
it.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np

from aoi3d.policy.base import Policy, as_aoi_vector
from aoi3d.policy.budget import DisplayLag, check_budget

__all__ = ["Act", "Deliveries", "NewestAt", "Selection", "decide"]

NewestAt = Callable[[Any], np.ndarray]
"""``newest_at(s)``: U_n(s) per camera — the generation time (ms) of camera n's newest frame
delivered by time s; NaN where none was."""

Deliveries = Callable[[Any], Sequence[tuple[int, float, float]]]
"""``deliveries(s)``: the frames delivered since the previous call, up to time s, each
``(camera index, generation ms, delivery ms)`` (the camera's position in the AoI vector)."""

Act = Callable[[np.ndarray, Any], np.ndarray]
"""``act(aoi_ms, eval_ms)``: an agent's selection bits on the AoI vector at ``eval_ms``, in
place of the policy's own ``select``."""


@dataclass(frozen=True, eq=False)
class Selection:
    """What one decision selected.

    ``decision_ms``: the epoch t; ``eval_ms``: s = t + the policy's wait, when the AoI was
    taken (and the time the render made from the selection stands for); ``aoi_ms`` and
    ``newest_ms``: Δ(s) and U(s) of every camera (NaN: unknown); ``mask``: the selected
    cameras (never one of unknown AoI); ``policy``: the spec of the policy that decided.
    """

    decision_ms: Any
    eval_ms: Any
    aoi_ms: np.ndarray
    newest_ms: np.ndarray
    mask: np.ndarray
    policy: str
    budget_steps: int | None = None
    """The training steps the decision's render may take (None: the caller's default)."""
    lag_ms: float = math.nan
    """The expected lag from the decision to its display at that budget (NaN: the caller
    gave none)."""

    @property
    def indices(self) -> np.ndarray:
        """Positions (in the AoI vector) of the selected cameras, ascending."""
        return np.flatnonzero(self.mask)

    def cameras(self, camera_ids: Sequence[int]) -> tuple[int, ...]:
        """The selected cameras' ids, given the ids of the vector's positions."""
        return tuple(int(camera_ids[i]) for i in self.indices)

    @property
    def gen_ms(self) -> np.ndarray:
        """U_n(s) of the selected cameras: their frames' generation times."""
        gen: np.ndarray = self.newest_ms[self.mask]
        return gen

    @property
    def selected_aoi_ms(self) -> np.ndarray:
        """Δ_n(s) of the selected cameras."""
        aoi: np.ndarray = self.aoi_ms[self.mask]
        return aoi

    @property
    def known(self) -> np.ndarray:
        """Cameras with some delivered frame (known AoI)."""
        known: np.ndarray = ~np.isnan(self.aoi_ms)
        return known

    @property
    def mean_aoi_all_ms(self) -> float:
        """Mean AoI over the cameras whose AoI is known; NaN when none is."""
        known = self.known
        return float(self.aoi_ms[known].mean()) if known.any() else math.nan


def decide(policy: Policy, decision_ms: Any, newest_at: NewestAt, *,
           act: Act | None = None, deliveries: Deliveries | None = None,
           lag: DisplayLag | None = None) -> Selection:
    """Take the decision of epoch ``decision_ms`` (see the module docstring).

    ``newest_at``: the caller's U(s) (the simulated links' ``newest_ms``, the scheduler's
    tracker). ``act``: an agent's selection in place of ``policy.select`` (the policy still
    says when to select and names the decision). ``deliveries``: the caller's record of the
    frames delivered since its previous decision (handed to ``policy.observe``). ``lag``: the
    caller's expected lag from a decision to its display (handed to ``policy.observe_lag``;
    its ``default_steps`` is the caller's budget of a decision that names none). A
    selection of the wrong shape, or a budget out of range, raises ``ValueError``.
    """
    wait = policy.wait_ms
    if isinstance(wait, bool) or not isinstance(wait, int | np.integer) or wait < 0:
        raise ValueError(f"policy {policy.spec!r} declares wait_ms={wait!r}; need an int >= 0")
    eval_ms = decision_ms + int(wait)
    newest = as_aoi_vector(newest_at(eval_ms))
    aoi = eval_ms - newest
    policy.observe(eval_ms, deliveries(eval_ms) if deliveries is not None else ())
    if lag is not None:
        policy.observe_lag(lag)
    bits = policy.select(aoi) if act is None else act(aoi, eval_ms)
    mask = np.asarray(bits, dtype=bool)
    if mask.shape != aoi.shape:
        raise ValueError(f"policy {policy.spec!r} returned a selection of shape {mask.shape}, "
                         f"expected ({aoi.shape[0]},)")
    budget = policy.budget_for(aoi)
    if budget is not None:
        budget = check_budget(budget, name=f"policy {policy.spec!r}'s budget")
    return Selection(decision_ms=decision_ms, eval_ms=eval_ms, aoi_ms=aoi, newest_ms=newest,
                     mask=mask & ~np.isnan(aoi), policy=policy.spec, budget_steps=budget,
                     lag_ms=math.nan if lag is None else lag.lag_ms(budget))
