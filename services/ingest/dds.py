"""A robot on DDS, without a bridge: the rig's ``source.format: dds``.

The ingest becomes a ROS 2 node itself (rclpy from the ROS 2 wheels, ``pip install
'aoi3d[ros2]'``, on Fast DDS: rmw_fastrtps_cpp) in the rig's ``domain_id`` and subscribes to
the rig's topics with the QoS camera drivers publish with (``qos: sensor_data``: best effort,
keep last ``depth``; it matches reliable publishers too). Its subscriptions are *raw*: rclpy
hands over each sample's CDR bytes as they came off the wire, and the ingest's core decodes
them exactly as it decodes a Zenoh sample (:mod:`services.ingest.core`, the bridge's case: no
attachment) — the same decoder, refusals, clocks, poses and counters. The ROS graph of
``/status`` (``source.graph``) comes from DDS discovery (rclpy's graph queries), shaped as the
rmw_zenoh liveliness tokens the core already reads.

Where DDS goes (``source.interface``): ``loopback`` (the default) writes a Fast DDS profile
that whitelists 127.0.0.1 for discovery and data, with unicast discovery through initial
peers on 127.0.0.1 and no multicast — nothing leaves the host; ``all`` leaves Fast DDS's
defaults (every interface, multicast discovery: a robot on the LAN); an IPv4 address
whitelists that interface (multicast discovery on it). The profile
(:mod:`services.ingest.fastdds`) is set in this process's environment before its DDS
participant exists (``FASTDDS_DEFAULT_PROFILES_FILE``, with
``ROS_AUTOMATIC_DISCOVERY_RANGE=SYSTEM_DEFAULT`` so that rmw_fastrtps keeps it).

rclpy is imported lazily: this module imports without the ROS 2 wheels, and only a rig with
``format: dds`` needs them (:class:`DdsSource` says how to install them when missing).
"""

from __future__ import annotations

import importlib
import logging
import threading
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from aoi3d.rigfile import Rig, SourceSpec
from services import ros
from services.ingest.core import IngestCore
from services.ingest.fastdds import configure_fastdds
from services.ingest.graph import RosGraph
from services.kit.keys import Keys

log = logging.getLogger(__name__)

__all__ = ["NODE", "DdsGraph", "DdsIngestCore", "DdsKeyFormat", "DdsSource", "message_class",
           "parse_subscription", "qos_profile"]

NODE = "aoi3d_ingest"
"""The ingest's node name in the ROS graph."""
INSTALL_HINT = ("source.format dds needs ROS 2's rclpy and the message packages: pip install "
                "'aoi3d[ros2]' (the ROS 2 Kilted wheels for Python 3.11), or source a ROS 2 "
                "installation of Python 3.11")
GRAPH_POLL_S = 0.5
_SEP = " ["


@dataclass(frozen=True)
class DdsKeyFormat(ros.KeyFormat):
    """The "keys" of a DDS source: a topic's subscription is ``/<topic> [<ROS type>]`` (what
    :class:`DdsSource` subscribes to); samples carry no attachment, and no key holds a type
    hash (DDS matches the type itself)."""

    format: str = "dds"

    def __post_init__(self) -> None:
        if self.format != "dds":
            raise ValueError("a DDS key format is dds")

    @property
    def attached(self) -> bool:
        return False

    def key(self, topic: str, ros_type: str, hash_: str | None = None) -> str:
        return self.subscription(topic, ros_type)

    def subscription(self, topic: str, ros_type: str) -> str:
        return f"/{topic.strip('/')}{_SEP}{ros_type}]"

    def check_key(self, key: str, ros_type: str) -> None:
        return None


def parse_subscription(key_expr: str) -> tuple[str, str]:
    """``/cam0/image_raw [sensor_msgs/msg/Image]`` → (topic, ROS type)."""
    topic, sep, rest = key_expr.partition(_SEP)
    if not sep or not rest.endswith("]") or not topic.startswith("/"):
        raise ValueError(f"{key_expr!r} is not a DDS subscription (/<topic> [<ROS type>])")
    return topic, rest[:-1]


class DdsGraph(RosGraph):
    """The ROS graph of a DDS domain: DDS discovery fills it (:class:`DdsSource` turns what it
    discovers into rmw_zenoh-shaped tokens); :attr:`key` only names the watch."""

    @property
    def key(self) -> str | None:
        return f"dds/{self.format.domain_id}"


class DdsIngestCore(IngestCore):
    """The ingest core on a DDS source: unchanged but for its key format and the ROS graph,
    which DDS discovery fills (:class:`DdsGraph`)."""

    def __init__(self, rig: Rig, keys: Keys, *, epoch_s: float, time_scale: float,
                 through_network: bool = False, wire_encoding: str = "png") -> None:
        super().__init__(rig, keys, epoch_s=epoch_s, time_scale=time_scale,
                         through_network=through_network, wire_encoding=wire_encoding,
                         key_format=DdsKeyFormat(domain_id=rig.source.domain_id))
        self.ros_graph = DdsGraph(self.format)

    def status(self, now_s: float) -> dict[str, Any]:
        out = super().status(now_s)
        src = self.rig.source
        out["source"]["connect"] = (f"DDS domain {src.domain_id} straight (rclpy, "
                                    f"rmw_fastrtps_cpp), interface {src.interface}")
        out["source"]["qos"] = {"profile": src.qos, "depth": src.depth,
                                "reliability": ("best_effort" if src.qos == "sensor_data"
                                                else "reliable"),
                                "history": "keep_last"}
        return out


def message_class(ros_type: str) -> Any:
    """``sensor_msgs/msg/Image`` → rclpy's message class (from the ROS 2 packages)."""
    pkg, kind, name = ros_type.split("/")
    return getattr(importlib.import_module(f"{pkg}.{kind}"), name)


def qos_profile(spec_qos: str, depth: int) -> Any:
    from rclpy.qos import DurabilityPolicy, HistoryPolicy, QoSProfile, ReliabilityPolicy

    return QoSProfile(history=HistoryPolicy.KEEP_LAST, depth=depth,
                      reliability=(ReliabilityPolicy.BEST_EFFORT if spec_qos == "sensor_data"
                                   else ReliabilityPolicy.RELIABLE),
                      durability=DurabilityPolicy.VOLATILE)


# ---------------------------------------------------------------- the source
class DdsSource:
    """A ROS 2 node on DDS standing where the ingest's Zenoh source bus stands: it offers the
    bus methods the ingest worker uses (:meth:`subscribe_attached`, :meth:`watch_liveliness`,
    :meth:`close`) plus :meth:`publisher` for aoi3d's outputs in ROS. One rclpy context of its
    own (no signal handlers: the service's are uvicorn's), one executor thread."""

    def __init__(self, spec: SourceSpec, *, node: str = NODE,
                 profile_dir: str | Path | None = None) -> None:
        self.spec = spec
        self.node_name = node
        if spec.format != "dds":
            raise ValueError(f"a DDS source for format {spec.format!r}")
        configure_fastdds(spec.interface, profile_dir)
        try:
            import rclpy
            from rclpy.executors import SingleThreadedExecutor
            from rclpy.signals import SignalHandlerOptions
        except ImportError as err:
            raise RuntimeError(f"{INSTALL_HINT} ({err})") from None
        self._rclpy = rclpy
        self._ctx = rclpy.Context()
        rclpy.init(context=self._ctx, domain_id=spec.domain_id,
                   signal_handler_options=SignalHandlerOptions.NO)
        self.node = rclpy.create_node(node, context=self._ctx,
                                      start_parameter_services=False)
        self._qos = qos_profile(spec.qos, spec.depth)
        self._executor = SingleThreadedExecutor(context=self._ctx)
        self._executor.add_node(self.node)
        self._stop = threading.Event()
        self._threads = [threading.Thread(target=self._spin, name="dds-spin", daemon=True)]
        self._threads[0].start()
        self._lock = threading.Lock()
        self._subs: list[Any] = []
        log.info("DDS source: node /%s in domain %d (%s, %s depth %d)", node, spec.domain_id,
                 spec.interface, spec.qos, spec.depth)

    def _spin(self) -> None:
        while not self._stop.is_set() and self._ctx.ok():
            try:
                self._executor.spin_once(timeout_sec=0.1)
            except Exception as err:  # shutdown races; a callback's bug
                if self._stop.is_set() or not self._ctx.ok():
                    return
                log.warning("DDS executor: %r", err)

    # ------------------------------------------------------------------ the Bus side
    def subscribe_attached(self, key: str, handler: Callable[[str, bytes, bytes | None],
                                                             None]) -> None:
        """Subscribe to ``key`` (``/<topic> [<ROS type>]``): each sample's CDR bytes go to
        ``handler(key, payload, None)``."""
        topic, ros_type = parse_subscription(key)
        cls = message_class(ros_type)

        def on_raw(payload: bytes) -> None:
            try:
                handler(key, bytes(payload), None)
            except Exception:  # a handler bug must not kill the executor
                log.exception("handler for %s failed", key)

        with self._lock:
            self._subs.append(self.node.create_subscription(cls, topic, on_raw, self._qos,
                                                            raw=True))

    def subscribe(self, key: str, handler: Callable[[str, bytes], None]) -> None:
        self.subscribe_attached(key, lambda k, payload, _att: handler(k, payload))

    def watch_liveliness(self, key: str, handler: Callable[[str, bool], None]) -> None:
        """The ROS graph from DDS discovery, polled every :data:`GRAPH_POLL_S`: each node and
        publisher (but this node) as an rmw_zenoh-shaped token, ``handler(token, alive)``
        when one appears or goes (``key`` only names the watch)."""
        t = threading.Thread(target=self._watch, args=(handler,), name="dds-graph",
                             daemon=True)
        self._threads.append(t)
        t.start()

    def graph_tokens(self) -> set[str]:
        """The ROS graph now, as tokens (:func:`services.ros.parse_liveliness`'s
        layout)."""
        d = self.spec.domain_id
        out: set[str] = set()
        for name, ns in self.node.get_node_names_and_namespaces():
            if (name, ns) == (self.node_name, "/"):
                continue
            out.add(ros.liveliness_key(d, "dds", 0, 0, "node", name, namespace=ns or "/"))
        for topic, _types in self.node.get_topic_names_and_types():
            for info in self.node.get_publishers_info_by_topic(topic):
                if (info.node_name, info.node_namespace) == (self.node_name, "/"):
                    continue
                gid = bytes(info.endpoint_gid).hex()[:32] or "0"
                hash_ = str(getattr(info, "topic_type_hash", "") or ros.HUMBLE_HASH)
                if not hash_.startswith("RIHS01_"):
                    hash_ = ros.HUMBLE_HASH
                try:
                    out.add(ros.liveliness_key(d, gid, 0, 0, "publisher", info.node_name or "_",
                                               namespace=info.node_namespace or "/",
                                               topic=topic, ros_type=info.topic_type,
                                               hash_=hash_))
                except ValueError:  # a type name not pkg/msg/Name
                    continue
        return out

    def _watch(self, handler: Callable[[str, bool], None]) -> None:
        known: set[str] = set()
        while not self._stop.wait(GRAPH_POLL_S):
            try:
                now = self.graph_tokens()
            except Exception as err:  # the context went away under us
                if self._stop.is_set():
                    return
                log.warning("DDS graph: %r", err)
                continue
            for token in sorted(now - known):
                handler(token, True)
            for token in sorted(known - now):
                handler(token, False)
            known = now

    # ------------------------------------------------------------------ outputs
    def publisher(self, topic: str, ros_type: str, depth: int = 5) -> Callable[[bytes], None]:
        """A reliable, keep-last publisher of ``topic``: the callable publishes one CDR-encoded
        sample (reliable: best-effort subscribers such as sensor-data ones match it too)."""
        from rclpy.qos import ReliabilityPolicy

        qos = qos_profile("reliable", depth)
        qos.reliability = ReliabilityPolicy.RELIABLE
        with self._lock:
            pub = self.node.create_publisher(message_class(ros_type), topic, qos)
        return pub.publish

    def close(self) -> None:
        self._stop.set()
        for t in self._threads:
            t.join(timeout=2.0)
        try:
            self._executor.shutdown(timeout_sec=1.0)
            self.node.destroy_node()
        finally:
            if self._ctx.ok():
                self._ctx.shutdown()
