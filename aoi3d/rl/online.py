"""Online PPO: each decision of the live scheduler is a one-step episode, its Quality the reward.

While a ``ppo`` policy that learns (``learn: true``) is in force, the scheduler's decision
step (:func:`aoi3d.policy.decide.decide`) takes its selection from :meth:`OnlineLearner.act`
— a *sampled* action, not the deterministic one — and the learner remembers
``decision_id → (observation, action, log π(action))`` as a pending episode. The metrics
service later publishes a ``Quality`` whose ``decision_id`` names the decision the scored
render was trained under; its ``reward`` closes that episode (:meth:`OnlineLearner.reward`).
Every ``batch_size`` closed episodes the learner runs one PPO update
(:meth:`~aoi3d.policy.ppo.learner.PPOLearner.update`, the same as offline training), and it
writes the agent (weights, optimizer state, generator) to its online checkpoint every
``checkpoint_every`` updates and when it is closed (policy replaced, service stopped).

What can go wrong with the rewards, and what happens:

- Most decisions are never scored: the trainer renders every ``render_period_s`` with the
  decision in force then, so only that one gets a Quality. Renders are published, and
  scored, in decision order, so a reward for decision d means no decision before d will get
  one: those pending episodes are dropped at once and counted as *unscored*.
- A reward that never comes (metrics or trainer down) lets its episode *expire* after
  ``reward_timeout_s`` wall seconds (counted).
- A Quality for a decision this learner did not take or no longer waits for is *ignored*
  and counted by reason: ``unknown`` (never pending here: another policy, a restart),
  ``duplicate`` (its reward was already used), ``late`` (it had expired or was unscored),
  ``time_mismatch`` (its time is not the decision's: not a render of this decision).

The action bits of cameras whose AoI is unknown are masked out of the selection by the
decision step (an unknown AoI is never selected) but the sampled bits and their
log-probability are what the update sees: those bits do not change the reward, so they add
noise, not bias.

An update must not hold up a decision: the decision thread acts with its own copy of the
agent (same weights, its generator started from the loaded agent's state), and the learning
thread updates the agent and then copies the new weights into the acting copy — a lock held
for a ``load_state_dict`` of a tiny network, not for the update.

The learner is used from three threads: the decision thread (:meth:`OnlineLearner.act`), the
caller's learning thread (:meth:`~OnlineLearner.reward`, :meth:`~OnlineLearner.expire`,
:meth:`~OnlineLearner.update_if_ready`) and readers (:meth:`~OnlineLearner.status`,
:meth:`~OnlineLearner.close`). ``_lock`` guards the bookkeeping, ``_act_lock`` the acting copy
and ``_agent_lock`` the learning agent (updates, saves). ``_lock`` may be taken while
``_agent_lock`` is held (to book an update), never the other way round.

What the learner does is reported to a :class:`LearnerHook` (the scheduler's Prometheus
series); the domain knows no metrics library. This module imports torch only through the
agent it is given (:meth:`OnlineLearner.for_policy` loads one).
"""

from __future__ import annotations

import logging
import math
import os
import threading
import time
from collections import OrderedDict
from collections.abc import Callable, Mapping
from dataclasses import dataclass, field
from enum import StrEnum
from pathlib import Path
from typing import TYPE_CHECKING, cast

import numpy as np

from aoi3d.policy.base import Policy
from aoi3d.policy.ppo.batch import Batch, Episode

if TYPE_CHECKING:  # torch is imported only once an agent is loaded
    from aoi3d.policy.ppo.learner import PPOLearner
    from aoi3d.policy.ppo.policy import PPOPolicy

__all__ = ["LearnConfig", "LearnerHook", "LearnerStatus", "OnlineLearner", "Outcome",
           "online_checkpoint_path"]

log = logging.getLogger(__name__)

_TIME_TOL_MS = 1e-6  # a Quality's time must be the decision's (both carry the same double)
_RESOLVED_KEPT = 4096  # decision ids remembered after their episode closed (duplicates, late)


class Outcome(StrEnum):
    """What became of one Quality handed to :meth:`OnlineLearner.reward`."""

    USED = "used"
    UNKNOWN = "unknown"
    DUPLICATE = "duplicate"
    LATE = "late"
    TIME_MISMATCH = "time_mismatch"


@dataclass(frozen=True)
class LearnConfig:
    """How the scheduler learns online (from its settings ``learn_*``)."""

    batch_size: int = 8
    """Rewarded decisions per PPO update."""
    reward_timeout_s: float = 10.0
    """Wall seconds a decision waits for its reward before it expires."""
    checkpoint_every: int = 10
    """Updates between two online checkpoints (one is also written on close)."""

    def __post_init__(self) -> None:
        if isinstance(self.batch_size, bool) or not isinstance(self.batch_size, int) \
                or self.batch_size < 1:
            raise ValueError(f"batch_size must be an int >= 1, got {self.batch_size!r}")
        if not (isinstance(self.reward_timeout_s, int | float)
                and math.isfinite(self.reward_timeout_s) and self.reward_timeout_s > 0):
            raise ValueError(f"reward_timeout_s must be > 0, got {self.reward_timeout_s!r}")
        if isinstance(self.checkpoint_every, bool) or not isinstance(self.checkpoint_every, int) \
                or self.checkpoint_every < 1:
            raise ValueError(f"checkpoint_every must be an int >= 1, got "
                             f"{self.checkpoint_every!r}")


def online_checkpoint_path(checkpoint: str | Path, save_to: str | Path | None = None) -> Path:
    """Where the online checkpoint of a policy loaded from ``checkpoint`` is written.

    Default: next to the source, ``<stem>.online.pt`` (``policy.pt`` → ``policy.online.pt``),
    so the source is never overwritten; ``save_to`` names another file (the source itself
    only when asked for explicitly). Raises ``ValueError`` when the file could not be
    written: its folder is missing or read-only, or the path is a folder.
    """
    if save_to is not None and not str(save_to).strip():
        raise ValueError("save_to must be a non-empty path")
    source = Path(checkpoint)
    if save_to is None:
        stem = source.stem if source.suffix else source.name
        path = source.with_name(f"{stem}.online.pt")
    else:
        path = Path(save_to)
    folder = path.parent
    if path.is_dir():
        raise ValueError(f"online checkpoint path {path} is a folder, not a file")
    if not folder.is_dir():
        raise ValueError(f"cannot write the online checkpoint {path}: folder {folder} does not "
                         f"exist")
    if not os.access(folder, os.W_OK):
        raise ValueError(f"cannot write the online checkpoint {path}: folder {folder} is not "
                         f"writable")
    return path


class LearnerHook:
    """What an :class:`OnlineLearner` reports as it goes (e.g. to metrics); every method
    here does nothing. Some are called with the learner's bookkeeping lock held: keep them
    quick and never call back into the learner."""

    def acted(self, entropy: float, pending: int) -> None:
        """A decision's action was sampled (its policy entropy); ``pending`` now wait."""

    def rewarded(self, unscored: int, pending: int) -> None:
        """A reward closed an episode; ``unscored`` earlier decisions were dropped with it."""

    def expired(self, n: int, pending: int) -> None:
        """``n`` pending decisions expired without a reward."""

    def ignored(self, reason: str) -> None:
        """A reward was not used (``unknown``, ``duplicate``, ``late``, ``time_mismatch``,
        or the caller's reason, e.g. ``inbox_overflow``)."""

    def updated(self, episodes: int, stats: Mapping[str, float], seconds: float) -> None:
        """A PPO update on ``episodes`` episodes took ``seconds``; its statistics."""

    def saved(self, path: Path) -> None:
        """The online checkpoint was written to ``path``."""


@dataclass
class _Pending:
    """A learn-mode decision waiting for its reward."""

    time_ms: float
    obs: np.ndarray
    action: np.ndarray
    logp: float
    born_s: float


@dataclass(frozen=True)
class LearnerStatus:
    """A snapshot of one learner (``GET /policy`` shows it as ``online``)."""

    save_to: str
    batch_size: int
    episodes_learned: int
    agent_episodes: int
    updates: int
    pending_rewards: int
    batch_filled: int
    expired: int
    unscored: int
    ignored: dict[str, int]
    mean_reward: float | None
    entropy: float | None
    last_update: dict[str, float] | None
    checkpoints_saved: int
    last_saved_s: float | None


@dataclass
class _Counts:
    episodes: int = 0
    updates: int = 0
    expired: int = 0
    unscored: int = 0
    checkpoints: int = 0
    ignored: dict[str, int] = field(default_factory=dict)


class OnlineLearner:
    """Acts stochastically for a live decision loop and learns from the decisions' rewards.

    ``agent``: the loaded agent (it is updated in place); ``source``: the checkpoint it came
    from (recorded in the online checkpoint); ``save_to``: where the online checkpoint goes;
    ``hook``: told what happens (:class:`LearnerHook`); ``wall``: the wall clock in seconds
    (expiry; injectable for tests).
    """

    def __init__(self, agent: PPOLearner, *, source: str, save_to: str | Path,
                 config: LearnConfig | None = None, hook: LearnerHook | None = None,
                 wall: Callable[[], float] = time.time) -> None:
        self.agent = agent
        self.source = source
        self.save_to = Path(save_to)
        self.config = config or LearnConfig()
        self._hook = hook or LearnerHook()
        self._wall = wall
        self._lock = threading.Lock()
        self._agent_lock = threading.Lock()
        self._act_lock = threading.Lock()
        self._acting = agent.copy()
        self._pending: OrderedDict[int, _Pending] = OrderedDict()  # by decision id (= by age)
        self._resolved: OrderedDict[int, Outcome | str] = OrderedDict()
        self._batch: list[Episode] = []
        self._counts = _Counts()
        self._unsaved_updates = 0
        self._last_stats: dict[str, float] | None = None
        self._last_entropy: float | None = None
        self._last_saved_s: float | None = None
        self._closed = False

    @classmethod
    def for_policy(cls, policy: Policy, *, save_to: str | Path | None = None,
                   config: LearnConfig | None = None, hook: LearnerHook | None = None,
                   wall: Callable[[], float] = time.time) -> OnlineLearner:
        """A learner for a policy that learns (:attr:`~aoi3d.policy.Policy.learns`; any other
        is a ``ValueError``) — a ``ppo`` policy with ``learn``, whose ``checkpoint`` and
        ``device`` name the agent: its checkpoint loaded as a learner (with the optimizer
        state and the generator's position) on the policy's device; the online checkpoint
        goes to ``save_to`` (default: :func:`online_checkpoint_path`). Raises ``ValueError``
        when the checkpoint cannot be loaded or the online checkpoint could not be
        written."""
        if not policy.learns:
            raise ValueError(f"{policy.spec}: this policy does not learn (a ppo policy learns "
                             "online with learn: true)")
        from aoi3d.policy.ppo.learner import PPOLearner

        ppo = cast("PPOPolicy", policy)  # the policy that learns (above)
        path = online_checkpoint_path(ppo.checkpoint, save_to)
        try:
            agent = PPOLearner.load(ppo.checkpoint, device=ppo.device)
        except FileNotFoundError as err:
            raise ValueError(str(err)) from None
        return cls(agent, source=ppo.checkpoint, save_to=path, config=config, hook=hook,
                   wall=wall)

    # ------------------------------------------------------------------ the decision thread
    def act(self, decision_id: int, aoi_ms: np.ndarray, time_ms: float) -> np.ndarray:
        """Sample the action for decision ``decision_id`` on the AoI vector at ``time_ms``
        and remember it until its reward comes; returns the sampled bits (bool per camera;
        the decision step drops the cameras of unknown AoI). As an
        :data:`aoi3d.policy.decide.Act`: ``functools.partial(learner.act, decision_id)``."""
        aoi = np.asarray(aoi_ms, dtype=np.float64)
        obs = self.agent.observe(aoi)
        with self._act_lock:
            sample = self._acting.sample(obs)
        action = np.asarray(sample.action, dtype=np.int8)
        with self._lock:
            if not self._closed:
                self._pending[decision_id] = _Pending(time_ms=float(time_ms), obs=obs,
                                                      action=action, logp=float(sample.logp),
                                                      born_s=self._wall())
                self._last_entropy = float(sample.entropy)
                self._hook.acted(float(sample.entropy), len(self._pending))
        return action.astype(bool)

    # ------------------------------------------------------------------ the learning thread
    def reward(self, decision_id: int, time_ms: float, reward: float) -> Outcome:
        """Close decision ``decision_id``'s episode with ``reward`` (a finite number)."""
        if not math.isfinite(reward):
            raise ValueError(f"reward must be finite, got {reward}")
        with self._lock:
            if self._closed:  # the policy was replaced: nothing learns from it any more
                return Outcome.UNKNOWN
            entry = self._pending.get(decision_id)
            if entry is None:
                prior = self._resolved.get(decision_id)
                outcome = (Outcome.UNKNOWN if prior is None else
                           Outcome.DUPLICATE if prior == Outcome.USED else Outcome.LATE)
                self._ignore(outcome)
                return outcome
            if abs(entry.time_ms - time_ms) > _TIME_TOL_MS:
                self._ignore(Outcome.TIME_MISMATCH)
                return Outcome.TIME_MISMATCH
            # renders are scored in decision order: earlier pending decisions get no reward
            unscored = 0
            while (first_id := next(iter(self._pending))) != decision_id:
                self._pending.popitem(last=False)
                self._resolve(first_id, "unscored")
                unscored += 1
            self._counts.unscored += unscored
            del self._pending[decision_id]
            self._resolve(decision_id, Outcome.USED)
            self._batch.append(Episode(obs=entry.obs, action=entry.action, logp=entry.logp,
                                       reward=float(reward)))
            self._hook.rewarded(unscored, len(self._pending))
        return Outcome.USED

    def ignore(self, reason: str) -> None:
        """Count a Quality that never reached :meth:`reward` (e.g. ``inbox_overflow``)."""
        with self._lock:
            self._ignore(reason)

    def expire(self) -> int:
        """Drop the pending decisions older than ``reward_timeout_s``; how many."""
        cutoff = self._wall() - self.config.reward_timeout_s
        n = 0
        with self._lock:
            while self._pending:
                first_id, first = next(iter(self._pending.items()))
                if first.born_s > cutoff:
                    break
                self._pending.popitem(last=False)
                self._resolve(first_id, "expired")
                n += 1
            if n:
                self._counts.expired += n
                self._hook.expired(n, len(self._pending))
        return n

    def update_if_ready(self) -> dict[str, float] | None:
        """Run one PPO update when ``batch_size`` rewarded decisions are waiting (then
        checkpoint every ``checkpoint_every`` updates); the update's stats, else None."""
        b = self.config.batch_size
        with self._lock:
            if self._closed or len(self._batch) < b:
                return None
            batch, self._batch = self._batch[:b], self._batch[b:]
        t0 = time.perf_counter()
        with self._agent_lock:
            stats = self.agent.update(Batch.of(batch))
            weights = {k: v.detach().clone() for k, v in self.agent.net.state_dict().items()}
            with self._lock:  # booked before the agent is free: close() sees this update
                self._counts.episodes += b
                self._counts.updates += 1
                self._unsaved_updates += 1
                self._last_stats = dict(stats)
                due = self._unsaved_updates >= self.config.checkpoint_every
        elapsed = time.perf_counter() - t0
        with self._act_lock:
            self._acting.net.load_state_dict(weights)
        self._hook.updated(b, stats, elapsed)
        log.info("PPO update %d on %d episodes in %.1f ms: mean reward %.4f, entropy %.3f, "
                 "approx KL %.4f", self.agent.updates, b, elapsed * 1e3, stats["mean_reward"],
                 stats["entropy"], stats["approx_kl"])
        if due:
            self.save()
        return stats

    # ------------------------------------------------------------------ checkpoints, lifecycle
    def save(self) -> Path:
        """Write the agent (weights, optimizer, generator, episodes) to ``save_to``,
        atomically."""
        with self._lock:
            counts = self._counts
            extra = {"online": {"source_checkpoint": self.source,
                                "episodes_learned": counts.episodes,
                                "updates": counts.updates, "saved_at_s": time.time()}}
        with self._agent_lock:
            self.agent.save(self.save_to, extra=extra)
        with self._lock:
            self._unsaved_updates = 0
            self._counts.checkpoints += 1
            self._last_saved_s = time.time()
        self._hook.saved(self.save_to)
        log.info("online PPO checkpoint written to %s (%d episodes learned here)",
                 self.save_to, counts.episodes)
        return self.save_to

    def close(self) -> Path | None:
        """Stop learning: drop the pending decisions and the partial batch, and write the
        online checkpoint if an update happened since the last one (its path, else None)."""
        with self._lock:
            if self._closed:
                return None
            self._closed = True
            dropped, partial = len(self._pending), len(self._batch)
            self._pending.clear()
            self._batch.clear()
        with self._agent_lock, self._lock:  # after an update in flight, if any
            unsaved = self._unsaved_updates
        if dropped or partial:
            log.info("learning stopped: %d pending decision(s) and %d rewarded one(s) short of "
                     "a batch dropped", dropped, partial)
        return self.save() if unsaved else None

    @property
    def acting_agent(self) -> PPOLearner:
        """The copy of the agent the decision thread samples from (weights of the latest
        update)."""
        return self._acting

    @property
    def closed(self) -> bool:
        with self._lock:
            return self._closed

    def status(self) -> LearnerStatus:
        with self._lock:
            c = self._counts
            stats = dict(self._last_stats) if self._last_stats is not None else None
            return LearnerStatus(
                save_to=str(self.save_to), batch_size=self.config.batch_size,
                episodes_learned=c.episodes, agent_episodes=self.agent.episodes,
                updates=c.updates, pending_rewards=len(self._pending),
                batch_filled=len(self._batch), expired=c.expired, unscored=c.unscored,
                ignored=dict(c.ignored),
                mean_reward=None if stats is None else stats["mean_reward"],
                entropy=self._last_entropy, last_update=stats,
                checkpoints_saved=c.checkpoints, last_saved_s=self._last_saved_s)

    # ------------------------------------------------------------------ helpers (under _lock)
    def _ignore(self, reason: str) -> None:
        self._counts.ignored[reason] = self._counts.ignored.get(reason, 0) + 1
        self._hook.ignored(str(reason))

    def _resolve(self, decision_id: int, outcome: Outcome | str) -> None:
        self._resolved[decision_id] = outcome
        while len(self._resolved) > _RESOLVED_KEPT:
            self._resolved.popitem(last=False)

