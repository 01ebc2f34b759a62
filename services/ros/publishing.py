"""Publishing on Zenoh: a plain client session to a router, with the ROS graph's tokens held,
for the test robot (``aoi3d ros2 publish``) and the player (``aoi3d replay --play``)."""

from __future__ import annotations

import contextlib
import time
from collections.abc import Callable, Iterator

__all__ = ["zenoh_publishing"]


@contextlib.contextmanager
def zenoh_publishing(connect: list[str], keys: list[str] | None = None,
                     wait_s: float = 10.0, tokens: Callable[[str], list[str]] | None = None
                     ) -> Iterator[Callable[[str, bytes, bytes | None], None]]:
    """``put(key, payload, attachment)`` on a plain Zenoh client session to ``connect``, for
    the block (the session closed after it). ``tokens(session id)``: liveliness tokens to
    hold for the block (a ROS node's graph entities, :meth:`Robot.tokens`).

    A new client session learns who subscribes to what from the router a moment after it
    opens, and drops what it puts before that (seen: each camera's first pose and camera
    info, and more on a loaded machine). So a publisher is declared for each of ``keys`` and
    the robot waits — as a real one takes to start — until every image key has a subscriber
    (then a moment more for the rest), or ``wait_s``."""
    import json

    import zenoh

    conf = zenoh.Config()
    conf.insert_json5("mode", json.dumps("client"))
    conf.insert_json5("scouting/multicast/enabled", "false")
    conf.insert_json5("connect/endpoints", json.dumps(connect))
    session = zenoh.open(conf)
    pubs = {key: session.declare_publisher(key) for key in keys or []}
    held = [session.liveliness().declare_token(t)
            for t in (tokens(str(session.zid())) if tokens else [])]
    try:
        deadline = time.monotonic() + wait_s
        images = [p for k, p in pubs.items() if "image" in k] or list(pubs.values())
        # zenoh's stub says matching_status is a bool; it is a MatchingStatus (1.x runtime)
        while time.monotonic() < deadline and not all(
                p.matching_status.matching for p in images):  # type: ignore[attr-defined]
            time.sleep(0.05)
        time.sleep(0.5 if pubs else 1.0)

        def put(key: str, payload: bytes, attachment: bytes | None) -> None:
            pub = pubs.get(key)
            if pub is not None:
                pub.put(payload, attachment=attachment)
            else:
                session.put(key, payload, attachment=attachment)

        yield put
    finally:
        for pub in pubs.values():
            pub.undeclare()
        for token in held:
            token.undeclare()
        session.close()
