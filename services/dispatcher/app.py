"""REST API of the dispatcher service — the pool's dispatcher, which hands each decision to one
reconstruction worker and publishes its render (it trains no model itself; the name is the
service's, kept for its REST paths, compose service and ``aoi3d_dispatcher_*`` series): status,
model reset, backend switch and the latest novel-view render."""

from __future__ import annotations

import time
from typing import Annotated, Literal

from fastapi import APIRouter, Body, Depends, FastAPI, HTTPException, Query, Request
from fastapi.responses import Response
from pydantic import BaseModel, Field

from aoi3d.clock import SimClock
from aoi3d.field.carry import CarryMode
from aoi3d.rigfile import load_rig
from aoi3d.scene import SceneDataset, open_dataset
from services.dispatcher.runtime import DispatcherRuntime
from services.dispatcher.schemas import PoolInfo, StatusResponse, pool_body, status_body
from services.dispatcher.settings import Settings
from services.dispatcher.state import (
    CarryError,
    UnknownBackendError,
)
from services.dispatcher.views import ViewRefused
from services.kit.app import include_site_routers, service_app
from services.kit.bus import Bus


def _pool(request: Request) -> DispatcherRuntime:
    """The dispatcher's one worker: the pool's, serving every site."""
    return request.app.state.worker


Worker = Annotated[DispatcherRuntime, Depends(_pool)]


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
        description="stream (the default, with 25 steps): each worker starts from its "
                    "previous decision's model and trains `render_steps` steps, a share of "
                    "them on the pixels that changed (cold starts: cold_steps); fresh: a new "
                    "model trains `render_steps` steps on the rendered decision's frames "
                    "alone, then renders (the paper's per-time reconstruction; give it 100 "
                    "steps); fork: a copy of the continuously trained model does; warm: the "
                    "continuously trained model renders as it is.",
        examples=["fresh"])
    render_steps: int | None = Field(
        None, ge=1, le=100_000,
        description="Steps on a rendered decision's own frames; null keeps the current "
                    "value (so name it when switching between stream's 25 and fresh's "
                    "100).", examples=[100])


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


_VIEW_HEADERS = ("X-Decision-Id (the decision whose model answered), X-Time-Ms, "
                 "X-Training-Step, X-Worker, X-Free-View: 1, X-Compute-S")


@render_router.get(
    "/render.png", summary="The latest render of the held-out (novel) view, or a free view "
                           "of the latest model from any pose.",
    description="Without `c2w`: the latest render of the held-out camera, the scored one. With "
                "`c2w`: the site's latest model (kept by the worker that rendered its latest "
                "decision) rendered from that pose on request — a free view, never scored "
                "(there is no truth there) and never delaying a decision's render; rate "
                "limited (429) and bounded in size (`AOI3D_DISPATCHER_VIEW_RATE_PER_S`, "
                "`AOI3D_DISPATCHER_MAX_VIEW_SIDE`), every refusal counted in "
                "`aoi3d_dispatcher_views_total{outcome}`.",
    response_class=Response,
    responses={200: {"content": {"image/png": {}},
                     "description": "PNG; headers X-Decision-Id, X-Time-Ms (the time it "
                                    "represents), X-Training-Step, X-Views, X-Carry, "
                                    "X-Render-Steps, X-Frames-Age-Ms (mean age of its frames "
                                    "at X-Time-Ms), X-Render-Age-S (wall s since the "
                                    "publication). A free view: " + _VIEW_HEADERS + "."},
               404: {"description": "No render (or, for a free view, no model) yet."},
               422: {"description": "A bad pose (not 16 finite numbers, not a rigid "
                                    "transform, too far from the scene box) or size."},
               429: {"description": "Too many free views or exports a second."},
               503: {"description": "The worker took a newer free view instead."},
               504: {"description": "The worker did not answer in time."}})
def get_render(
    worker: Worker, site: Site,
    c2w: Annotated[str | None, Query(
        description="A free view's camera-to-world pose: 16 numbers separated by commas, "
                    "row-major 4x4, OpenGL axes as in transforms.json (the camera looks along "
                    "its -z axis, y up).", max_length=2000,
        examples=["1,0,0,0,0,0,-1,-4,0,1,0,1.5,0,0,0,1"])] = None,
    width: Annotated[int | None, Query(
        ge=1, le=100_000, description="A free view's width in pixels (default: the held-out "
                                      "camera's).")] = None,
    height: Annotated[int | None, Query(
        ge=1, le=100_000, description="A free view's height in pixels (default: the held-out "
                                      "camera's).")] = None,
    fov: Annotated[float | None, Query(
        gt=0, lt=180, description="A free view's vertical field of view in degrees (default: "
                                  "the held-out camera's).")] = None,
) -> Response:
    if c2w is not None:
        try:
            png, reply = worker.views.free_view(site, c2w, width, height, fov)
        except ViewRefused as err:
            raise HTTPException(err.status, err.detail) from None
        return Response(content=png, media_type="image/png",
                        headers=_view_headers(reply))
    if width is not None or height is not None or fov is not None:
        raise HTTPException(422, "width, height and fov set a free view: give c2w too")
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


def _view_headers(reply) -> dict[str, str]:
    return {"X-Decision-Id": str(reply.decision_id), "X-Time-Ms": f"{reply.time_ms:g}",
            "X-Training-Step": str(reply.training_step), "X-Worker": reply.worker_id,
            "X-Free-View": "1", "X-Compute-S": f"{reply.compute_s:.3f}",
            "Cache-Control": "no-store"}


@render_router.get(
    "/export.ply", summary="The latest model as a .ply other tools open (point cloud or mesh).",
    description="`format=points` (default): a coloured point cloud — the field's density "
                "sampled on a `resolution`³ lattice over the scene box where its occupancy "
                "grid allows, the points whose opacity over one lattice step reaches `alpha`, "
                "each with its colour seen from the box's centre (x y z, red green blue, "
                "density). `format=mesh`: marching cubes (scikit-image) at that opacity, "
                "vertices coloured. Lost either way: view dependence, the background, "
                "anything finer than the lattice. Rate limited as free views "
                "(`aoi3d_dispatcher_views_total{kind=\"export\"}`).",
    response_class=Response,
    responses={200: {"content": {"application/octet-stream": {}},
                     "description": "A binary PLY; headers " + _VIEW_HEADERS + "."},
               404: {"description": "No model yet."},
               422: {"description": "A bad format, resolution or alpha."},
               429: {"description": "Too many free views or exports a second."}})
def get_export(
    worker: Worker, site: Site,
    format: Annotated[Literal["points", "mesh"], Query(
        description="points: a coloured point cloud; mesh: a coloured triangle mesh.")]
    = "points",
    resolution: Annotated[int, Query(ge=8, le=256, description="Lattice points a side.")] = 96,
    alpha: Annotated[float, Query(gt=0, lt=1, description="Opacity kept.")] = 0.1,
) -> Response:
    try:
        data, reply = worker.views.export(site, "ply" if format == "points" else "mesh", resolution,
                                    alpha)
    except ViewRefused as err:
        raise HTTPException(err.status, err.detail) from None
    headers = _view_headers(reply)
    headers["Content-Disposition"] = f'attachment; filename="{site}.ply"'
    return Response(content=data, media_type="application/octet-stream", headers=headers)


def create_app(settings: Settings | None = None, *, bus: Bus | None = None,
               clock: SimClock | None = None, dataset: SceneDataset | None = None) -> FastAPI:
    """The dispatcher's app. ``dataset`` defaults to ``open_dataset(settings.common.dataset)``
    (read when the app starts: the held-out camera, the scene box and the image size); with a
    rig file (``AOI3D_RIG``, real cameras) they are the rig's view, box and working size."""
    settings = settings or Settings()
    clock = clock or SimClock(settings.common.epoch_s, settings.common.time_scale)

    def build_worker(the_bus: Bus, registry) -> DispatcherRuntime:
        if settings.common.rig is not None and dataset is None:  # real cameras
            return DispatcherRuntime(settings, the_bus, registry, rig=load_rig(settings.common.rig),
                                 clock=clock)
        data = dataset if dataset is not None else open_dataset(settings.common.dataset)
        return DispatcherRuntime(settings, the_bus, registry, dataset=data, clock=clock)

    app = service_app(
        title="aoi3d dispatcher",
        description="The pool's dispatcher: takes each scheduler decision and hands it, with "
                    "the frames it selected, to exactly one reconstruction worker (`python -m "
                    "services.recon`, any number, joining and leaving at run time: GET "
                    "/workers), which trains a radiance field on them and publishes the render "
                    "of the held-out novel view. When the pool cannot keep up the newest "
                    "decision wins. The backend (grid, ngp, tensorf, nerfacto, … whatever "
                    "aoi3d.field.BACKENDS registers) is chosen at start "
                    "(AOI3D_DISPATCHER_BACKEND) and switched at run time with `PUT /backend "
                    "{\"backend\": \"ngp\"}`.",
        settings=settings, build_worker=build_worker, bus=bus)
    app.include_router(model_router)
    app.include_router(pool_router)
    # status and render are per site (/sites/<site>/status …); the pool and the settings the
    # run's
    include_site_routers(app, status_router, render_router)
    return app
