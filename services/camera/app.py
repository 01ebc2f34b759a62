"""The camera service's FastAPI app: the rig's generation config, plus the kit's ops routes."""

from __future__ import annotations

from typing import Annotated

from fastapi import APIRouter, Depends, FastAPI, HTTPException
from prometheus_client import CollectorRegistry
from pydantic import BaseModel, ConfigDict, Field

from aoi3d.clock import SimClock
from aoi3d.scene import SceneDataset, open_dataset
from services.camera.runtime import (
    MAX_PERIOD_MS,
    MIN_PERIOD_MS,
    CameraConfig,
    CameraConfigError,
    CameraRuntime,
)
from services.camera.settings import Settings
from services.kit.app import get_worker, include_site_routers, service_app
from services.kit.bus import Bus
from services.kit.keys import Keys

DESCRIPTION = """
Plays the scene dataset back as a live camera rig on the shared simulation clock.

Every period C (sim ms), at t = k·C, each active training camera n publishes the frame shown
at t on `aoi3d/<run>/cam/<n>/frame`; the held-out camera 0 publishes on
`aoi3d/<run>/truth/frame`. `GET/PUT /config` reads and changes the period, pause state and
active cameras.
"""

WorkerDep = Annotated[CameraRuntime, Depends(get_worker)]


class CameraConfigView(BaseModel):
    """The rig's current generation settings."""

    period_ms: float = Field(description="Generation period C in sim ms; frames at t = k·C.",
                             examples=[30.0])
    paused: bool = Field(description="Whether generation is paused.", examples=[False])
    cameras: list[int] = Field(description="Training cameras that stream, by id.",
                               examples=[[1, 2, 3]])
    rig: list[int] = Field(description="All training camera ids of this run (1..N): the ids "
                                       "`cameras` accepts.", examples=[[1, 2, 3, 4]])
    heldout_id: int = Field(description="The held-out camera (ground truth on truth/frame; "
                                        "always published while not paused).", examples=[0])


class CameraConfigUpdate(BaseModel):
    """A partial update: fields left out keep their value. Effective from the next tick."""

    model_config = ConfigDict(extra="forbid", json_schema_extra={"examples": [
        {"period_ms": 30}, {"paused": True}, {"cameras": [1, 2, 3]}]})

    period_ms: float | None = Field(None, ge=MIN_PERIOD_MS, le=MAX_PERIOD_MS,
                                    description="New generation period C in sim ms (one slot, "
                                                "1 ms, to 60 s).",
                                    examples=[30.0])
    paused: bool | None = Field(None, description="Pause (true) or resume (false).",
                                examples=[True])
    cameras: list[int] | None = Field(None, description="Training camera ids to stream (a "
                                      "subset of `rig`; [] streams only the held-out view).",
                                      examples=[[1, 2, 3]])


def _view(worker: CameraRuntime, cfg: CameraConfig) -> CameraConfigView:
    return CameraConfigView(period_ms=cfg.period_ms, paused=cfg.paused, cameras=list(cfg.cameras),
                            rig=list(worker.rig), heldout_id=worker.heldout_id)


config_router = APIRouter(prefix="/config", tags=["config"])


@config_router.get("", summary="The rig's generation settings.")
def get_config(worker: WorkerDep) -> CameraConfigView:
    return _view(worker, worker.config)


@config_router.put("", summary="Change period, pause state or active cameras (partial).",
                   responses={422: {"description": "Invalid value; the detail says what is "
                                                   "accepted."}})
def put_config(update: CameraConfigUpdate, worker: WorkerDep) -> CameraConfigView:
    try:
        cfg = worker.update(period_ms=update.period_ms, paused=update.paused,
                            cameras=update.cameras)
    except CameraConfigError as err:
        raise HTTPException(status_code=422, detail=str(err)) from err
    return _view(worker, cfg)


def create_app(settings: Settings | None = None, *, bus: Bus | None = None,
               clock: SimClock | None = None, dataset: SceneDataset | None = None,
               registry: CollectorRegistry | None = None) -> FastAPI:
    """The camera service. Tests inject a ``MemoryBus``, a fast clock and/or a dataset."""
    settings = settings or Settings()
    common = settings.common
    clock = clock or SimClock(common.epoch_s, common.time_scale)

    opened: list[SceneDataset] = [] if dataset is None else [dataset]

    def build_worker(the_bus: Bus, the_registry: CollectorRegistry, site: str) -> CameraRuntime:
        if not opened:
            opened.append(open_dataset(common.dataset))
        ds = opened[0]
        # each site films the same scene at its own phase: the loop split evenly among them
        loop_ms = 1000.0 * ds.n_frames / ds.fps
        phase_ms = loop_ms * common.sites.index(site) / len(common.sites)
        return CameraRuntime(
            bus=the_bus, registry=the_registry, dataset=ds, clock=clock,
            keys=Keys(common.run_id, site), n_cameras=common.cameras,
            period_ms=settings.period_ms, paused=settings.paused,
            cameras=settings.active_cameras or None, phase_ms=phase_ms)

    app = service_app(title="aoi3d camera", description=DESCRIPTION, settings=settings,
                      build_worker=build_worker, bus=bus, registry=registry, per_site=True)
    include_site_routers(app, config_router)
    return app
