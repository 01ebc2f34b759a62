"""The dispatcher's free views and exports at run time: each is asked of the worker that rendered
the site's latest decision (``aoi3d/<run>/pool/view/<worker>``, a :class:`pb.ViewRequest`),
bounded by the token bucket and counted by outcome in ``aoi3d_dispatcher_views_total``. The pure
parts — the bucket, the outcomes and their HTTP statuses — are :mod:`services.dispatcher.views`;
:class:`services.dispatcher.runtime.DispatcherRuntime` owns one :class:`ViewRelay` and shares its
lock.
"""

from __future__ import annotations

import threading
import time

import numpy as np
from prometheus_client import CollectorRegistry, Counter

from aoi3d.freeview import PoseError, check_pose, check_size, free_camera
from services.dispatcher.core import DispatcherCore
from services.dispatcher.settings import Settings
from services.dispatcher.views import OUTCOMES, TokenBucket, ViewRefused
from services.kit.bus import Bus
from services.kit.codec import camera_to_pb
from services.kit.keys import Keys
from services.kit.pb import aoi3d_pb2 as pb

__all__ = ["ViewRelay"]

_REASONS = {"no_model": "no_model", "busy": "busy", "bad_request": "bad_request",
            "bad_format": "bad_request"}
"""A worker's ``ViewReply.reason`` → the outcome counted (anything else: ``failed``)."""


class ViewRelay:
    """Free views and exports of the sites' latest models; ``lock`` guards ``cores``."""

    def __init__(self, settings: Settings, bus: Bus, registry: CollectorRegistry,
                 cores: dict[str, DispatcherCore], lock: threading.Lock) -> None:
        self.settings = settings
        self.bus = bus
        self.cores = cores
        self._lock = lock
        self._bucket = TokenBucket(settings.view_rate_per_s, settings.view_burst)
        self._total = Counter(
            "aoi3d_dispatcher_views", "Free views and exports asked of the dispatcher, by outcome "
            "(served, or why refused: rate_limited, bad_request, no_model, busy, timeout, "
            "failed); never scored.", ["outcome", "kind"], registry=registry)
        for outcome in OUTCOMES:
            for kind in ("view", "export"):
                self._total.labels(outcome, kind)

    def free_view(self, site: str, c2w: str, width: int | None, height: int | None,
                  fov_y_deg: float | None = None) -> tuple[bytes, pb.ViewReply]:
        """The PNG of ``site``'s latest model seen from ``c2w`` (16 numbers, OpenGL axes),
        ``width``×``height`` (default: the held-out camera's size), vertical field of view
        ``fov_y_deg`` (default: the held-out camera's); :class:`ViewRefused` otherwise."""
        try:
            core = self.cores[site]
            m = check_pose(c2w, core._aabb)
            heldout = core.heldout
            w, h = check_size(width or heldout.width, height or heldout.height,
                              self.settings.max_view_side)
            fov = None if fov_y_deg is None else float(np.radians(fov_y_deg))
            camera = free_camera(m, w, h, like=heldout, fov_y=fov)
        except PoseError as err:
            raise self._refused("view", "bad_request", str(err)) from None
        pose, intrinsics = camera_to_pb(camera)
        req = pb.ViewRequest(site=site, format="png", pose=pose, intrinsics=intrinsics)
        return self._ask("view", site, req, self.settings.view_timeout_s)

    def export(self, site: str, fmt: str, resolution: int = 0,
               alpha: float = 0.0) -> tuple[bytes, pb.ViewReply]:
        """A PLY of ``site``'s latest model: ``fmt`` ``ply`` (a coloured point cloud) or
        ``mesh`` (marching cubes); :class:`ViewRefused` otherwise."""
        req = pb.ViewRequest(site=site, format=fmt, resolution=resolution, alpha=alpha)
        return self._ask("export", site, req, self.settings.export_timeout_s)

    def _refused(self, kind: str, outcome: str, detail: str) -> ViewRefused:
        self._total.labels(outcome, kind).inc()
        return ViewRefused(outcome, detail)

    def _ask(self, kind: str, site: str, req: pb.ViewRequest,
             timeout_s: float) -> tuple[bytes, pb.ViewReply]:
        with self._lock:
            allowed = self._bucket.take(time.monotonic())
            latest = self.cores[site].latest
        if not allowed:
            raise self._refused(kind, "rate_limited",
                                f"more than {self.settings.view_rate_per_s:g} free views or "
                                f"exports a second (bursts of {self.settings.view_burst}); "
                                "try again shortly")
        if latest is None or not latest.worker_id:
            raise self._refused(kind, "no_model",
                                f"no model of site {site!r} yet: free views come once a "
                                "worker has rendered one of its decisions")
        answer = self.bus.query(Keys(self.settings.common.run_id).pool_view(latest.worker_id),
                                req.SerializeToString(), timeout_s=timeout_s)
        if answer is None:
            raise self._refused(kind, "timeout",
                                f"worker {latest.worker_id} (the latest render's) did not "
                                f"answer within {timeout_s:g} s (gone, or busy)")
        try:
            reply = pb.ViewReply.FromString(answer)
        except Exception:
            raise self._refused(kind, "failed", "the worker's answer is not a ViewReply"
                                ) from None
        if reply.error:
            outcome = _REASONS.get(reply.reason, "failed")
            raise self._refused(kind, outcome, f"worker {latest.worker_id}: {reply.error}")
        self._total.labels("served", kind).inc()
        return bytes(reply.data), reply
