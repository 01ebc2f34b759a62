"""The dispatcher service's core: decoded messages and a time in, what to send out.

No bus, no threads, no web framework, no metrics library: the runtime
(:mod:`services.dispatcher.runtime`) feeds it and sends what it returns; tests drive it directly.

It holds the delivered frames (still encoded, per camera), takes the newest decision (in
(sim time, id) order within a scheduler incarnation; a new incarnation at once), and hands
each decision to one reconstruction worker through the pool's :class:`Dispatcher` as a
:class:`pb.Job` carrying that decision's frames and the render settings in force (backend,
carry, steps, seed, model epoch, the held-out camera and the scene box). Renders published by
the workers are read back for the latest image and the status.
"""

from __future__ import annotations

import math
from collections import OrderedDict
from dataclasses import dataclass, replace

import numpy as np

from aoi3d.field.carry import CARRY_MODES, check_carry
from aoi3d.pool import Assignment, DecisionRef, Dispatcher, Report
from aoi3d.scene.camera import Camera
from services.dispatcher.frames import FrameBuffer
from services.dispatcher.state import (
    CarryError,
    DecisionInForce,
    JobTimes,
    LatestRender,
    check_backend,
)
from services.kit.codec import camera_to_pb, decode_decision, decode_frame, decode_render
from services.kit.keys import DEFAULT_SITE
from services.kit.pb import aoi3d_pb2 as pb
from services.kit.rejected import Rejected, RejectReason

__all__ = ["DispatcherCore", "RenderSettings", "decode_request"]

_ARRIVALS_KEPT = 4096
"""Recent decisions whose arrival time is kept (two minutes of decisions every 30 ms)."""
MAX_NOT_RECEIVED = 1000
"""Most ids of one gap told ``not_received`` (50 s of decisions at one per 50 ms); a hostile
id cannot make the dispatcher publish more."""


@dataclass(frozen=True)
class RenderSettings:
    """What every job carries: how the worker reconstructs and renders. The run's, one for
    every site; changes make a new value (checked; a refused change raises and changes
    nothing). ``model_epoch`` counts the resets (backend switches included)."""

    backend: str
    carry: str
    render_steps: int
    seed: int
    model_epoch: int = 0
    cold_steps: int = 100
    """stream: the budget of a cold start."""
    warm_max_gap_ms: float = 500.0
    """stream: a model whose last decision is further away (scene ms) starts cold."""

    def __post_init__(self) -> None:
        check_backend(self.backend)
        try:
            check_carry(self.carry, self.render_steps)
        except ValueError as err:
            raise CarryError(f"{err}; accepted carry modes: {', '.join(CARRY_MODES)}") from None

    def with_backend(self, name: str) -> RenderSettings:
        """Backend ``name`` from now on: a new model (the model epoch moves on)."""
        return replace(self, backend=name, model_epoch=self.model_epoch + 1)

    def with_carry(self, carry: str, render_steps: int) -> RenderSettings:
        """Another carry or budget; the models (warm, fork) are kept."""
        return replace(self, carry=carry, render_steps=int(render_steps))

    def reset(self) -> RenderSettings:
        """New models at every worker's next job (warm and fork carry one from job to job)."""
        return replace(self, model_epoch=self.model_epoch + 1)


@dataclass(frozen=True)
class HeldFrame:
    """A delivered frame as received (validated), kept to put into jobs."""

    camera_id: int
    generation_ms: float
    payload: bytes


def decode_request(payload: bytes) -> Report:
    try:
        msg = pb.WorkRequest.FromString(payload)
    except Exception as err:  # protobuf's DecodeError and friends
        raise Rejected(RejectReason.MALFORMED,
                       f"not a WorkRequest ({err.__class__.__name__})") from None
    if not msg.worker_id or len(msg.worker_id) > 128 or "/" in msg.worker_id:
        raise Rejected(RejectReason.MALFORMED,
                       "a WorkRequest needs a worker_id of 1-128 characters "
                       "without '/'")
    values = (msg.busy_s, msg.max_wait_s)
    if not all(math.isfinite(v) and v >= 0 for v in values) or msg.max_wait_s > 3600:
        raise Rejected(RejectReason.MALFORMED,
                       "busy_s and max_wait_s must be finite, >= 0 (wait <= 1 h)")
    done = ((msg.done_site or DEFAULT_SITE, int(msg.done_incarnation),
             int(msg.done_decision_id)) if msg.done_decision_id else None)
    return Report(worker_id=msg.worker_id, done=done, rendered=msg.done_rendered,
                  reason=msg.done_reason[:64], busy_s=msg.busy_s, jobs=int(msg.jobs),
                  max_wait_s=msg.max_wait_s, device=msg.device[:16], pid=int(msg.pid),
                  host=msg.host[:64])


class DispatcherCore:
    """See the module docstring. Not thread-safe: the runtime serialises calls."""

    def __init__(self, *, camera_ids: frozenset[int], size: tuple[int, int] | None,
                 skew_ms: float, heldout: Camera, aabb: np.ndarray, frames_per_camera: int,
                 dispatcher: Dispatcher,
                 site: str = DEFAULT_SITE) -> None:
        self.site = site
        self._camera_ids = camera_ids
        self._size = size
        self._skew_ms = skew_ms
        self.heldout = heldout
        self._aabb = [float(v) for v in np.asarray(aabb, dtype=np.float64).reshape(-1)]
        self._frames: FrameBuffer[HeldFrame] = FrameBuffer(frames_per_camera)
        self.pool = dispatcher
        self.decision: DecisionInForce | None = None
        self._decisions: dict[tuple[str, int, int], pb.Decision] = {}
        """Decisions pending or held by a worker, by (incarnation, id), to build their job."""
        self._highest: dict[int, int] = {}
        """incarnation → highest decision id received (the gaps: :meth:`_never_received`)."""
        self._arrived: OrderedDict[tuple[str, int, int], float] = OrderedDict()
        """Wall s each recent decision reached the dispatcher (its render's age is measured from
        it, whether or not the worker's report of the job came first)."""
        self.latest: LatestRender | None = None
        self._latest_incarnation = 0
        self.frames_received = 0
        self.frames_missing = 0
        self.decisions_applied = 0
        self.renders_seen = 0
        self.steps_total = 0
        self.loss: float | None = None
        self.n_views = 0
        self.last_render_steps = 0
        self.warm_starts = 0
        self.job_times = JobTimes()
        """Renders whose worker started from its previous model (the stream carry)."""
        self.render_lag_ms = math.nan
        self.frames_age_ms = math.nan

    # ------------------------------------------------------------------ frames, decisions
    def on_frame(self, payload: bytes, now_ms: float) -> None:
        """Keep a delivered frame; :class:`Rejected` when it is invalid or from the future."""
        frame = decode_frame(payload, self._camera_ids, self._size)
        if frame.generation_ms > now_ms + self._skew_ms:
            raise Rejected(RejectReason.CLOCK_SKEW,
                           f"frame generated at {frame.generation_ms:g} ms, "
                           f"ahead of this clock")
        self._frames.add(HeldFrame(frame.camera_id, frame.generation_ms, payload))
        self.frames_received += 1

    @property
    def frames_buffered(self) -> int:
        return len(self._frames)

    def on_decision(self, payload: bytes, now_ms: float, now_s: float) -> Assignment | None:
        """Take a decision if it supersedes the one in force (else :class:`Rejected`) and offer
        it to the pool; the assignment when a waiting worker takes it at once."""
        msg = decode_decision(payload)
        self._never_received(msg)
        try:
            self._check_order(msg, now_ms)
        except Rejected as err:
            self.pool.refuse(DecisionRef(msg.incarnation, msg.decision_id, msg.time_ms,
                                         self.site), err.reason)
            raise
        gens = []
        missing = 0
        for ref in msg.selected:
            if self._frames.find(ref.camera_id, ref.generation_ms) is None:
                missing += 1
            else:
                gens.append(float(ref.generation_ms))
        self.frames_missing += missing
        self.decisions_applied += 1
        self.decision = DecisionInForce(
            decision_id=msg.decision_id, incarnation=msg.incarnation, time_ms=msg.time_ms,
            policy=msg.policy, n_selected=len(msg.selected), n_missing=missing,
            applied_wall_s=now_s, generation_ms=tuple(gens))
        ref = DecisionRef(msg.incarnation, msg.decision_id, msg.time_ms, self.site)
        self._arrived[ref.key] = now_s
        while len(self._arrived) > _ARRIVALS_KEPT:
            self._arrived.popitem(last=False)
        self._decisions[ref.key] = msg
        assignment = self.pool.offer(ref, now_s)
        self.forget()
        return assignment

    def _never_received(self, msg: pb.Decision) -> None:
        """Ids skipped since the highest received of the incarnation (since this process
        started) never reached the dispatcher — lost in transit, a router restarting: each is told
        lost (``not_received``), up to :data:`MAX_NOT_RECEIVED` per gap (the ledger counts any
        beyond that ``expired``)."""
        high = self._highest.get(msg.incarnation)
        if high is not None and msg.decision_id > high + 1:
            for i in range(high + 1, min(msg.decision_id, high + 1 + MAX_NOT_RECEIVED)):
                self.pool.never_received(DecisionRef(msg.incarnation, i, math.nan, self.site))
        if high is None or msg.decision_id > high:
            self._highest[msg.incarnation] = msg.decision_id

    def _check_order(self, msg: pb.Decision, now_ms: float) -> None:
        """Decisions are ordered by the sim time they are for, then by id, within one
        scheduler incarnation; a decision of another incarnation (a restarted scheduler, which
        numbers from 1 again) supersedes at once. Times further ahead of this clock than the
        skew are rejected, so no message — not even one with id 2^64−1 — can hold the pool
        for longer than the skew."""
        if msg.time_ms > now_ms + self._skew_ms:
            raise Rejected(RejectReason.CLOCK_SKEW,
                           f"decision for {msg.time_ms:g} ms but this clock says "
                           f"{now_ms:g} ms")
        d = self.decision
        if d is None or msg.incarnation != d.incarnation:
            return
        if (msg.time_ms, msg.decision_id) <= (d.time_ms, d.decision_id):
            raise Rejected(RejectReason.STALE_DECISION,
                           f"decision {msg.decision_id} for {msg.time_ms:g} ms is not newer "
                           f"than decision {d.decision_id} for {d.time_ms:g} ms")

    def forget(self) -> None:
        """Keep only the decisions still pending or held (bounded by the pool's size + 1)."""
        keep = {a.decision.key for a in self.pool.held()}
        pending = self.pool.pending(self.site)
        if pending is not None:
            keep.add(pending.key)
        self._decisions = {k: v for k, v in self._decisions.items() if k in keep}

    # ------------------------------------------------------------------ workers
    def job(self, assignment: Assignment, now_s: float, r: RenderSettings) -> bytes:
        """The WorkReply carrying ``assignment``'s job (the decision's frames that are held)
        with the render settings ``r``."""
        msg = self._decisions[assignment.decision.key]
        pose, intrinsics = camera_to_pb(self.heldout)
        # the decision's own budget (a policy's "@<steps>") wins over the pool's render_steps
        steps = msg.budget_steps if msg.HasField("budget_steps") else r.render_steps
        job = pb.Job(decision=msg, backend=r.backend, carry=r.carry,
                     render_steps=steps, seed=r.seed, model_epoch=r.model_epoch,
                     cold_steps=r.cold_steps, warm_max_gap_ms=r.warm_max_gap_ms,
                     pose=pose, intrinsics=intrinsics, aabb=self._aabb,
                     assigned_unix_s=now_s, site=self.site)
        for ref in msg.selected:
            held = self._frames.find(ref.camera_id, ref.generation_ms)
            if held is None:
                job.n_missing += 1
            else:
                job.frames.add().MergeFromString(held.payload)
        reply: bytes = pb.WorkReply(job=job).SerializeToString()
        return reply

    @staticmethod
    def no_job(reason: str) -> bytes:
        reply: bytes = pb.WorkReply(reason=reason).SerializeToString()
        return reply

    # ------------------------------------------------------------------ renders
    def on_render(self, payload: bytes, now_s: float, now_ms: float) -> LatestRender:
        """A worker's Render: the latest image and the render statistics."""
        msg, _camera = decode_render(payload)
        if msg.time_ms > now_ms + self._skew_ms:
            raise Rejected(RejectReason.CLOCK_SKEW,
                           f"render for {msg.time_ms:g} ms, ahead of this clock")
        if self.latest is not None and msg.time_ms < self.latest.time_ms \
                and msg.decision_incarnation == self._latest_incarnation:
            # an older decision finished after a newer one (several workers): counted, not shown
            self._count_render(msg, now_ms)
            return self.latest
        gens = list(msg.frame_generation_ms)
        frames_age_ms = (msg.time_ms - float(np.mean(gens))) if gens else math.nan
        self._count_render(msg, now_ms)
        self.frames_age_ms = frames_age_ms
        self._latest_incarnation = msg.decision_incarnation
        key = (self.site, msg.decision_incarnation, msg.decision_id)
        arrived = self._arrived.get(key, math.nan)
        self.latest = LatestRender(
            png=msg.image.data, decision_id=msg.decision_id, time_ms=msg.time_ms,
            training_step=msg.training_step, n_views=msg.n_views, wall_s=now_s,
            carry=msg.carry, render_steps=msg.render_steps, frames_age_ms=frames_age_ms,
            lag_ms=now_ms - msg.time_ms, age_s=now_s - arrived if math.isfinite(arrived)
            else math.nan, worker_id=msg.worker_id)
        return self.latest

    def _count_render(self, msg: pb.Render, now_ms: float) -> None:
        self.renders_seen += 1
        self.warm_starts += int(msg.warm_start)
        self.job_times.add(msg.backend, msg.carry, int(msg.render_steps), int(msg.n_views),
                           float(msg.compute_s))
        self.steps_total += int(msg.render_steps)
        self.loss = float(msg.loss) if math.isfinite(msg.loss) and msg.render_steps else None
        self.n_views = int(msg.n_views)
        self.last_render_steps = int(msg.render_steps)
        self.render_lag_ms = now_ms - msg.time_ms
