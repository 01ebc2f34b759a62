"""Observability helpers: rejected-message accounting and logging set-up."""

from __future__ import annotations

import logging
import threading
import time
from collections import deque

from prometheus_client import CollectorRegistry, Counter

from services.kit.rejected import Rejected  # re-exported: the workers count what cores raise

log = logging.getLogger("aoi3d.rejected")


class Rejections:
    """Counts dropped messages in ``aoi3d_messages_rejected_total{reason}``.

    Logs once per reason per ``log_interval_s`` (with how many were dropped since), so a
    flood of bad input never floods the log.
    """

    def __init__(self, registry: CollectorRegistry, log_interval_s: float = 10.0) -> None:
        self.counter = Counter(
            "aoi3d_messages_rejected", "Messages dropped because they were invalid.",
            ["reason"], registry=registry)
        self._interval = log_interval_s
        self._last: dict[str, float] = {}
        self._since: dict[str, int] = {}
        self._lock = threading.Lock()

    def reject(self, err: Rejected, key: str = "") -> None:
        self.counter.labels(reason=err.reason).inc()
        now = time.monotonic()
        with self._lock:
            self._since[err.reason] = self._since.get(err.reason, 0) + 1
            last = self._last.get(err.reason)
            if last is not None and now - last < self._interval:
                return
            count, self._since[err.reason] = self._since[err.reason], 0
            self._last[err.reason] = now
        log.warning("dropped %d message(s) [%s] on %s: %s", count, err.reason, key or "?",
                    err.detail)

    def total(self, reason: str) -> float:
        return self.counter.labels(reason=reason)._value.get()


def setup_logging(level: str, service: str) -> None:
    logging.basicConfig(
        level=getattr(logging, level.upper(), logging.INFO),
        format=f"%(asctime)s {service} %(levelname)s %(name)s: %(message)s",
    )


class RateMeter:
    """A counter's rate per wall second over the last ``window_s`` seconds (e.g. training
    steps per second): feed it the running total with :meth:`add`."""

    def __init__(self, window_s: float = 5.0) -> None:
        self._window_s = window_s
        self._samples: deque[tuple[float, int]] = deque()

    def add(self, now_s: float, total: int) -> float:
        """Record ``total`` at ``now_s``; the rate over the window."""
        self._samples.append((now_s, total))
        while len(self._samples) > 2 and now_s - self._samples[1][0] >= self._window_s:
            self._samples.popleft()
        (t0, s0), (t1, s1) = self._samples[0], self._samples[-1]
        return (s1 - s0) / (t1 - t0) if t1 > t0 else 0.0

    def idle(self, now_s: float, total: int) -> float:
        """Record a moment without progress (the rate decays to 0 over the window)."""
        return self.add(now_s, total)


class Heartbeat:
    """When a worker last did its job (monotonic clock), for a readiness that tells the
    truth: alive but idle for longer than ``stall_s`` is not ready. Counts from creation, so
    a worker that never did its job turns not ready ``stall_s`` after it started."""

    def __init__(self, stall_s: float) -> None:
        self.stall_s = float(stall_s)
        self._last = time.monotonic()

    def beat(self) -> None:
        self._last = time.monotonic()

    def idle_s(self) -> float:
        return time.monotonic() - self._last

    def stalled(self) -> bool:
        return self.idle_s() > self.stall_s
