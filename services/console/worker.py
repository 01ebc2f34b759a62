"""The console's worker: what the page shows, gathered from the bus and the services.

From the bus (the same messages the services exchange): the latest Render, the truth frame of
the same simulated time (kept in a ring by generation time), every Quality (a timeline), the
latest Decision (AoI per camera, the frames selected, the policy). From the services' REST
APIs, polled every ``poll_period_s`` on a thread of its own: the channel (links' counts and
delay spec), the trainer's status and the policy in force. A policy or channel change puts a
marker on the timeline. :meth:`snapshot` is the JSON pushed to the page.
"""

from __future__ import annotations

import bisect
import io
import logging
import math
import threading
import time
from collections import deque
from dataclasses import dataclass
from typing import Any

import httpx
import numpy as np
from prometheus_client import CollectorRegistry, Counter

from aoi3d.channel import parse_delay
from services.kit.bus import Bus
from services.kit.codec import decode_decision, decode_frame, decode_quality, decode_render
from services.kit.keys import DEFAULT_SITE, Keys
from services.kit.observe import Rejected, Rejections

log = logging.getLogger(__name__)

TRUTH_FRAMES = 256
"""Truth frames kept to pair a render with the truth of its own time."""


@dataclass(frozen=True)
class Pair:
    """The latest render and the truth frame of the same simulated time (PNG bytes)."""

    render_png: bytes
    truth_png: bytes | None
    decision_id: int
    render_time_ms: float
    truth_time_ms: float | None
    training_step: int
    n_views: int
    carry: str
    received_wall_s: float


class ConsoleWorker:
    def __init__(self, bus: Bus, registry: CollectorRegistry, *, run_id: str,
                 upstream: dict[str, str], headers: dict[str, str], site: str = DEFAULT_SITE,
                 poll_prefix: str = "", period_ms: float = 30.0,
                 poll_period_s: float = 1.0, history_s: float = 300.0,
                 timeout_s: float = 10.0) -> None:
        self._bus = bus
        self._keys = Keys(run_id, site)
        self.site = site
        self._prefix = poll_prefix
        """Before each polled path: "" for the first site, /sites/<site> for the others."""
        self.upstream = upstream
        self._period_ms = period_ms
        self._poll_period_s = poll_period_s
        self._history_s = history_s
        self._http = httpx.Client(timeout=timeout_s, headers=headers)
        self.rejections = Rejections(registry)
        self._m_renders = Counter("aoi3d_console_renders", "Renders the console received.",
                                  registry=registry)
        self._lock = threading.Lock()
        self._truth_times: list[float] = []
        self._truth: dict[float, bytes] = {}
        self._pair: Pair | None = None
        self._diff: tuple[int, bytes] | None = None
        self._quality: deque[dict[str, Any]] = deque()
        self._markers: deque[dict[str, Any]] = deque()
        self._decision: dict[str, Any] | None = None
        self._status: dict[str, Any] = {}
        self._channel_prev: tuple[float, int, int] | None = None  # wall, delivered, offered
        self._last_policy: str | None = None
        self._last_channel: str | None = None
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None

    # ------------------------------------------------------------------ lifecycle
    def start(self) -> None:
        self._bus.subscribe(self._keys.truth, self._guard(self._on_truth))
        self._bus.subscribe(self._keys.render, self._guard(self._on_render))
        self._bus.subscribe(self._keys.quality, self._guard(self._on_quality))
        self._bus.subscribe(self._keys.decision, self._guard(self._on_decision))
        self._thread = threading.Thread(target=self._poll_loop, name="console-poll",
                                        daemon=True)
        self._thread.start()

    def stop(self) -> None:
        self._stop.set()
        if self._thread is not None:
            self._thread.join(timeout=5)
        self._http.close()

    def readiness(self) -> tuple[bool, str]:
        if self._thread is None or not self._thread.is_alive():
            return False, "poll thread not running"
        with self._lock:
            have = self._pair is not None
        return True, "showing renders" if have else "waiting for the first render"

    # ------------------------------------------------------------------ the bus
    def _guard(self, handler):
        def wrapped(key: str, payload: bytes) -> None:
            try:
                handler(payload)
            except Rejected as err:
                self.rejections.reject(err, key)
            except Exception as err:  # a bug must not stop the subscriber
                log.exception("console failed on %s", key)
                self.rejections.reject(Rejected("internal_error", repr(err)), key)
        return wrapped

    def _on_truth(self, payload: bytes) -> None:
        frame = decode_frame(payload, camera_ids={0})
        with self._lock:
            t = frame.generation_ms
            if t not in self._truth:
                bisect.insort(self._truth_times, t)
            self._truth[t] = frame.image.data
            while len(self._truth_times) > TRUTH_FRAMES:
                self._truth.pop(self._truth_times.pop(0), None)

    def _truth_at(self, t_ms: float) -> tuple[float, bytes] | None:
        """The truth frame generated at ``t_ms``, else the newest at most one period older."""
        i = bisect.bisect_right(self._truth_times, t_ms + 1e-6)
        if i == 0:
            return None
        t = self._truth_times[i - 1]
        return (t, self._truth[t]) if t_ms - t <= self._period_ms + 1e-6 else None

    def _on_render(self, payload: bytes) -> None:
        msg, _camera = decode_render(payload)
        with self._lock:
            truth = self._truth_at(msg.time_ms)
            self._pair = Pair(render_png=msg.image.data,
                              truth_png=None if truth is None else truth[1],
                              decision_id=msg.decision_id, render_time_ms=msg.time_ms,
                              truth_time_ms=None if truth is None else truth[0],
                              training_step=msg.training_step, n_views=msg.n_views,
                              carry=msg.carry, received_wall_s=time.time())
        self._m_renders.inc()

    def _on_quality(self, payload: bytes) -> None:
        q = decode_quality(payload)
        now = time.time()
        entry = {"wall_s": now, "time_ms": q.time_ms, "psnr_db": q.psnr_db,
                 "ssim": q.ssim, "reward": q.reward,
                 "lpips": q.lpips if q.HasField("lpips") else None,
                 "psnr_dynamic_db": q.psnr_dynamic_db if q.HasField("psnr_dynamic_db")
                 else None}
        with self._lock:
            self._quality.append({k: _finite(v) for k, v in entry.items()})
            self._trim(now)

    def _on_decision(self, payload: bytes) -> None:
        d = decode_decision(payload)
        selected = sorted(int(r.camera_id) for r in d.selected)
        doc = {"decision_id": d.decision_id, "time_ms": d.time_ms, "policy": d.policy,
               "camera_ids": list(d.camera_ids),
               "aoi_ms": [_finite(a) for a in d.aoi_ms], "selected": selected}
        with self._lock:
            self._decision = doc
            if d.policy != self._last_policy:
                if self._last_policy is not None:
                    self._markers.append({"wall_s": time.time(), "text": f"policy {d.policy}"})
                self._last_policy = d.policy

    def _trim(self, now: float) -> None:
        for q in (self._quality, self._markers):
            while q and q[0]["wall_s"] < now - self._history_s:
                q.popleft()

    # ------------------------------------------------------------------ the services
    def _get(self, service: str, path: str) -> Any:
        r = self._http.get(self.upstream[service] + self._prefix + path)
        r.raise_for_status()
        return r.json()

    def _poll_loop(self) -> None:
        while not self._stop.is_set():
            status: dict[str, Any] = {}
            for key, service, path in (("channel", "network", "/channel"),
                                       ("trainer", "trainer", "/status"),
                                       ("policy", "scheduler", "/policy"),
                                       ("ledger", "metrics", "/ledger")):
                try:
                    status[key] = self._get(service, path)
                except (httpx.HTTPError, ValueError) as err:
                    status[key] = {"error": f"{service} unreachable ({type(err).__name__})"}
            now = time.time()
            with self._lock:
                self._status = {**status, "channel_summary": self._channel(status["channel"],
                                                                           now)}
                self._trim(now)
            self._stop.wait(self._poll_period_s)

    def _channel(self, channel: dict[str, Any], now: float) -> dict[str, Any] | None:
        """Delivered/s and drop ratio since the previous poll; the configured delay's
        quantiles. Called with the lock held."""
        links = channel.get("links")
        if not links:
            return None
        delivered = sum(link["delivered"] for link in links)
        offered = sum(link["offered"] for link in links)
        dropped = sum(link["dropped"] for link in links)
        out: dict[str, Any] = {"delay": channel.get("delay"), "delivered_total": delivered,
                               "drop_ratio_total": dropped / offered if offered else None}
        if self._channel_prev is not None:
            t0, d0, o0 = self._channel_prev
            dt = now - t0
            if dt > 0 and offered >= o0:
                out["delivered_per_s"] = (delivered - d0) / dt
                out["drop_ratio"] = (1 - (delivered - d0) / (offered - o0)
                                     if offered > o0 else None)
        self._channel_prev = (now, delivered, offered)
        spec = str(channel.get("delay"))
        try:
            dist = parse_delay(spec)
            out["delay_quantiles_ms"] = {q: dist.ppf(float(q)) for q in ("0.5", "0.9", "0.99")}
        except ValueError:
            out["delay_quantiles_ms"] = None
        if spec != self._last_channel:
            if self._last_channel is not None:
                self._markers.append({"wall_s": now, "text": f"delay {spec}"})
            self._last_channel = spec
        return out

    # ------------------------------------------------------------------ for the page
    def pair(self) -> Pair | None:
        with self._lock:
            return self._pair

    def diff_png(self) -> bytes | None:
        """|render − truth| averaged over the channels, as a heat map (black → red → yellow
        → white), for the latest pair; cached per render."""
        pair = self.pair()
        if pair is None or pair.truth_png is None:
            return None
        with self._lock:
            if self._diff is not None and self._diff[0] == pair.decision_id:
                return self._diff[1]
        from PIL import Image

        a = np.asarray(Image.open(io.BytesIO(pair.render_png)).convert("RGB"), np.float32)
        b = np.asarray(Image.open(io.BytesIO(pair.truth_png)).convert("RGB"), np.float32)
        if a.shape != b.shape:
            return None
        e = np.clip(np.abs(a - b).mean(axis=2) / 128.0, 0.0, 1.0)
        heat = np.stack([np.clip(3 * e, 0, 1), np.clip(3 * e - 1, 0, 1),
                         np.clip(3 * e - 2, 0, 1)], axis=2)
        buf = io.BytesIO()
        Image.fromarray((heat * 255).astype(np.uint8), "RGB").save(buf, format="PNG")
        png = buf.getvalue()
        with self._lock:
            self._diff = (pair.decision_id, png)
        return png

    def snapshot(self) -> dict[str, Any]:
        with self._lock:
            pair = self._pair
            return {
                "wall_s": time.time(),
                "render": None if pair is None else {
                    "decision_id": pair.decision_id, "time_ms": pair.render_time_ms,
                    "truth_time_ms": pair.truth_time_ms, "training_step": pair.training_step,
                    "n_views": pair.n_views, "carry": pair.carry,
                    "age_s": time.time() - pair.received_wall_s},
                "decision": self._decision,
                "quality": list(self._quality),
                "markers": list(self._markers),
                **self._status,
            }


def _finite(value: Any) -> Any:
    """NaN and infinities as None: JSON has no such numbers."""
    if isinstance(value, float) and not math.isfinite(value):
        return None
    return value
