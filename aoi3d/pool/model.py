"""The values the pool's dispatcher (:mod:`aoi3d.pool.dispatcher`) takes and gives: a
decision as the pool knows it, an assignment, a decision ended without a render and why, a
worker's report, and the status views. Pure data, no logic."""

from __future__ import annotations

from dataclasses import dataclass
from enum import StrEnum

from aoi3d.sites import DEFAULT_SITE

__all__ = ["Assignment", "DecisionRef", "Ended", "PoolReason", "PoolStatus", "Report",
           "WorkerView"]


class PoolReason(StrEnum):
    """Why a decision ended in the pool without a render: the pool's share of the wire's
    ``EndReason`` (proto/aoi3d.proto; a member's value is its label there, so
    ``services.kit.reasons.EndReason(reason)`` is the wire's member, and
    tests/unit/domain/test_pool.py checks that every one is a reason the dispatcher tells)."""

    SUPERSEDED = "superseded"
    WORKER_DIED = "worker_died"
    TIMEOUT = "timeout"
    NOT_DELIVERED = "not_delivered"
    RENDER_FAILED = "render_failed"
    REFUSED = "refused"
    NOT_RECEIVED = "not_received"


@dataclass(frozen=True)
class DecisionRef:
    """A decision as the pool knows it: (site, incarnation, id) names it."""

    incarnation: int
    decision_id: int
    time_ms: float
    site: str = DEFAULT_SITE

    @property
    def key(self) -> tuple[str, int, int]:
        return self.site, self.incarnation, self.decision_id


@dataclass(frozen=True)
class Assignment:
    """A decision handed to one worker."""

    decision: DecisionRef
    worker_id: str
    arrived_s: float
    """Wall time the decision reached the dispatcher."""
    assigned_s: float

    @property
    def wait_s(self) -> float:
        """From the decision's arrival to the start of its reconstruction (its hand-out)."""
        return self.assigned_s - self.arrived_s


@dataclass(frozen=True)
class Ended:
    """A decision that ended in the pool without a render: the dispatcher publishes it as an
    Outcome for the decision ledger (services.metrics.ledger)."""

    decision: DecisionRef
    state: str
    """``skipped`` or ``lost``."""
    reason: PoolReason
    """skipped: ``superseded``; lost: one the dispatcher tells
    (``services.kit.reasons.TRAINER_LOST``)."""
    detail: str = ""


@dataclass(frozen=True)
class Report:
    """What a worker says when it asks for work (decoded from its WorkRequest)."""

    worker_id: str
    done: tuple[str, int, int] | None = None
    """(site, incarnation, decision id) of the job finished since its last request."""
    rendered: bool = False
    reason: str = ""
    busy_s: float = 0.0
    jobs: int = 0
    max_wait_s: float = 0.0
    device: str = ""
    pid: int = 0
    host: str = ""


@dataclass(frozen=True)
class WorkerView:
    worker_id: str
    pid: int
    host: str
    device: str
    joined_s: float
    rendered: int
    lost: int
    holding: int | None
    """Decision id it is reconstructing now, None when idle."""
    holding_site: str | None
    busy_fraction: float
    """Share of the last window's wall time it spent reconstructing (NaN: too new to say)."""


@dataclass(frozen=True)
class PoolStatus:
    workers: tuple[WorkerView, ...]
    decisions: int
    """Decisions offered to the pool since start."""
    assigned: int
    rendered: int
    superseded: int
    lost: dict[str, int]
    pending: dict[str, int]
    """Site → id of its decision waiting for a worker."""
    in_flight: int
    renders_per_s: float
    decisions_per_s: float
    rendered_fraction: float
    """Decisions rendered / decisions offered over the window (NaN before any decision)."""
    wait_s_mean: float
    """Mean wait from a decision's arrival to its hand-out over the window (NaN: none)."""
    render_age_s_mean: float
    """Mean wall s from a decision's arrival to its render's report, over the window."""
    late_reports: int
    window_s: float
    by_site: dict[str, dict[str, int]]
    """Site → its counts: decisions, assigned, rendered, superseded, lost."""
    fresh_fraction: float = 1.0
    """The dispatcher's ``fresh_fraction`` (1: a free worker never waits for a fresher one)."""
    waited_fresh: int = 0
    """Requests that left a stale pending decision to wait for the next one."""
