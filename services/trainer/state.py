"""What the trainer service reports and accepts: its status types and errors.

Plain data shared by the dispatcher's runtime (:mod:`services.trainer.worker`) and the REST
layer (:mod:`services.trainer.app`). The trainer service trains no model itself: it hands
decisions to the reconstruction workers (:mod:`services.recon`) and publishes their renders.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

from aoi3d.field import UnknownBackendError, check_backend  # re-exported: one check
from services.trainer.pool import PoolStatus

__all__ = [
    "CarryError",
    "DecisionInForce",
    "LatestRender",
    "TrainerStatus",
    "UnknownBackendError",
    "check_backend",
]


class CarryError(ValueError):
    """A carry mode or render budget the trainer cannot use; nothing was changed."""


@dataclass(frozen=True)
class DecisionInForce:
    """The decision whose selection the model is being trained on.

    ``generation_ms``: generation times of the frames it selected that the trainer holds."""

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
    effect at the trainer to the publication."""

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


@dataclass(frozen=True)
class TrainerStatus:
    """A consistent snapshot of the trainer for ``GET /status``."""

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
