"""REST API of the trainer service — the pool's dispatcher, which hands each decision to one
reconstruction worker and publishes its render (it trains no model itself; the name is the
service's, kept for its REST paths, compose service and ``aoi3d_trainer_*`` series): status,
model reset, backend switch and the latest novel-view render."""

from __future__ import annotations

import time
from typing import Annotated

from fastapi import APIRouter, Body, Depends, FastAPI, HTTPException, Request
from fastapi.responses import Response
from pydantic import BaseModel, Field

from aoi3d.clock import SimClock
from aoi3d.field.carry import CarryMode
from aoi3d.rigfile import load_rig
from aoi3d.scene import SceneDataset, open_dataset
from services.kit.app import include_site_routers, service_app
from services.kit.bus import Bus
from services.trainer.schemas import PoolInfo, StatusResponse, pool_body, status_body
from services.trainer.settings import Settings
from services.trainer.state import (
    CarryError,
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


status_router = APIRouter(tags=["status"])


@status_router.get("/status", summary="Renders, the decision in force and the pool.")
def get_status(worker: Worker, site: Site) -> StatusResponse:
    return status_body(worker.status(site), site)


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
    return status_body(worker.status(), worker.sites[0])


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
    return status_body(worker.status(), worker.sites[0])


class CarryRequest(BaseModel):
    """How renders are made from the next render on."""

    carry: CarryMode = Field(
        description="fresh: a new model trains `render_steps` steps on the rendered "
                    "decision's frames alone, then renders (the paper's per-time "
                    "reconstruction; the default); stream: each worker starts from its "
                    "previous decision's model and trains `render_steps` steps, a share of "
                    "them on the pixels that changed (cold starts: cold_steps); fork: a copy "
                    "of the continuously trained model does; warm: the continuously trained "
                    "model renders as it is.",
        examples=["fresh"])
    render_steps: int | None = Field(
        None, ge=1, le=100_000,
        description="Steps on a rendered decision's own frames; null keeps the current "
                    "value.", examples=[100])


@model_router.put(
    "/carry", summary="Change how renders are made (fresh, stream, fork or warm).",
    description="The experiments' carry modes (`aoi3d experiment ... --carry`), the same code "
                "(aoi3d.field.carry). Jobs handed out from now on carry it; warm and fork "
                "models (one per worker) are kept.",
    responses={422: {"description": "Unknown carry mode or render budget."}})
def put_carry(worker: Worker, body: CarryRequest) -> StatusResponse:
    steps = (body.render_steps if body.render_steps is not None
             else worker.render.render_steps)
    try:
        worker.set_carry(body.carry, steps)
    except CarryError as err:
        raise HTTPException(422, str(err)) from None
    return status_body(worker.status(), worker.sites[0])


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
    (read when the app starts: the held-out camera, the scene box and the image size); with a
    rig file (``AOI3D_RIG``, real cameras) they are the rig's view, box and working size."""
    settings = settings or Settings()
    clock = clock or SimClock(settings.common.epoch_s, settings.common.time_scale)

    def build_worker(the_bus: Bus, registry) -> TrainerWorker:
        if settings.common.rig is not None and dataset is None:  # real cameras
            return TrainerWorker(settings, the_bus, registry, rig=load_rig(settings.common.rig),
                                 clock=clock)
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
