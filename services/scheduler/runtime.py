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
(``policy.check_fits``), where its model goes (``policy.on_device``),
whether it learns (``policy.learns``). A policy that learns (``ppo`` with
``learn: true``) gets an :class:`aoi3d.rl.online.OnlineLearner`: the decision step then takes
the learner's sampled action, the worker subscribes ``Keys.quality`` (handler: enqueue only),
and a second thread, the learning thread, decodes the ``Quality`` messages and hands their
rewards, expiry and updates to the learner. What the learner does reaches Prometheus through
its hook (:class:`services.scheduler.metrics.LearnerMetrics`). Replacing the policy or
stopping the worker closes the learner (which writes its online checkpoint).
"""

from __future__ import annotations

import logging
import math
import threading

from prometheus_client import CollectorRegistry

from aoi3d.clock import SimClock
from aoi3d.device import check_device
from aoi3d.policy import Policy, PolicySpecError
from aoi3d.rl.online import LearnConfig, OnlineLearner
from services.kit.bus import Bus, Inbox
from services.kit.codec import decode_quality, quality_scores
from services.kit.keys import DEFAULT_SITE, Keys
from services.kit.observe import Heartbeat, Rejected, Rejections
from services.kit.pb import aoi3d_pb2 as pb
from services.kit.rejected import RejectReason
from services.kit.runtime import Loops, guarded
from services.scheduler.core import MAX_AHEAD_MS, AoISnapshot, NewestFrame, SchedulerCore
from services.scheduler.metrics import DecisionMetrics, LearnerMetrics

log = logging.getLogger(__name__)

_POLL_S = 0.05  # longest wait before re-checking the clock and the stop flag

__all__ = ["MAX_AHEAD_MS", "AoISnapshot", "NewestFrame", "SchedulerRuntime"]


class SchedulerRuntime:
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
                 stall_s: float = 30.0, step_ms_prior: float = 0.34) -> None:
        if not (math.isfinite(decision_period_ms) and decision_period_ms > 0):
            raise ValueError(f"decision_period_ms must be > 0, got {decision_period_ms}")
        check_device(device)  # fail on a bad name now, not at the first policy with a model
        policy.check_fits(n_cameras)
        self._bus = bus
        self._keys = Keys(run_id, site)
        self.site = site
        self._clock = clock
        self._period_ms = float(decision_period_ms)
        self._learn_cfg = learn or LearnConfig()
        self._device = device
        self.core = SchedulerCore(n_cameras, step_ms_prior=step_ms_prior)
        self.camera_ids = self.core.camera_ids
        self.incarnation = self.core.incarnation
        self._inbox = Inbox(inbox_size, on_drop=lambda: self._m.inbox_dropped.inc())
        self._inbox_wake_at = max(1, inbox_size // 2)
        self._frames_due = threading.Event()  # set when the inbox is half full
        self._quality_inbox = Inbox(quality_inbox_size, on_drop=self._on_quality_overflow)

        self._lock = threading.Lock()  # guards the core and the policy that routes read
        self._policy: Policy = policy
        self._learner: OnlineLearner | None = None
        self._frames_beat = Heartbeat(stall_s)  # a delivered frame accepted

        self._loops = Loops("scheduler")
        self._loops.thread("decisions", self._run)
        self._loops.forever("learning", self._learn_step)

        self.rejections = Rejections(registry)
        self._m = DecisionMetrics(registry)
        self._m_learn = LearnerMetrics(registry)
        self._install(policy.on_device(device), save_to=None)

    # ------------------------------------------------------------------ lifecycle
    def start(self) -> None:
        self._loops.start()
        self._bus.subscribe(self._keys.edge_frames, self._on_frame)
        self._bus.subscribe(self._keys.quality, self._on_quality)

    def stop(self) -> None:
        """Stop both threads, then close the learner (writing its online checkpoint)."""
        self._loops.stop()
        with self._lock:
            learner, self._learner = self._learner, None
        if learner is not None:
            self._close_learner(learner)

    def readiness(self) -> tuple[bool, str]:
        why_not = self._loops.not_running()
        if why_not is not None:
            return False, why_not
        with self._lock:
            known = self.core.cameras_known
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
        policy.check_fits(len(self.camera_ids))
        if save_to is not None and not policy.learns:
            raise PolicySpecError("save_to applies only to a ppo policy with learn: true",
                                  policy.to_json())
        policy = policy.on_device(self._device)
        old = self._install(policy, save_to=save_to)
        if old is not None:
            self._close_learner(old)
        log.info("policy set to %s%s", policy.spec, " (learning online)"
                 if policy.learns else "")
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
        if policy.learns:
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
        self._m.policy_changed(policy)
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
            return self.core.aoi(t)

    @property
    def last_decision(self) -> pb.Decision | None:
        with self._lock:
            return self.core.last_decision

    # ------------------------------------------------------------------ the decision thread
    def _on_frame(self, key: str, payload: bytes) -> None:
        """Hand off with the arrival time (a frame without a delivery stamp is delivered
        then); the decision thread takes the frames in batches."""
        self._inbox.put((key, payload, self._clock.now_ms()))
        if len(self._inbox) >= self._inbox_wake_at:
            self._frames_due.set()

    def _run(self, stop: threading.Event) -> None:
        """Epoch t = next_t is decided at s = t + the policy's wait (the policy in force
        when s comes; one read per pass, so the wait and the decision agree). Delivered
        frames are taken in batches, at each decision and at least every ``_POLL_S`` (or when
        the inbox is half full), each with the time it arrived: not a wake-up per frame (600
        a second at the default rig), and the same AoI at every decision."""
        clock = self._clock
        next_t = math.ceil(clock.now_ms() / self._period_ms) * self._period_ms
        while not stop.is_set():
            now = clock.now_ms()
            policy, learner = self.policy_and_learner()
            due = next_t + policy.wait_ms
            if now >= due:
                behind = math.floor((now - due) / self._period_ms)
                if behind > 0:  # skip missed epochs rather than bursting decisions
                    self._m.skipped.inc(behind)
                    next_t += behind * self._period_ms
                self._ingest_all()
                guarded(f"the decision at t = {next_t} ms", self._decide, next_t,
                        policy=policy, learner=learner)
                next_t += self._period_ms
                continue
            wait_s = min(max(clock.wall_s(due) - clock.wall(), 0.0), _POLL_S)
            if self._frames_due.wait(wait_s):
                self._frames_due.clear()
            self._ingest_all()
            guarded("applying delivered frames", self._apply_pending,
                    min(clock.now_ms(), due))

    def _ingest_all(self) -> None:
        for key, payload, arrived_ms in self._inbox.drain():
            self._ingest(key, payload, now_ms=arrived_ms)

    def _ingest(self, key: str, payload: bytes, *, now_ms: float) -> None:
        """Validate a delivered frame and queue it until its delivery time."""
        try:
            with self._lock:
                frame = self.core.ingest(payload, now_ms)
        except Rejected as err:
            self.rejections.reject(err, key)
            return
        except Exception as err:
            log.exception("failed to decode a frame on %s", key)
            self.rejections.reject(Rejected(RejectReason.INTERNAL_ERROR, repr(err)), key)
            return
        self._m.frames.labels(camera=str(frame.camera_id)).inc()
        self._frames_beat.beat()

    def _apply_pending(self, upto_ms: float) -> None:
        with self._lock:
            self.core.apply_pending(upto_ms)

    def _decide(self, t_ms: float, *, policy: Policy, learner: OnlineLearner | None) -> None:
        """Take the decision step of epoch ``t_ms`` and publish the Decision (stamped with
        the time the selection is for: t, or t + ω for a waiting policy)."""
        with self._lock:
            msg = self.core.decide(t_ms, policy, None if learner is None else learner.act)
        self._bus.publish(self._keys.decision, msg.SerializeToString())
        self._m.decided(msg)

    # ------------------------------------------------------------------ the learning thread
    def _on_quality(self, key: str, payload: bytes) -> None:
        self._quality_inbox.put((key, payload))

    def _on_quality_overflow(self) -> None:
        learner = self.learner
        if learner is not None:
            learner.ignore("inbox_overflow")

    def _learn_step(self) -> None:
        """Rewards in, updates and checkpoints out; idle while no learner is installed."""
        item = self._quality_inbox.get(timeout=_POLL_S)
        learner = self.learner
        if item is not None:
            self._on_reward(*item, learner=learner)
        if learner is not None and not learner.closed:
            learner.expire()
            while learner.update_if_ready() is not None:
                pass

    def _on_reward(self, key: str, payload: bytes, *, learner: OnlineLearner | None) -> None:
        """Validate a Quality and, while learning, hand its reward to the learner."""
        try:
            msg = decode_quality(payload)
            if not msg.lpips_skipped and not math.isfinite(msg.reward):
                raise Rejected(RejectReason.NON_FINITE,
                               f"quality reward is not finite ({msg.reward})")
        except Rejected as err:
            self.rejections.reject(err, key)
            return
        if msg.decision_incarnation != self.incarnation:
            return  # scores a decision of another scheduler process (before a restart)
        with self._lock:
            self.core.observe_render(msg)  # the lag model learns the decision → display lag
            policy = self._policy
            if policy.wants_quality:  # a policy rewarded by quality (adaptive:bandit)
                policy.observe_quality(msg.time_ms, quality_scores(msg))
        if learner is not None and not msg.lpips_skipped:  # a skipped render has no reward
            learner.reward(int(msg.decision_id), msg.time_ms, msg.reward)
