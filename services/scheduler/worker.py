"""The scheduler worker: AoI tracking of delivered frames and the periodic decision.

Bus handlers only enqueue. The decision thread applies delivered frames to an
:class:`aoi3d.aoi.AoITracker` in order of their delivery time and, at every decision epoch
t = k·period (sim ms), takes the decision step every setting shares,
:func:`aoi3d.policy.decide.decide`, with the tracker as U(s), and publishes a ``Decision``.
A frame counts for a decision at s iff it was delivered at or before s (``delivery_ms <=
s``), so a frame that reaches this process a little early (clock jitter between processes) is
held back until its delivery time; a frame without a delivery stamp counts as delivered when
it is received.

A policy that waits (``wait:<ω>``) decides the epoch t at s = t + ω: the thread waits until
s, the AoI vector is the one at s, and the Decision is stamped ``time_ms = s`` — the time its
render is scored against, exactly as in the experiments (:func:`aoi3d.experiment.plan_episode`).

The scheduler asks the policy, never its kind: whether it fits N cameras
(:func:`aoi3d.policy.check_fits`), where its model goes (:func:`aoi3d.policy.place_on`),
whether it learns (:func:`aoi3d.policy.learns`). A policy that learns (``ppo`` with
``learn: true``) gets an :class:`aoi3d.rl.online.OnlineLearner`: the decision step then takes
the learner's sampled action, the worker subscribes ``Keys.quality`` (handler: enqueue only),
and a second thread, the learning thread, decodes the ``Quality`` messages and hands their
rewards, expiry and updates to the learner. What the learner does reaches Prometheus through
its hook (:class:`services.scheduler.metrics.LearnerMetrics`). Replacing the policy or
stopping the worker closes the learner (which writes its online checkpoint).
"""

from __future__ import annotations

import functools
import heapq
import itertools
import logging
import math
import secrets
import threading
from dataclasses import dataclass

import numpy as np
from prometheus_client import CollectorRegistry, Counter, Gauge, Info, Summary

from aoi3d.aoi import AoITracker
from aoi3d.clock import SimClock
from aoi3d.device import check_device
from aoi3d.policy import (
    Policy,
    PolicySpecError,
    check_fits,
    decide,
    learns,
    place_on,
    wait_ms_of,
)
from aoi3d.rl.online import LearnConfig, OnlineLearner
from services.kit.bus import Bus, Inbox
from services.kit.codec import decode_frame, decode_quality
from services.kit.keys import DEFAULT_SITE, Keys
from services.kit.observe import Heartbeat, Rejected, Rejections
from services.kit.pb import aoi3d_pb2 as pb
from services.scheduler.metrics import LearnerMetrics

log = logging.getLogger(__name__)

MAX_AHEAD_MS = 60_000.0
"""A frame stamped as delivered further than this in the (sim) future is rejected: the
sender's clock (epoch/time scale) disagrees with ours."""

_POLL_S = 0.05  # longest wait before re-checking the clock and the stop flag


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
    """Subscribes ``edge/*/frame`` (and ``quality``), publishes ``decision`` every
    ``decision_period_ms``; learns online while a ``ppo`` policy with ``learn`` is in force.

    ``learn``: batch size, reward timeout and checkpoint interval of online learning;
    ``device``: torch device of a ``ppo`` policy's agent (``cpu``, ``cuda`` or ``auto``).
    """

    def __init__(self, bus: Bus, registry: CollectorRegistry, *, run_id: str,
                 site: str = DEFAULT_SITE, n_cameras: int,
                 clock: SimClock, policy: Policy, decision_period_ms: float = 30.0,
                 inbox_size: int = 1024, learn: LearnConfig | None = None,
                 device: str = "cpu", quality_inbox_size: int = 256,
                 stall_s: float = 30.0) -> None:
        if not (math.isfinite(decision_period_ms) and decision_period_ms > 0):
            raise ValueError(f"decision_period_ms must be > 0, got {decision_period_ms}")
        if n_cameras < 1:
            raise ValueError(f"n_cameras must be >= 1, got {n_cameras}")
        check_device(device)  # fail on a bad name now, not at the first policy with a model
        check_fits(policy, n_cameras)
        self._bus = bus
        self._keys = Keys(run_id, site)
        self.site = site
        self._clock = clock
        self._period_ms = float(decision_period_ms)
        self._learn_cfg = learn or LearnConfig()
        self._device = device
        self.camera_ids: tuple[int, ...] = tuple(range(1, n_cameras + 1))
        self._accepted = frozenset(self.camera_ids)
        self._inbox = Inbox(inbox_size, on_drop=lambda: self._m_inbox_dropped.inc())
        self._quality_inbox = Inbox(quality_inbox_size, on_drop=self._on_quality_overflow)

        self._lock = threading.Lock()  # guards everything below that routes read
        self._policy: Policy = policy
        self._learner: OnlineLearner | None = None
        self._tracker = AoITracker(list(self.camera_ids))
        self._newest: dict[int, NewestFrame] = {}
        self._last_decision: pb.Decision | None = None
        # frames received but not yet delivered in sim time: (delivery_ms, tie, cam, seq, gen)
        self._pending: list[tuple[float, int, int, int, float]] = []
        self._tie = itertools.count()
        self._decision_id = 0
        # This process's decisions are (incarnation, decision_id): a restarted scheduler gets a
        # new incarnation, so the trainer takes its decisions at once (proto Decision).
        self.incarnation = secrets.randbits(63) | 1
        self._frames_beat = Heartbeat(stall_s)  # a delivered frame accepted

        self._stop = threading.Event()
        self._thread: threading.Thread | None = None
        self._learn_thread: threading.Thread | None = None
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
        self._m_selections = Counter(
            "aoi3d_camera_selections",
            "Cameras selected, summed over every decision: rate(...) / "
            "rate(aoi3d_decisions_total) is the mean selected per decision, none missed.",
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
        self._m_aoi_summary = Summary(
            "aoi3d_decision_aoi_seconds",
            "AoI of each camera at every decision (sim s): rate(_sum)/rate(_count) is its "
            "mean over a window, not a snapshot.", ["camera"], registry=registry)
        self._m_policy = Info("aoi3d_policy", "The selection policy in force (kind and spec).",
                              registry=registry)
        self._m_mat = Gauge("aoi3d_policy_mat_seconds",
                            "Γ of the MAT policy in force (sim s); NaN for other kinds.",
                            registry=registry)
        self._m_learn = LearnerMetrics(registry)
        self._install(place_on(policy, device), save_to=None)

    # ------------------------------------------------------------------ lifecycle
    def start(self) -> None:
        if self._started:
            raise RuntimeError("the scheduler worker was already started")
        self._started = True
        self._bus.subscribe(self._keys.edge_frames, self._on_frame)
        self._bus.subscribe(self._keys.quality, self._on_quality)
        self._thread = threading.Thread(target=self._run, name="scheduler-decisions",
                                        daemon=True)
        self._learn_thread = threading.Thread(target=self._learn_loop,
                                              name="scheduler-learning", daemon=True)
        self._thread.start()
        self._learn_thread.start()

    def stop(self) -> None:
        """Stop both threads, then close the learner (writing its online checkpoint)."""
        self._stop.set()
        for thread in (self._thread, self._learn_thread):
            if thread is not None:
                thread.join(timeout=5.0)
        with self._lock:
            learner, self._learner = self._learner, None
        if learner is not None:
            self._close_learner(learner)

    def readiness(self) -> tuple[bool, str]:
        if self._thread is None or not self._thread.is_alive():
            return False, "decision thread not running"
        if self._learn_thread is None or not self._learn_thread.is_alive():
            return False, "learning thread not running"
        with self._lock:
            known = len(self._newest)
            learning = self._learner is not None
        if self._frames_beat.stalled():
            return False, (f"no frame delivered for {self._frames_beat.idle_s():.0f} s "
                           f"(camera paused, network or router down?)")
        why = f"deciding; {known} of {len(self.camera_ids)} camera(s) delivered a frame"
        return True, why + ("; learning online" if learning else "")

    # ------------------------------------------------------------------ control and queries
    @property
    def decision_period_ms(self) -> float:
        return self._period_ms

    @property
    def policy(self) -> Policy:
        with self._lock:
            return self._policy

    def set_policy(self, policy: Policy, *, save_to: str | None = None) -> Policy:
        """Use ``policy`` from the next decision on; returns the policy installed (a ``ppo``
        agent moved to this scheduler's device).

        A ``ppo`` policy with ``learn`` starts online learning, writing its online checkpoint
        to ``save_to`` (default: ``<stem>.online.pt`` next to its checkpoint). The learner of
        the previous policy, if any, is closed (its checkpoint written). Raises
        ``PolicySpecError`` — with nothing changed — when the policy does not fit the rig,
        ``save_to`` is given without learning, or the online checkpoint cannot be written.
        """
        check_fits(policy, len(self.camera_ids))
        if save_to is not None and not learns(policy):
            raise PolicySpecError("save_to applies only to a ppo policy with learn: true",
                                  policy.to_json())
        policy = place_on(policy, self._device)
        old = self._install(policy, save_to=save_to)
        if old is not None:
            self._close_learner(old)
        log.info("policy set to %s%s", policy.spec, " (learning online)"
                 if learns(policy) else "")
        return policy

    @property
    def learner(self) -> OnlineLearner | None:
        """The online learner while a learning ``ppo`` policy is in force."""
        with self._lock:
            return self._learner

    def policy_and_learner(self) -> tuple[Policy, OnlineLearner | None]:
        """The policy in force and its learner (None unless learning), read together."""
        with self._lock:
            return self._policy, self._learner

    def _install(self, policy: Policy, *, save_to: str | None) -> OnlineLearner | None:
        """Make ``policy`` (and its learner) current; returns the replaced learner."""
        learner = None
        if learns(policy):
            try:
                learner = OnlineLearner.for_policy(policy, save_to=save_to,
                                                   config=self._learn_cfg, hook=self._m_learn,
                                                   wall=self._clock.wall)
            except ValueError as err:
                raise PolicySpecError(str(err), policy.to_json()) from None
        with self._lock:
            old, self._learner = self._learner, learner
            self._policy = policy
        self._m_learn.learning_changed(learner is not None)
        doc = policy.to_json()
        self._m_policy.info({"kind": str(doc.get("kind", "")), "spec": policy.spec})
        mat_ms = doc.get("mat_ms") if doc.get("kind") == "mat" else None
        self._m_mat.set(float(mat_ms) / 1000.0 if mat_ms is not None else math.nan)
        return old

    def _close_learner(self, learner: OnlineLearner) -> None:
        try:
            path = learner.close()
        except Exception:  # a failed save must not stop a policy change or a shutdown
            log.exception("could not write the online checkpoint to %s", learner.save_to)
            return
        if path is not None:
            log.info("learning stopped; online checkpoint at %s", path)

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
        """Epoch t = next_t is decided at s = t + the policy's wait (the policy in force
        when s comes; one read per pass, so the wait and the decision agree)."""
        clock = self._clock
        next_t = math.ceil(clock.now_ms() / self._period_ms) * self._period_ms
        while not self._stop.is_set():
            now = clock.now_ms()
            policy, learner = self.policy_and_learner()
            due = next_t + wait_ms_of(policy)
            if now >= due:
                behind = math.floor((now - due) / self._period_ms)
                if behind > 0:  # skip missed epochs rather than bursting decisions
                    self._m_skipped.inc(behind)
                    next_t += behind * self._period_ms
                for item in self._inbox.drain():
                    self._ingest(*item, now_ms=now)
                self._guarded(functools.partial(self._decide, policy=policy, learner=learner),
                              next_t)
                next_t += self._period_ms
                continue
            wait_s = min(max(clock.wall_s(due) - clock.wall(), 0.0), _POLL_S)
            item = self._inbox.get(timeout=wait_s)
            if item is not None:
                self._ingest(*item, now_ms=clock.now_ms())
            self._guarded(self._apply_pending, min(clock.now_ms(), due))

    def _guarded(self, fn, t_ms: float) -> None:
        try:
            fn(t_ms)
        except Exception:  # a bug must not stop the decisions
            log.exception("%s at t = %s ms failed", getattr(fn, "__name__", fn), t_ms)

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
        self._frames_beat.beat()
        heapq.heappush(self._pending, (delivery_ms, next(self._tie), frame.camera_id,
                                       frame.sequence, frame.generation_ms))

    def _apply_pending(self, upto_ms: float) -> None:
        """Deliver every queued frame whose delivery time is ≤ ``upto_ms`` to the tracker."""
        with self._lock:
            while self._pending and self._pending[0][0] <= upto_ms:
                _, _, cam, seq, gen_ms = heapq.heappop(self._pending)
                if self._tracker.deliver(cam, gen_ms):  # it is the camera's newest frame
                    self._newest[cam] = NewestFrame(sequence=seq, generation_ms=gen_ms)

    def _newest_at(self, s_ms: float) -> np.ndarray:
        """U(s) from the frames delivered by ``s_ms`` (the decision step's ``newest_at``)."""
        self._apply_pending(s_ms)
        with self._lock:
            return np.asarray(self._tracker.newest_ms, dtype=np.float64).copy()

    def _decide(self, t_ms: float, *, policy: Policy, learner: OnlineLearner | None) -> None:
        """Take the decision step of epoch ``t_ms`` and publish the Decision (stamped with
        the time the selection is for: t, or t + ω for a waiting policy)."""
        decision_id = self._decision_id + 1
        act = None if learner is None else functools.partial(learner.act, decision_id)
        sel = decide(policy, t_ms, self._newest_at, act=act)
        with self._lock:
            newest = dict(self._newest)
        selected = [
            pb.FrameRef(camera_id=cam, sequence=newest[cam].sequence,
                        generation_ms=newest[cam].generation_ms, aoi_ms=float(sel.aoi_ms[i]))
            for i, cam in zip(sel.indices, sel.cameras(self.camera_ids), strict=True)
        ]
        self._decision_id = decision_id
        msg = pb.Decision(decision_id=decision_id, incarnation=self.incarnation,
                          time_ms=sel.eval_ms,
                          camera_ids=list(self.camera_ids), aoi_ms=[float(a) for a in sel.aoi_ms],
                          selected=selected, policy=sel.policy)
        self._bus.publish(self._keys.decision, msg.SerializeToString())
        with self._lock:
            self._last_decision = msg
        self._m_decisions.inc()
        self._m_selected.set(len(selected))
        self._m_selections.inc(len(selected))
        for cam, a in zip(self.camera_ids, sel.aoi_ms, strict=True):
            if math.isfinite(a):
                self._m_aoi.labels(camera=str(cam)).set(a / 1000.0)
                self._m_aoi_summary.labels(camera=str(cam)).observe(a / 1000.0)

    # ------------------------------------------------------------------ the learning thread
    def _on_quality(self, key: str, payload: bytes) -> None:
        self._quality_inbox.put((key, payload))

    def _on_quality_overflow(self) -> None:
        learner = self.learner
        if learner is not None:
            learner.ignore("inbox_overflow")

    def _learn_loop(self) -> None:
        """Rewards in, updates and checkpoints out; idle while no learner is installed."""
        while not self._stop.is_set():
            item = self._quality_inbox.get(timeout=_POLL_S)
            learner = self.learner
            try:
                if item is not None:
                    self._on_reward(*item, learner=learner)
                if learner is not None and not learner.closed:
                    learner.expire()
                    while learner.update_if_ready() is not None:
                        pass
            except Exception:  # a bug must not stop learning for good; logged, next item
                log.exception("online learning step failed")

    def _on_reward(self, key: str, payload: bytes, *, learner: OnlineLearner | None) -> None:
        """Validate a Quality and, while learning, hand its reward to the learner."""
        try:
            msg = decode_quality(payload)
            if not math.isfinite(msg.reward):
                raise Rejected("non_finite", f"quality reward is not finite ({msg.reward})")
        except Rejected as err:
            self.rejections.reject(err, key)
            return
        if msg.decision_incarnation != self.incarnation:
            return  # scores a decision of another scheduler process (before a restart)
        if learner is not None:
            learner.reward(int(msg.decision_id), msg.time_ms, msg.reward)
