"""The scheduler worker: AoI tracking of delivered frames and the periodic frame selection.

Bus handlers only enqueue. The decision thread applies delivered frames to an
:class:`aoi3d.aoi.AoITracker` in order of their delivery time and, at every decision epoch
t = k·period (sim ms), applies the current :mod:`aoi3d.policy` policy to the AoI vector and
publishes a ``Decision``. A frame counts for the decision at t iff it was delivered at or
before t (``delivery_ms <= t``), so a frame that reaches this process a little early (clock
jitter between processes) is held back until its delivery time; a frame without a delivery
stamp counts as delivered when it is received.

Feedback seam (PPO): a learning policy will also need the published ``Quality`` messages;
subscribe ``Keys.quality`` in :meth:`SchedulerWorker.start` and hand them to the policy from
the decision thread (``_decide`` is the only place a policy is consulted).
"""

from __future__ import annotations

import heapq
import itertools
import logging
import math
import threading
from dataclasses import dataclass

import numpy as np
from prometheus_client import CollectorRegistry, Counter, Gauge

from aoi3d.aoi import AoITracker
from aoi3d.clock import SimClock
from aoi3d.policy import FreshestPolicy, Policy, PolicySpecError
from services.kit.bus import Bus, Inbox
from services.kit.codec import decode_frame
from services.kit.keys import Keys
from services.kit.observe import Rejected, Rejections
from services.kit.pb import aoi3d_pb2 as pb

log = logging.getLogger(__name__)

MAX_AHEAD_MS = 60_000.0
"""A frame stamped as delivered further than this in the (sim) future is rejected: the
sender's clock (epoch/time scale) disagrees with ours."""

_POLL_S = 0.05  # longest wait before re-checking the clock and the stop flag


def check_policy_fits(policy: Policy, n_cameras: int) -> None:
    """Raise ``PolicySpecError`` when ``policy`` asks for more cameras than the rig has."""
    if isinstance(policy, FreshestPolicy) and not 0 <= policy.k <= n_cameras:
        raise PolicySpecError(f"freshest k must be in 0..{n_cameras} (the training cameras), "
                              f"got {policy.k}", policy.to_json())


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


class SchedulerWorker:
    """Subscribes ``edge/*/frame``, publishes ``decision`` every ``decision_period_ms``."""

    def __init__(self, bus: Bus, registry: CollectorRegistry, *, run_id: str, n_cameras: int,
                 clock: SimClock, policy: Policy, decision_period_ms: float = 30.0,
                 inbox_size: int = 1024) -> None:
        if not (math.isfinite(decision_period_ms) and decision_period_ms > 0):
            raise ValueError(f"decision_period_ms must be > 0, got {decision_period_ms}")
        if n_cameras < 1:
            raise ValueError(f"n_cameras must be >= 1, got {n_cameras}")
        check_policy_fits(policy, n_cameras)
        self._bus = bus
        self._keys = Keys(run_id)
        self._clock = clock
        self._period_ms = float(decision_period_ms)
        self.camera_ids: tuple[int, ...] = tuple(range(1, n_cameras + 1))
        self._accepted = frozenset(self.camera_ids)
        self._inbox = Inbox(inbox_size, on_drop=lambda: self._m_inbox_dropped.inc())

        self._lock = threading.Lock()  # guards everything below that routes read
        self._policy = policy
        self._tracker = AoITracker(list(self.camera_ids))
        self._newest: dict[int, NewestFrame] = {}
        self._last_decision: pb.Decision | None = None
        # frames received but not yet delivered in sim time: (delivery_ms, tie, cam, seq, gen)
        self._pending: list[tuple[float, int, int, int, float]] = []
        self._tie = itertools.count()
        self._decision_id = 0

        self._stop = threading.Event()
        self._thread: threading.Thread | None = None
        self._started = False

        self.rejections = Rejections(registry)
        self._m_aoi = Gauge(
            "aoi3d_aoi_seconds",
            "AoI of each camera at the latest decision (sim s); a camera is exported only "
            "once a frame of it was delivered (unknown AoI has no series).",
            ["camera"], registry=registry)
        self._m_selected = Gauge("aoi3d_cameras_selected",
                                 "Cameras selected at the latest decision.", registry=registry)
        self._m_decisions = Counter("aoi3d_decisions", "Decisions published.",
                                    registry=registry)
        self._m_skipped = Counter(
            "aoi3d_decisions_skipped",
            "Decision epochs skipped because the decision thread fell behind the clock.",
            registry=registry)
        self._m_frames = Counter("aoi3d_frames_received", "Delivered frames received.",
                                 ["camera"], registry=registry)
        self._m_inbox_dropped = Counter(
            "aoi3d_inbox_dropped", "Frames dropped because the decision thread fell behind.",
            registry=registry)

    # ------------------------------------------------------------------ lifecycle
    def start(self) -> None:
        if self._started:
            raise RuntimeError("the scheduler worker was already started")
        self._started = True
        self._bus.subscribe(self._keys.edge_frames, self._on_frame)
        self._thread = threading.Thread(target=self._run, name="scheduler-decisions",
                                        daemon=True)
        self._thread.start()

    def stop(self) -> None:
        self._stop.set()
        if self._thread is not None:
            self._thread.join(timeout=2.0)

    def readiness(self) -> tuple[bool, str]:
        if self._thread is None or not self._thread.is_alive():
            return False, "decision thread not running"
        with self._lock:
            known = len(self._newest)
        return True, f"deciding; {known} of {len(self.camera_ids)} camera(s) delivered a frame"

    # ------------------------------------------------------------------ control and queries
    @property
    def decision_period_ms(self) -> float:
        return self._period_ms

    @property
    def policy(self) -> Policy:
        with self._lock:
            return self._policy

    def set_policy(self, policy: Policy) -> None:
        """Use ``policy`` from the next decision on."""
        with self._lock:
            self._policy = policy
        log.info("policy set to %s", policy.spec)

    def aoi(self, time_ms: float | None = None) -> AoISnapshot:
        """The AoI vector at ``time_ms`` (default: now) from the frames applied so far."""
        t = self._clock.now_ms() if time_ms is None else time_ms
        with self._lock:
            aoi = np.asarray(self._tracker.aoi_ms(t), dtype=np.float64).copy()
            newest = np.asarray(self._tracker.newest_ms, dtype=np.float64).copy()
        return AoISnapshot(time_ms=t, camera_ids=self.camera_ids, aoi_ms=aoi, newest_ms=newest)

    @property
    def last_decision(self) -> pb.Decision | None:
        with self._lock:
            return self._last_decision

    # ------------------------------------------------------------------ the decision thread
    def _on_frame(self, key: str, payload: bytes) -> None:
        self._inbox.put((key, payload))

    def _run(self) -> None:
        clock = self._clock
        next_t = math.ceil(clock.now_ms() / self._period_ms) * self._period_ms
        while not self._stop.is_set():
            now = clock.now_ms()
            if now >= next_t:
                behind = math.floor((now - next_t) / self._period_ms)
                if behind > 0:  # skip missed epochs rather than bursting decisions
                    self._m_skipped.inc(behind)
                    next_t += behind * self._period_ms
                for item in self._inbox.drain():
                    self._ingest(*item, now_ms=now)
                self._guarded(self._decide, next_t)
                next_t += self._period_ms
                continue
            wait_s = min(max(clock.wall_s(next_t) - clock.wall(), 0.0), _POLL_S)
            item = self._inbox.get(timeout=wait_s)
            if item is not None:
                self._ingest(*item, now_ms=clock.now_ms())
            self._guarded(self._apply_pending, min(clock.now_ms(), next_t))

    def _guarded(self, fn, t_ms: float) -> None:
        try:
            fn(t_ms)
        except Exception:  # a bug must not stop the decisions
            log.exception("%s at t = %s ms failed", fn.__name__, t_ms)

    def _ingest(self, key: str, payload: bytes, *, now_ms: float) -> None:
        """Validate a delivered frame and queue it until its delivery time."""
        try:
            frame = decode_frame(payload, self._accepted)
            delivery_ms = frame.delivery_ms if frame.delivery_ms > 0 else now_ms
            if frame.generation_ms > delivery_ms:
                raise Rejected("bad_time", f"frame generated at {frame.generation_ms:g} ms but "
                                           f"delivered at {delivery_ms:g} ms")
            if delivery_ms > now_ms + MAX_AHEAD_MS:
                raise Rejected("future_delivery",
                               f"delivery at {delivery_ms:g} ms is more than {MAX_AHEAD_MS:g} ms "
                               f"ahead of this clock ({now_ms:g} ms): epoch/time scale differ?")
        except Rejected as err:
            self.rejections.reject(err, key)
            return
        except Exception as err:
            log.exception("failed to decode a frame on %s", key)
            self.rejections.reject(Rejected("internal_error", repr(err)), key)
            return
        self._m_frames.labels(camera=str(frame.camera_id)).inc()
        heapq.heappush(self._pending, (delivery_ms, next(self._tie), frame.camera_id,
                                       frame.sequence, frame.generation_ms))

    def _apply_pending(self, upto_ms: float) -> None:
        """Deliver every queued frame whose delivery time is ≤ ``upto_ms`` to the tracker."""
        with self._lock:
            while self._pending and self._pending[0][0] <= upto_ms:
                _, _, cam, seq, gen_ms = heapq.heappop(self._pending)
                if self._tracker.deliver(cam, gen_ms):  # it is the camera's newest frame
                    self._newest[cam] = NewestFrame(sequence=seq, generation_ms=gen_ms)

    def _decide(self, t_ms: float) -> None:
        """Apply the policy to the AoI vector at ``t_ms`` and publish the Decision."""
        self._apply_pending(t_ms)
        with self._lock:
            policy = self._policy
            aoi = np.asarray(self._tracker.aoi_ms(t_ms), dtype=np.float64).copy()
            newest = dict(self._newest)
        chosen = np.asarray(policy.select(aoi), dtype=bool)
        if chosen.shape != aoi.shape:
            raise RuntimeError(f"policy {policy.spec} returned a selection of shape "
                               f"{chosen.shape} for {aoi.shape[0]} cameras")
        chosen &= np.isfinite(aoi)  # an unknown AoI is never selected
        selected = [
            pb.FrameRef(camera_id=cam, sequence=newest[cam].sequence,
                        generation_ms=newest[cam].generation_ms, aoi_ms=float(aoi[i]))
            for i, cam in enumerate(self.camera_ids) if chosen[i]
        ]
        self._decision_id += 1
        msg = pb.Decision(decision_id=self._decision_id, time_ms=t_ms,
                          camera_ids=list(self.camera_ids), aoi_ms=[float(a) for a in aoi],
                          selected=selected, policy=policy.spec)
        self._bus.publish(self._keys.decision, msg.SerializeToString())
        with self._lock:
            self._last_decision = msg
        self._m_decisions.inc()
        self._m_selected.set(len(selected))
        for cam, a in zip(self.camera_ids, aoi, strict=True):
            if math.isfinite(a):
                self._m_aoi.labels(camera=str(cam)).set(a / 1000.0)
