"""An in-process :class:`~services.kit.bus.Bus` for tests and benches: ``publish`` calls the
matching handlers directly, queries are answered by the queryable's handler on the caller's
thread (or later, from another), liveliness tokens are seen at once. Zenoh's key-expression
matching (``*``, ``**``) is :func:`key_matches`."""

from __future__ import annotations

import threading
import time

from services.kit.bus import AttachedHandler, Handler, LivelinessHandler, QueryHandler, Token

__all__ = ["MemoryBus", "MemoryQuery", "key_matches"]


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
        self._attached: list[tuple[str, AttachedHandler]] = []
        self._queryables: list[tuple[str, QueryHandler]] = []
        self._tokens: set[str] = set()
        self._watchers: list[tuple[str, LivelinessHandler]] = []
        self.published: list[tuple[str, bytes]] = []
        self._lock = threading.Lock()
        self.closed = False

    def publish(self, key: str, payload: bytes) -> None:
        self.put(key, payload)

    def put(self, key: str, payload: bytes, attachment: bytes | None = None) -> None:
        """Publish with an attachment (seen by :meth:`subscribe_attached` handlers)."""
        with self._lock:
            self.published.append((key, payload))
            subs = list(self._subs)
            attached = list(self._attached)
        for pattern, handler in subs:
            if key_matches(pattern, key):
                handler(key, payload)
        for pattern, handler_a in attached:
            if key_matches(pattern, key):
                handler_a(key, payload, attachment)

    def subscribe(self, key: str, handler: Handler) -> _MemorySubscription:
        entry = (key, handler)
        with self._lock:
            self._subs.append(entry)
        return _MemorySubscription(self, entry)

    def _unsubscribe(self, entry: tuple[str, Handler]) -> None:
        with self._lock:
            if entry in self._subs:
                self._subs.remove(entry)

    def subscribe_attached(self, key: str, handler: AttachedHandler) -> None:
        with self._lock:
            self._attached.append((key, handler))

    def declare_queryable(self, key: str, handler: QueryHandler) -> None:
        with self._lock:
            self._queryables.append((key, handler))

    def query(self, key: str, payload: bytes, timeout_s: float) -> bytes | None:
        with self._lock:
            handlers = [h for pattern, h in self._queryables if key_matches(pattern, key)]
        queries = [MemoryQuery(key, payload) for _ in handlers]
        for handler, query in zip(handlers, queries, strict=True):
            handler(query)
        deadline = time.monotonic() + timeout_s
        for query in queries:
            if query.wait(max(0.0, deadline - time.monotonic())) and query.answer is not None:
                return query.answer
        return None

    def declare_token(self, key: str) -> Token:
        with self._lock:
            self._tokens.add(key)
        self._notify(key, True)
        return _MemoryToken(self, key)

    def _drop_token(self, key: str) -> None:
        with self._lock:
            if key not in self._tokens:
                return
            self._tokens.discard(key)
        self._notify(key, False)

    def _notify(self, key: str, alive: bool) -> None:
        with self._lock:
            watchers = [h for pattern, h in self._watchers if key_matches(pattern, key)]
        for handler in watchers:
            handler(key, alive)

    def watch_liveliness(self, key: str, handler: LivelinessHandler) -> None:
        with self._lock:
            self._watchers.append((key, handler))
            alive = sorted(t for t in self._tokens if key_matches(key, t))
        for token in alive:
            handler(token, True)

    def close(self) -> None:
        self.closed = True

    def messages(self, pattern: str) -> list[bytes]:
        with self._lock:
            return [p for k, p in self.published if key_matches(pattern, k)]


class MemoryQuery:
    """A query on the :class:`MemoryBus`: answered (or closed) once, from any thread."""

    def __init__(self, key: str, payload: bytes) -> None:
        self.key = key
        self.payload = payload
        self.answer: bytes | None = None
        self._done = threading.Event()

    def reply(self, payload: bytes) -> None:
        if not self._done.is_set():
            self.answer = payload
            self._done.set()

    def close(self) -> None:
        self._done.set()

    def wait(self, timeout_s: float) -> bool:
        return self._done.wait(timeout_s)


class _MemoryToken:
    def __init__(self, bus: MemoryBus, key: str) -> None:
        self._bus = bus
        self.key = key

    def undeclare(self) -> None:
        self._bus._drop_token(self.key)


class _MemorySubscription:
    def __init__(self, bus: MemoryBus, entry: tuple[str, Handler]) -> None:
        self._bus, self._entry = bus, entry

    def undeclare(self) -> None:
        self._bus._unsubscribe(self._entry)
