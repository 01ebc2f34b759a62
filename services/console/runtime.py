"""The console's worker: feeds the console's core from the bus and the services' REST APIs.

What the page shows is the core's (:class:`services.console.core.ConsoleCore`, no I/O). This
worker subscribes the messages the services exchange (truth frames, Renders, Quality,
Decisions: handlers only hand the bytes to the core under its lock) and polls, every
``poll_period_s`` on a thread of its own (:class:`services.kit.runtime.Loops`), the channel,
the dispatcher's status, the policy in force and the decision ledger.
"""

from __future__ import annotations

import logging
import threading
import time
from collections.abc import Callable
from typing import Any

import httpx
from prometheus_client import CollectorRegistry, Counter

from services.console.core import TRUTH_FRAMES, ConsoleCore, Pair
from services.kit.bus import Bus
from services.kit.keys import DEFAULT_SITE, Keys
from services.kit.observe import Rejected, Rejections
from services.kit.rejected import RejectReason
from services.kit.runtime import Loops

log = logging.getLogger(__name__)

__all__ = ["TRUTH_FRAMES", "ConsoleRuntime", "Pair"]

POLLED = (("channel", "network", "/channel"), ("dispatcher", "dispatcher", "/status"),
          ("policy", "scheduler", "/policy"), ("ledger", "metrics", "/ledger"))
"""What each poll asks: (status key, service, path)."""


class ConsoleRuntime:
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
        self._http = httpx.Client(timeout=timeout_s, headers=headers)
        self.rejections = Rejections(registry)
        self._m_renders = Counter("aoi3d_console_renders", "Renders the console received.",
                                  registry=registry)
        self._lock = threading.Lock()
        self.core = ConsoleCore(period_ms=period_ms, history_s=history_s)
        self._loops = Loops("console")
        self._loops.every("poll", poll_period_s, self._poll)

    # ------------------------------------------------------------------ lifecycle
    def start(self) -> None:
        core = self.core
        self._bus.subscribe(self._keys.truth, self._guard(core.on_truth))
        self._bus.subscribe(self._keys.render, self._guard(self._on_render))
        self._bus.subscribe(self._keys.quality,
                            self._guard(lambda p: core.on_quality(p, time.time())))
        self._bus.subscribe(self._keys.decision,
                            self._guard(lambda p: core.on_decision(p, time.time())))
        self._loops.start()

    def stop(self) -> None:
        self._loops.stop()
        self._http.close()

    def readiness(self) -> tuple[bool, str]:
        why_not = self._loops.not_running()
        if why_not is not None:
            return False, why_not
        return True, "showing renders" if self.pair() is not None else \
            "waiting for the first render"

    # ------------------------------------------------------------------ the bus
    def _guard(self, handler: Callable[[bytes], None]) -> Callable[[str, bytes], None]:
        def wrapped(key: str, payload: bytes) -> None:
            try:
                with self._lock:
                    handler(payload)
            except Rejected as err:
                self.rejections.reject(err, key)
            except Exception as err:  # a bug must not stop the subscriber
                log.exception("console failed on %s", key)
                self.rejections.reject(Rejected(RejectReason.INTERNAL_ERROR, repr(err)), key)
        return wrapped

    def _on_render(self, payload: bytes) -> None:
        self.core.on_render(payload, time.time())
        self._m_renders.inc()

    # ------------------------------------------------------------------ the services
    def _get(self, service: str, path: str) -> Any:
        r = self._http.get(self.upstream[service] + self._prefix + path)
        r.raise_for_status()
        return r.json()

    def _poll(self) -> None:
        status: dict[str, Any] = {}
        for key, service, path in POLLED:
            try:
                status[key] = self._get(service, path)
            except (httpx.HTTPError, ValueError) as err:
                status[key] = {"error": f"{service} unreachable ({type(err).__name__})"}
        with self._lock:
            self.core.on_status(status, time.time())

    # ------------------------------------------------------------------ for the page
    def pair(self) -> Pair | None:
        with self._lock:
            return self.core.pair

    def diff_png(self) -> bytes | None:
        """The latest pair's |render − truth| heat map (see :meth:`ConsoleCore.diff_png`)."""
        with self._lock:
            return self.core.diff_png()

    def snapshot(self) -> dict[str, Any]:
        with self._lock:
            return self.core.snapshot(time.time())
