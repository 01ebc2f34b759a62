"""The decision ledger's runtime in the metrics service: one :class:`LedgerKeeper` per site.

It feeds :class:`services.metrics.ledger.Ledger` from the scoring thread (Decision and Outcome
messages, and each render's fate), saves its snapshot to ``<state_dir>/ledger-<run>-<site>.json``
at most once a second and on stop (atomically), restores it on start, and exports it to
Prometheus at scrape time:

- ``aoi3d_ledger_decisions_total{state, reason}``: decisions ended (scored, skipped by choice,
  lost) — every reason listed from 0;
- ``aoi3d_ledger_open``: decisions not ended yet; ``aoi3d_ledger_oldest_open_seconds``;
- ``aoi3d_ledger_after_close_total``: events for a decision that had already ended.
"""

from __future__ import annotations

import logging
import math
import threading
import time
from pathlib import Path

from prometheus_client import CollectorRegistry
from prometheus_client.core import CounterMetricFamily, GaugeMetricFamily

from aoi3d.atomic import write_atomic
from services.kit.codec import decode_decision
from services.kit.observe import Rejected
from services.kit.reasons import EndReason
from services.kit.rejected import RejectReason
from services.metrics.ledger import (
    LOST_REASONS,
    SKIPPED_REASONS,
    Ledger,
    LedgerSummary,
    decode_outcome,
)

log = logging.getLogger(__name__)

SAVE_EVERY_S = 1.0

__all__ = ["LedgerKeeper"]


class LedgerKeeper:
    """See the module docstring. Events come from one thread; reads from any (one lock)."""

    def __init__(self, registry: CollectorRegistry, *, run_id: str, site: str,
                 open_bound_s: float, state_dir: Path | None) -> None:
        self.site = site
        self.path = None if state_dir is None else Path(state_dir) / f"ledger-{run_id}-{site}.json"
        self.ledger = self._restore(open_bound_s)
        self._lock = threading.Lock()
        self._saved_changes = self.ledger.changes
        self._saved_s = 0.0
        registry.register(_Collector(self))

    def _restore(self, open_bound_s: float) -> Ledger:
        if self.path is None or not self.path.exists():
            return Ledger(open_bound_s=open_bound_s)
        try:
            led = Ledger.from_json(self.path.read_text(), open_bound_s=open_bound_s)
        except (OSError, ValueError) as err:
            log.error("decision ledger %s unreadable (%s): starting a new one", self.path, err)
            return Ledger(open_bound_s=open_bound_s)
        s = led.summary(time.time())
        log.info("decision ledger restored from %s: %d decisions, %d open", self.path,
                 s.decisions, s.open)
        return led

    # ------------------------------------------------------------------ events (scoring thread)
    def on_decision(self, payload: bytes) -> None:
        msg = decode_decision(payload)
        with self._lock:
            self.ledger.decided(msg.incarnation, msg.decision_id, time.time())

    def on_outcome(self, payload: bytes) -> None:
        msg = decode_outcome(payload, self.site)
        with self._lock:
            self.ledger.closed(msg.incarnation, msg.decision_id, msg.state, str(msg.reason),
                               time.time())

    def on_render(self, ids: tuple[int, int] | None, rejected: Rejected | None) -> None:
        """The render of decision ``ids`` (incarnation, id) was scored (``rejected`` None) or
        could not be (``no_truth`` → ``truth_missing``, anything else → ``render_rejected``).
        ``ids`` None: not a Render of a decision — nothing to close (an open decision whose
        render was unreadable expires)."""
        if ids is None:
            return
        truth_missing = rejected is not None and rejected.reason == RejectReason.NO_TRUTH
        state, reason = (("scored", "") if rejected is None else
                         ("lost", str(EndReason.TRUTH_MISSING if truth_missing
                                      else EndReason.RENDER_REJECTED)))
        with self._lock:
            self.ledger.closed(*ids, state, reason, time.time())

    def tick(self, force: bool = False) -> None:
        """Expire what waited too long; save when something changed (at most once a second
        unless ``force``)."""
        now = time.monotonic()
        with self._lock:
            self.ledger.expire(time.time())
            changes = self.ledger.changes
            due = self.path is not None and changes != self._saved_changes and (
                force or now - self._saved_s >= SAVE_EVERY_S)
            text = self.ledger.to_json() if due else None
        if text is None or self.path is None:  # text is None unless a path is set
            return
        try:
            write_atomic(self.path, text)
        except OSError as err:
            log.error("could not save the decision ledger to %s: %s", self.path, err)
            return
        self._saved_changes, self._saved_s = changes, now

    # ------------------------------------------------------------------ reading (any thread)
    def summary(self) -> LedgerSummary:
        with self._lock:
            return self.ledger.summary(time.time())


class _Collector:
    def __init__(self, keeper: LedgerKeeper) -> None:
        self._keeper = keeper

    def describe(self):
        return []

    def collect(self):
        s = self._keeper.summary()
        ended = CounterMetricFamily(
            "aoi3d_ledger_decisions", "Decisions ended, by state (scored, skipped by choice, "
            "lost) and reason (docs/architecture.md, \"The decision ledger\").",
            labels=["state", "reason"])
        ended.add_metric(["scored", ""], s.scored)
        for reason in (*SKIPPED_REASONS, *sorted(set(s.skipped) - set(SKIPPED_REASONS))):
            ended.add_metric(["skipped", reason], s.skipped.get(reason, 0))
        for reason in (*LOST_REASONS, *sorted(set(s.lost) - set(LOST_REASONS))):
            ended.add_metric(["lost", reason], s.lost.get(reason, 0))
        yield ended
        yield GaugeMetricFamily("aoi3d_ledger_open", "Decisions seen and not ended yet.",
                                value=s.open)
        yield GaugeMetricFamily(
            "aoi3d_ledger_oldest_open_seconds", "Wall seconds the oldest open decision has "
            "waited; NaN when none is open.",
            value=math.nan if s.oldest_open_s is None else s.oldest_open_s)
        yield CounterMetricFamily(
            "aoi3d_ledger_after_close", "Events for a decision that had already ended (a late "
            "render of a decision counted lost, a repeated message).", value=s.after_close)
