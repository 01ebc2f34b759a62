"""The console's REST API and web page (routes only translate to the worker)."""

from __future__ import annotations

import asyncio
import json
from pathlib import Path
from typing import Annotated, Any

import httpx
from fastapi import APIRouter, Depends, FastAPI, HTTPException, Request
from fastapi.responses import FileResponse, JSONResponse, Response, StreamingResponse
from fastapi.staticfiles import StaticFiles

from services.console.runtime import ConsoleRuntime
from services.console.settings import UPSTREAMS, Settings
from services.kit.app import get_worker, include_site_routers, service_app
from services.kit.bus import Bus

STATIC = Path(__file__).parent / "static"

DESCRIPTION = """\
One page for the running pipeline: open `/` in a browser. It shows the novel view beside the
ground truth of the same simulated time and their difference, the AoI of every camera with
the MAT line and the cameras the decision in force used, the channel, the quality over the
last minutes (PSNR at the decision's time and at display time) with a marker at every policy
or channel change, the lag from decision to display (measured, and the scheduler's expected
lag), the training budget in force, and controls that call the services' REST APIs through
`/api/<service>/<path>` (forwarding the browser's `Authorization` header; the policy with
its budget goes to the scheduler's `PUT /policy`). Updates are pushed as Server-Sent Events
on `/events`. Everything the page loads is served here: no CDN.
"""

Worker = Annotated[ConsoleRuntime, Depends(get_worker)]
router = APIRouter(tags=["console"])
site_router = APIRouter(tags=["console"])
"""What the page shows of one site: at the root for the first, under /sites/{site}."""


@router.get("/", include_in_schema=False)
def page() -> FileResponse:
    return FileResponse(STATIC / "index.html", media_type="text/html")


@site_router.get("/state", summary="What the page shows, now (the payload of each event).")
def state(worker: Worker) -> JSONResponse:
    return JSONResponse(worker.snapshot())


@router.get("/config", summary="Static facts the page needs (services, push period, token).")
def config(request: Request) -> dict[str, Any]:
    settings: Settings = request.app.state.settings
    return {"services": sorted(UPSTREAMS),
            "sites": list(settings.common.sites),
            "push_period_s": settings.push_period_s,
            "viewer_port": settings.viewer_port,
            "token_required": settings.common.token() is not None}


@site_router.get("/events", summary="Server-Sent Events: the state every push period.",
            response_class=StreamingResponse)
async def events(request: Request, worker: Worker) -> StreamingResponse:
    period = request.app.state.settings.push_period_s

    async def stream():
        while not await request.is_disconnected():
            yield f"data: {json.dumps(worker.snapshot())}\n\n"
            await asyncio.sleep(period)

    return StreamingResponse(stream(), media_type="text/event-stream",
                             headers={"Cache-Control": "no-store"})


def _png(data: bytes | None, what: str) -> Response:
    if data is None:
        raise HTTPException(status_code=404, detail=f"no {what} yet")
    return Response(data, media_type="image/png", headers={"Cache-Control": "no-store"})


@site_router.get("/render.png", summary="The latest render of the novel view.",
            response_class=Response, responses={404: {"description": "No render yet."}})
def render_png(worker: Worker) -> Response:
    pair = worker.pair()
    return _png(None if pair is None else pair.render_png, "render")


@site_router.get("/truth.png", summary="The ground truth of the latest render's simulated time.",
            response_class=Response, responses={404: {"description": "No truth of that time."}})
def truth_png(worker: Worker) -> Response:
    pair = worker.pair()
    return _png(None if pair is None else pair.truth_png, "truth frame of the render's time")


@site_router.get("/diff.png", summary="|render − truth| of the latest pair as a heat map.",
            response_class=Response, responses={404: {"description": "No pair yet."}})
def diff_png(worker: Worker) -> Response:
    return _png(worker.diff_png(), "render and truth pair")


_FORWARD: dict[str, Any] = {
    "summary": "Call a service's REST API (server-side; the page's controls).",
    "responses": {404: {"description": "Unknown service."},
                  502: {"description": "The service did not answer."}}}


# One route per method, each with its own operationId: one api_route with three methods gave
# all three the same id, and which method's name it took varied with the hash seed.
@router.get("/api/{service}/{path:path}", operation_id="forward_get", **_FORWARD)
@router.put("/api/{service}/{path:path}", operation_id="forward_put", **_FORWARD)
@router.post("/api/{service}/{path:path}", operation_id="forward_post", **_FORWARD)
async def forward(service: str, path: str, request: Request) -> Response:
    worker: ConsoleRuntime = request.app.state.worker
    if service not in worker.upstream:
        raise HTTPException(status_code=404, detail=f"unknown service {service!r}; "
                                                    f"known: {', '.join(sorted(UPSTREAMS))}")
    headers = {"content-type": "application/json"}
    auth = request.headers.get("authorization")
    if auth:
        headers["authorization"] = auth
    body = await request.body()
    url = f"{worker.upstream[service]}/{path}"
    try:
        async with httpx.AsyncClient(timeout=30.0) as client:
            r = await client.request(request.method, url, content=body or None,
                                     headers=headers, params=dict(request.query_params))
    except httpx.HTTPError as err:
        raise HTTPException(status_code=502,
                            detail=f"{service} did not answer ({type(err).__name__})") from None
    return Response(r.content, status_code=r.status_code,
                    media_type=r.headers.get("content-type", "application/json"))


def create_app(settings: Settings | None = None, *, bus: Bus | None = None) -> FastAPI:
    settings = settings or Settings()
    common = settings.common
    token = common.token()

    def build_worker(the_bus: Bus, registry, site: str) -> ConsoleRuntime:
        return ConsoleRuntime(the_bus, registry, run_id=common.run_id, site=site,
                             poll_prefix="" if site == common.sites[0] else f"/sites/{site}",
                             upstream=settings.upstream,
                             headers={"authorization": f"Bearer {token}"} if token else {},
                             poll_period_s=settings.poll_period_s,
                             history_s=settings.history_s)

    app = service_app(title="aoi3d console", description=DESCRIPTION, settings=settings,
                      build_worker=build_worker, bus=bus, per_site=True)
    app.include_router(router)
    include_site_routers(app, site_router)
    app.mount("/static", StaticFiles(directory=STATIC), name="static")
    return app
