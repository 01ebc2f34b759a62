"""REST API of the trainer: status, model reset, backend switch and the latest novel-view
render."""

from __future__ import annotations

import time
from typing import Annotated, Literal

from fastapi import APIRouter, Body, Depends, FastAPI, HTTPException
from fastapi.responses import Response
from pydantic import BaseModel, Field

from aoi3d.clock import SimClock
from aoi3d.field import BACKENDS, FieldConfig
from aoi3d.scene import SceneDataset, open_dataset
from services.kit.app import get_worker, service_app
from services.kit.bus import Bus
from services.trainer.settings import Settings
from services.trainer.state import (
    BackendBuildError,
    CarryError,
    TrainerStatus,
    UnknownBackendError,
)
from services.trainer.worker import TrainerWorker

Worker = Annotated[TrainerWorker, Depends(get_worker)]


class DecisionInfo(BaseModel):
    decision_id: int = Field(description="Id of the decision the model trains on.", examples=[42])
    time_ms: float = Field(description="Its epoch t (sim ms): the time renders represent.",
                           examples=[1260.0])
    policy: str = Field(description="The scheduler's policy spec.", examples=["mat:51"])
    n_selected: int = Field(description="Frames the decision selected.", examples=[9])
    n_missing: int = Field(description="Selected frames the trainer never received (skipped).",
                           examples=[0])
    age_ms: float = Field(description="Sim ms since the decision epoch.", examples=[35.0])


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
    running: bool = Field(description="Whether the training thread is alive.", examples=[True])


def _status_body(status: TrainerStatus) -> StatusResponse:
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
        frames_missing=status.frames_missing, resets=status.resets, running=status.running)


status_router = APIRouter(tags=["status"])


@status_router.get("/status", summary="Training progress and the decision in force.")
def get_status(worker: Worker) -> StatusResponse:
    return _status_body(worker.status())


model_router = APIRouter(tags=["model"])


@model_router.post(
    "/reset", summary="Re-initialise the radiance field (training set and frames kept).",
    responses={503: {"description": "The training thread did not get to the reset in time."}})
def post_reset(worker: Worker) -> StatusResponse:
    if not worker.reset():
        raise HTTPException(503, "the training thread did not perform the reset within 10 s; "
                                 "check GET /status and /readyz")
    return _status_body(worker.status())


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
    "/backend", summary="Switch the radiance-field backend (a new model; views and frames kept).",
    description="Replaces the model by a fresh one of the named backend, built with its "
                "default config on the same device and seed. The training set (the decision "
                "in force) and the buffered frames are kept, and training resumes at once; "
                "like POST /reset it restarts `steps` at 0 and counts in `resets`. Renders "
                "from then on carry the new backend's name. The switch is done by the "
                "training thread between two chunks of steps.",
    responses={422: {"description": "Unknown backend; the detail lists the available ones."},
               500: {"description": "The backend's model could not be built; the previous "
                                    "backend keeps training."},
               503: {"description": "The training thread did not get to the switch in time."}})
def put_backend(worker: Worker,
                body: Annotated[BackendRequest, Body(openapi_examples=_BACKEND_EXAMPLES)]
                ) -> StatusResponse:
    try:
        switched = worker.set_backend(body.backend)
    except UnknownBackendError as err:
        raise HTTPException(422, str(err)) from None
    except BackendBuildError as err:
        raise HTTPException(500, str(err)) from None
    if not switched:
        raise HTTPException(503, "the training thread did not switch the backend within 30 s; "
                                 "check GET /status and /readyz")
    return _status_body(worker.status())


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
                "(aoi3d.field.carry). Takes effect at the next render; the continuously "
                "trained model (fork, warm) and the decision in force are kept.",
    responses={422: {"description": "Unknown carry mode or render budget."},
               503: {"description": "The training thread did not get to the change in time."}})
def put_carry(worker: Worker, body: CarryRequest) -> StatusResponse:
    steps = body.render_steps if body.render_steps is not None else worker.rec.render_steps
    try:
        done = worker.set_carry(body.carry, steps)
    except CarryError as err:
        raise HTTPException(422, str(err)) from None
    if not done:
        raise HTTPException(503, "the training thread did not change the carry within 10 s; "
                                 "check GET /status and /readyz")
    return _status_body(worker.status())


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
def get_render(worker: Worker) -> Response:
    latest = worker.latest_render()
    if latest is None:
        raise HTTPException(
            404, f"no render yet: the trainer renders the held-out camera "
                 f"{worker.settings.render_period_s:g} s after each previous render once a "
                 f"decision has arrived")
    headers = {"X-Decision-Id": str(latest.decision_id), "X-Time-Ms": f"{latest.time_ms:g}",
               "X-Training-Step": str(latest.training_step), "X-Views": str(latest.n_views),
               "X-Carry": latest.carry, "X-Render-Steps": str(latest.render_steps),
               "X-Frames-Age-Ms": f"{latest.frames_age_ms:g}",
               "X-Render-Age-S": f"{time.time() - latest.wall_s:.3f}",
               "Cache-Control": "no-store"}
    return Response(content=latest.png, media_type="image/png", headers=headers)


def create_app(settings: Settings | None = None, *, bus: Bus | None = None,
               clock: SimClock | None = None, dataset: SceneDataset | None = None,
               field_config: FieldConfig | None = None) -> FastAPI:
    """The trainer's app. ``dataset`` defaults to ``open_dataset(settings.common.dataset)``
    (read when the app starts); ``field_config`` overrides the backend's default config."""
    settings = settings or Settings()
    clock = clock or SimClock(settings.common.epoch_s, settings.common.time_scale)

    def build_worker(the_bus: Bus, registry) -> TrainerWorker:
        data = dataset if dataset is not None else open_dataset(settings.common.dataset)
        return TrainerWorker(settings, the_bus, registry, dataset=data, clock=clock,
                             field_config=field_config)

    app = service_app(
        title="aoi3d trainer",
        description="Trains a radiance field on the frames each scheduler decision selects "
                    "and publishes renders of the held-out novel view. The backend (grid, "
                    "ngp, tensorf, nerfacto, … whatever aoi3d.field.BACKENDS registers) is "
                    "chosen at start (AOI3D_TRAINER_BACKEND) and can be switched at run time "
                    "with `PUT /backend {\"backend\": \"ngp\"}`: the model restarts, views "
                    "and buffered frames are kept.",
        settings=settings, build_worker=build_worker, bus=bus)
    app.include_router(status_router)
    app.include_router(model_router)
    app.include_router(render_router)
    return app
