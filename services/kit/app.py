"""The FastAPI app factory every service uses.

``service_app`` gives each service ``/healthz``, ``/readyz`` and ``/metrics`` and a lifespan
that opens the bus (Zenoh unless a bus is injected, as tests do), builds and starts the
worker, and stops both on shutdown. Routes reach the worker through ``app.state.worker``.

A per-site service (camera, network, scheduler, metrics) builds one worker per site of the run
(``CommonSettings.sites``), each with a registry of its own; ``/metrics`` shows them all with a
``site`` label (:class:`SiteLabels`). :func:`include_site_routers` mounts the service's routers
twice: at the root (the first site, today's paths) and under ``/sites/{site}``;
:func:`get_worker` picks the worker the path names.
"""

from __future__ import annotations

import logging
import os
from collections.abc import AsyncIterator, Callable, Iterator
from contextlib import asynccontextmanager
from typing import Annotated, Literal, Protocol, TypeVar

from fastapi import APIRouter, Depends, FastAPI, HTTPException, Path, Request
from fastapi.responses import JSONResponse, Response
from fastapi_offline import FastAPIOffline
from prometheus_client import CONTENT_TYPE_LATEST, CollectorRegistry, generate_latest
from prometheus_client.metrics_core import Metric
from prometheus_client.samples import Sample

from services.kit.bus import Bus, ZenohBus
from services.kit.guard import guard_app
from services.kit.settings import ServiceSettings, zenoh_config

log = logging.getLogger(__name__)

LOOPBACK = frozenset({"127.0.0.1", "localhost", "::1"})


class Worker(Protocol):
    def start(self) -> None: ...

    def stop(self) -> None: ...

    def readiness(self) -> tuple[bool, str]:
        """(ready, why not) — e.g. (False, "no frame delivered yet")."""
        ...


def get_worker(request: Request):
    """The worker of the site the path names (``/sites/{site}/…``), else the first site's."""
    site = request.path_params.get("site")
    if site is None:
        return request.app.state.worker
    workers = request.app.state.workers
    if site not in workers:
        raise HTTPException(404, f"no site {site!r} in this run; its sites: "
                                 f"{', '.join(workers)}")
    return workers[site]


def _site_param(site: Annotated[str, Path(
        description="A site of the run (AOI3D_SITES; GET /sites lists them).",
        examples=["site1"], max_length=32)]) -> str:
    return site


def include_site_routers(app: FastAPI, *routers: APIRouter) -> None:
    """Each router at the root (the first site) and under ``/sites/{site}``."""
    for router in routers:
        app.include_router(router)
    for router in routers:
        app.include_router(router, prefix="/sites/{site}", dependencies=[Depends(_site_param)],
                           responses={404: {"description": "No such site in this run."}})


class SiteLabels:
    """A collector showing the per-site registries as one, each sample labelled ``site``."""

    def __init__(self, registries: dict[str, CollectorRegistry]) -> None:
        self._registries = registries

    def describe(self) -> list[Metric]:
        return []

    def collect(self) -> Iterator[Metric]:
        merged: dict[str, Metric] = {}
        for site, registry in self._registries.items():
            for family in registry.collect():
                out = merged.get(family.name)
                if out is None:
                    out = merged[family.name] = Metric(family.name, family.documentation,
                                                       family.type, family.unit)
                out.samples.extend(
                    Sample(s.name, {**s.labels, "site": site}, s.value, s.timestamp,
                           s.exemplar) for s in family.samples)
        yield from merged.values()


def service_app(
    *,
    title: str,
    description: str,
    settings: ServiceSettings,
    build_worker: Callable[..., Worker],
    bus: Bus | None = None,
    registry: CollectorRegistry | None = None,
    per_site: bool = False,
) -> FastAPI:
    """``build_worker(bus, registry)``, or with ``per_site`` ``build_worker(bus, registry,
    site)`` once per site of the run."""
    registry = registry or CollectorRegistry()
    sites = list(settings.common.sites)
    site_registries = {site: CollectorRegistry() for site in sites} if per_site else {}
    if per_site:
        registry.register(SiteLabels(site_registries))

    @asynccontextmanager
    async def lifespan(app: FastAPI) -> AsyncIterator[None]:
        own_bus = bus is None
        the_bus = bus or ZenohBus(zenoh_config(settings.common))
        if per_site:
            workers = {site: build_worker(the_bus, site_registries[site], site)
                       for site in sites}
        else:
            workers = {sites[0]: build_worker(the_bus, registry)}
        app.state.workers = workers
        app.state.worker = next(iter(workers.values()))
        app.state.bus = the_bus
        for worker in workers.values():
            worker.start()
        log.info("%s started (run %s, sites %s)", title, settings.common.run_id,
                 ", ".join(sites))
        try:
            yield
        finally:
            for worker in workers.values():
                worker.stop()
            if own_bus:
                the_bus.close()
            log.info("%s stopped", title)

    # /docs and /redoc from the Swagger UI and ReDoc assets installed with fastapi-offline
    # (served under /static-offline-docs): no CDN, so the API docs work on an offline machine
    app = FastAPIOffline(title=title, description=description, version="0.1.0",
                         lifespan=lifespan)
    app.state.registry = registry
    app.state.settings = settings
    common = settings.common
    guard_app(app, allowed_hosts=common.allowed_hosts, token=common.token(),
              max_body_bytes=common.max_body_bytes)

    _ops_routes(app, registry, sites if per_site else None)
    return app


def _ops_routes(app: FastAPI, registry: CollectorRegistry, sites: list[str] | None) -> None:
    """/healthz, /readyz, /sites (a service run per site: ``sites``) and /metrics."""
    @app.get("/healthz", tags=["ops"], summary="Liveness: the process serves requests.",
             description="`pid` is the serving process's id: `aoi3d up` checks that its own "
                         "child answers, not another pipeline on the same port.")
    def healthz() -> dict[str, str | int]:
        return {"status": "ok", "pid": os.getpid()}

    @app.get("/readyz", tags=["ops"], summary="Readiness: the worker is connected and working.",
             responses={503: {"description": "Not ready; the body says why."}})
    def readyz(request: Request):
        workers = getattr(request.app.state, "workers", None)
        if workers is None:
            return JSONResponse({"ready": False, "reason": "starting"}, status_code=503)
        answers = {site: w.readiness() for site, w in workers.items()}
        ok = all(a for a, _ in answers.values())
        if len(answers) == 1:
            why = next(iter(answers.values()))[1]
        else:
            why = "; ".join(f"{site}: {w}" for site, (_, w) in answers.items())
        return JSONResponse({"ready": ok, "reason": why}, status_code=200 if ok else 503)

    if sites is not None:
        @app.get("/sites", tags=["ops"], summary="The run's sites (AOI3D_SITES).",
                 description="Each site has its own cameras, channel, policy and quality; "
                             "`/sites/<site>/…` addresses one, the paths without it the "
                             "first.")
        def get_sites() -> dict[str, list[str]]:
            return {"sites": sites}

    @app.get("/metrics", tags=["ops"], summary="Prometheus metrics of this service.")
    def metrics() -> Response:
        return Response(generate_latest(registry), media_type=CONTENT_TYPE_LATEST)


def serve(app: FastAPI, settings: ServiceSettings) -> None:
    """Run the app with uvicorn until SIGINT/SIGTERM (uvicorn then runs the lifespan exit)."""
    import uvicorn

    if settings.host not in LOOPBACK and settings.common.token() is None:
        log.warning("the REST API listens on %s without a control token: anyone who can reach "
                    "it can change the pipeline; set AOI3D_CONTROL_TOKEN (docs/operations.md, "
                    "'Reliability and security')",
                    settings.host)

    uvicorn.run(app, host=settings.host, port=settings.port, log_level="warning",
                access_log=False)


_S = TypeVar("_S", bound=ServiceSettings)


def run_service(name: str, settings_cls: Callable[[], _S],
                create_app: Callable[..., FastAPI],
                prepare: Callable[[_S], None] | None = None, *,
                dataset: Literal["frames", "metadata"] | None = None) -> None:
    """``python -m services.<name>``: settings from the environment, logging, then serve.

    ``dataset``: the service reads the scene dataset (``AOI3D_DATASET``); it is opened here,
    before serving, and passed as ``create_app(settings, dataset=…)``. ``"frames"`` also checks
    every frame file (the camera streams them). A dataset that cannot be read is one error
    line naming the file and what to do, and exit status 2 — no traceback, no server.
    """
    from services.kit.observe import setup_logging

    settings = settings_cls()
    setup_logging(settings.common.log_level, name)
    if prepare is not None:
        prepare(settings)
    extra = {}
    if dataset is not None:
        from aoi3d.scene import DatasetError, open_dataset

        try:
            extra["dataset"] = open_dataset(settings.common.dataset,
                                            verify=dataset == "frames")
        except DatasetError as err:
            log.error("%s", err)
            raise SystemExit(2) from None
    serve(create_app(settings, **extra), settings)
