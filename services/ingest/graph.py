"""The ROS graph as the ingest sees it: rmw_zenoh's liveliness tokens of the rig's domain (who
publishes what), and what they say about the rig's topics — the live publishers of each, the
types others publish on it, and why no frame may have come.

Pure: the runtime watches the tokens (:mod:`services.ingest.runtime`) and hands each to
:meth:`RosGraph.on_token`."""

from __future__ import annotations

from collections.abc import Iterable
from typing import Any

from services import ros
from services.ingest.routes import Route

__all__ = ["GRAPH_MAX", "RosGraph"]

GRAPH_MAX = 4096
"""Entities of the ROS graph kept at most (a token beyond is counted, not kept)."""


class RosGraph:
    """The tokens of ``fmt``'s domain (rmw_zenoh; the bridge has none: :attr:`key` is None)."""

    def __init__(self, fmt: ros.KeyFormat) -> None:
        self.format = fmt
        self.entities: dict[str, ros.GraphEntity] = {}
        """The ROS graph (rmw_zenoh's liveliness tokens of the rig's domain), by token."""
        self.unparsed = 0
        self.dropped = 0

    @property
    def key(self) -> str | None:
        """The liveliness tokens to watch: the rig's domain (rmw_zenoh; the bridge has
        none)."""
        if self.format.format != "rmw_zenoh":
            return None
        return f"{ros.LIVELINESS_SPACE}/{self.format.domain_id}/**"

    def on_token(self, key: str, alive: bool) -> None:
        """A token of the ROS graph appeared (``alive``) or vanished; one in another layout is
        counted (``unparsed``) and otherwise left alone."""
        if not alive:
            self.entities.pop(key, None)
            return
        try:
            entity = ros.parse_liveliness(key)
        except ValueError:
            self.unparsed += 1
            return
        if key not in self.entities and len(self.entities) >= GRAPH_MAX:
            self.dropped += 1  # a flood of tokens cannot grow the ingest without bound
            return
        self.entities[key] = entity

    def topic_publishers(self, routes: Iterable[Route]) -> list[dict[str, Any]]:
        """Per subscribed topic: the live publishers of the rig's type, and the types others
        publish on it (a rig that names Image where the camera sends CompressedImage)."""
        out = []
        pubs = [e for e in self.entities.values() if e.kind == "publisher"]
        for r in routes:
            topic = "/" + r.topic.strip("/")
            mine = [e for e in pubs if e.topic == topic]
            same = [e for e in mine if e.ros_type == r.ros_type]
            out.append({"topic": topic, "type": r.ros_type, "publishers": len(same),
                        "nodes": sorted({e.namespace.rstrip("/") + "/" + e.node
                                         for e in same}),
                        "other_types": sorted({e.ros_type or "?" for e in mine} - {r.ros_type})})
        return out

    def hint(self, routes: Iterable[Route]) -> str:
        """Why no frame may have come, from the graph: the rig's image topics nobody
        publishes (empty without a graph, or when each has a publisher)."""
        if self.key is None or not self.entities:
            return ""
        missing = [t for t in self.topic_publishers(routes)
                   if t["publishers"] == 0 and t["type"] in (ros.IMAGE, ros.COMPRESSED)]
        if not missing:
            return ""
        what = ", ".join(t["topic"] + (f" (published as {', '.join(t['other_types'])})"
                                       if t["other_types"] else "") for t in missing[:3])
        more = f" and {len(missing) - 3} more" if len(missing) > 3 else ""
        return f"no publisher of the rig's type in the ROS graph on {what}{more}"

    def status(self, routes: Iterable[Route]) -> dict[str, Any] | None:
        """The status route's ``source.graph`` (None for the bridge)."""
        if self.key is None:
            return None
        entities = self.entities.values()
        return {"nodes": sum(e.kind == "node" for e in entities),
                "publishers": sum(e.kind == "publisher" for e in entities),
                "unparsed_tokens": self.unparsed,
                "dropped_tokens": self.dropped,
                "topics": self.topic_publishers(routes)}
