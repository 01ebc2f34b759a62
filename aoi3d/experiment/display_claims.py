"""Issue 40 §3: the display-time question of a compute-aware policy against the best fixed
(Γ, steps) in hindsight, asked of a compare run over a grid of ``mat:Γ@s`` / ``all@s`` and
the compute-aware kinds (``dmat``, ``deadline``: :mod:`aoi3d.policy.display`; and any label
the caller names, such as a PPO agent with the lag in its state), with the oracle over
(Γ, steps) at display time (``oracle:budgets:<metric>``, :mod:`aoi3d.experiment.oracle`) as
the bound when the run has it."""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from typing import Any

import numpy as np

from aoi3d.experiment.claims import DISPLAY_METRIC, Verdict, metric_name
from aoi3d.experiment.results import Results
from aoi3d.policy import kind_of
from aoi3d.stats import paired_difference

FIXED_KINDS = ("mat", "all")
"""Fixed (Γ, steps) cells: a MAT threshold or every frame, each at its own budget."""
COMPUTE_AWARE_KINDS = ("dmat", "deadline")
"""Policies that choose with the compute lag in view."""


def compute_aware_beats_best_fixed(compare: Results | Mapping[str, Any],
                                   metric: str = DISPLAY_METRIC, goal: float = 0.5,
                                   aware_labels: Sequence[str] = ()) -> Verdict:
    """The best compute-aware policy (highest mean ``metric``; the kinds
    :data:`COMPUTE_AWARE_KINDS` and the runs ``aware_labels`` names) is significantly better
    than the best fixed cell in hindsight (highest mean). The evidence states the paired
    difference per seed (mean ± 95% CI), the goal (≥ ``goal`` dB), the room a per-seed
    hindsight choice among the fixed cells leaves (mean over seeds of the best cell of that
    seed minus the best cell's value) and, when the run has it, the oracle's: the bound
    ``oracle:budgets:<metric>`` (the best cell per *decision*, with the truth) minus the best
    fixed cell, paired by seed."""
    doc = Results.parse(compare)
    runs = {r.policy: r.own for r in doc.runs()}
    fixed = [p for p, own in runs.items() if kind_of(own).kind in FIXED_KINDS]
    aware = [p for p, own in runs.items()
             if kind_of(own).kind in COMPUTE_AWARE_KINDS or p in aware_labels]
    statement = (f"A compute-aware policy is significantly better in {metric_name(metric)} "
                 "than the best fixed (Γ, steps) in hindsight")
    if not fixed or not aware:
        return Verdict("compute-aware-beats-best-fixed", statement, False,
                       "not tested: the compare run has no fixed cell or no compute-aware "
                       "policy")
    per_seed = {p: doc.per_seed(p, metric) for p in [*fixed, *aware]}
    means = {p: float(np.mean(list(v.values()))) for p, v in per_seed.items()}
    best_fixed = max(fixed, key=lambda p: means[p])
    best_aware = max(aware, key=lambda p: means[p])
    d = paired_difference(per_seed[best_aware], per_seed[best_fixed])
    holds = d.significant and d.mean > 0
    verdict = ("significantly better" if holds else "significantly worse"
               if d.significant else "not significantly different")
    seeds = sorted(per_seed[best_fixed])
    room = [max(per_seed[p][s] for p in fixed) - per_seed[best_fixed][s] for s in seeds]
    winners = {s: max(fixed, key=lambda p: per_seed[p][s]) for s in seeds}
    numbers: dict[str, Any] = {
        "best_fixed": best_fixed, "best_compute_aware": best_aware, "means": means,
        "aware_minus_fixed": d.to_dict(), "per_seed_room_mean": float(np.mean(room)),
        "per_seed_room_max": float(np.max(room)), "per_seed_best_cell": winners}
    evidence = (f"best fixed {best_fixed} ({means[best_fixed]:.2f} dB); best compute-aware "
                f"{best_aware} ({means[best_aware]:.2f} dB); {best_aware} − {best_fixed}: "
                f"{d.mean:+.2f} ± {d.half:.2f} over {d.n} seeds: {verdict}; goal ≥ {goal:g}: "
                f"{'met' if holds and d.mean >= goal else 'not met'}; room of the per-seed "
                f"best cell over {best_fixed}: {np.mean(room):.2f} dB mean, "
                f"{np.max(room):.2f} max")
    oracle = f"oracle:budgets:{metric}"
    bound = doc.per_seed(oracle, metric)
    if bound:
        o = paired_difference(bound, per_seed[best_fixed])
        a = paired_difference(bound, per_seed[best_aware])
        numbers.update(oracle=oracle, oracle_mean=float(np.mean(list(bound.values()))),
                       oracle_minus_best_fixed=o.to_dict(),
                       oracle_minus_best_compute_aware=a.to_dict())
        evidence += (f"; oracle over (Γ, steps) per decision ({oracle}, "
                     f"{numbers['oracle_mean']:.2f} dB) − best fixed: {o.mean:+.2f} ± "
                     f"{o.half:.2f} dB; − {best_aware}: {a.mean:+.2f} ± {a.half:.2f} dB")
    else:
        evidence += " (no oracle searched)"
    return Verdict("compute-aware-beats-best-fixed", statement, holds, evidence, numbers)
