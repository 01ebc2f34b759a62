"""Free views and exports at the dispatcher, as pure logic: the bound on their rate and the
reasons one is refused (no bus, no clock of its own: the runtime passes the time).

A free view (``GET /render.png?c2w=…``) or an export (``GET /export.ply``) is asked of the
worker that rendered the site's latest decision (it keeps that model). They are not scored
(there is no truth at a free pose) and never delay a decision's render: the worker answers
them on a thread of their own from a snapshot. The dispatcher bounds them — a token bucket
(``view_rate_per_s``, bursts of ``view_burst``) and a largest side (``max_view_side``) — and
counts every refusal by reason (``aoi3d_dispatcher_views_total{outcome}``).
"""

from __future__ import annotations

from dataclasses import dataclass

__all__ = ["OUTCOMES", "TokenBucket", "ViewRefused"]

OUTCOMES = ("served", "rate_limited", "bad_request", "no_model", "busy", "timeout", "failed")
"""How a free view or export ended: ``served``, or why it was refused (the label values of
``aoi3d_dispatcher_views_total{outcome}``)."""

STATUS = {"rate_limited": 429, "bad_request": 422, "no_model": 404, "busy": 503,
          "timeout": 504, "failed": 502}
"""The HTTP status of each refusal."""


class ViewRefused(Exception):
    """A free view or export that is not served; ``outcome`` is one of :data:`OUTCOMES`."""

    def __init__(self, outcome: str, detail: str) -> None:
        super().__init__(detail)
        self.outcome = outcome
        self.detail = detail

    @property
    def status(self) -> int:
        return STATUS.get(self.outcome, 500)


@dataclass
class TokenBucket:
    """``rate_per_s`` requests a second on average, bursts of up to ``burst``."""

    rate_per_s: float
    burst: float
    _tokens: float = -1.0
    _last_s: float | None = None

    def take(self, now_s: float) -> bool:
        """Whether a request at ``now_s`` (monotonic seconds) may go ahead (and count it)."""
        if self._last_s is None:
            self._tokens = self.burst
        else:
            self._tokens = min(self.burst,
                               self._tokens + max(0.0, now_s - self._last_s) * self.rate_per_s)
        self._last_s = now_s
        if self._tokens >= 1.0:
            self._tokens -= 1.0
            return True
        return False
