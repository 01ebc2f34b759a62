"""Why a decision ended without a Quality: the wire contract's one enum, ``EndReason``
(proto/aoi3d.proto), as the Python the services use.

:class:`EndReason` is built from the generated protobuf enum, so there is no second list to
keep in step: a member's value is its *label*, the proto name without ``END_REASON_`` in lower
case (``END_REASON_WORKER_DIED`` → ``"worker_died"``). A member is a ``str``: it is the
Prometheus label value, the key of the ledger's JSON and saved file and of the dispatcher's
``/status`` as it is; :meth:`EndReason.wire` and :func:`from_wire` cross to the Outcome's
enum number. The proto's number ranges say who tells a reason; the groups below read them.
Standard library and the generated module only (a service's core may import it).
"""

from __future__ import annotations

from enum import StrEnum
from typing import TYPE_CHECKING

from services.kit.pb import aoi3d_pb2 as pb

__all__ = ["LEDGER_LOST", "LOST", "METRICS_LOST", "SKIPPED", "TRAINER_LOST", "EndReason",
           "from_wire"]

_PREFIX = "END_REASON_"


def _members() -> dict[str, str]:
    return {name.removeprefix(_PREFIX): name.removeprefix(_PREFIX).lower()
            for name, number in pb.EndReason.items() if number != pb.END_REASON_UNSPECIFIED}


class _Reason(StrEnum):
    """A reason of proto/aoi3d.proto's EndReason; its value is its label."""

    @property
    def wire(self) -> pb.EndReason:
        """The reason's number on the wire (``Outcome.reason``)."""
        number: pb.EndReason = pb.EndReason.Value(_PREFIX + self.name)
        return number


if TYPE_CHECKING:
    # What the type checker sees: the members the proto has today, spelled out for it alone
    # (tests/unit/cores/test_ledger.py checks this list against the built enum, so it cannot drift).
    # At run time the enum is built from the generated module, below.
    class EndReason(_Reason):
        SUPERSEDED = "superseded"
        WORKER_DIED = "worker_died"
        TIMEOUT = "timeout"
        NOT_DELIVERED = "not_delivered"
        RENDER_FAILED = "render_failed"
        REFUSED = "refused"
        NOT_RECEIVED = "not_received"
        TRUTH_MISSING = "truth_missing"
        RENDER_REJECTED = "render_rejected"
        UNSEEN = "unseen"
        EXPIRED = "expired"
else:
    EndReason = _Reason("EndReason", _members(), module=__name__)


def from_wire(number: int) -> EndReason:
    """The reason of an Outcome's enum number; ``ValueError`` for 0 (unset) or an unknown one."""
    if number == pb.END_REASON_UNSPECIFIED:
        raise ValueError("no reason given (END_REASON_UNSPECIFIED)")
    try:
        return EndReason[pb.EndReason.Name(number).removeprefix(_PREFIX)]
    except ValueError:
        raise ValueError(f"unknown EndReason {number}") from None


def _within(low: int, high: int) -> tuple[EndReason, ...]:
    return tuple(r for r in EndReason if low <= r.wire <= high)


SKIPPED = _within(1, 9)
"""Skipped by choice: ``superseded``."""
TRAINER_LOST = _within(10, 29)
"""Lost, told by the dispatcher in an Outcome: ``worker_died``, ``timeout``, ``not_delivered``,
``render_failed``, ``refused``, ``not_received``."""
METRICS_LOST = _within(30, 39)
"""Lost, found by the metrics service: ``truth_missing``, ``render_rejected``."""
LEDGER_LOST = _within(40, 49)
"""Lost, found by the ledger: ``unseen``, ``expired``."""
LOST = (*TRAINER_LOST, *METRICS_LOST, *LEDGER_LOST)
"""Every reason a decision is lost for, in the proto's order."""
assert set(SKIPPED) | set(LOST) == set(EndReason), "an EndReason outside the proto's ranges"
