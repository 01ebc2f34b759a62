"""Experiments on a virtual clock: the episode engine, sweeps, figures (``aoi3d experiment``).

The same scene, links, AoI, policies, radiance field and quality code as the live services,
composed in one process and driven slot by slot: deterministic per seed, as fast as the
machine allows. :mod:`~aoi3d.experiment.config` holds the episode config and the presets,
:mod:`~aoi3d.experiment.episode` plans and runs one episode, :mod:`~aoi3d.experiment.sweep`
runs many (cached, on local cores or Ray), :mod:`~aoi3d.experiment.figures` draws them.
:mod:`~aoi3d.experiment.oracle` is the bound a selection could reach (search with the truth),
:mod:`~aoi3d.experiment.baselines` the follow-up paper's trainer options.
"""

from aoi3d.experiment.config import (
    CAMERA_PHASES,
    CARRY_MODES,
    PRESETS,
    EpisodeConfig,
    Preset,
    get_preset,
)
from aoi3d.experiment.episode import (
    ENGINE_VERSION,
    EpisodePlan,
    EpisodeResult,
    EpochScore,
    PlannedDecision,
    episode_result,
    plan_episode,
    plan_key,
    run_plan,
)
from aoi3d.experiment.sweep import (
    METRICS,
    Job,
    OracleOutcome,
    PlansOutcome,
    ResultCache,
    SweepOutcome,
    aggregate,
    default_processes,
    run_jobs,
    run_oracle,
    run_plans,
)
from aoi3d.stats import mean_ci95  # re-exported: the one home is aoi3d.stats

__all__ = [
    "CAMERA_PHASES",
    "CARRY_MODES",
    "ENGINE_VERSION",
    "METRICS",
    "PRESETS",
    "EpisodeConfig",
    "EpisodePlan",
    "EpisodeResult",
    "EpochScore",
    "Job",
    "OracleOutcome",
    "PlannedDecision",
    "PlansOutcome",
    "Preset",
    "ResultCache",
    "SweepOutcome",
    "aggregate",
    "default_processes",
    "episode_result",
    "get_preset",
    "mean_ci95",
    "plan_episode",
    "plan_key",
    "run_jobs",
    "run_oracle",
    "run_plan",
    "run_plans",
]
