"""One episode on the virtual clock: channel → AoI → policy → radiance field → quality.

An episode runs in two stages, so that a sweep knows what it must compute before it trains:

1. :func:`plan_episode` (cheap, milliseconds) simulates the N links with
   :func:`aoi3d.channel.simulate` for the seed and applies the policy to the AoI vector at
   every decision epoch with :func:`aoi3d.policy.decide.decide` — the decision step the live
   scheduler takes too. The channel does not depend on what the policy selects, so the whole
   selection — which camera's frame, generated when, at which decision — is known up front:
   an :class:`EpisodePlan`. A policy that waits (``wait:<ω>``, see
   :mod:`aoi3d.policy.wait`) is asked at t + ω, and its render is scored against the truth
   at t + ω.
2. :func:`run_plan` trains a :class:`aoi3d.field.FieldTrainer` on the planned frames
   (each selected camera's newest delivered frame, generated at U_n(t)) with the configured
   budget, renders the held-out camera at each scored decision and scores it against the
   ground truth of that time (the held-out camera's frame at that time) — the only use of
   the truth — over the whole image and over the dynamic region, the pixels that changed
   since the truth at t − C and t − 2C (:func:`aoi3d.quality.dynamic_mask`).

The numbers are a function of the plan, the config and the seed alone (channel draws from
``camera_rngs(seed, N)``, camera phases and the scene offset from an auxiliary stream of the
same seed, the model's ray sampling from ``seed``): two policies that select the same frames
give the same numbers, which is what :func:`plan_key` lets a sweep exploit.

With ``pool_workers`` ≥ 1 stage 2 is the twin of the live pool (:mod:`.pool`): every decision
is offered to the live dispatcher's code, simulated workers with their own models take the
newest, each job occupies its worker for its compute time, and what is rendered is scored at
its display time.

The package's modules, each importing only those before it: :mod:`.links` (the simulated
links, frame sizes), :mod:`.plan` (stage 1 and the cache key), :mod:`.result` (the scores and
their means), :mod:`.scoring` (a rendered decision's scores), :mod:`.pool` (the pool's twin),
:mod:`.run` (stage 2).
"""

from aoi3d.experiment.episode.links import EpisodeLinks, episode_links, frame_sizes, train_ids
from aoi3d.experiment.episode.plan import (
    ENGINE_VERSION,
    EpisodePlan,
    PlannedDecision,
    dataset_fingerprint,
    decision_budget,
    display_lag,
    plan_episode,
    plan_key,
    planned_decision,
)
from aoi3d.experiment.episode.pool import PoolOutcome, run_pool_plan
from aoi3d.experiment.episode.result import EpisodeResult, EpochScore, episode_result
from aoi3d.experiment.episode.run import run_plan, set_torch_threads

__all__ = [
    "ENGINE_VERSION",
    "EpisodeLinks",
    "EpisodePlan",
    "EpisodeResult",
    "EpochScore",
    "PlannedDecision",
    "PoolOutcome",
    "dataset_fingerprint",
    "decision_budget",
    "display_lag",
    "episode_links",
    "episode_result",
    "frame_sizes",
    "plan_episode",
    "plan_key",
    "planned_decision",
    "run_plan",
    "run_pool_plan",
    "set_torch_threads",
    "train_ids",
]
