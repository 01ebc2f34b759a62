"""REST API of the trainer: status, model reset, backend switch and the latest novel-view
render."""

from __future__ import annotations

import math
import time
from typing import Annotated, Literal

from fastapi import APIRouter, Body, Depends, FastAPI, HTTPException, Request
from fastapi.responses import Response
from pydantic import BaseModel, Field

from aoi3d.clock import SimClock
from aoi3d.field import BACKENDS
from aoi3d.scene import SceneDataset, open_dataset
from services.kit.app import include_site_routers, service_app
from services.kit.bus import Bus
from services.trainer.pool import PoolStatus
from services.trainer.settings import Settings
from services.trainer.state import (
    CarryError,
    TrainerStatus,
    UnknownBackendError,
)
from services.trainer.worker import TrainerWorker


def _pool(request: Request) -> TrainerWorker:
    """The trainer's one worker: the pool's, serving every site."""
    return request.app.state.worker


Worker = Annotated[TrainerWorker, Depends(_pool)]


def _site(request: Request, worker: Worker) -> str:
    """The site the path names (``/sites/{site}/…``; checked), else the run's first."""
    site = request.path_params.get("site")
    if site is None:
        return worker.sites[0]
    if site not in worker.sites:
        raise HTTPException(404, f"no site {site!r} in this run; its sites: "
                                 f"{', '.join(worker.sites)}")
    return site


Site = Annotated[str, Depends(_site)]


class DecisionInfo(BaseModel):
    decision_id: int = Field(description="Id of the decision the model trains on.", examples=[42])
    time_ms: float = Field(description="Its epoch t (sim ms): the time renders represent.",
                           examples=[1260.0])
    policy: str = Field(description="The scheduler's policy spec.", examples=["mat:51"])
    n_selected: int = Field(description="Frames the decision selected.", examples=[9])
    n_missing: int = Field(description="Selected frames the trainer never received (skipped).",
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
                                             "failed:<why>.", examples=[{"worker_died": 1}])
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
    window_s: float = Field(description="The window of the rates (AOI3D_TRAINER_WINDOW_S).",
                            examples=[30.0])
    by_site: dict[str, dict[str, int]] = Field(
        description="Site → its counts since start: decisions, assigned, rendered, superseded, "
                    "lost.", examples=[{"site1": {"decisions": 300, "assigned": 120,
                                                  "rendered": 118, "superseded": 180}}])


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
        window_s=pool.window_s, by_site=pool.by_site)


class StatusResponse(BaseModel):
    steps: int = Field(description="Training steps of the current model (since the last "
                                   "reset); the Render's training_step.", examples=[1200])
    steps_total: int = Field(description="Training steps since the service started.",
                             examples=[5400])
    steps_per_s: float = Field(description="Training steps per wall second over the last few "
                                           "seconds.", examples=[38.5])
    loss: float | None = Field(description="Loss of the last training step; null before the "
                                           "first step after start or reset.",
                               examples=[0.0123])
    n_views: int = Field(description="Frames in the training set.", examples=[9])
    decision: DecisionInfo | None = Field(description="The decision in force; null before the "
                                                      "first one.")
    backend: str = Field(description="Radiance-field backend in use (PUT /backend changes it).",
                         examples=["grid"])
    backends: list[str] = Field(description="Available backends (aoi3d.field.BACKENDS).",
                                examples=[["grid", "nerfacto", "ngp", "tensorf"]])
    device: str = Field(description="Torch device the field trains on.", examples=["cpu"])
    carry: str = Field(description="How renders are made (PUT /carry): fresh, fork or warm.",
                       examples=["fresh"])
    render_steps: int = Field(description="Training steps spent on a rendered decision's own "
                                          "frames (fork, fresh).", examples=[100])
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


def _status_body(status: TrainerStatus, site: str) -> StatusResponse:
    d = status.decision
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
        pool=pool_body(status.pool), site=site)


status_router = APIRouter(tags=["status"])


@status_router.get("/status", summary="Renders, the decision in force and the pool.")
def get_status(worker: Worker, site: Site) -> StatusResponse:
    return _status_body(worker.status(site), site)


pool_router = APIRouter(tags=["pool"])


@pool_router.get("/workers", summary="The reconstruction workers of the pool.",
                   description="Membership is Zenoh liveliness: a worker is listed from its "
                               "token's appearance to its vanishing (a killed worker's token "
                               "vanishes when the router loses its session). Rates, fraction, "
                               "waits and busy fractions are over the last `window_s`.")
def get_workers(worker: Worker) -> PoolInfo:
    return pool_body(worker.pool_status())


model_router = APIRouter(tags=["model"])


@model_router.post(
    "/reset", summary="Start new models (warm and fork carry one per worker; fresh always does).",
    description="Moves the model epoch on: each worker starts a new model at its next job. "
                "Counts in `resets`.")
def post_reset(worker: Worker) -> StatusResponse:
    worker.reset()
    return _status_body(worker.status(), worker.sites[0])


class BackendRequest(BaseModel):
    """The backend to train from now on."""

    backend: str = Field(description="A registered backend name (GET /status lists them under "
                                     "`backends`; `aoi3d field backends` describes them).",
                         examples=["ngp"])


_BACKEND_EXAMPLES = {
    "ngp": {"summary": "Instant-NGP (hash grid + tiny MLP)", "value": {"backend": "ngp"}},
    "grid": {"summary": "The dense voxel grid", "value": {"backend": "grid"}},
}


@model_router.put(
    "/backend", summary="Switch the radiance-field backend of the jobs from now on.",
    description="Every job handed out from now on names this backend; each worker builds its "
                "model with the backend's default config on its own device, with the same "
                "seed. Like POST /reset it moves the model epoch on (warm and fork models "
                "restart) and counts in `resets`. Renders from then on carry the new "
                "backend's name.",
    responses={422: {"description": "Unknown backend; the detail lists the available ones."}})
def put_backend(worker: Worker,
                body: Annotated[BackendRequest, Body(openapi_examples=_BACKEND_EXAMPLES)]
                ) -> StatusResponse:
    try:
        worker.set_backend(body.backend)
    except UnknownBackendError as err:
        raise HTTPException(422, str(err)) from None
    return _status_body(worker.status(), worker.sites[0])


class CarryRequest(BaseModel):
    """How renders are made from the next render on."""

    carry: Literal["fork", "fresh", "warm"] = Field(
        description="fresh: a new model trains `render_steps` steps on the rendered "
                    "decision's frames alone, then renders (the paper's per-time "
                    "reconstruction; the default); fork: a copy of the continuously trained "
                    "model does; warm: the continuously trained model renders as it is.",
        examples=["fresh"])
    render_steps: int | None = Field(
        None, ge=1, le=100_000,
        description="Steps on a rendered decision's own frames; null keeps the current "
                    "value.", examples=[100])


@model_router.put(
    "/carry", summary="Change how renders are made (fresh, fork or warm).",
    description="The experiments' carry modes (`aoi3d experiment ... --carry`), the same code "
                "(aoi3d.field.carry). Jobs handed out from now on carry it; warm and fork "
                "models (one per worker) are kept.",
    responses={422: {"description": "Unknown carry mode or render budget."}})
def put_carry(worker: Worker, body: CarryRequest) -> StatusResponse:
    steps = (body.render_steps if body.render_steps is not None
             else worker.render_settings.render_steps)
    try:
        worker.set_carry(body.carry, steps)
    except CarryError as err:
        raise HTTPException(422, str(err)) from None
    return _status_body(worker.status(), worker.sites[0])


render_router = APIRouter(tags=["render"])


@render_router.get(
    "/render.png", summary="The latest render of the held-out (novel) view.",
    response_class=Response,
    responses={200: {"content": {"image/png": {}},
                     "description": "PNG; headers X-Decision-Id, X-Time-Ms (the time it "
                                    "represents), X-Training-Step, X-Views, X-Carry, "
                                    "X-Render-Steps, X-Frames-Age-Ms (mean age of its frames "
                                    "at X-Time-Ms), X-Render-Age-S (wall s since the "
                                    "publication)."},
               404: {"description": "No render published yet."}})
def get_render(worker: Worker, site: Site) -> Response:
    latest = worker.latest_render(site)
    if latest is None:
        raise HTTPException(
            404, "no render yet: renders come once a decision has arrived and a "
                 "reconstruction worker has rendered it (GET /workers lists the pool)")
    headers = {"X-Decision-Id": str(latest.decision_id), "X-Time-Ms": f"{latest.time_ms:g}",
               "X-Training-Step": str(latest.training_step), "X-Views": str(latest.n_views),
               "X-Carry": latest.carry, "X-Render-Steps": str(latest.render_steps),
               "X-Frames-Age-Ms": f"{latest.frames_age_ms:g}",
               "X-Render-Age-S": f"{time.time() - latest.wall_s:.3f}",
               "X-Worker": latest.worker_id,
               "Cache-Control": "no-store"}
    return Response(content=latest.png, media_type="image/png", headers=headers)


def create_app(settings: Settings | None = None, *, bus: Bus | None = None,
               clock: SimClock | None = None, dataset: SceneDataset | None = None) -> FastAPI:
    """The trainer's app. ``dataset`` defaults to ``open_dataset(settings.common.dataset)``
    (read when the app starts: the held-out camera, the scene box and the image size)."""
    settings = settings or Settings()
    clock = clock or SimClock(settings.common.epoch_s, settings.common.time_scale)

    def build_worker(the_bus: Bus, registry) -> TrainerWorker:
        data = dataset if dataset is not None else open_dataset(settings.common.dataset)
        return TrainerWorker(settings, the_bus, registry, dataset=data, clock=clock)

    app = service_app(
        title="aoi3d trainer",
        description="The pool's dispatcher: takes each scheduler decision and hands it, with "
                    "the frames it selected, to exactly one reconstruction worker (`python -m "
                    "services.recon`, any number, joining and leaving at run time: GET "
                    "/workers), which trains a radiance field on them and publishes the render "
                    "of the held-out novel view. When the pool cannot keep up the newest "
                    "decision wins. The backend (grid, ngp, tensorf, nerfacto, … whatever "
                    "aoi3d.field.BACKENDS registers) is chosen at start "
                    "(AOI3D_TRAINER_BACKEND) and switched at run time with `PUT /backend "
                    "{\"backend\": \"ngp\"}`.",
        settings=settings, build_worker=build_worker, bus=bus)
    app.include_router(model_router)
    app.include_router(pool_router)
    # status and render are per site (/sites/<site>/status …); the pool and the settings the
    # run's
    include_site_routers(app, status_router, render_router)
    return app
