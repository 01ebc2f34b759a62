"""The 3D viewer's runtime: a viser server, the bus, the free views and the controls.

viser (the viewer library nerfstudio's viewer is built on) serves its web client from its
wheel and talks to the browser over a websocket; here it listens on a loopback port of its own
and the service's port (:mod:`services.viewer.app`) serves the client and relays the
websocket, beside ``/healthz``, ``/metrics`` and ``/scene.json``. What is drawn is the core's
(:class:`services.viewer.core.ViewerCore`):

- decisions and delivered frames of every site (subscriptions) go to the core under a lock;
- a drawing loop redraws the frustums (colour: AoI at the decision in force; thicker and
  labelled ✓: used by it; image: the latest delivered frame) when a decision came;
- each browser's camera, as the user orbits, is turned into a free view: the trainer's
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

from aoi3d.freeview import MAX_VIEW_SIDE, c2w_from_viser
from aoi3d.scene.camera import Camera
from services.kit.bus import Bus
from services.kit.keys import Keys
from services.kit.observe import Rejected, Rejections
from services.kit.rejected import RejectReason
from services.kit.runtime import Loops
from services.viewer.core import ViewerCore, box_segments
from services.viewer.settings import Settings

log = logging.getLogger(__name__)

POLICIES = ("all", "mat", "freshest", "wait")
"""The policies the viewer's controls offer (ppo needs a checkpoint path: the console)."""


class ViewerWorker:
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
        self.views = Counter("aoi3d_viewer_views", "Free views the viewer asked the trainer "
                             "for, by outcome (shown, or the trainer's HTTP status).",
                             ["outcome"], registry=registry)
        self.views_shown = 0
        self.views_asked = 0
        self.last_view: dict[str, Any] = {}
        self._lock = threading.Lock()
        self._drawn: dict[str, int] = {}
        self._poses: dict[int, tuple[Any, float]] = {}
        """client id → (client handle, monotonic time of its last free view)."""
        self._moved: set[int] = set()
        self._wake = threading.Event()
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
        self._draw_static()
        self._gui()
        self.server.on_client_connect(self._on_client)
        self.server.on_client_disconnect(self._on_client_gone)
        self.bus.subscribe(self.keys.decision, self._on_decision)
        self.bus.subscribe(self.keys.edge_frames, self._on_frame)
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
    def _draw_static(self) -> None:
        scene = self.server.scene
        box = box_segments(self.core.aabb)
        scene.add_line_segments("/box", box, (200, 200, 200), thickness=2.0,
                                thickness_units="screen")
        t = self.core.truth_frustum
        scene.add_camera_frustum("/truth", fov=t.fov, aspect=t.aspect,
                                 scale=self.core.frustum_scale * 1.3, color=(60, 140, 255),
                                 wxyz=t.wxyz, position=t.position, thickness=3.0,
                                 thickness_units="screen")
        scene.add_label("/truth/label", "truth", position=(0.0, 0.0, 0.0))

    def _draw(self) -> None:
        """Redraw the frustums of the site shown when a decision came since the last time."""
        if self.server is None:
            return
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
        scene = self.server.scene
        scale = self.core.frustum_scale
        for c, st in states.items():
            f = self.core.frustums[c]
            scene.add_camera_frustum(
                f"/cameras/cam{c}", fov=f.fov, aspect=f.aspect, scale=scale, color=st.colour,
                wxyz=f.wxyz, position=f.position, image=thumbs.get(c),
                thickness=5.0 if st.selected else 2.0, thickness_units="screen")
            aoi = "?" if np.isnan(st.aoi_ms) else f"{st.aoi_ms:.0f} ms"
            scene.add_label(f"/cameras/cam{c}/label",
                            f"{c}{' ✓' if st.selected else ''} {aoi}", position=(0, 0, 0))
        self._status(scene_doc)
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

    def _status(self, doc: dict[str, Any]) -> None:
        if self._status_md is None:
            return
        d = doc["decision"]
        if d is None:
            text = f"**{doc['site']}**: waiting for the first decision"
        else:
            gamma = "—" if d["gamma_ms"] is None else f"{d['gamma_ms']:.0f} ms"
            text = (f"**{doc['site']}** decision {d['decision_id']} ({d['policy']}, "
                    f"Γ {gamma}): {len(d['selected'])} of {len(doc['cameras'])} cameras used")
        view = self.last_view
        if view:
            text += (f"  \nview: decision {view.get('decision_id')}, step "
                     f"{view.get('training_step')}, worker {view.get('worker')}")
        self._status_md.content = text

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
                self._look_from_truth(event.client)

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
    def _look_from_truth(self, client: Any) -> None:
        t = self.core.truth_frustum
        with client.atomic():
            client.camera.position = t.position
            client.camera.look_at = tuple(self.core.aabb.mean(axis=0))
            client.camera.up_direction = (0.0, 0.0, 1.0)

    def _overview(self, client: Any) -> None:
        """Back from the truth camera and above it, far enough to see every camera."""
        centre = self.core.aabb.mean(axis=0)
        t = np.asarray(self.core.truth_frustum.position)
        reach = max(float(np.linalg.norm(np.asarray(f.position) - centre))
                    for f in [*self.core.frustums.values(), self.core.truth_frustum])
        away = t - centre
        away[2] = 0.0
        away = away / max(float(np.linalg.norm(away)), 1e-9)
        eye = centre + away * 2.0 * reach + np.array([0.0, 0.0, 1.2 * reach])
        with client.atomic():
            client.camera.position = tuple(eye)
            client.camera.look_at = tuple(centre)
            client.camera.up_direction = (0.0, 0.0, 1.0)

    def _on_client(self, client: Any) -> None:
        self._overview(client)

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
        cam = client.camera
        try:
            c2w = c2w_from_viser(cam.wxyz, cam.position)
            aspect = float(cam.aspect) if cam.aspect and np.isfinite(cam.aspect) else 4 / 3
            fov_deg = float(np.degrees(cam.fov))
        except Exception:  # the client's camera is not known yet
            return
        h = self.settings.render_height
        w = int(min(MAX_VIEW_SIDE, max(8, round(h * aspect))))
        params: dict[str, str | int | float] = {
            "c2w": ",".join(f"{v:.7g}" for v in c2w.ravel()), "width": w, "height": h,
            "fov": min(179.0, max(1.0, fov_deg))}
        url = f"{self.settings.trainer_url.rstrip('/')}/sites/{self.site}/render.png"
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
                          "size": [w, h]}

    # ------------------------------------------------------------------ REST
    def scene_doc(self, site: str | None = None) -> dict[str, Any]:
        with self._lock:
            doc = self.core.scene(site or self.site)
            clients = len(self._poses)
        doc["views"] = {"asked": self.views_asked, "shown": self.views_shown,
                        "last": self.last_view, "clients": clients}
        return doc
