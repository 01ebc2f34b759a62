"""The runtime every service worker shares: its threads, their stop and their health.

A service is a pure core (message and time in, what to publish out: ``services/*/core.py``)
run by a worker that owns the I/O. The parts of that I/O every worker needs are here and in
the kit beside it, written once:

- :class:`Loops` — a worker's named threads on one stop event: started together, stopped and
  joined together, each body guarded (an exception is logged and the loop goes on: a bug must
  not stop a service), and the readiness line when one is not running;
- :class:`services.kit.bus.Inbox` — the bounded hand-off from a bus callback to a thread
  (bus handlers only enqueue);
- :func:`services.kit.app.service_app` — the REST wiring, ``/healthz``, ``/readyz`` and
  ``/metrics``;
- :class:`services.kit.observe.Rejections` and ``Heartbeat`` — the metrics hook for dropped
  input and stalls.
"""

from __future__ import annotations

import logging
import threading
from collections.abc import Callable
from typing import Any

log = logging.getLogger(__name__)

__all__ = ["Loops", "guarded"]


def guarded(what: str, fn: Callable[..., Any], *args: Any, **kwargs: Any) -> Any:
    """``fn(*args, **kwargs)``, or None after logging what failed (with its traceback)."""
    try:
        return fn(*args, **kwargs)
    except Exception:
        log.exception("%s failed", what)
        return None


class Loops:
    """The named threads of one worker, sharing one stop event.

    ``forever(name, step)`` runs ``step()`` until the worker stops; ``every(name, period_s,
    step)`` runs it every ``period_s`` wall seconds (the first at once); ``thread(name,
    target)`` runs ``target(stop_event)`` once, for a loop that keeps its own state between
    passes. Steps are guarded; a target is not (it guards what it must). Nothing runs before
    :meth:`start`; :meth:`stop` sets the event and joins every thread.
    """

    def __init__(self, owner: str) -> None:
        self.owner = owner
        self.stop_event = threading.Event()
        self._planned: list[tuple[str, Callable[[], None]]] = []
        self._threads: dict[str, threading.Thread] = {}
        self._started = False

    @property
    def stopping(self) -> bool:
        return self.stop_event.is_set()

    def wait(self, seconds: float) -> bool:
        """Sleep up to ``seconds``; True when the worker is stopping."""
        return self.stop_event.wait(seconds)

    def thread(self, name: str, target: Callable[[threading.Event], None]) -> None:
        self._plan(name, lambda: target(self.stop_event))

    def forever(self, name: str, step: Callable[[], None]) -> None:
        what = f"{self.owner} {name}"

        def run() -> None:
            while not self.stop_event.is_set():
                guarded(what, step)
        self._plan(name, run)

    def every(self, name: str, period_s: float, step: Callable[[], None]) -> None:
        if not period_s > 0:
            raise ValueError(f"period_s must be > 0, got {period_s}")
        what = f"{self.owner} {name}"

        def run() -> None:
            while not self.stop_event.is_set():
                guarded(what, step)
                self.stop_event.wait(period_s)
        self._plan(name, run)

    def _plan(self, name: str, run: Callable[[], None]) -> None:
        if self._started:
            raise RuntimeError(f"{self.owner}: loops are planned before start()")
        if any(n == name for n, _ in self._planned):
            raise ValueError(f"{self.owner}: a loop named {name!r} is already planned")
        self._planned.append((name, run))

    def start(self) -> None:
        if self._started:
            raise RuntimeError(f"{self.owner} was already started")
        self._started = True
        for name, run in self._planned:
            t = threading.Thread(target=run, name=f"{self.owner}-{name}", daemon=True)
            self._threads[name] = t
            t.start()

    def stop(self, timeout_s: float = 5.0) -> list[str]:
        """Stop and join every loop (each up to ``timeout_s``); the names still running."""
        self.stop_event.set()
        late = []
        for name, t in self._threads.items():
            if t is not threading.current_thread():
                t.join(timeout=timeout_s)
            if t.is_alive():
                late.append(name)
        if late:
            log.warning("%s: %s did not stop within %.0f s", self.owner, ", ".join(late),
                        timeout_s)
        return late

    def not_running(self) -> str | None:
        """Why the worker is not ready as far as its threads go (``"<name> thread not
        running"``), or None when every planned loop runs."""
        if not self._started:
            return "not started"
        for name, _ in self._planned:
            t = self._threads.get(name)
            if t is None or not t.is_alive():
                return f"{name} thread not running"
        return None
