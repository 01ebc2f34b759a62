"""The dispatcher's REST bodies (status, the pool) and how the runtime's snapshots become them."""

from __future__ import annotations

import math

from pydantic import BaseModel, Field

from aoi3d.field import BACKENDS
from aoi3d.pool import PoolStatus
from services.dispatcher.state import DispatcherStatus

__all__ = ["DecisionInfo", "PoolInfo", "StatusResponse", "WorkerInfo", "pool_body",
           "status_body"]


class DecisionInfo(BaseModel):
    decision_id: int = Field(description="Id of the decision the model trains on.", examples=[42])
    time_ms: float = Field(description="Its epoch t (sim ms): the time renders represent.",
                           examples=[1260.0])
    policy: str = Field(description="The scheduler's policy spec.", examples=["mat:51"])
    n_selected: int = Field(description="Frames the decision selected.", examples=[9])
    n_missing: int = Field(description="Selected frames the dispatcher never received (skipped).",
                           examples=[0])
    age_ms: float = Field(description="Sim ms since the decision epoch.", examples=[35.0])


class WorkerInfo(BaseModel):
    worker_id: str = Field(description="The worker's id (its Zenoh liveliness token's last "
                                       "chunk).", examples=["edge-1-4242-a1b2"])
    pid: int = Field(description="Its process id (0 before its first request).", examples=[4242])
    host: str = Field(description="Its host name.", examples=["edge-1"])
    device: str = Field(description="Its torch device.", examples=["cpu"])
    rendered: int = Field(description="Decisions it rendered since it joined.", examples=[12])
    lost: int = Field(description="Decisions it held that ended without a render.",
                      examples=[0])
    holding: int | None = Field(description="The decision it is reconstructing now; null: idle.",
                                examples=[42])
    holding_site: str | None = Field(description="The site of that decision.",
                                     examples=["site1"])
    busy_fraction: float | None = Field(description="Share of the window's wall time it spent "
                                                    "reconstructing; null until it reported "
                                                    "twice.", examples=[0.93])


class PoolInfo(BaseModel):
    workers: list[WorkerInfo] = Field(description="Live workers (membership: Zenoh liveliness).")
    decisions: int = Field(description="Decisions offered to the pool since start.",
                           examples=[300])
    assigned: int = Field(description="Decisions handed to a worker (each to exactly one).",
                          examples=[120])
    rendered: int = Field(description="Decisions whose render its worker reported published.",
                          examples=[118])
    superseded: int = Field(description="Decisions skipped by choice: a newer one came before a "
                                        "worker was free.", examples=[180])
    lost: dict[str, int] = Field(description="Decisions handed out that ended without a render, "
                                             "by reason: worker_died, timeout, not_delivered, "
                                             "render_failed.", examples=[{"worker_died": 1}])
    pending: dict[str, int] = Field(description="Site → its decision waiting for a free worker "
                                                "(each site's newest not handed out).",
                                    examples=[{"site1": 301}])
    in_flight: int = Field(description="Decisions being reconstructed now.", examples=[2])
    renders_per_s: float = Field(description="Renders per wall second over the window.",
                                 examples=[1.4])
    decisions_per_s: float = Field(description="Decisions per wall second over the window.",
                                   examples=[3.3])
    rendered_fraction: float | None = Field(description="Decisions rendered / taken over the "
                                                        "window (null before any).",
                                            examples=[0.42])
    wait_s_mean: float | None = Field(description="Mean wall s from a decision's arrival to its "
                                                  "hand-out over the window.", examples=[0.08])
    render_age_s_mean: float | None = Field(description="Mean wall s from a decision's arrival "
                                                        "to its render over the window.",
                                            examples=[1.5])
    late_reports: int = Field(description="Worker reports of decisions already counted lost.",
                              examples=[0])
    window_s: float = Field(description="The window of the rates (AOI3D_DISPATCHER_WINDOW_S).",
                            examples=[30.0])
    by_site: dict[str, dict[str, int]] = Field(
        description="Site → its counts since start: decisions, assigned, rendered, superseded, "
                    "lost.", examples=[{"site1": {"decisions": 300, "assigned": 120,
                                                  "rendered": 118, "superseded": 180}}])
    fresh_fraction: float = Field(
        1.0, description="AOI3D_DISPATCHER_FRESH_FRACTION: a worker that asks when the pending "
                         "decision has waited longer than this fraction of the decision period "
                         "waits for the next one (1: never).", examples=[0.5])
    waited_fresh: int = Field(
        0, description="Requests that left a stale pending decision to wait for the next one "
                       "(it is then superseded).", examples=[40])


def _num(x: float) -> float | None:
    return None if not math.isfinite(x) else round(x, 4)


def pool_body(pool: PoolStatus) -> PoolInfo:
    return PoolInfo(
        workers=[WorkerInfo(worker_id=w.worker_id, pid=w.pid, host=w.host, device=w.device,
                            rendered=w.rendered, lost=w.lost, holding=w.holding,
                            holding_site=w.holding_site,
                            busy_fraction=_num(w.busy_fraction)) for w in pool.workers],
        decisions=pool.decisions, assigned=pool.assigned, rendered=pool.rendered,
        superseded=pool.superseded, lost=pool.lost, pending=pool.pending,
        in_flight=pool.in_flight, renders_per_s=round(pool.renders_per_s, 4),
        decisions_per_s=round(pool.decisions_per_s, 4),
        rendered_fraction=_num(pool.rendered_fraction), wait_s_mean=_num(pool.wait_s_mean),
        render_age_s_mean=_num(pool.render_age_s_mean), late_reports=pool.late_reports,
        window_s=pool.window_s, by_site=pool.by_site, fresh_fraction=pool.fresh_fraction,
        waited_fresh=pool.waited_fresh)


class StatusResponse(BaseModel):
    steps: int = Field(description="Training steps of the latest render's model (since the "
                                   "last reset), as its reconstruction worker reported them: "
                                   "the Render's training_step. The dispatcher service trains "
                                   "nothing itself; it hands decisions to the workers.",
                       examples=[1200])
    steps_total: int = Field(description="Training steps of every render the workers "
                                         "published since the service started.",
                             examples=[5400])
    steps_per_s: float = Field(description="The pool's training steps per wall second over "
                                           "the last few seconds (all workers).",
                               examples=[38.5])
    loss: float | None = Field(description="Loss of the latest render's last training step (its "
                                           "worker's); null before the first render after "
                                           "start or reset.", examples=[0.0123])
    n_views: int = Field(description="Frames in the training set.", examples=[9])
    decision: DecisionInfo | None = Field(description="The decision in force; null before the "
                                                      "first one.")
    backend: str = Field(description="Radiance-field backend in use (PUT /backend changes it).",
                         examples=["grid"])
    backends: list[str] = Field(description="Available backends (aoi3d.field.BACKENDS).",
                                examples=[["grid", "nerfacto", "ngp", "tensorf"]])
    device: str = Field(description="Torch device the field trains on.", examples=["cpu"])
    carry: str = Field(description="How renders are made (PUT /carry): stream (the "
                                   "default), fresh, fork or warm.", examples=["stream"])
    render_steps: int = Field(description="Training steps spent on a rendered decision's own "
                                          "frames (fork, fresh; stream: a warm start's).",
                              examples=[25])
    renders: int = Field(description="Renders published.", examples=[17])
    frames_received: int = Field(description="Delivered frames accepted since start.",
                                 examples=[5400])
    frames_buffered: int = Field(description="Delivered frames held (encoded) for selections.",
                                 examples=[144])
    frames_missing: int = Field(description="Selected frames skipped since start because they "
                                            "never arrived.", examples=[0])
    resets: int = Field(description="Model resets since start (backend switches included).",
                        examples=[0])
    running: bool = Field(description="Whether the pool's thread is alive.", examples=[True])
    site: str = Field(description="The site this status is of (the decision, renders, frames "
                                  "and views; the backend, carry and pool are the run's).",
                      examples=["site1"])
    pool: PoolInfo = Field(description="The reconstruction workers and what they did "
                                       "(GET /workers has the same).")
    job_s: dict[str, dict[str, float]] = Field(
        default_factory=dict,
        description="The workers' own compute time per job of this site (Render.compute_s), "
                    "by `backend/carry/steps/frames` (a stream cold start trains more steps "
                    "than a warm one; more frames take longer): median_s, mean_s and n over "
                    "the last 500 of each. What the virtual clock's twin of the pool charges "
                    "a job.",
        examples=[{"grid/stream/25/18": {"median_s": 0.094, "mean_s": 0.097, "n": 500.0}}])
    time_scale: float = Field(description="The run's time scale (scene seconds per wall "
                                          "second): a job's compute_s in scene time is "
                                          "compute_s × time_scale.", examples=[1.0])


def status_body(status: DispatcherStatus, site: str) -> StatusResponse:
    d = status.decision
    assert status.pool is not None  # the worker's status always carries its pool
    return StatusResponse(
        steps=status.steps, steps_total=status.steps_total,
        steps_per_s=round(status.steps_per_s, 3), loss=status.loss, n_views=status.n_views,
        decision=None if d is None else DecisionInfo(
            decision_id=d.decision_id, time_ms=d.time_ms, policy=d.policy,
            n_selected=d.n_selected, n_missing=d.n_missing,
            age_ms=status.decision_age_ms if status.decision_age_ms is not None else 0.0),
        backend=status.backend, backends=sorted(BACKENDS), device=status.device,
        carry=status.carry, render_steps=status.render_steps,
        renders=status.renders, frames_received=status.frames_received,
        frames_buffered=status.frames_buffered,
        frames_missing=status.frames_missing, resets=status.resets, running=status.running,
        pool=pool_body(status.pool), site=site, job_s=status.job_s,
        time_scale=status.time_scale)
