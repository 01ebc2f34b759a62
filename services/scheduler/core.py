"""The scheduler's core: delivered frames and a time in, Decisions out.

No bus, no threads, no metrics library: the runtime (:mod:`services.scheduler.runtime`) feeds
it under its lock and publishes what it returns; tests drive it directly.

A delivered frame counts for a decision at s iff it was delivered at or before s
(``delivery_ms <= s``): frames are queued by delivery time and applied to an
:class:`aoi3d.aoi.AoITracker` only when the decision step asks for U(s). The decision step is
the one every setting shares, :func:`aoi3d.policy.decide`.
"""

from __future__ import annotations

import heapq
import itertools
import math
import secrets
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from aoi3d.aoi import AoITracker
from aoi3d.policy import LagEstimator, Policy, decide
from services.kit.codec import FrameData, decode_frame
from services.kit.pb import aoi3d_pb2 as pb
from services.kit.rejected import Rejected, RejectReason

__all__ = ["MAX_AHEAD_MS", "MAX_DELIVERED", "AoISnapshot", "NewestFrame", "SchedulerCore"]

MAX_AHEAD_MS = 60_000.0
"""A frame stamped as delivered further than this in the (sim) future is rejected: the
sender's clock (epoch/time scale) disagrees with ours."""

MAX_DELIVERED = 100_000
"""Deliveries kept for the next decision's ``policy.observe`` (the newest, past this)."""

LearnerAct = Callable[[int, np.ndarray, float], np.ndarray]
"""``(decision_id, aoi_ms, time_ms) -> mask``: an online learner acting in the policy's place."""


@dataclass(frozen=True)
class NewestFrame:
    """The newest delivered frame of one camera (what a selection refers to)."""

    sequence: int
    generation_ms: float


@dataclass(frozen=True)
class AoISnapshot:
    """The AoI vector at one time; NaN where no frame of the camera was delivered yet."""

    time_ms: float
    camera_ids: tuple[int, ...]
    aoi_ms: np.ndarray
    newest_ms: np.ndarray


class SchedulerCore:
    """One site's AoI state and decisions. Not thread-safe: the runtime serialises calls.

    ``incarnation``: this process's random id on every Decision (a restarted scheduler gets
    a new one, so the dispatcher follows it at once although it numbers from 1 again)."""

    def __init__(self, n_cameras: int, incarnation: int | None = None, *,
                 step_ms_prior: float = 0.34) -> None:
        if n_cameras < 1:
            raise ValueError(f"n_cameras must be >= 1, got {n_cameras}")
        self.camera_ids: tuple[int, ...] = tuple(range(1, n_cameras + 1))
        self._accepted = frozenset(self.camera_ids)
        self.incarnation = incarnation if incarnation is not None else secrets.randbits(63) | 1
        self._tracker = AoITracker(list(self.camera_ids))
        self.newest: dict[int, NewestFrame] = {}
        # frames received but not yet delivered in sim time: (delivery_ms, tie, cam, seq, gen)
        self._pending: list[tuple[float, int, int, int, float]] = []
        self._tie = itertools.count()
        self.decision_id = 0
        self.last_decision: pb.Decision | None = None
        # frames applied since the last decision, (camera index, gen, delivery): what the
        # decision step tells the policy (policy.observe)
        self._delivered: list[tuple[int, float, float]] = []
        # the lag from a decision to its display, learned from the scored renders
        self.lag = LagEstimator(step_ms_prior)

    def ingest(self, payload: bytes, now_ms: float) -> FrameData:
        """Validate a delivered frame and queue it until its delivery time (a frame without a
        delivery stamp counts as delivered now); :class:`Rejected` when it cannot count."""
        frame = decode_frame(payload, self._accepted)
        delivery_ms = frame.delivery_ms if frame.delivery_ms > 0 else now_ms
        if frame.generation_ms > delivery_ms:
            raise Rejected(RejectReason.BAD_TIME,
                           f"frame generated at {frame.generation_ms:g} ms but "
                           f"delivered at {delivery_ms:g} ms")
        if delivery_ms > now_ms + MAX_AHEAD_MS:
            raise Rejected(RejectReason.FUTURE_DELIVERY,
                           f"delivery at {delivery_ms:g} ms is more than {MAX_AHEAD_MS:g} ms "
                           f"ahead of this clock ({now_ms:g} ms): epoch/time scale differ?")
        heapq.heappush(self._pending, (delivery_ms, next(self._tie), frame.camera_id,
                                       frame.sequence, frame.generation_ms))
        return frame

    def apply_pending(self, upto_ms: float) -> None:
        """Deliver every queued frame whose delivery time is ≤ ``upto_ms`` to the tracker."""
        while self._pending and self._pending[0][0] <= upto_ms:
            delivery_ms, _, cam, seq, gen_ms = heapq.heappop(self._pending)
            self._delivered.append((cam - 1, gen_ms, delivery_ms))
            if len(self._delivered) > MAX_DELIVERED:  # no decision for long: keep the newest
                del self._delivered[: len(self._delivered) - MAX_DELIVERED]
            if self._tracker.deliver(cam, gen_ms):  # it is the camera's newest frame
                self.newest[cam] = NewestFrame(sequence=seq, generation_ms=gen_ms)

    def newest_at(self, s_ms: float) -> np.ndarray:
        """U(s) from the frames delivered by ``s_ms`` (the decision step's ``newest_at``)."""
        self.apply_pending(s_ms)
        return np.asarray(self._tracker.newest_ms, dtype=np.float64).copy()

    def deliveries(self, s_ms: float) -> list[tuple[int, float, float]]:
        """The frames delivered since the previous call, up to ``s_ms`` (the decision step's
        ``deliveries``): ``(camera index, generation ms, delivery ms)``."""
        self.apply_pending(s_ms)
        out, self._delivered = self._delivered, []
        return out

    def aoi(self, time_ms: float) -> AoISnapshot:
        """The AoI vector at ``time_ms`` from the frames applied so far."""
        return AoISnapshot(time_ms=time_ms, camera_ids=self.camera_ids,
                           aoi_ms=np.asarray(self._tracker.aoi_ms(time_ms),
                                             dtype=np.float64).copy(),
                           newest_ms=np.asarray(self._tracker.newest_ms,
                                                dtype=np.float64).copy())

    def decide(self, t_ms: float, policy: Policy, act: LearnerAct | None = None) -> pb.Decision:
        """The decision step of epoch ``t_ms``: the Decision, stamped with the time the
        selection is for (t, or t + ω for a waiting policy), with the next decision id."""
        decision_id = self.decision_id + 1
        bound = None if act is None else (lambda aoi, s: act(decision_id, aoi, s))
        sel = decide(policy, t_ms, self.newest_at, act=bound, deliveries=self.deliveries,
                     lag=self.lag.estimate())
        selected = [
            pb.FrameRef(camera_id=cam, sequence=self.newest[cam].sequence,
                        generation_ms=self.newest[cam].generation_ms,
                        aoi_ms=float(sel.aoi_ms[i]))
            for i, cam in zip(sel.indices, sel.cameras(self.camera_ids), strict=True)
        ]
        self.decision_id = decision_id
        msg = pb.Decision(decision_id=decision_id, incarnation=self.incarnation,
                          time_ms=sel.eval_ms, camera_ids=list(self.camera_ids),
                          aoi_ms=[float(a) for a in sel.aoi_ms], selected=selected,
                          policy=sel.policy)
        if policy.gamma_ms is not None and math.isfinite(policy.gamma_ms):
            msg.gamma_ms = float(policy.gamma_ms)
        if sel.budget_steps is not None:
            msg.budget_steps = sel.budget_steps
        if math.isfinite(sel.lag_ms):
            msg.expected_lag_ms = sel.lag_ms
        self.last_decision = msg
        return msg

    def observe_render(self, quality: pb.Quality) -> bool:
        """A scored render of this scheduler's: its steps and its lag (ready − decision time)
        teach the lag model; False when it carries neither (an older metrics service)."""
        if not (quality.HasField("render_steps") and quality.HasField("ready_ms")):
            return False
        return self.lag.observe(quality.render_steps, quality.ready_ms - quality.time_ms)

    @property
    def cameras_known(self) -> int:
        """Cameras that delivered a frame so far."""
        return len(self.newest)
