"""The scheduler worker: AoI tracking of delivered frames and the periodic frame selection.

Bus handlers only enqueue. The decision thread applies delivered frames to an
:class:`aoi3d.aoi.AoITracker` in order of their delivery time and, at every decision epoch
t = k·period (sim ms), applies the current :mod:`aoi3d.policy` policy to the AoI vector and
publishes a ``Decision``. A frame counts for the decision at t iff it was delivered at or
before t (``delivery_ms <= t``), so a frame that reaches this process a little early (clock
jitter between processes) is held back until its delivery time; a frame without a delivery
stamp counts as delivered when it is received.

Online learning (PPO): a ``ppo`` policy put with ``learn: true`` gets an
:class:`~services.scheduler.learner.OnlineLearner`. The decision thread then asks the learner
for a sampled action (``_decide`` is the only place a policy is consulted) and the learner
remembers the pending decision; the worker subscribes ``Keys.quality`` (handler: enqueue
only), and a second thread, the learning thread, decodes the ``Quality`` messages, hands
their rewards to the learner, expires rewards that never came and runs the PPO updates and
checkpoints. The decision thread acts with the learner's own copy of the agent, so it never
waits for an update. Replacing the policy or stopping the worker closes the learner (which
writes its online checkpoint).
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
from services.kit.codec import decode_frame, decode_quality
from services.kit.keys import Keys
from services.kit.observe import Rejected, Rejections
from services.kit.pb import aoi3d_pb2 as pb
from services.scheduler.learner import (
    LearnConfig,
    LearnerMetrics,
    OnlineLearner,
    online_checkpoint_path,
)

log = logging.getLogger(__name__)

MAX_AHEAD_MS = 60_000.0
"""A frame stamped as delivered further than this in the (sim) future is rejected: the
sender's clock (epoch/time scale) disagrees with ours."""

_POLL_S = 0.05  # longest wait before re-checking the clock and the stop flag


def check_policy_fits(policy: Policy, n_cameras: int) -> None:
    """Raise ``PolicySpecError`` when ``policy`` does not fit a rig of ``n_cameras``: more
    cameras asked for than there are, or a PPO checkpoint trained for another N."""
    if isinstance(policy, FreshestPolicy) and not 0 <= policy.k <= n_cameras:
        raise PolicySpecError(f"freshest k must be in 0..{n_cameras} (the training cameras), "
                              f"got {policy.k}", policy.to_json())
    if policy.kind == "ppo":
        from aoi3d.rl.policy import PPOPolicy  # loaded already: the registry built ``policy``

        assert isinstance(policy, PPOPolicy)
        if policy.n_cameras != n_cameras:
            raise PolicySpecError(
                f"PPO checkpoint {policy.checkpoint} was trained for {policy.n_cameras} "
                f"cameras, but this scheduler has N = {n_cameras}", policy.to_json())


def is_learning(policy: Policy) -> bool:
    """Whether ``policy`` asks the scheduler to learn online (a ``ppo`` policy, learn on)."""
    return policy.kind == "ppo" and bool(getattr(policy, "learn", False))


def resolve_device(device: str) -> str:
    """``auto`` → ``cuda`` when available, else ``cpu``; ``cpu``/``cuda`` as they are."""
    if device not in ("auto", "cpu", "cuda"):
        raise ValueError(f"device must be auto, cpu or cuda, got {device!r}")
    if device != "auto":
        return device
    import torch

    return "cuda" if torch.cuda.is_available() else "cpu"


def place_policy(policy: Policy, device: str) -> Policy:
    """``policy`` with a ``ppo`` agent on ``device`` (loaded again from its checkpoint when
    the registry loaded it elsewhere); other policies pass through."""
    if policy.kind != "ppo":
        return policy
    from aoi3d.rl.policy import PPOPolicy

    assert isinstance(policy, PPOPolicy)
    dev = resolve_device(device)
    if policy.agent.device.type == dev:
        return policy
    import torch

    if dev == "cuda" and not torch.cuda.is_available():
        raise PolicySpecError("the scheduler's device is cuda (AOI3D_SCHEDULER_DEVICE), but "
                              "CUDA is not available here", policy.to_json())
    return PPOPolicy.from_checkpoint(policy.checkpoint, learn=policy.learn, device=dev)


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

    def __init__(self, bus: Bus, registry: CollectorRegistry, *, run_id: str, n_cameras: int,
                 clock: SimClock, policy: Policy, decision_period_ms: float = 30.0,
                 inbox_size: int = 1024, learn: LearnConfig | None = None,
                 device: str = "cpu", quality_inbox_size: int = 256) -> None:
        if not (math.isfinite(decision_period_ms) and decision_period_ms > 0):
            raise ValueError(f"decision_period_ms must be > 0, got {decision_period_ms}")
        if n_cameras < 1:
            raise ValueError(f"n_cameras must be >= 1, got {n_cameras}")
        resolve_device(device)  # fail on a bad name now, not at the first ppo policy
        check_policy_fits(policy, n_cameras)
        self._bus = bus
        self._keys = Keys(run_id)
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
        self._m_skipped = Counter(
            "aoi3d_decisions_skipped",
            "Decision epochs skipped because the decision thread fell behind the clock.",
            registry=registry)
        self._m_frames = Counter("aoi3d_frames_received", "Delivered frames received.",
                                 ["camera"], registry=registry)
        self._m_inbox_dropped = Counter(
            "aoi3d_inbox_dropped", "Frames dropped because the decision thread fell behind.",
            registry=registry)
        self._m_learn = LearnerMetrics(registry)
        self._install(place_policy(policy, device), save_to=None)

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
        check_policy_fits(policy, len(self.camera_ids))
        if save_to is not None and not is_learning(policy):
            raise PolicySpecError("save_to applies only to a ppo policy with learn: true",
                                  policy.to_json())
        policy = place_policy(policy, self._device)
        old = self._install(policy, save_to=save_to)
        if old is not None:
            self._close_learner(old)
        log.info("policy set to %s%s", policy.spec, " (learning online)"
                 if is_learning(policy) else "")
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
        if is_learning(policy):
            from aoi3d.rl.policy import PPOPolicy

            assert isinstance(policy, PPOPolicy)
            try:
                path = online_checkpoint_path(policy.checkpoint, save_to)
            except ValueError as err:
                raise PolicySpecError(str(err), policy.to_json()) from None
            learner = OnlineLearner(policy.agent, source=policy.checkpoint, save_to=path,
                                    config=self._learn_cfg, metrics=self._m_learn,
                                    wall=self._clock.wall)
        with self._lock:
            old, self._learner = self._learner, learner
            self._policy = policy
        self._m_learn.learning.set(1 if learner is not None else 0)
        if learner is None:
            self._m_learn.entropy.set(math.nan)
            self._m_learn.pending.set(0)
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
            learner = self._learner
            aoi = np.asarray(self._tracker.aoi_ms(t_ms), dtype=np.float64).copy()
            newest = dict(self._newest)
        decision_id = self._decision_id + 1
        if learner is not None:  # learning: a sampled action, remembered until its reward
            chosen = np.asarray(learner.decide(decision_id, t_ms, aoi), dtype=bool)
        else:
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
        self._decision_id = decision_id
        msg = pb.Decision(decision_id=decision_id, time_ms=t_ms,
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
        if learner is not None:
            learner.reward(int(msg.decision_id), msg.time_ms, msg.reward)
