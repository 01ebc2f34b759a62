"""``Rejected``: a message that must be dropped, with a short reason for the metrics.

Its own module so that the cores, which raise it, import nothing that does I/O; the counting
(Prometheus) is :class:`services.kit.observe.Rejections`.
"""

from __future__ import annotations

__all__ = ["Rejected"]


class Rejected(ValueError):
    """A message that must be dropped; ``reason`` is a short label for metrics."""

    def __init__(self, reason: str, detail: str) -> None:
        super().__init__(f"{reason}: {detail}")
        self.reason = reason
        self.detail = detail
