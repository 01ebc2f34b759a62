"""What the dispatcher service reports and accepts: its status types and errors.

Plain data shared by the dispatcher's runtime (:mod:`services.dispatcher.runtime`) and the REST
layer (:mod:`services.dispatcher.app`). The dispatcher service trains no model itself: it hands
decisions to the reconstruction workers (:mod:`services.recon`) and publishes their renders.
"""

from __future__ import annotations

import math
import statistics
from collections import deque
from dataclasses import dataclass, field

from aoi3d.field import UnknownBackendError, check_backend  # re-exported: one check
from aoi3d.pool import PoolStatus

__all__ = [
    "CarryError",
    "DecisionInForce",
    "DispatcherStatus",
    "JobTimes",
    "LatestRender",
    "UnknownBackendError",
    "check_backend",
]


class CarryError(ValueError):
    """A carry mode or render budget the dispatcher cannot use; nothing was changed."""


@dataclass(frozen=True)
class DecisionInForce:
    """The decision whose selection the model is being trained on.

    ``generation_ms``: generation times of the frames it selected that the dispatcher holds."""

    decision_id: int
    incarnation: int
    time_ms: float
    policy: str
    n_selected: int
    n_missing: int
    applied_wall_s: float
    generation_ms: tuple[float, ...] = ()


@dataclass(frozen=True)
class LatestRender:
    """The newest published render (PNG bytes and what it represents).

    ``frames_age_ms``: mean age of its frames at ``time_ms`` (NaN: none); ``lag_ms``: sim ms
    from ``time_ms`` to the render's publication; ``age_s``: wall s from the decision taking
    effect at the dispatcher to the publication."""

    png: bytes
    decision_id: int
    time_ms: float
    training_step: int
    n_views: int
    wall_s: float
    carry: str = "warm"
    render_steps: int = 0
    frames_age_ms: float = math.nan
    lag_ms: float = math.nan
    age_s: float = math.nan
    worker_id: str = ""


class JobTimes:
    """The workers' own compute time per job (``Render.compute_s``), by backend, carry, the
    steps the job trained (a stream cold start's differ from a warm start's) and the frames it
    trained on (a job of 18 frames takes longer than one of 5): what the
    virtual clock's twin of the pool charges a job (``compute_fixed_ms``, ``compute_step_ms``;
    docs/experiments.md, "Does the virtual clock's twin of the pool predict the live
    pipeline?"). The last :attr:`KEEP` of each."""

    KEEP = 500

    def __init__(self) -> None:
        self._s: dict[str, deque[float]] = {}

    def add(self, backend: str, carry: str, steps: int, views: int, compute_s: float) -> None:
        if math.isfinite(compute_s) and compute_s > 0:
            key = f"{backend}/{carry}/{int(steps)}/{int(views)}"
            self._s.setdefault(key, deque(maxlen=self.KEEP)).append(float(compute_s))

    def summary(self) -> dict[str, dict[str, float]]:
        """``{"grid/stream/25/18": {"median_s", "mean_s", "n"}, …}``."""
        return {k: {"median_s": statistics.median(v), "mean_s": statistics.fmean(v),
                    "n": float(len(v))} for k, v in sorted(self._s.items())}


@dataclass(frozen=True)
class DispatcherStatus:
    """A consistent snapshot of the dispatcher for ``GET /status``."""

    steps: int
    steps_total: int
    steps_per_s: float
    loss: float | None
    n_views: int
    decision: DecisionInForce | None
    decision_age_ms: float | None
    backend: str
    device: str
    carry: str
    render_steps: int
    renders: int
    frames_received: int
    frames_buffered: int
    frames_missing: int
    resets: int
    running: bool
    pool: PoolStatus | None = None
    job_s: dict[str, dict[str, float]] = field(default_factory=dict)
    time_scale: float = 1.0
