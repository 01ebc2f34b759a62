"""Topics → Zenoh keys, in either format: ``rmw_zenoh`` (``<domain>/<topic>/<DDS type>/<type
hash>``) or ``bridge`` (zenoh-bridge-ros2dds: ``[<namespace>/]<topic>``)."""

from __future__ import annotations

import re
from dataclasses import dataclass

from services.kit.rejected import Rejected, RejectReason
from services.ros.types import HUMBLE_HASH, dds_type, type_hash

__all__ = ["KeyFormat"]

_HASH_RE = re.compile(r"^RIHS01_[0-9a-f]{64}$")


@dataclass(frozen=True)
class KeyFormat:
    """How topics map to Zenoh keys: ``rmw_zenoh`` (with ``domain_id``) or ``bridge`` (with
    ``namespace``)."""

    format: str = "rmw_zenoh"
    domain_id: int = 0
    namespace: str = ""

    def __post_init__(self) -> None:
        if self.format not in ("rmw_zenoh", "bridge"):
            raise ValueError(f"key format {self.format!r}: rmw_zenoh or bridge")

    @property
    def attached(self) -> bool:
        """Whether samples carry the rmw_zenoh attachment."""
        return self.format == "rmw_zenoh"

    def _topic(self, topic: str) -> str:
        return topic.strip("/")

    def key(self, topic: str, ros_type: str, hash_: str | None = None) -> str:
        """The key a publisher of ``topic`` puts on; ``hash_`` (rmw_zenoh): the type hash,
        default the Jazzy one (:data:`HUMBLE_HASH` for Humble)."""
        if self.format == "bridge":
            ns = self.namespace.strip("/")
            return f"{ns}/{self._topic(topic)}" if ns else self._topic(topic)
        return (f"{self.domain_id}/{self._topic(topic)}/{dds_type(ros_type)}/"
                f"{hash_ or type_hash(ros_type)}")

    def subscription(self, topic: str, ros_type: str) -> str:
        """The key expression a subscriber of ``topic`` declares (any type hash)."""
        if self.format == "bridge":
            return self.key(topic, ros_type)
        return f"{self.domain_id}/{self._topic(topic)}/{dds_type(ros_type)}/*"

    def check_key(self, key: str, ros_type: str) -> None:
        """An rmw_zenoh key's type hash must be the type's or Humble's placeholder."""
        if self.format == "bridge":
            return
        got = key.rsplit("/", 1)[-1]
        if got == HUMBLE_HASH or got == type_hash(ros_type):
            return
        what = "another definition of the type" if _HASH_RE.match(got) else "not a type hash"
        raise Rejected(RejectReason.TYPE_HASH_MISMATCH,
                       f"{key}: {got[:80]!r} is {what} (expected {type_hash(ros_type)} or "
                       f"{HUMBLE_HASH})")
