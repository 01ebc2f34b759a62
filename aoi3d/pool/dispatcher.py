"""Who reconstructs which decision: the pool's dispatcher, as pure logic (no bus, no threads).

The dispatcher service runs one :class:`Dispatcher`; reconstruction workers (``python -m
services.recon``) pull work from it. The virtual clock's twin of the pool
(:mod:`aoi3d.experiment.episode.pool`) runs the same one, with simulated workers. Design
(docs/architecture.md, "The worker pool"):

- **Membership** is Zenoh liveliness: each worker holds a token
  ``aoi3d/<run>/pool/worker/<id>`` for as long as its session lives; the runtime calls
  :meth:`Dispatcher.joined` / :meth:`Dispatcher.left` as tokens appear and vanish. No list is
  kept by hand and no port is configured.
- **Pull**: an idle worker asks (a Zenoh query, :meth:`Dispatcher.request`). The dispatcher
  keeps at most one *pending* decision per site, the site's newest; a newer one replaces it
  (the older is counted ``superseded``: skipped by choice). A pending decision goes to exactly
  one asker, under the caller's lock — of the sites with one pending, the site served longest
  ago (round robin, so no site starves another); a worker that finds nothing pending waits
  (its query is held, up to its ``max_wait_s``), and the next decision of any site goes to
  the worker that has waited longest (:meth:`Dispatcher.offer`) — or, with ``prefer_warm``
  (the ``stream`` carry), to the waiting worker whose last decision of that site is the
  newest, so that a pool with slack keeps warm-starting from one decision ago. No queue
  grows and no render is older than one that could have been done instead.
- **Fresh wait** (``fresh_fraction`` < 1): a worker that asks when its site's pending
  decision has waited longer than that fraction of the site's decision period (learned from
  the offers), and less than :data:`OVERDUE` periods, waits for the next decision instead;
  the stale one is superseded by it. Decisions come every period, so the wait is at most the
  rest of one, and the render shows a decision a fraction of a period old instead of up to a
  whole one (waiting can beat zero-wait for the age of what is shown: Sun et al., "Update or
  Wait", IEEE/ACM ToN 2017). A worker that cannot wait (``max_wait_s`` 0) takes it.
- **Ledger**: a handed-out decision ends ``rendered`` (the worker reports its Render
  published in its next request) or ``lost`` with a reason: ``worker_died`` (its token
  vanished while it held the decision: a crash, a SIGKILL, a network cut), ``timeout`` (held
  longer than ``job_timeout_s``), ``not_delivered`` (the worker asked again without reporting
  it: the reply never reached it) or ``render_failed`` (the worker could not render it; its
  own why is the detail). The reasons are :class:`aoi3d.pool.model.PoolReason` (the wire's
  ``EndReason``). A decision
  is never handed out twice, so nothing is rendered twice; a worker that comes back after its
  decision was counted lost has its late report ignored (``late_reports``).
"""

from __future__ import annotations

import math
from collections import Counter, deque
from dataclasses import dataclass, field

from aoi3d.pool.model import (
    Assignment,
    DecisionRef,
    Ended,
    PoolReason,
    PoolStatus,
    Report,
    WorkerView,
)
from aoi3d.sites import DEFAULT_SITE

__all__ = ["POOL_LOST", "Dispatcher"]

POOL_LOST = (PoolReason.WORKER_DIED, PoolReason.TIMEOUT, PoolReason.NOT_DELIVERED,
             PoolReason.RENDER_FAILED)
"""Why the pool itself loses a decision it handed out (``Dispatcher.lost``, the
``aoi3d_pool_decisions_lost{reason}`` series); the dispatcher tells ``refused`` and
``not_received`` too, for decisions that never reached the pool."""


OVERDUE = 1.5
"""A pending decision older than this many decision periods is taken at once: the next one is
late (a paused camera, a stalled scheduler), so waiting for it could wait for nothing."""
PERIOD_GAIN = 0.1
"""The smoothing of the decision period's estimate (an exponential moving average)."""


@dataclass
class _Member:
    """A member of the pool as the dispatcher sees it: one reconstruction worker (a
    ``python -m services.recon`` process, named by its liveliness token)."""

    worker_id: str
    joined_s: float
    pid: int = 0
    host: str = ""
    device: str = ""
    rendered: int = 0
    lost: int = 0
    holding: Assignment | None = None
    busy: deque[tuple[float, float]] = field(default_factory=deque)
    """(wall s, reported busy s) samples over the window."""
    last_ms: dict[str, float] = field(default_factory=dict)
    """The time of the last decision handed to it, by site (how recent its model is)."""


class Dispatcher:
    """The pool's assignment state; see the module docstring. Not thread-safe: the caller
    serialises calls (the dispatcher's runtime holds one lock). Times are wall seconds."""

    def __init__(self, *, window_s: float = 30.0, job_timeout_s: float = 120.0,
                 fresh_fraction: float = 1.0) -> None:
        if not 0.0 <= fresh_fraction <= 1.0:
            raise ValueError(f"fresh_fraction must be in [0, 1], got {fresh_fraction!r}")
        self.window_s = float(window_s)
        self.job_timeout_s = float(job_timeout_s)
        self.fresh_fraction = float(fresh_fraction)
        """Wait for the next decision: a worker that asks when its site's pending decision has
        waited longer than this fraction of the site's decision period (and less than
        :data:`OVERDUE` periods: the next one is due) waits for the next decision instead, and
        the stale one is superseded by it. 1: never (take the pending one at once)."""
        self._period_s: dict[str, float] = {}
        """Each site's decision period (wall s): the smoothed interval between its offers."""
        self._offered_s: dict[str, float] = {}
        self.waited_fresh = 0
        """Requests that waited for the next decision rather than take a stale pending one."""
        self._workers: dict[str, _Member] = {}
        self._waiting: deque[str] = deque()
        self.prefer_warm = False
        """Give a new decision to the waiting worker whose last decision of the site is the
        newest (its model the warmest: the ``stream`` carry starts from it) instead of the one
        that waited longest (ties: the longest waiting)."""
        self._pending: dict[str, tuple[DecisionRef, float]] = {}
        self._served_s: dict[str, float] = {}
        """When each site last had a decision handed out (round robin between sites)."""
        self.by_site: dict[str, Counter[str]] = {}
        self.decisions = 0
        self.assigned = 0
        self.rendered = 0
        self.superseded = 0
        self.lost: Counter[str] = Counter()  # PoolReason keys (a str)
        """Handed-out decisions lost, by reason (:data:`POOL_LOST`)."""
        self.late_reports = 0
        self.wait_sum_s = 0.0
        self.age_sum_s = 0.0
        self._events: deque[tuple[float, str, float]] = deque()
        """(wall s, kind, value) over the window: kind decision | render | wait | age."""
        self._first_s: float | None = None
        self._ended: deque[Ended] = deque(maxlen=100_000)
        """Bounded: should nobody drain it, the ledger counts what falls out ``expired``."""

    def drain_ended(self) -> list[Ended]:
        """The decisions that ended without a render since the last call (oldest first)."""
        ended = list(self._ended)
        self._ended.clear()
        return ended

    # ------------------------------------------------------------------ membership
    def joined(self, worker_id: str, now_s: float) -> None:
        if worker_id not in self._workers:
            self._workers[worker_id] = _Member(worker_id, joined_s=now_s)

    def left(self, worker_id: str, now_s: float) -> Assignment | None:
        """The worker's token vanished: its decision (if any) is lost, ``worker_died``."""
        worker = self._workers.pop(worker_id, None)
        self._unwait(worker_id)
        if worker is None or worker.holding is None:
            return None
        held = worker.holding
        self._lose(held.decision, PoolReason.WORKER_DIED)
        return held

    @property
    def worker_ids(self) -> list[str]:
        return sorted(self._workers)

    def pending(self, site: str = DEFAULT_SITE) -> DecisionRef | None:
        """The site's decision waiting for a worker (its newest not handed out), if any."""
        entry = self._pending.get(site)
        return None if entry is None else entry[0]

    def held(self) -> list[Assignment]:
        """The decisions being reconstructed now, one per busy worker."""
        return [w.holding for w in self._workers.values() if w.holding is not None]

    # ------------------------------------------------------------------ decisions
    def offer(self, decision: DecisionRef, now_s: float) -> Assignment | None:
        """A new decision (newer than every one before: the caller checks). Handed at once to
        the worker that has waited longest, else pending (replacing, and counting
        ``superseded``, an older pending one)."""
        self.decisions += 1
        self._count(decision.site, "decisions")
        self._event(now_s, "decision", 1.0)
        self._learn_period(decision.site, now_s)
        if decision.site in self._pending:  # handed out or pending, this one replaces it
            self._supersede(decision.site)
        if self.prefer_warm:
            free = [w for i in self._waiting
                    if (w := self._workers.get(i)) is not None and w.holding is None]
            if free:
                warm = max(free, key=lambda w: w.last_ms.get(decision.site, -math.inf))
                self._unwait(warm.worker_id)
                return self._assign(warm, decision, now_s, now_s)
            self._waiting.clear()
        while self._waiting:
            worker = self._workers.get(self._waiting.popleft())
            if worker is not None and worker.holding is None:
                return self._assign(worker, decision, now_s, now_s)
        self._pending[decision.site] = (decision, now_s)
        return None

    def request(self, report: Report, now_s: float) -> Assignment | None:
        """A worker asks for work (after reporting how its last job ended). Returns its
        assignment, or None: then it waits (if its ``max_wait_s`` > 0) for :meth:`offer`."""
        worker = self._workers.get(report.worker_id)
        if worker is None:  # its query came before its token: it is alive, count it in
            self.joined(report.worker_id, now_s)
            worker = self._workers[report.worker_id]
        worker.pid, worker.host, worker.device = report.pid, report.host, report.device
        worker.busy.append((now_s, report.busy_s))
        while len(worker.busy) > 2 and now_s - worker.busy[1][0] >= self.window_s:
            worker.busy.popleft()
        self._close(worker, report, now_s)
        self._unwait(worker.worker_id)
        sites = list(self._pending)
        if report.max_wait_s > 0:  # a worker that can wait leaves a stale one for the next
            sites = [s for s in sites if not self._stale(s, now_s)]
            self.waited_fresh += not sites and bool(self._pending)
        if sites:
            site = min(sites, key=lambda s: (self._served_s.get(s, -math.inf),
                                             self._pending[s][1]))
            decision, arrived_s = self._pending.pop(site)
            return self._assign(worker, decision, arrived_s, now_s)
        if report.max_wait_s > 0:
            self._waiting.append(worker.worker_id)
        return None

    def refuse(self, decision: DecisionRef, why: str) -> None:
        """The dispatcher did not take ``decision`` (stale, or ahead of its clock): it never
        reaches the pool, but its end is told (lost, ``refused``)."""
        self._ended.append(Ended(decision, "lost", PoolReason.REFUSED, why))

    def never_received(self, decision: DecisionRef) -> None:
        """The dispatcher never received ``decision`` (a gap in its incarnation's ids): its end
        is told (lost, ``not_received``)."""
        self._ended.append(Ended(decision, "lost", PoolReason.NOT_RECEIVED))

    def give_up(self, worker_id: str) -> None:
        """The worker's held query was answered with no job (its wait ran out)."""
        self._unwait(worker_id)

    def expire(self, now_s: float) -> list[Assignment]:
        """Decisions held longer than ``job_timeout_s``: lost (``timeout``)."""
        out = []
        for worker in self._workers.values():
            held = worker.holding
            if held is not None and now_s - held.assigned_s > self.job_timeout_s:
                worker.holding = None
                worker.lost += 1
                self._lose(held.decision, PoolReason.TIMEOUT)
                out.append(held)
        return out

    # ------------------------------------------------------------------ internals
    def _learn_period(self, site: str, now_s: float) -> None:
        last = self._offered_s.get(site)
        self._offered_s[site] = now_s
        if last is None or now_s <= last:
            return
        gap = now_s - last
        period = self._period_s.get(site)
        self._period_s[site] = gap if period is None else period + PERIOD_GAIN * (gap - period)

    def _stale(self, site: str, now_s: float) -> bool:
        """Whether the site's pending decision is better left for the next one (see
        ``fresh_fraction``): older than that fraction of the period, the next one due."""
        period = self._period_s.get(site)
        if self.fresh_fraction >= 1.0 or period is None or site not in self._pending:
            return False
        age = now_s - self._pending[site][1]
        return self.fresh_fraction * period < age < OVERDUE * period

    def _supersede(self, site: str) -> None:
        self.superseded += 1
        self._count(site, "superseded")
        self._ended.append(Ended(self._pending.pop(site)[0], "skipped", PoolReason.SUPERSEDED))

    def _assign(self, worker: _Member, decision: DecisionRef, arrived_s: float,
                now_s: float) -> Assignment:
        held = Assignment(decision, worker.worker_id, arrived_s, now_s)
        worker.holding = held
        worker.last_ms[decision.site] = decision.time_ms
        self.assigned += 1
        self._served_s[decision.site] = now_s
        self._count(decision.site, "assigned")
        self.wait_sum_s += held.wait_s
        self._event(now_s, "wait", held.wait_s)
        return held

    def _close(self, worker: _Member, report: Report, now_s: float) -> None:
        held = worker.holding
        if report.done is not None and (held is None or held.decision.key != report.done):
            self.late_reports += 1  # counted lost already (timeout), or not ours
        if held is None:
            return
        worker.holding = None
        site = held.decision.site
        if report.done != held.decision.key:
            worker.lost += 1
            self._lose(held.decision, PoolReason.NOT_DELIVERED)
            return
        if report.rendered:
            worker.rendered += 1
            self.rendered += 1
            self._count(site, "rendered")
            age = now_s - held.arrived_s
            self.age_sum_s += age
            self._event(now_s, "render", 1.0)
            self._event(now_s, "age", age)
        else:
            worker.lost += 1
            self._lose(held.decision, PoolReason.RENDER_FAILED, report.reason or "unknown")

    def _lose(self, decision: DecisionRef, reason: PoolReason, detail: str = "") -> None:
        """Count a handed-out decision lost for ``reason`` (one of :data:`POOL_LOST`)."""
        self.lost[reason] += 1
        self._count(decision.site, "lost")
        self._ended.append(Ended(decision, "lost", reason, detail))

    def _count(self, site: str, what: str) -> None:
        self.by_site.setdefault(site, Counter())[what] += 1

    def _unwait(self, worker_id: str) -> None:
        if worker_id in self._waiting:
            self._waiting = deque(w for w in self._waiting if w != worker_id)

    def _event(self, now_s: float, kind: str, value: float) -> None:
        if self._first_s is None:
            self._first_s = now_s
        self._events.append((now_s, kind, value))
        while self._events and now_s - self._events[0][0] > self.window_s:
            self._events.popleft()

    # ------------------------------------------------------------------ status
    def status(self, now_s: float) -> PoolStatus:
        while self._events and now_s - self._events[0][0] > self.window_s:
            self._events.popleft()
        by_kind: dict[str, list[float]] = {"decision": [], "render": [], "wait": [], "age": []}
        for _, kind, value in self._events:
            by_kind[kind].append(value)
        n_dec, n_ren = len(by_kind["decision"]), len(by_kind["render"])
        # rates over the window, or over the time since the first event when that is shorter
        span = self.window_s if self._first_s is None else min(
            self.window_s, max(1e-9, now_s - self._first_s))

        def mean(xs: list[float]) -> float:
            return sum(xs) / len(xs) if xs else math.nan

        workers = []
        for w in sorted(self._workers.values(), key=lambda w: w.worker_id):
            if len(w.busy) >= 2 and w.busy[-1][0] > w.busy[0][0]:
                (t0, b0), (t1, b1) = w.busy[0], w.busy[-1]
                busy = min(1.0, max(0.0, (b1 - b0) / (t1 - t0)))
            else:
                busy = math.nan
            workers.append(WorkerView(
                worker_id=w.worker_id, pid=w.pid, host=w.host, device=w.device,
                joined_s=w.joined_s, rendered=w.rendered, lost=w.lost,
                holding=None if w.holding is None else w.holding.decision.decision_id,
                holding_site=None if w.holding is None else w.holding.decision.site,
                busy_fraction=busy))
        return PoolStatus(
            workers=tuple(workers), decisions=self.decisions, assigned=self.assigned,
            rendered=self.rendered, superseded=self.superseded, lost=dict(self.lost),
            pending={site: d.decision_id for site, (d, _) in sorted(self._pending.items())},
            in_flight=sum(w.holding is not None for w in self._workers.values()),
            renders_per_s=n_ren / span, decisions_per_s=n_dec / span,
            rendered_fraction=n_ren / n_dec if n_dec else math.nan,
            wait_s_mean=mean(by_kind["wait"]), render_age_s_mean=mean(by_kind["age"]),
            late_reports=self.late_reports, window_s=self.window_s,
            by_site={site: dict(c) for site, c in sorted(self.by_site.items())},
            fresh_fraction=self.fresh_fraction, waited_fresh=self.waited_fresh)
