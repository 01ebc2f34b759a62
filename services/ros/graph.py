"""The ROS graph on rmw_zenoh: the liveliness tokens that announce nodes and their publishers,
subscriptions, services and clients (how ``ros2 node list`` sees them) — made and read."""

from __future__ import annotations

from collections.abc import Iterable
from dataclasses import dataclass

from services.ros.types import dds_type, ros_type_of, type_hash

__all__ = ["DEFAULT_QOS", "ENTITY_KINDS", "LIVELINESS_SPACE", "GraphEntity", "liveliness_key",
           "node_tokens", "parse_liveliness"]

LIVELINESS_SPACE = "@ros2_lv"
"""The key space of rmw_zenoh's liveliness tokens: how ROS 2 nodes see one another."""
ENTITY_KINDS = {"NN": "node", "MP": "publisher", "MS": "subscription", "SS": "service",
                "SC": "client"}
DEFAULT_QOS = "::,:,:,:,,"
"""A token's QoS chunk when every policy is rmw_zenoh's default (each non-default value goes
between its delimiters: reliability:durability:history,depth:deadline s,ns:lifespan
s,ns:liveliness,lease s,ns)."""


@dataclass(frozen=True)
class GraphEntity:
    """One liveliness token of the ROS graph: a node, or a node's publisher, subscription,
    service or client with its topic (``/cam0/image_raw``), ROS type
    (``sensor_msgs/msg/Image``) and type hash."""

    kind: str
    domain_id: int
    session: str
    node: str
    namespace: str = "/"
    topic: str | None = None
    ros_type: str | None = None
    type_hash: str | None = None


def _mangle(name: str) -> str:
    return name.replace("/", "%")


def _demangle(name: str) -> str:
    return name.replace("%", "/")


def liveliness_key(domain_id: int, session: str, node_id: int, entity_id: int, kind: str,
                   node: str, *, namespace: str = "/", enclave: str = "/",
                   topic: str | None = None, ros_type: str | None = None,
                   hash_: str | None = None, qos: str = DEFAULT_QOS) -> str:
    """The token rmw_zenoh declares for an entity (the layout of its Jazzy branch and its
    Humble backport, ``liveliness_utils.cpp``): ``@ros2_lv/<domain>/<session id>/<node
    id>/<entity id>/<NN|MP|MS|SS|SC>/<enclave>/<namespace>/<node>`` and, for a topic's
    entity, ``/<topic>/<DDS type>/<type hash>/<qos>``; a name's slashes become ``%``."""
    code = {v: k for k, v in ENTITY_KINDS.items()}[kind]
    parts = [LIVELINESS_SPACE, str(domain_id), session, str(node_id), str(entity_id), code,
             _mangle(enclave), _mangle(namespace), _mangle(node)]
    if kind != "node":
        if topic is None or ros_type is None:
            raise ValueError(f"a {kind}'s token names its topic and type")
        parts += [_mangle("/" + topic.strip("/")), dds_type(ros_type),
                  hash_ or type_hash(ros_type), qos]
    return "/".join(parts)


def node_tokens(domain_id: int, session: str, node: str,
                publishers: Iterable[tuple[str, str]], hash_: str | None = None) -> list[str]:
    """A node's liveliness tokens: the node, then a publisher of each (topic, ROS type), as
    rmw_zenoh declares them (entity ids 1, 2, … within node 0 of the session)."""
    out = [liveliness_key(domain_id, session, 0, 0, "node", node)]
    for entity_id, (topic, ros_type) in enumerate(publishers, start=1):
        out.append(liveliness_key(domain_id, session, 0, entity_id, "publisher", node,
                                  topic=topic, ros_type=ros_type, hash_=hash_))
    return out


def parse_liveliness(key: str) -> GraphEntity:
    """A token of the ROS graph (:func:`liveliness_key`'s layout). :class:`ValueError` that
    says what is wrong otherwise (another layout, another key space, a missing part)."""
    parts = str(key).split("/")
    if parts[0] != LIVELINESS_SPACE:
        raise ValueError(f"{key[:120]!r}: not under {LIVELINESS_SPACE}/")
    if len(parts) < 9 or any(not p for p in parts):
        raise ValueError(f"{key[:120]!r}: {len(parts)} parts, a token has 9 or 13")
    kind = ENTITY_KINDS.get(parts[5])
    if kind is None or not parts[1].isdigit():
        raise ValueError(f"{key[:120]!r}: no entity kind (NN, MP, MS, SS, SC) in part 6 or "
                         f"no domain id in part 2 (an older rmw_zenoh's layout?)")
    out = GraphEntity(kind, int(parts[1]), parts[2], _demangle(parts[8]),
                      _demangle(parts[7]))
    if kind == "node":
        return out
    if len(parts) < 13:
        raise ValueError(f"{key[:120]!r}: a {kind}'s token has 13 parts, not {len(parts)}")
    return GraphEntity(kind, out.domain_id, out.session, out.node, out.namespace,
                       "/" + _demangle(parts[9]).strip("/"), ros_type_of(_demangle(parts[10])),
                       parts[11])
