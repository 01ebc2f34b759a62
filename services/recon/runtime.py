"""The reconstruction worker's runtime: its liveliness token, the request loop, the bus.

It declares ``aoi3d/<run>/pool/worker/<id>`` (membership: the token lives as long as the
session), then asks the dispatcher service for work — a query on ``aoi3d/<run>/pool/work``
carrying a :class:`pb.WorkRequest` that reports how the previous job ended — reconstructs the
job it is given with :class:`services.recon.core.ReconCore` and publishes the Render on
``aoi3d/<run>/render``. One thread does all of it: the worker never does two jobs at once.

Free views and exports (``aoi3d/<run>/pool/view/<id>``, a :class:`pb.ViewRequest`) are
answered by a second thread from the snapshot of each site's latest model
(:meth:`ReconCore.view`), so they never hold up a job; one is done at a time and a newer
request replaces one still waiting (answered ``busy``): no queue grows.
"""

from __future__ import annotations

import logging
import os
import secrets
import socket
import threading
import time

from aoi3d.clock import SimClock
from services.kit.bus import Bus, Query
from services.kit.keys import DEFAULT_SITE, Keys, check_site
from services.kit.observe import Rejected
from services.kit.pb import aoi3d_pb2 as pb
from services.recon.core import JobFailed, ReconCore, decode_reply
from services.recon.settings import Settings

log = logging.getLogger(__name__)

_NO_DISPATCHER_BACKOFF_S = 0.2


def default_worker_id() -> str:
    host = "".join(c if c.isalnum() or c in "-_." else "-" for c in socket.gethostname())
    return f"{host[:40] or 'host'}-{os.getpid()}-{secrets.token_hex(2)}"


class ReconWorker:
    """See the module docstring. :meth:`run` blocks until ``stop`` is set."""

    def __init__(self, settings: Settings, bus: Bus, core: ReconCore) -> None:
        self.settings = settings
        self.bus = bus
        self.core = core
        self.keys = Keys(settings.common.run_id)
        self.clock = SimClock(settings.common.epoch_s, settings.common.time_scale)
        self.busy_s = 0.0
        self.failed = 0
        self.rendered = 0
        self._done: tuple[pb.Job, bool, str] | None = None
        self._view_lock = threading.Condition()
        self._view_waiting: Query | None = None
        self.views_superseded = 0

    @property
    def worker_id(self) -> str:
        return self.core.worker_id

    def _request(self, wait_s: float) -> bytes:
        req = pb.WorkRequest(worker_id=self.worker_id, busy_s=self.busy_s,
                             jobs=self.core.jobs + self.failed, max_wait_s=wait_s,
                             device=self.core.device, pid=os.getpid(),
                             host=socket.gethostname()[:64])
        if self._done is not None:
            job, rendered, reason = self._done
            req.done_decision_id = job.decision.decision_id
            req.done_incarnation = job.decision.incarnation
            req.done_rendered = rendered
            req.done_reason = reason
            req.done_site = job.site
        return req.SerializeToString()

    def step(self) -> bool:
        """One request and, if a job comes, its reconstruction; True when a job was done."""
        background = self.core.trains_in_background
        wait_s = 0.0 if background else self.settings.max_wait_s
        answer = self.bus.query(self.keys.work, self._request(wait_s),
                                timeout_s=wait_s + self.settings.query_margin_s)
        if answer is None:  # no dispatcher reachable (yet): the report is sent again next time
            if background:
                self.core.train_between_jobs(self.settings.background_steps)
            else:
                time.sleep(_NO_DISPATCHER_BACKOFF_S)
            return False
        self._done = None
        try:
            reply = decode_reply(answer)
        except Rejected as err:
            log.warning("dropped a malformed reply from the dispatcher: %s", err)
            return False
        if not reply.HasField("job"):
            if background:
                self.core.train_between_jobs(self.settings.background_steps)
            return False
        job = reply.job
        try:
            check_site(job.site or DEFAULT_SITE)
        except ValueError as err:  # a site name that cannot be a key chunk: not published
            log.warning("job for decision %d refused: %s", job.decision.decision_id, err)
            self._done = (job, False, "bad_site")
            self.failed += 1
            return True
        t0 = time.monotonic()
        try:
            outcome = self.core.run(job, now_ms=self.clock.now_ms)
            outcome.render.compute_s = time.monotonic() - t0  # (its ready_ms: the core's)
            self.bus.publish(Keys(self.keys.run_id, job.site or DEFAULT_SITE).render,
                             outcome.render.SerializeToString())
            self._done = (job, True, "")
            self.rendered += 1
            self.core.keep_latest(job)  # after the publication: never delays the render
        except JobFailed as err:
            log.warning("job for decision %d failed: %s", job.decision.decision_id, err)
            self._done = (job, False, err.reason)
            self.failed += 1
        except Exception as err:  # keep serving: the pool counts the decision lost
            log.exception("job for decision %d failed", job.decision.decision_id)
            self._done = (job, False, type(err).__name__[:32])
            self.failed += 1
        finally:
            self.busy_s += time.monotonic() - t0
        return True

    # ------------------------------------------------------------------ free views
    def _on_view(self, query: Query) -> None:
        """Keep the newest view request (an older one still waiting is answered busy)."""
        with self._view_lock:
            older, self._view_waiting = self._view_waiting, query
            self._view_lock.notify()
        if older is not None:
            self.views_superseded += 1
            older.reply(pb.ViewReply(error="a newer view request replaced this one",
                                     reason="busy", worker_id=self.worker_id
                                     ).SerializeToString())

    def _serve_views(self, stop: threading.Event) -> None:
        while not stop.is_set():
            with self._view_lock:
                if self._view_waiting is None:
                    self._view_lock.wait(0.2)
                query, self._view_waiting = self._view_waiting, None
            if query is None:
                continue
            try:
                req = pb.ViewRequest.FromString(query.payload)
            except Exception as err:
                query.reply(pb.ViewReply(error=f"not a ViewRequest ({type(err).__name__})",
                                         reason="malformed").SerializeToString())
                continue
            try:
                reply = self.core.view(req)
            except Exception as err:  # keep serving
                log.exception("view request failed")
                reply = pb.ViewReply(error=type(err).__name__, reason="failed",
                                     worker_id=self.worker_id)
            query.reply(reply.SerializeToString())

    def run(self, stop: threading.Event) -> None:
        self.bus.declare_queryable(self.keys.pool_view(self.worker_id), self._on_view)
        views = threading.Thread(target=self._serve_views, args=(stop,), name="views",
                                 daemon=True)
        views.start()
        token = self.bus.declare_token(self.keys.pool_worker(self.worker_id))
        log.info("worker %s joined the pool of run %s", self.worker_id,
                 self.settings.common.run_id)
        try:
            while not stop.is_set():
                self.step()
        finally:
            token.undeclare()
            log.info("worker %s left the pool (%d rendered, %d failed)", self.worker_id,
                     self.rendered, self.failed)
