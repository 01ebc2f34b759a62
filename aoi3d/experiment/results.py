"""A typed view of a results document, parsed once: what the claims (and whoever else reads a
run back) ask of a ``results.json`` of ``aoi3d experiment tradeoff``, ``delay`` or
``compare``, or an ``eval.json`` of ``aoi3d ppo eval``.

The documents are written by :mod:`aoi3d.experiment.report` (and :mod:`aoi3d.rl.report`);
:meth:`Results.parse` reads one — a dict as ``json.loads`` gives it — into frozen dataclasses,
so a reader names fields instead of walking keys. A section a document does not have (a
tradeoff has no ``policies``, an eval no ``optimum`` of its own metrics) is empty; a field a
reader needs and the document lacks raises :class:`KeyError` where it is asked for. Every view
keeps the mapping it was read from (``raw``), so what is quoted back into a verdict's numbers
is the document's own text, unchanged. Pure: no I/O.
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import dataclass, field
from typing import Any

__all__ = ["DelayOptimum", "Difference", "Episode", "Meta", "OptimumView", "PolicyRun",
           "Results"]

Candidate = Any
"""A candidate of an optimum as the document writes it: Γ in ms (a number), or a policy label
(``all``, ``mat:70``…)."""


@dataclass(frozen=True)
class Difference:
    """A paired difference as written (:meth:`aoi3d.stats.PairedDifference.to_dict`)."""

    mean: float
    """NaN where the document has none (a metric not measured: LPIPS without its weights)."""
    ci95: float | None
    n: int | None
    raw: Mapping[str, Any] = field(repr=False)

    @classmethod
    def parse(cls, d: Mapping[str, Any]) -> Difference:
        mean, half, n = d.get("mean"), d.get("ci95"), d.get("n")
        return cls(math.nan if mean is None else float(mean),
                   None if half is None else float(half), None if n is None else int(n), d)


@dataclass(frozen=True)
class OptimumView:
    """One metric's optimum as written (:meth:`aoi3d.experiment.optimum.Optimum.to_dict`)."""

    metric: str
    best: Candidate
    members: tuple[Candidate, ...]
    interior: bool
    ends: tuple[Candidate, ...]
    excluded: tuple[Candidate, ...]
    seeds: tuple[int, ...]
    best_minus: Mapping[str, Difference]
    """best − candidate, by the candidate as a string (``"40.0"``, ``"all"``)."""
    raw: Mapping[str, Any] = field(repr=False)

    @classmethod
    def parse(cls, d: Mapping[str, Any]) -> OptimumView:
        return cls(metric=str(d.get("metric", "")), best=d["best"],
                   members=tuple(d["members"]), interior=bool(d.get("interior", False)),
                   ends=tuple(d.get("ends", ())), excluded=tuple(d.get("excluded", ())),
                   seeds=tuple(int(s) for s in d.get("seeds", ())),
                   best_minus={str(k): Difference.parse(v)
                               for k, v in d.get("best_minus", {}).items()},
                   raw=d)


@dataclass(frozen=True)
class DelayOptimum:
    """A row of a ``delay`` document's ``optima``: one mean delay's optimum over Γ."""

    mean_delay_ms: float
    optimum: OptimumView

    @classmethod
    def parse(cls, d: Mapping[str, Any]) -> DelayOptimum:
        return cls(float(d["mean_delay_ms"]), OptimumView.parse(d["optimum"]))


@dataclass(frozen=True)
class PolicyRun:
    """A row of a ``compare`` document's ``policies``: a policy run (or a bound)."""

    policy: str
    own: str | Mapping[str, Any]
    """Its own JSON form (``policy_json``) where the row carries one, else its label: what
    :func:`aoi3d.policy.kind_of` reads its kind from."""
    bound: bool

    @classmethod
    def parse(cls, d: Mapping[str, Any]) -> PolicyRun:
        return cls(str(d["policy"]), d.get("policy_json") or d["policy"],
                   bool(d.get("bound", False)))


@dataclass(frozen=True)
class Episode:
    """An episode of a document's ``episodes``: its policy, seed, scores and (where the
    document has them) its scored decisions' scores, each ``(eval_ms, scores)``."""

    policy: str
    seed: int
    scores: Mapping[str, Any] = field(repr=False)
    epochs: tuple[tuple[float, Mapping[str, Any]], ...] = field(default=(), repr=False)

    @classmethod
    def parse(cls, d: Mapping[str, Any]) -> Episode:
        return cls(str(d["policy"]), int(d["seed"]), d,
                   tuple((float(e["eval_ms"]), e) for e in d.get("epochs", ())))

    def value(self, metric: str) -> float:
        """The episode's ``metric`` (KeyError where it has none)."""
        return float(self.scores[metric])

    def epoch_values(self, metric: str) -> list[tuple[float, float]]:
        """``(eval_ms, metric)`` of the scored decisions that have ``metric``."""
        return [(t, float(e[metric])) for t, e in self.epochs if e.get(metric) is not None]


@dataclass(frozen=True)
class Meta:
    """What the claims read of a document's ``meta``."""

    raw: Mapping[str, Any] = field(repr=False)

    @property
    def delay(self) -> str:
        """The channel spec of the run (its ``--delay``); ``""`` when it has none."""
        return str(self.raw.get("args", {}).get("delay") or self.raw.get("delay") or "")

    @property
    def policies(self) -> tuple[str, ...]:
        """The policies an evaluation scored (``eval.json``), in order."""
        return tuple(self.raw["policies"])

    @property
    def seeds(self) -> tuple[int, ...]:
        """The seeds of an evaluation (``eval.json``'s ``seeds``)."""
        return tuple(self.raw["seeds"])

    @property
    def seed_list(self) -> tuple[int, ...]:
        """The seeds of an experiment command (``seed_list``)."""
        return tuple(self.raw["seed_list"])

    @property
    def steps_per_epoch(self) -> int:
        """The field steps per decision of the run's episode config."""
        return int(self.raw["episode_config"]["steps_per_epoch"])

    @property
    def equal_budget(self) -> bool:
        """Whether the agent was evaluated at the budget it was trained for."""
        return bool(self.raw.get("equal_budget"))

    @property
    def trained_steps_per_epoch(self) -> Any:
        """The budget the agent was trained at, as written (None where unknown)."""
        return self.raw.get("trained_steps_per_epoch")


@dataclass(frozen=True)
class Results:
    """A results document, parsed: its meta, optima (one per metric; ``delay``: one row per
    mean delay), policy runs, oracle bounds and episodes."""

    meta: Meta
    optimum: Mapping[str, OptimumView]
    optima: tuple[DelayOptimum, ...]
    policies: tuple[PolicyRun, ...]
    bound: Mapping[str, Mapping[str, Mapping[str, Difference]]]
    """Per bound spec (``oracle:rules:psnr_db``), its ``minus``: per metric, per policy, the
    paired difference bound − policy."""
    episodes: tuple[Episode, ...]
    raw: Mapping[str, Any] = field(repr=False)

    @classmethod
    def parse(cls, doc: Results | Mapping[str, Any]) -> Results:
        """The view of ``doc`` (a view is returned as it is)."""
        if isinstance(doc, Results):
            return doc
        return cls(
            meta=Meta(doc.get("meta", {})),
            optimum={str(m): OptimumView.parse(o) for m, o in doc.get("optimum", {}).items()},
            optima=tuple(DelayOptimum.parse(o) for o in doc.get("optima", ())),
            policies=tuple(PolicyRun.parse(p) for p in doc.get("policies", ())),
            bound={str(spec): {str(m): {str(p): Difference.parse(d) for p, d in per.items()}
                               for m, per in b.get("minus", {}).items()}
                   for spec, b in doc.get("bound", {}).items()},
            episodes=tuple(Episode.parse(e) for e in doc.get("episodes", ())),
            raw=doc)

    def runs(self) -> list[PolicyRun]:
        """The policies run, bounds left out, in order."""
        return [p for p in self.policies if not p.bound]

    def per_seed(self, policy: str, metric: str) -> dict[int, float]:
        """``policy``'s ``metric`` per seed."""
        return {e.seed: e.value(metric) for e in self.episodes if e.policy == policy}

    def epochs(self, policy: str, metric: str) -> dict[int, list[tuple[float, float]]]:
        """Per seed, ``policy``'s scored decisions: ``(eval_ms, metric)``."""
        return {e.seed: e.epoch_values(metric) for e in self.episodes if e.policy == policy}
