"""The network service's FastAPI app: the links' delay config, plus the kit's ops routes."""

from __future__ import annotations

from typing import Annotated

from fastapi import APIRouter, Depends, FastAPI, HTTPException, Request
from prometheus_client import CollectorRegistry
from pydantic import BaseModel, ConfigDict, Field

from aoi3d.channel import ACCEPTED_FORMS, CHANNEL_FORMS, trace_path_of
from aoi3d.clock import SimClock
from services.kit.app import get_worker, include_site_routers, service_app
from services.kit.bus import Bus
from services.kit.guard import OutsideRoots, confined_path
from services.kit.keys import Keys
from services.network.runtime import ChannelConfig, NetworkRuntime
from services.network.settings import Settings

DESCRIPTION = """
The cameras' uplinks: one D/G/1/0 link per training camera (single server, no waiting room).

A frame offered on `aoi3d/<run>/cam/<n>/frame` while camera n's previous frame is still in
flight is dropped; otherwise it is delivered on `aoi3d/<run>/edge/<n>/frame` after a sampled
delay (slotted, 1 ms slots), stamped with its delivery time. `GET/PUT /channel` reads and
changes the delay distributions and the seed. The channel may also change by itself:
`regimes:exp:20@10s,exp:200@10s` cycles through regimes, `trace:PATH` replays a mahimahi
cellular trace per camera (a frame's transmission time from its encoded bytes), `cell:PATH`
shares one trace's capacity among the cameras; each starts playing when it is set. `changes`
lists when the channel changed (set here, or the next regime) and `measured_delay_ms` is the
mean delay of the frames delivered over the last few seconds.
"""

WorkerDep = Annotated[NetworkRuntime, Depends(get_worker)]
_ALL_FORMS = (*ACCEPTED_FORMS, *CHANNEL_FORMS)
_FORMS = ", ".join(_ALL_FORMS)


class LinkView(BaseModel):
    """One camera's link."""

    camera: int = Field(description="Camera id.", examples=[3])
    delay: str = Field(description="Delay spec in force.", examples=["exp:60"])
    mean_delay_ms: float = Field(description="Mean transmission time E[Y] in ms.",
                                 examples=[60.0])
    offered: int = Field(description="Frames offered since the service started.")
    dropped: int = Field(description="Frames dropped: the previous one was still in flight.")
    delivered: int = Field(description="Frames delivered to the edge.")
    in_flight: bool = Field(description="Whether a frame is on the link now.")


class ChannelChange(BaseModel):
    """One change of the channel: set over REST, or the next regime of a schedule."""

    time_ms: float = Field(description="Sim time of the change (ms).")
    spec: str = Field(description="The spec in force from then.", examples=["exp:200"])
    cause: str = Field(description="`set` (over REST or at start) or `regime`.")
    delay: str | None = Field(None, description="The whole spec set (for `set`).")


class ChannelView(BaseModel):
    """The links' settings and state."""

    delay: str = Field(description="Delay spec of the links without an override.",
                       examples=["exp:60"])
    per_camera: dict[int, str] = Field(description="Per-camera delay overrides.",
                                       examples=[{"3": "const:40"}])
    seed: int = Field(description="Seed of the links' random streams.", examples=[1])
    accepted_forms: list[str] = Field(description="Delay spec forms (values in ms; "
                                                  "lognormal's MU and SIGMA are of ln Y).",
                                      examples=[list(_ALL_FORMS)])
    links: list[LinkView] = Field(description="Every camera's link, by camera id.")
    in_force: str = Field(description="The spec in force now on the links without an "
                                      "override (a regimes schedule's current regime).",
                          examples=["exp:200"])
    started_ms: float = Field(description="Sim time (ms) the default channel was set at; its "
                                          "regimes and trace count from there.")
    changes: list[ChannelChange] = Field(description="The channel's recent changes, oldest "
                                                     "first.")
    measured_delay_ms: float | None = Field(
        description="Mean delay (delivery − generation, ms) of the frames delivered in the "
                    "last `measure_window_ms` of sim time; null when none was.")
    measured_frames: int = Field(description="Frames that mean is over.")
    measure_window_ms: float = Field(description="The window of the measured delay (ms).")


class ChannelUpdate(BaseModel):
    """A partial update: fields left out keep their value."""

    model_config = ConfigDict(extra="forbid", json_schema_extra={"examples": [
        {"delay": "exp:60"}, {"per_camera": {"3": "const:40"}}, {"seed": 7},
        {"delay": "regimes:exp:20@10s,exp:200@10s"},
        {"delay": "trace:../shared/data/traces/TMobile-LTE-short.up"},
        {"delay": "uniform:20:100", "per_camera": {}, "seed": 1}]})

    delay: str | None = Field(None, description=f"Delay spec of every link without an "
                                                f"override ({_FORMS}; ms).",
                              examples=["exp:60"])
    per_camera: dict[int, str] | None = Field(
        None, description="Per-camera overrides; replaces the whole map ({} clears it).",
        examples=[{"3": "const:40"}])
    seed: int | None = Field(None, ge=0, description="New seed; each link restarts its random "
                                                     "stream once its frame in flight is "
                                                     "delivered.", examples=[1])


def _view(worker: NetworkRuntime, cfg: ChannelConfig) -> ChannelView:
    links = [LinkView(camera=s.camera_id, delay=s.delay.spec, mean_delay_ms=s.delay.mean_ms,
                      offered=s.offered, dropped=s.dropped, delivered=s.delivered,
                      in_flight=s.in_flight) for s in worker.link_stats()]
    state = worker.channel_state()
    return ChannelView(delay=cfg.delay, per_camera=dict(cfg.per_camera), seed=cfg.seed,
                       accepted_forms=list(_ALL_FORMS), links=links,
                       in_force=state["in_force"], started_ms=state["started_ms"],
                       changes=[ChannelChange(**c) for c in state["changes"]],
                       measured_delay_ms=state["measured_delay_ms"],
                       measured_frames=state["measured_frames"],
                       measure_window_ms=state["measure_window_ms"])


channel_router = APIRouter(prefix="/channel", tags=["channel"])


@channel_router.get("", summary="The links' delay settings and counts.")
def get_channel(worker: WorkerDep) -> ChannelView:
    return _view(worker, worker.config)


@channel_router.put("", summary="Change the delay spec, per-camera overrides or seed.",
                    responses={422: {"description": "Bad delay spec, unreadable trace or unknown "
                                                    "camera (nothing changes); the detail "
                                                    "lists what is accepted."}})
def put_channel(update: ChannelUpdate, worker: WorkerDep, request: Request) -> ChannelView:
    roots = request.app.state.settings.common.files_roots
    try:  # a trace is read only from the folders requests may name, checked before reading
        for spec in [update.delay, *(update.per_camera or {}).values()]:
            path = trace_path_of(spec) if spec is not None else None
            if path:
                confined_path(path, roots, "a trace path")
    except OutsideRoots as err:
        raise HTTPException(status_code=422, detail=str(err)) from None
    try:
        cfg = worker.update(delay=update.delay, per_camera=update.per_camera, seed=update.seed)
    except ValueError as err:  # DelaySpecError, ChannelConfigError
        raise HTTPException(status_code=422, detail=str(err)) from err
    return _view(worker, cfg)


def create_app(settings: Settings | None = None, *, bus: Bus | None = None,
               clock: SimClock | None = None,
               registry: CollectorRegistry | None = None) -> FastAPI:
    """The network service. Tests inject a ``MemoryBus`` and a fast clock."""
    settings = settings or Settings()
    common = settings.common
    clock = clock or SimClock(common.epoch_s, common.time_scale)

    def build_worker(the_bus: Bus, the_registry: CollectorRegistry, site: str) -> NetworkRuntime:
        # each site's links draw their own delays: the seed moves on by the site's index
        return NetworkRuntime(
            bus=the_bus, registry=the_registry, clock=clock, keys=Keys(common.run_id, site),
            n_cameras=common.cameras, delay=settings.delay, per_camera=settings.per_camera,
            seed=settings.seed + common.sites.index(site), max_skew_ms=settings.common.skew_ms,
            inbox_size=settings.inbox_size, frame_encoding=settings.frame_encoding)

    app = service_app(title="aoi3d network", description=DESCRIPTION, settings=settings,
                      build_worker=build_worker, bus=bus, registry=registry, per_site=True)
    include_site_routers(app, channel_router)
    return app
