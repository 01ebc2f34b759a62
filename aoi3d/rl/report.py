"""What ``aoi3d ppo eval`` found and writes (:class:`EvalReport`): the scores on held-out seeds
(:func:`aoi3d.rl.evaluate.evaluate`), the optimum set per metric, and ``meta`` (the checkpoint,
the seeds, the budget it was trained and scored at, the code version and the machine)."""

from __future__ import annotations

import time
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from aoi3d.experiment import EpisodeConfig
from aoi3d.experiment.optimum import Optimum, optima
from aoi3d.experiment.report import code_version, machine, write_csv, write_json
from aoi3d.rl.evaluate import EVAL_SCORES, EvalOutcome
from aoi3d.rl.presets import EVAL_SEED_BASE

__all__ = ["EvalReport"]


@dataclass(frozen=True)
class EvalReport:
    """One evaluation: its outcome, per metric the policies not significantly worse than the
    best (paired by seed), and the ``meta`` of eval.json."""

    outcome: EvalOutcome
    optima: dict[str, Optimum]
    meta: dict[str, Any]

    @classmethod
    def of(cls, outcome: EvalOutcome, *, checkpoint: Path, specs: Sequence[str],
           seeds: Sequence[int], seed_offset: int, episode: EpisodeConfig,
           extra: Mapping[str, Any], started: float) -> EvalReport:
        """``extra``: what the checkpoint carries besides the weights (its training's episode
        and train config); ``started``: ``time.time()`` when the command began."""
        best = optima(outcome.rows, EVAL_SCORES, ordered=False)
        trained = (extra.get("episode_config") or {}).get("steps_per_epoch")
        meta = {"command": "aoi3d ppo eval", "checkpoint": str(checkpoint),
                "policies": list(specs), "seeds": list(seeds), "eval_seed_base": EVAL_SEED_BASE,
                "seed_offset": seed_offset, "trained_steps_per_epoch": trained,
                "equal_budget": trained == episode.steps_per_epoch,
                "episode_config": episode.to_dict(), "train_config": extra.get("train_config"),
                "code_version": code_version(), "machine": machine(),
                "wall_s": time.time() - started}
        return cls(outcome, best, meta)

    @property
    def trained_steps(self) -> int | None:
        """Field steps per episode the agent was trained at (None: not recorded)."""
        return self.meta["trained_steps_per_epoch"]

    def write(self, folder: Path) -> None:
        """eval.csv (one row per episode), eval_summary.csv (per policy) and eval.json."""
        write_csv(folder / "eval.csv", self.outcome.rows)
        write_csv(folder / "eval_summary.csv", self.outcome.summary)
        write_json(folder / "eval.json", {
            "meta": self.meta, "summary": self.outcome.summary,
            "optimum": {m: o.to_dict() for m, o in self.optima.items()},
            "episodes": self.outcome.rows})
