"""The FastAPI app factory every service uses.

``service_app`` gives each service ``/healthz``, ``/readyz`` and ``/metrics`` and a lifespan
that opens the bus (Zenoh unless a bus is injected, as tests do), builds and starts the
worker, and stops both on shutdown. Routes reach the worker through ``app.state.worker``.
"""

from __future__ import annotations

import logging
import os
from collections.abc import AsyncIterator, Callable
from contextlib import asynccontextmanager
from typing import Literal, Protocol

from fastapi import FastAPI, Request
from fastapi.responses import JSONResponse, Response
from fastapi_offline import FastAPIOffline
from prometheus_client import CONTENT_TYPE_LATEST, CollectorRegistry, generate_latest

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
    return request.app.state.worker


def service_app(
    *,
    title: str,
    description: str,
    settings: ServiceSettings,
    build_worker: Callable[[Bus, CollectorRegistry], Worker],
    bus: Bus | None = None,
    registry: CollectorRegistry | None = None,
) -> FastAPI:
    registry = registry or CollectorRegistry()

    @asynccontextmanager
    async def lifespan(app: FastAPI) -> AsyncIterator[None]:
        own_bus = bus is None
        the_bus = bus or ZenohBus(zenoh_config(settings.common))
        worker = build_worker(the_bus, registry)
        app.state.worker = worker
        app.state.bus = the_bus
        worker.start()
        log.info("%s started (run %s)", title, settings.common.run_id)
        try:
            yield
        finally:
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

    @app.get("/healthz", tags=["ops"], summary="Liveness: the process serves requests.",
             description="`pid` is the serving process's id: `aoi3d up` checks that its own "
                         "child answers, not another pipeline on the same port.")
    def healthz() -> dict[str, str | int]:
        return {"status": "ok", "pid": os.getpid()}

    @app.get("/readyz", tags=["ops"], summary="Readiness: the worker is connected and working.",
             responses={503: {"description": "Not ready; the body says why."}})
    def readyz(request: Request):
        worker = getattr(request.app.state, "worker", None)
        if worker is None:
            return JSONResponse({"ready": False, "reason": "starting"}, status_code=503)
        ok, why = worker.readiness()
        return JSONResponse({"ready": ok, "reason": why}, status_code=200 if ok else 503)

    @app.get("/metrics", tags=["ops"], summary="Prometheus metrics of this service.")
    def metrics() -> Response:
        return Response(generate_latest(registry), media_type=CONTENT_TYPE_LATEST)

    return app


def serve(app: FastAPI, settings: ServiceSettings) -> None:
    """Run the app with uvicorn until SIGINT/SIGTERM (uvicorn then runs the lifespan exit)."""
    import uvicorn

    if settings.host not in LOOPBACK and settings.common.token() is None:
        log.warning("the REST API listens on %s without a control token: anyone who can reach "
                    "it can change the pipeline; set AOI3D_CONTROL_TOKEN (README, 'Reliability "
                    "and security')",
                    settings.host)

    uvicorn.run(app, host=settings.host, port=settings.port, log_level="warning",
                access_log=False)


def run_service(name: str, settings_cls: Callable[[], ServiceSettings],
                create_app: Callable[..., FastAPI],
                prepare: Callable[[ServiceSettings], None] | None = None, *,
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
