"""The 3D viewer's runtime: a viser server, the bus, the free views and the controls.

viser (the viewer library nerfstudio's viewer is built on) serves its web client from its
wheel and talks to the browser over a websocket; here it listens on a loopback port of its own
and the service's port (:mod:`services.viewer.app`) serves the client and relays the
websocket, beside ``/healthz``, ``/metrics`` and ``/scene.json``. What is drawn is the core's
(:class:`services.viewer.core.ViewerCore`), put on viser's scene by
:mod:`services.viewer.drawing`:

- decisions of every site (a subscription) go to the core under a lock, and so do the
  delivered frames while a browser is connected (subscribed at the first, undeclared when the
  last leaves: 600 frames a second at time scale 1, six percent of a core for nobody);
- a drawing loop redraws the frustums (colour: AoI at the decision in force; thicker and
  labelled ✓: used by it; image: the latest delivered frame) when a decision came, while a
  browser is connected (the frustums and their thumbnails cost a tenth of a core at time
  scale 1; nobody watching, nothing is drawn);
- each browser's camera, as the user orbits, is turned into a free view: the dispatcher's
  ``GET /sites/<site>/render.png?c2w=…`` (the pool renders the latest model from that pose),
  shown as the scene's background — the newest pose of each browser wins, and an unmoved
  camera is rendered again every ``refresh_s`` so the view follows the live reconstruction;
- the controls call the scheduler's ``PUT /sites/<site>/policy``, the console's REST.
"""

from __future__ import annotations

import io
import logging
import threading
import time
from typing import Any

import httpx
import numpy as np
from prometheus_client import CollectorRegistry, Counter

from aoi3d.scene.camera import Camera
from services.kit.bus import Bus, Subscription
from services.kit.keys import Keys
from services.kit.observe import Rejected, Rejections
from services.kit.rejected import RejectReason
from services.kit.runtime import Loops
from services.viewer import drawing
from services.viewer.core import ViewerCore
from services.viewer.settings import Settings

log = logging.getLogger(__name__)

POLICIES = ("all", "mat", "freshest", "wait")
"""The policies the viewer's controls offer (ppo needs a checkpoint path: the console)."""


class ViewerRuntime:
    """See the module docstring."""

    def __init__(self, settings: Settings, bus: Bus, registry: CollectorRegistry, *,
                 cameras: dict[int, Camera], truth: Camera, aabb: np.ndarray) -> None:
        self.settings = settings
        self.bus = bus
        common = settings.common
        self.keys = Keys(common.run_id, "*")
        self.core = ViewerCore(cameras, truth, np.asarray(aabb), list(common.sites))
        self.site = common.sites[0]
        self.rejections = Rejections(registry)
        self.views = Counter("aoi3d_viewer_views", "Free views the viewer asked the dispatcher "
                             "for, by outcome (shown, or the dispatcher's HTTP status).",
                             ["outcome"], registry=registry)
        self.views_shown = 0
        self.views_asked = 0
        self.last_view: dict[str, Any] = {}
        self._lock = threading.Lock()
        self._drawn: dict[str, int] = {}
        self._poses: dict[int, tuple[Any, float]] = {}
        """client id → (client handle, monotonic time of its last free view)."""
        self._moved: set[int] = set()
        self._frames_sub: Subscription | None = None
        """The delivered frames (the thumbnails), subscribed only while a browser is
        connected: 600 a second at the default rig, for nobody otherwise."""
        self._wake = threading.Event()
        self._draw_lock = threading.Lock()
        token = common.token()
        self._headers = {"authorization": f"Bearer {token}"} if token else {}
        self._http = httpx.Client(timeout=30.0, headers=self._headers)
        self.server: Any = None
        self.viser_port: int | None = None
        self._loops = Loops("viewer")
        self._loops.every("draw", settings.update_period_s, self._draw)
        self._loops.forever("views", self._serve_views)
        self._status_md: Any = None
        self._controls: dict[str, Any] = {}
        self._synced = False
        """Whether the controls were set once to the policy in force (then they are yours)."""

    # ------------------------------------------------------------------ lifecycle
    def start(self) -> None:
        import viser

        self.server = viser.ViserServer(host="127.0.0.1", port=0, label="aoi3d",
                                        verbose=False)
        self.viser_port = self.server.get_port()
        self.server.scene.set_up_direction("+z")
        drawing.draw_static(self.server.scene, self.core)
        self._gui()
        self.server.on_client_connect(self._on_client)
        self.server.on_client_disconnect(self._on_client_gone)
        self.bus.subscribe(self.keys.decision, self._on_decision)
        self._loops.start()
        log.info("viser serves on 127.0.0.1:%d (relayed on port %d)", self.viser_port,
                 self.settings.port)

    def stop(self) -> None:
        self._loops.stop(timeout_s=2.0)
        if self.server is not None:
            self.server.stop()
        self._http.close()

    def readiness(self) -> tuple[bool, str]:
        if self.server is None or self._loops.not_running() is not None:
            return False, "viewer not running"
        with self._lock:
            d = self.core.sites[self.site].decision
        return True, ("waiting for the first decision" if d is None
                      else f"decision {d.decision_id} in force at {self.site}")

    # ------------------------------------------------------------------ bus
    def _on_decision(self, key: str, payload: bytes) -> None:
        try:
            with self._lock:
                self.core.on_decision(self._site_of(key), payload)
        except Rejected as err:
            self.rejections.reject(err, key)

    def _on_frame(self, key: str, payload: bytes) -> None:
        try:
            with self._lock:
                self.core.on_frame(self._site_of(key), payload)
        except Rejected as err:
            self.rejections.reject(err, key)

    def _site_of(self, key: str) -> str:
        site = Keys.site_of(key)
        if site not in self.core.sites:
            raise Rejected(RejectReason.UNKNOWN_SITE, f"{key}: not a site of this run")
        return site

    # ------------------------------------------------------------------ drawing
    def _draw(self) -> None:
        """Redraw the frustums of the site shown when a decision came since the last time,
        while a browser is connected (nobody watching: nothing is drawn, and a browser that
        connects gets the scene of the decision in force at once)."""
        if self.server is None or not self.server.get_clients():
            return
        with self._draw_lock:  # the loop's and a new browser's (one drawing at a time)
            self._redraw()

    def _redraw(self) -> None:
        with self._lock:
            site = self.site
            version = self.core.version(site)
            if self._drawn.get(site) == version and version > 0:
                return
            states = self.core.states(site)
            thumbs = ({c: self.core.thumbnail(site, c) for c in states}
                      if self.settings.thumbnails else {})
            scene_doc = self.core.scene(site)
        self._drawn = {site: version}
        drawing.draw_cameras(self.server.scene, self.core, states, thumbs)
        if self._status_md is not None:
            self._status_md.content = drawing.status_text(scene_doc, self.last_view)
        self._sync_controls(scene_doc)

    def _sync_controls(self, doc: dict[str, Any]) -> None:
        """Show the policy in force in the controls, once (the first decision)."""
        d = doc["decision"]
        if self._synced or d is None or not self._controls:
            return
        self._synced = True
        kind = str(d["policy"]).split(":", 1)[0]
        if kind in POLICIES:
            self._controls["kind"].value = kind
        if d["gamma_ms"] is not None:
            self._controls["gamma"].value = float(d["gamma_ms"])

    # ------------------------------------------------------------------ controls
    def _gui(self) -> None:
        gui = self.server.gui
        self._status_md = gui.add_markdown("waiting for the first decision")
        sites = list(self.core.sites)
        if len(sites) > 1:
            site = gui.add_dropdown("site", sites, initial_value=self.site)

            @site.on_update
            def _(_event) -> None:
                with self._lock:
                    self.site = site.value
                    self._drawn.clear()
                self._moved.update(self._poses)
                self._wake.set()

        folder = gui.add_folder("policy")
        with folder:
            kind = gui.add_dropdown("kind", POLICIES, initial_value="mat")
            gamma = gui.add_number("Γ (ms)", initial_value=100.0, min=0.0, max=10_000.0,
                                   step=1.0)
            k = gui.add_number("k (freshest)", initial_value=6, min=0, max=256, step=1)
            wait = gui.add_number("ω ms (wait)", initial_value=40, min=0, max=10_000, step=1)
            apply = gui.add_button("apply")
            said = gui.add_markdown("")
        self._controls = {"kind": kind, "gamma": gamma}

        @apply.on_click
        def _(_event) -> None:
            body: dict[str, Any] = {"kind": kind.value}
            if kind.value == "mat":
                body["mat_ms"] = float(gamma.value)
            elif kind.value == "freshest":
                body["k"] = int(k.value)
            elif kind.value == "wait":
                body["wait_ms"] = int(wait.value)
            said.content = self.put_policy(body)

        reset = gui.add_button("view from the truth camera")

        @reset.on_click
        def _(event) -> None:
            if event.client is not None:
                drawing.look_from_truth(event.client, self.core)

    def put_policy(self, body: dict[str, Any]) -> str:
        """PUT the scheduler's policy of the site shown; one line saying how it went."""
        url = f"{self.settings.scheduler_url.rstrip('/')}/sites/{self.site}/policy"
        try:
            r = self._http.put(url, json=body)
        except httpx.HTTPError as err:
            return f"the scheduler did not answer ({type(err).__name__})"
        if r.status_code != 200:
            try:
                detail = r.json().get("detail")
            except ValueError:
                detail = r.text[:200]
            return f"refused ({r.status_code}): {detail}"
        return f"policy {body['kind']} in force from the next decision"

    # ------------------------------------------------------------------ free views
    def _on_client(self, client: Any) -> None:
        with self._lock:
            if self._frames_sub is None:  # the thumbnails fill in from the next decision
                self._frames_sub = self.bus.subscribe(self.keys.edge_frames, self._on_frame)
        with self._draw_lock:  # drawn for it at once (nothing is drawn while nobody watches)
            self._drawn.clear()
            self._redraw()
        drawing.overview(client, self.core)

        @client.camera.on_update
        def _(_camera) -> None:
            self._moved.add(client.client_id)
            self._wake.set()

        with self._lock:
            self._poses[client.client_id] = (client, 0.0)
        self._moved.add(client.client_id)
        self._wake.set()

    def _on_client_gone(self, client: Any) -> None:
        with self._lock:
            self._poses.pop(client.client_id, None)
            sub = None
            if not self._poses and self._frames_sub is not None:
                sub, self._frames_sub = self._frames_sub, None
        if sub is not None:
            sub.undeclare()
        self._moved.discard(client.client_id)

    def _serve_views(self) -> None:
        """Render the newest pose of each browser that moved (or waited ``refresh_s``)."""
        self._wake.wait(0.5)
        self._wake.clear()
        now = time.monotonic()
        with self._lock:
            due = [(cid, client) for cid, (client, last) in self._poses.items()
                   if cid in self._moved or now - last >= self.settings.refresh_s]
        for cid, client in due:
            self._moved.discard(cid)
            with self._lock:
                if cid in self._poses:
                    self._poses[cid] = (client, time.monotonic())
            self._render_for(client)

    def _render_for(self, client: Any) -> None:
        params = drawing.view_params(client.camera, self.settings.render_height)
        if params is None:
            return
        url = f"{self.settings.dispatcher_url.rstrip('/')}/sites/{self.site}/render.png"
        self.views_asked += 1
        try:
            r = self._http.get(url, params=params)
        except httpx.HTTPError as err:
            self.views.labels(type(err).__name__).inc()
            return
        if r.status_code != 200:
            self.views.labels(str(r.status_code)).inc()
            return
        from PIL import Image

        with Image.open(io.BytesIO(r.content)) as im:
            image = np.asarray(im.convert("RGB"))
        client.scene.set_background_image(image, format="jpeg", jpeg_quality=90)
        self.views.labels("shown").inc()
        self.views_shown += 1
        self.last_view = {"decision_id": r.headers.get("x-decision-id"),
                          "training_step": r.headers.get("x-training-step"),
                          "worker": r.headers.get("x-worker"), "c2w": params["c2w"],
                          "size": [params["width"], params["height"]]}

    # ------------------------------------------------------------------ REST
    def scene_doc(self, site: str | None = None) -> dict[str, Any]:
        with self._lock:
            doc = self.core.scene(site or self.site)
            clients = len(self._poses)
        doc["views"] = {"asked": self.views_asked, "shown": self.views_shown,
                        "last": self.last_view, "clients": clients}
        return doc
