"""The scheduler's Prometheus series of online learning: the learner's hook, translated.

:class:`aoi3d.rl.online.OnlineLearner` reports what it does to a
:class:`~aoi3d.rl.online.LearnerHook`; :class:`LearnerMetrics` is that hook as ``aoi3d_ppo_*``
series. No learning happens here.
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from pathlib import Path

from prometheus_client import CollectorRegistry, Counter, Gauge, Histogram, Info, Summary

from aoi3d.policy import Policy
from aoi3d.rl.online import LearnerHook
from services.kit.pb import aoi3d_pb2 as pb

__all__ = ["LearnerMetrics"]


class LearnerMetrics(LearnerHook):
    """The online-learning series of one scheduler: the hook its learners report to.
    Created once per registry and shared by the learners that come and go as the policy
    changes."""

    def __init__(self, registry: CollectorRegistry) -> None:
        self.learning = Gauge(
            "aoi3d_ppo_learning", "1 while a ppo policy learns online (learn: true), else 0.",
            registry=registry)
        self.episodes = Counter(
            "aoi3d_ppo_episodes_learned",
            "Decisions (one-step episodes) whose reward went into a PPO update.",
            registry=registry)
        self.updates = Counter("aoi3d_ppo_updates", "Online PPO updates.", registry=registry)
        self.mean_reward = Gauge(
            "aoi3d_ppo_mean_reward", "Mean reward of the latest update's batch; NaN before "
                                     "the first update.", registry=registry)
        self.entropy = Gauge(
            "aoi3d_ppo_policy_entropy",
            "Entropy (nats, summed over the N camera bits) of the learning policy at the "
            "latest decision; NaN while not learning.", registry=registry)
        self.pending = Gauge(
            "aoi3d_ppo_pending_rewards", "Learn-mode decisions waiting for their reward.",
            registry=registry)
        self.expired_total = Counter(
            "aoi3d_ppo_rewards_expired",
            "Learn-mode decisions dropped because no reward came within "
            "learn_reward_timeout_s.", registry=registry)
        self.unscored = Counter(
            "aoi3d_ppo_decisions_unscored",
            "Learn-mode decisions that no render represented (a later decision's reward came "
            "first; renders are scored in decision order).", registry=registry)
        self.ignored_total = Counter(
            "aoi3d_ppo_rewards_ignored",
            "Quality messages not used for learning, by reason: unknown, duplicate, late, "
            "time_mismatch, inbox_overflow.", ["reason"], registry=registry)
        self.update_seconds = Histogram(
            "aoi3d_ppo_update_seconds", "Wall time of one online PPO update.",
            buckets=(0.001, 0.003, 0.01, 0.03, 0.1, 0.3, 1.0, 3.0), registry=registry)
        self.checkpoints = Counter(
            "aoi3d_ppo_checkpoints", "Online checkpoints written.", registry=registry)
        self.learning.set(0)
        self.mean_reward.set(math.nan)
        self.entropy.set(math.nan)

    # ------------------------------------------------------------------ LearnerHook
    def acted(self, entropy: float, pending: int) -> None:
        self.entropy.set(entropy)
        self.pending.set(pending)

    def rewarded(self, unscored: int, pending: int) -> None:
        if unscored:
            self.unscored.inc(unscored)
        self.pending.set(pending)

    def expired(self, n: int, pending: int) -> None:
        self.expired_total.inc(n)
        self.pending.set(pending)

    def ignored(self, reason: str) -> None:
        self.ignored_total.labels(reason=reason).inc()

    def updated(self, episodes: int, stats: Mapping[str, float], seconds: float) -> None:
        self.update_seconds.observe(seconds)
        self.episodes.inc(episodes)
        self.updates.inc()
        self.mean_reward.set(stats["mean_reward"])

    def saved(self, path: Path) -> None:
        self.checkpoints.inc()

    # ------------------------------------------------------------------ the scheduler's
    def learning_changed(self, learning: bool) -> None:
        """A learner was installed (``learning``) or none is in force any more."""
        self.learning.set(1 if learning else 0)
        if not learning:
            self.entropy.set(math.nan)
            self.pending.set(0)


class DecisionMetrics:
    """The scheduler's decisions, frames and policy as Prometheus series."""

    def __init__(self, registry: CollectorRegistry) -> None:
        self.aoi = Gauge(
            "aoi3d_aoi_seconds",
            "AoI of each camera at the latest decision (sim s); a camera is exported only "
            "once a frame of it was delivered (unknown AoI has no series).",
            ["camera"], registry=registry)
        self.selected = Gauge("aoi3d_cameras_selected",
                              "Cameras selected at the latest decision.", registry=registry)
        self.decisions = Counter("aoi3d_decisions", "Decisions published.",
                                 registry=registry)
        self.selections = Counter(
            "aoi3d_camera_selections",
            "Cameras selected, summed over every decision: rate(...) / "
            "rate(aoi3d_decisions_total) is the mean selected per decision, none missed.",
            registry=registry)
        self.skipped = Counter(
            "aoi3d_decisions_skipped",
            "Decision epochs skipped because the decision thread fell behind the clock.",
            registry=registry)
        self.frames = Counter("aoi3d_frames_received", "Delivered frames received.",
                              ["camera"], registry=registry)
        self.inbox_dropped = Counter(
            "aoi3d_inbox_dropped", "Frames dropped because the decision thread fell behind.",
            registry=registry)
        self.aoi_summary = Summary(
            "aoi3d_decision_aoi_seconds",
            "AoI of each camera at every decision (sim s): rate(_sum)/rate(_count) is its "
            "mean over a window, not a snapshot.", ["camera"], registry=registry)
        self.policy = Info("aoi3d_policy", "The selection policy in force (kind and spec).",
                           registry=registry)
        self.mat = Gauge("aoi3d_policy_mat_seconds",
                         "Γ of the MAT policy in force (sim s); NaN for other kinds.",
                         registry=registry)

    def decided(self, msg: pb.Decision) -> None:
        self.decisions.inc()
        self.selected.set(len(msg.selected))
        self.selections.inc(len(msg.selected))
        for cam, a in zip(msg.camera_ids, msg.aoi_ms, strict=True):
            if math.isfinite(a):
                self.aoi.labels(camera=str(cam)).set(a / 1000.0)
                self.aoi_summary.labels(camera=str(cam)).observe(a / 1000.0)

    def policy_changed(self, policy: Policy) -> None:
        self.policy.info({"kind": policy.kind, "spec": policy.spec})
        gamma_ms = policy.gamma_ms  # Γ of a MAT rule, None for the other kinds
        self.mat.set(float(gamma_ms) / 1000.0 if gamma_ms is not None else math.nan)

