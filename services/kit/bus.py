"""The message bus the services talk through: Zenoh in production, in-memory in tests
(:class:`services.kit.membus.MemoryBus`).

Handlers run on the bus's delivery thread (Zenoh: its callback threads, concurrently for
different subscriptions) and must return quickly: hand work to an :class:`Inbox`.

Besides pub/sub, the worker pool uses two more of Zenoh's primitives through this protocol:
queries (:meth:`Bus.query` asks, :meth:`Bus.declare_queryable` answers, possibly later: a
:class:`Query` may be kept and replied to from another thread) and liveliness
(:meth:`Bus.declare_token` says "I am here" for as long as the session lives;
:meth:`Bus.watch_liveliness` hears tokens appear and vanish — a killed process's token
vanishes when the router loses its session).
"""

from __future__ import annotations

import contextlib
import logging
import threading
from collections import deque
from collections.abc import Callable
from typing import Any, Protocol

log = logging.getLogger(__name__)

Handler = Callable[[str, bytes], None]
AttachedHandler = Callable[[str, bytes, bytes | None], None]
"""``(key, payload, attachment)``: a sample with its Zenoh attachment (None when it has none)."""
LivelinessHandler = Callable[[str, bool], None]
"""``(key, alive)``: a token appeared (True) or vanished (False)."""


class Query(Protocol):
    """A question to a queryable: answer it once with :meth:`reply`, or :meth:`close` it
    unanswered (the asker then gets nothing); either may happen on any thread, later."""

    key: str
    payload: bytes

    def reply(self, payload: bytes) -> None: ...

    def close(self) -> None: ...


QueryHandler = Callable[[Query], None]


class Token(Protocol):
    def undeclare(self) -> None: ...


Subscription = Token
"""A subscription: :meth:`undeclare` ends it (its handler is called no more)."""


class Bus(Protocol):
    def publish(self, key: str, payload: bytes) -> None: ...

    def subscribe(self, key: str, handler: Handler) -> Subscription:
        """Call ``handler`` for every sample on ``key`` until the subscription is
        undeclared (most services keep theirs for the session's life)."""
        ...

    def subscribe_attached(self, key: str, handler: AttachedHandler) -> None:
        """As :meth:`subscribe`, with each sample's attachment (ROS 2's rmw_zenoh puts its
        sequence number, source time and publisher id there)."""
        ...

    def declare_queryable(self, key: str, handler: QueryHandler) -> None: ...

    def query(self, key: str, payload: bytes, timeout_s: float) -> bytes | None:
        """The first answer to a query on ``key``; None when none came within ``timeout_s``."""
        ...

    def declare_token(self, key: str) -> Token: ...

    def watch_liveliness(self, key: str, handler: LivelinessHandler) -> None:
        """Call ``handler`` for every token matching ``key``: those alive now, then each
        that appears or vanishes."""
        ...

    def close(self) -> None: ...


class ZenohBus:
    """A Zenoh session with a publisher per key, declared on first use."""

    def __init__(self, config) -> None:
        import zenoh

        self._zenoh = zenoh
        self._session = zenoh.open(config)
        self._publishers: dict[str, Any] = {}  # zenoh's Publisher
        self._subscribers: list[Any] = []  # zenoh's Subscriber
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

    def subscribe(self, key: str, handler: Handler) -> Subscription:
        def on_sample(sample) -> None:
            try:
                handler(str(sample.key_expr), sample.payload.to_bytes())
            except Exception:  # a handler bug must not kill Zenoh's thread
                log.exception("handler for %s failed", key)

        with self._lock:
            sub = self._session.declare_subscriber(key, on_sample)
            self._subscribers.append(sub)
        return _ZenohSubscription(self, sub)

    def _undeclare(self, sub: Any) -> None:
        with self._lock:
            if self._closed or sub not in self._subscribers:
                return
            self._subscribers.remove(sub)
        with contextlib.suppress(Exception):  # already gone with the session
            sub.undeclare()

    def subscribe_attached(self, key: str, handler: AttachedHandler) -> None:
        def on_sample(sample) -> None:
            try:
                att = sample.attachment
                handler(str(sample.key_expr), sample.payload.to_bytes(),
                        att.to_bytes() if att is not None else None)
            except Exception:  # a handler bug must not kill Zenoh's thread
                log.exception("handler for %s failed", key)

        with self._lock:
            self._subscribers.append(self._session.declare_subscriber(key, on_sample))

    def put(self, key: str, payload: bytes, attachment: bytes | None = None) -> None:
        """One sample on ``key`` with an attachment (no publisher kept: a ROS 2 robot's
        stand-in puts on many keys once per frame)."""
        with self._lock:
            if self._closed:
                return
        self._session.put(key, payload, attachment=attachment)

    def declare_queryable(self, key: str, handler: QueryHandler) -> None:
        def on_query(query) -> None:
            try:
                handler(_ZenohQuery(query))
            except Exception:  # a handler bug must not kill Zenoh's thread
                log.exception("queryable handler for %s failed", key)

        with self._lock:
            self._subscribers.append(self._session.declare_queryable(key, on_query))

    def query(self, key: str, payload: bytes, timeout_s: float) -> bytes | None:
        for reply in self._session.get(key, payload=payload, timeout=timeout_s):
            if reply.ok is not None:
                return reply.ok.payload.to_bytes()
        return None

    def declare_token(self, key: str) -> Token:
        return self._session.liveliness().declare_token(key)

    def watch_liveliness(self, key: str, handler: LivelinessHandler) -> None:
        put = self._zenoh.SampleKind.PUT

        def on_sample(sample) -> None:
            try:
                handler(str(sample.key_expr), sample.kind == put)
            except Exception:
                log.exception("liveliness handler for %s failed", key)

        with self._lock:
            self._subscribers.append(
                self._session.liveliness().declare_subscriber(key, on_sample, history=True))

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


class _ZenohSubscription:
    def __init__(self, bus: ZenohBus, sub: Any) -> None:
        self._bus, self._sub = bus, sub

    def undeclare(self) -> None:
        self._bus._undeclare(self._sub)


class _ZenohQuery:
    """A zenoh Query behind the :class:`Query` protocol (replied at most once, then dropped,
    so the asker is never left waiting for its timeout)."""

    def __init__(self, query) -> None:
        self._query = query
        self.key = str(query.key_expr)
        self.payload = query.payload.to_bytes() if query.payload is not None else b""
        self._done = False
        self._lock = threading.Lock()

    def reply(self, payload: bytes) -> None:
        with self._lock:
            if self._done:
                return
            self._done = True
        try:
            self._query.reply(self._query.key_expr, payload)
        finally:
            with contextlib.suppress(Exception):
                self._query.drop()

    def close(self) -> None:
        with self._lock:
            if self._done:
                return
            self._done = True
        with contextlib.suppress(Exception):
            self._query.drop()


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
