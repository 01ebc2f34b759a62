"""Requests from the HTTP threads carried out by the training thread, between two chunks.

The training thread owns the model; other threads never touch it. :meth:`ControlQueue.call`
queues a function for that thread and waits for it (or runs it at once when the thread is
not running), :meth:`ControlQueue.run_pending` is what the training thread calls between two
chunks of steps.
"""

from __future__ import annotations

import threading
from collections.abc import Callable


class ControlQueue:
    """Functions queued for the training thread, each with the event that reports it done."""

    def __init__(self, wake: threading.Event) -> None:
        self._wake = wake
        self._lock = threading.Lock()
        self._pending: list[tuple[Callable[[], None], threading.Event]] = []

    def call(self, fn: Callable[[], None], *, thread_alive: bool, timeout_s: float) -> bool:
        """Run ``fn`` on the training thread (now, here, if it is not alive); False if it was
        not done within ``timeout_s`` (it still runs later)."""
        if not thread_alive:
            fn()
            return True
        done = threading.Event()
        with self._lock:
            self._pending.append((fn, done))
        self._wake.set()
        return done.wait(timeout_s)

    def run_pending(self) -> None:
        """Run every queued function, in order (the training thread, between two chunks)."""
        with self._lock:
            pending, self._pending = self._pending, []
        for fn, done in pending:
            try:
                fn()
            finally:
                done.set()
