"""The 3D viewer's web page, websocket relay and REST API.

``GET /`` is viser's web client, served from the viser wheel (one HTML file: its scripts and
styles are inside it; nothing is loaded from a CDN), and the websocket it opens on the same
address is relayed to the viser server the worker runs on a loopback port. Beside them, as
every service: ``/healthz`` (with the pid ``aoi3d up`` checks), ``/readyz``, ``/metrics``,
``/docs``; and ``GET /scene.json``, what the viewer draws.
"""

from __future__ import annotations

import asyncio
import contextlib
import logging
from pathlib import Path
from typing import Annotated

import numpy as np
from fastapi import APIRouter, FastAPI, HTTPException, Query, Request, WebSocket
from fastapi.responses import HTMLResponse, JSONResponse

from aoi3d.scene import Camera, SceneDataset, open_dataset
from services.kit.app import service_app
from services.kit.bus import Bus
from services.kit.guard import host_name
from services.viewer.runtime import ViewerRuntime
from services.viewer.settings import Settings

log = logging.getLogger(__name__)

DESCRIPTION = """\
The live 3D viewer: open `/` in a browser. It shows the scene box, every camera as a frustum
coloured by its AoI at the decision in force (green fresh, yellow at Γ, red at 2Γ; the
cameras the decision used drawn thicker and marked ✓, each with its latest delivered frame),
the truth camera (blue), and the live reconstruction seen from the viewer's own camera: as you
orbit, the dispatcher's pool renders that pose (`GET /render.png?c2w=…` on the dispatcher) and the
view updates. Controls: the site, the policy and Γ (the scheduler's `PUT /policy`). Built on
viser, whose client is served from its wheel: no CDN.
"""

router = APIRouter(tags=["viewer"])


def _client_html() -> bytes:
    import viser

    return (Path(viser.__file__).parent / "client" / "build" / "index.html").read_bytes()


@router.get("/", include_in_schema=False)
def page() -> HTMLResponse:
    return HTMLResponse(_client_html(), headers={"Cache-Control": "no-store"})


@router.get("/scene.json", summary="What the viewer draws: box, cameras, decision, views.")
def scene(request: Request, site: Annotated[str | None, Query(
        description="A site of the run (default: the one shown).", max_length=32)] = None
          ) -> JSONResponse:
    worker: ViewerRuntime = request.app.state.worker
    if site is not None and site not in worker.core.sites:
        raise HTTPException(404, f"no site {site!r} in this run")
    return JSONResponse(worker.scene_doc(site))


async def _relay(websocket: WebSocket) -> None:
    """The browser's websocket, relayed to viser's server (same subprotocol, both ways)."""
    import websockets

    settings: Settings = websocket.app.state.settings
    allowed = {h.lower() for h in settings.common.allowed_hosts}
    origin = websocket.headers.get("origin")
    host = host_name(websocket.headers.get("host", ""))
    if "*" not in allowed and (host not in allowed or (
            origin is not None and host_name(origin.split("://", 1)[-1]) not in allowed)):
        await websocket.close(code=1008)
        return
    worker: ViewerRuntime = websocket.app.state.worker
    offered = websocket.scope.get("subprotocols") or []
    protocol = next((p for p in offered if p.startswith("viser-v")), None)
    url = f"ws://127.0.0.1:{worker.viser_port}/"
    async with websockets.connect(url, subprotocols=[protocol] if protocol else None,
                                  max_size=None, compression=None) as upstream:
        await websocket.accept(subprotocol=protocol)

        async def down() -> None:
            async for message in upstream:
                if isinstance(message, bytes):
                    await websocket.send_bytes(message)
                else:
                    await websocket.send_text(message)

        async def up() -> None:
            while True:
                message = await websocket.receive()
                if message["type"] == "websocket.disconnect":
                    return
                data = message.get("bytes")
                await upstream.send(data if data is not None else message.get("text", ""))

        tasks = [asyncio.create_task(down()), asyncio.create_task(up())]
        _, pending = await asyncio.wait(tasks, return_when=asyncio.FIRST_COMPLETED)
        for task in pending:
            task.cancel()
            with contextlib.suppress(asyncio.CancelledError, Exception):
                await task
    with contextlib.suppress(Exception):
        await websocket.close()


def create_app(settings: Settings | None = None, *, bus: Bus | None = None,
               dataset: SceneDataset | None = None) -> FastAPI:
    """The viewer's app; ``dataset`` (the cameras, the truth camera, the box) defaults to
    ``open_dataset(settings.common.dataset)``, read when the app starts."""
    settings = settings or Settings()

    def build_worker(the_bus: Bus, registry) -> ViewerRuntime:
        if settings.common.rig is not None and dataset is None:  # real cameras: the rig's
            from aoi3d.rigfile import load_rig, scaled_camera

            rig = load_rig(settings.common.rig)
            size = rig.working_size
            cams: dict[int, Camera] = {}
            for i, c in enumerate(rig.train, start=1):
                k, pose = c.intrinsics, c.pose
                fx, fy, cx, cy, w, h = k.fx, k.fy, k.cx, k.cy, k.width, k.height
                if (pose.topic is not None or fx is None or fy is None or cx is None
                        or cy is None or w is None or h is None):
                    continue  # known only from its topics: not drawn from the file alone
                cams[i] = scaled_camera(pose.static_c2w(), fx, fy, cx, cy, (w, h), size)
            return ViewerRuntime(settings, the_bus, registry, cameras=cams,
                                truth=rig.view_camera(), aabb=rig.scene_box)
        data = dataset if dataset is not None else open_dataset(settings.common.dataset)
        n = min(settings.common.cameras, len(data.cameras) - 1)
        cams = {c: data.cameras[c] for c in range(1, n + 1) if c != data.heldout_id}
        return ViewerRuntime(settings, the_bus, registry, cameras=cams,
                            truth=data.cameras[data.heldout_id], aabb=np.asarray(data.aabb))

    app = service_app(title="aoi3d viewer", description=DESCRIPTION, settings=settings,
                      build_worker=build_worker, bus=bus)
    app.include_router(router)
    app.add_api_websocket_route("/", _relay)
    return app
