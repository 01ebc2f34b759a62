"""The message bus the services talk through: Zenoh in production, in-memory in tests.

Handlers run on the bus's delivery thread (Zenoh: its callback threads, concurrently for
different subscriptions) and must return quickly: hand work to an :class:`Inbox`.
"""

from __future__ import annotations

import contextlib
import logging
import threading
from collections import deque
from collections.abc import Callable
from typing import Protocol

log = logging.getLogger(__name__)

Handler = Callable[[str, bytes], None]


class Bus(Protocol):
    def publish(self, key: str, payload: bytes) -> None: ...

    def subscribe(self, key: str, handler: Handler) -> None: ...

    def close(self) -> None: ...


class ZenohBus:
    """A Zenoh session with a publisher per key, declared on first use."""

    def __init__(self, config) -> None:
        import zenoh

        self._zenoh = zenoh
        self._session = zenoh.open(config)
        self._publishers: dict[str, object] = {}
        self._subscribers: list[object] = []
        self._lock = threading.Lock()
        self._closed = False

    def publish(self, key: str, payload: bytes) -> None:
        with self._lock:
            if self._closed:
                return
            pub = self._publishers.get(key)
            if pub is None:
                pub = self._session.declare_publisher(
                    key, congestion_control=self._zenoh.CongestionControl.DROP)
                self._publishers[key] = pub
        pub.put(payload)

    def subscribe(self, key: str, handler: Handler) -> None:
        def on_sample(sample) -> None:
            try:
                handler(str(sample.key_expr), sample.payload.to_bytes())
            except Exception:  # a handler bug must not kill Zenoh's thread
                log.exception("handler for %s failed", key)

        with self._lock:
            self._subscribers.append(self._session.declare_subscriber(key, on_sample))

    def close(self) -> None:
        with self._lock:
            if self._closed:
                return
            self._closed = True
            subs, pubs = self._subscribers, list(self._publishers.values())
            self._subscribers, self._publishers = [], {}
        for ent in subs + pubs:
            with contextlib.suppress(Exception):  # already gone with the session
                ent.undeclare()
        self._session.close()


def key_matches(pattern: str, key: str) -> bool:
    """Zenoh key-expression matching for ``*`` (one chunk) and ``**`` (any chunks)."""

    def match(p: list[str], k: list[str]) -> bool:
        if not p:
            return not k
        if p[0] == "**":
            return any(match(p[1:], k[i:]) for i in range(len(k) + 1))
        return bool(k) and (p[0] == "*" or p[0] == k[0]) and match(p[1:], k[1:])

    return match(pattern.split("/"), key.split("/"))


class MemoryBus:
    """Synchronous in-process bus for tests: ``publish`` calls matching handlers directly.

    Several services may share one instance; ``published`` records every message.
    """

    def __init__(self) -> None:
        self._subs: list[tuple[str, Handler]] = []
        self.published: list[tuple[str, bytes]] = []
        self._lock = threading.Lock()
        self.closed = False

    def publish(self, key: str, payload: bytes) -> None:
        with self._lock:
            self.published.append((key, payload))
            subs = list(self._subs)
        for pattern, handler in subs:
            if key_matches(pattern, key):
                handler(key, payload)

    def subscribe(self, key: str, handler: Handler) -> None:
        with self._lock:
            self._subs.append((key, handler))

    def close(self) -> None:
        self.closed = True

    def messages(self, pattern: str) -> list[bytes]:
        with self._lock:
            return [p for k, p in self.published if key_matches(pattern, k)]


class Inbox:
    """A bounded hand-off queue between a bus callback and a worker thread.

    When full, the oldest item is dropped (frames: only the newest matters), counted in
    ``dropped`` and reported to ``on_drop`` (e.g. a Prometheus counter's ``inc``).
    """

    def __init__(self, maxsize: int = 256, on_drop: Callable[[], None] | None = None) -> None:
        self._items: deque = deque()
        self._maxsize = maxsize
        self._cond = threading.Condition()
        self._on_drop = on_drop
        self.dropped = 0

    def put(self, item) -> None:
        with self._cond:
            overflow = len(self._items) >= self._maxsize
            if overflow:
                self._items.popleft()
                self.dropped += 1
            self._items.append(item)
            self._cond.notify()
        if overflow and self._on_drop is not None:
            self._on_drop()

    def get(self, timeout: float | None = None):
        """The oldest item, or None after ``timeout`` seconds."""
        with self._cond:
            if not self._items and not self._cond.wait_for(lambda: bool(self._items), timeout):
                return None
            return self._items.popleft()

    def drain(self) -> list:
        with self._cond:
            items = list(self._items)
            self._items.clear()
            return items

    def __len__(self) -> int:
        with self._cond:
            return len(self._items)
