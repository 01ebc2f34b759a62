"""Where the optimum lies: one criterion, stated before measuring, for every command.

The experiments run every policy on the same seeds (the same channel draws, scene phase and
model seed), so two policies are compared by their **paired** per-seed differences, not by
overlapping bands. The criterion (:func:`optimum`):

1. Only *eligible* candidates take part: for a MAT sweep, the thresholds that select at
   least one frame on average (Γ ≤ C selects nothing with synchronised cameras, so it says
   nothing about the tradeoff), plus the reference `all` (Γ = ∞) when it was run.
2. Only seeds that every eligible candidate has are used (the differences stay paired).
3. The *best* candidate has the highest mean (lowest, for LPIPS).
4. A candidate is *significantly worse* than the best when the 95% confidence interval
   (Student t, n − 1 degrees of freedom) of the mean per-seed difference best − candidate
   lies above zero.
5. The **optimum set** is every eligible candidate that is not significantly worse than the
   best; it is reported as a range of Γ. No correction for multiple comparisons is made: the
   set is, if anything, too narrow by chance, never wider.
6. The optimum is **interior** when the optimum set holds neither end of the eligible range:
   the smallest eligible Γ and the largest end — `all` (Γ = ∞) when it was run, else the
   largest swept Γ. That is :func:`aoi3d.stats.interior_maximum` on the paired differences
   best − each end: the project's one interior-maximum criterion.

With fewer than two paired seeds no interval exists; nothing is then significantly worse,
the set is every candidate and the optimum is never interior.

Pure numpy/scipy: used by ``aoi3d experiment tradeoff``, ``delay``, ``compare``, ``aoi3d ppo
eval`` (all through :func:`optima`) and the science check (``bench/science.py``) alike.
Which metrics are lower-is-better comes from the metrics' table (:mod:`aoi3d.metric`):
:data:`LOWER_IS_BETTER`, :func:`sign_of`.

``aoi3d live sweep`` cannot pair: its measurement windows are different renders of a running
pipeline, not episodes paired by seed. :func:`unpaired_interior_maximum` asks the same question
of it with Welch intervals of best − each end — the same :func:`aoi3d.stats.interior_maximum`.
The intervals themselves live in :mod:`aoi3d.stats`.

:func:`rederived` takes a results document's optima again, for metrics its command did not
judge (the display-time scores the science check asks about).
"""

from __future__ import annotations

import math
from collections.abc import Callable, Iterable, Mapping, Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from aoi3d.metric import METRICS, lower_is_better
from aoi3d.stats import (
    LEVEL,
    PairedDifference,
    interior_maximum,
    paired_difference,
    welch_ci95,
)

__all__ = [
    "LEVEL",
    "LOWER_IS_BETTER",
    "Optimum",
    "PairedDifference",
    "optima",
    "optimum",
    "paired_difference",
    "rederived",
    "sign_of",
    "sweep_position",
    "unpaired_interior_maximum",
]

LOWER_IS_BETTER = frozenset(m.name for m in METRICS if not m.higher_is_better)
"""The metrics whose better direction is down (LPIPS, a distance, at either time); every other
metric — PSNR, SSIM, their dynamic-region forms, the reward — is higher-is-better."""


def sign_of(metric: str) -> float:
    """+1 for a higher-is-better metric (or a name that is not a metric's), −1 for a
    lower-is-better one (:func:`aoi3d.metric.lower_is_better`)."""
    return -1.0 if lower_is_better(metric) else 1.0


@dataclass(frozen=True)
class Optimum:
    """The outcome of :func:`optimum` for one metric.

    ``best``: the candidate with the best mean; ``members``: the optimum set, in candidate
    order; ``to_best[c]``: the paired difference best − c in the metric's *better* direction
    (positive: c is worse), for every eligible candidate; ``excluded``: candidates left out
    (selecting nothing); ``seeds``: the paired seeds used; ``interior``: see the module."""

    metric: str
    best: Any
    members: tuple[Any, ...]
    to_best: dict[Any, PairedDifference]
    excluded: tuple[Any, ...]
    seeds: tuple[int, ...]
    ends: tuple[Any, ...] = field(default=())
    interior: bool = False
    positions: dict[Any, float] = field(default_factory=dict, repr=False)
    """Where each eligible candidate lies along the sweep (Γ in ms, ∞ for the reference);
    empty for policies without an order."""

    def range_of(self) -> tuple[float, float] | None:
        """The smallest and largest place of a member along the sweep (Γ in ms; the reference
        `all` at ∞), or None for policies without an order."""
        places = [self.positions[m] for m in self.members if m in self.positions]
        return (min(places), max(places)) if places else None

    def to_dict(self) -> dict[str, Any]:
        span = self.range_of()
        return {
            "metric": self.metric, "best": self.best, "members": list(self.members),
            "range": list(span) if span else None, "interior": self.interior,
            "ends": list(self.ends), "excluded": list(self.excluded), "seeds": list(self.seeds),
            "best_minus": {str(k): v.to_dict() for k, v in self.to_best.items()},
        }


def sweep_position(candidate: Any) -> float:
    """The default place of a candidate along a MAT sweep: a number is its Γ (ms); anything
    else — the reference, ``all`` — lies at Γ = ∞, the sweep's stale end."""
    if isinstance(candidate, int | float | np.integer | np.floating) and not isinstance(
            candidate, bool):
        return float(candidate)
    return math.inf


def optimum(values: Mapping[Any, Mapping[int, float]], *, metric: str = "psnr_db",
            lower_is_better: bool | None = None, selects: Mapping[Any, float] | None = None,
            ordered: bool = True, position: Mapping[Any, float] | None = None,
            level: float = LEVEL) -> Optimum:
    """Apply the criterion of this module.

    ``values[c][seed]``: the per-seed (episode mean) metric of candidate ``c`` — a Γ in ms,
    ``"all"`` or any policy label —; ``lower_is_better``: the metric's direction (default:
    :func:`sign_of` ``metric``); ``selects[c]``: its mean count of selected cameras
    (candidates with 0 are excluded; None: all eligible); ``ordered``: the candidates are
    points of a sweep in Γ (their order defines the ends, so ``interior`` is judged), else
    policies without an order (``interior`` is False, ``ends`` empty, no range);
    ``position[c]``: where ``c`` lies along the sweep (the caller's Γ of each candidate;
    default :func:`sweep_position`)."""
    if lower_is_better is None:
        lower_is_better = sign_of(metric) < 0
    if not values:
        raise ValueError("no candidates")
    excluded = tuple(c for c in values
                     if selects is not None and not (selects.get(c, 0.0) > 0.0))
    eligible = [c for c in values if c not in excluded]
    if not eligible:
        raise ValueError(f"no candidate selects a frame ({list(values)})")
    sign = -1.0 if lower_is_better else 1.0
    common = set.intersection(*({s for s, v in values[c].items() if math.isfinite(v)}
                                for c in eligible))
    seeds = tuple(sorted(common))
    if not seeds:
        raise ValueError(f"no seed has a finite {metric} for every candidate")
    signed = {c: {s: sign * float(values[c][s]) for s in seeds} for c in eligible}
    means = {c: float(np.mean(list(signed[c].values()))) for c in eligible}
    best = max(eligible, key=lambda c: means[c])  # first of equal means
    to_best = {c: paired_difference(signed[best], signed[c], level) for c in eligible}
    members = tuple(c for c in eligible
                    if c == best or not (to_best[c].significant and to_best[c].mean > 0))
    ends: tuple[Any, ...] = ()
    interior = False
    places = ({c: position[c] if position is not None and c in position
               else sweep_position(c) for c in eligible} if ordered else {})
    if ordered and len(eligible) >= 3:
        order = sorted(eligible, key=places.__getitem__)
        ends = (order[0], order[-1])
        interior = interior_maximum((to_best[e].mean, to_best[e].half) for e in ends)
    return Optimum(metric=metric, best=best, members=members, to_best=to_best,
                   excluded=excluded, seeds=seeds, ends=ends, interior=interior,
                   positions=places)


def optima(rows: Iterable[Mapping[str, Any]], metrics: Sequence[str], *,
           candidate: Callable[[Mapping[str, Any]], Any] = lambda r: r["policy"],
           selects: Mapping[Any, float] | None = None, ordered: bool = True,
           position: Mapping[Any, float] | None = None) -> dict[str, Optimum]:
    """:func:`optimum` for each of ``metrics`` over ``rows`` — one per episode, with its
    ``seed``, the metrics' values (None: not measured) and whatever ``candidate`` reads its
    candidate from (default: its ``policy``). Metrics the criterion cannot judge (no finite
    value on a common seed, no eligible candidate) are left out."""
    rows = list(rows)
    out: dict[str, Optimum] = {}
    for metric in metrics:
        values: dict[Any, dict[int, float]] = {}
        for r in rows:
            v = r.get(metric)
            values.setdefault(candidate(r), {})[int(r["seed"])] = (
                math.nan if v is None else float(v))
        try:
            out[metric] = optimum(values, metric=metric, selects=selects, ordered=ordered,
                                  position=position)
        except ValueError:
            continue
    return out


def unpaired_interior_maximum(results: Sequence[Mapping[str, Any]], metric: str
                              ) -> dict[str, Any] | None:
    """Whether the best policy by ``metric`` is an interior maximum beyond its uncertainty,
    judged on *unpaired* samples (``aoi3d live sweep``: its windows are different renders of a
    running pipeline, so each policy's renders are an independent sample).

    ``results``: one per policy, in sweep order (fresh to stale; the first and the last are
    the ends), each with its ``policy`` and ``{"mean", "ci95", "n"}`` per metric. The maximum
    is *interior* when the best mean is neither end's, and *beyond its confidence interval*
    when :func:`aoi3d.stats.interior_maximum` holds on the Welch intervals of best − each end
    (:func:`sign_of` says which side is better). None when the metric is missing or
    fewer than three policies were measured.
    """
    sign = sign_of(metric)
    stat = [r.get(metric) or {} for r in results]
    if len(results) < 3 or any(s.get("mean") is None for s in stat):
        return None
    means = [sign * s["mean"] for s in stat]
    best = max(range(len(means)), key=means.__getitem__)
    interior = 0 < best < len(means) - 1
    ends = {}
    for end in (0, len(means) - 1):
        half = welch_ci95(stat[best], stat[end])
        diff = sign * (means[best] - means[end])
        ends[results[end]["policy"]] = {"difference": diff, "ci95": half}
    separated = interior and interior_maximum((sign * e["difference"], e["ci95"])
                                              for e in ends.values())
    return {"best": results[best]["policy"], "best_mean": stat[best]["mean"],
            "interior": interior, "beyond_ci": bool(separated), "best_minus_end": ends}


def rederived(doc: Mapping[str, Any], metrics: Sequence[str], *, ordered: bool
              ) -> dict[str, Any]:
    """``doc`` (the ``results.json`` of ``tradeoff``, ``delay`` or ``compare``) with its optima
    for ``metrics`` taken from its episodes by the same criterion the command applies — for a
    metric the command does not judge, such as the display-time scores every episode carries.
    ``ordered``: the candidates are a MAT sweep's Γ (``tradeoff``, ``delay``: Γ from the policy
    objects, `all` at ∞), else the policies by label (``compare``; its bounds left out). A
    ``delay`` document's rows (``optima``) each get their delay's ``optimum`` of the first
    metric."""
    from aoi3d.policy import PolicySpecError, parse_policy

    def gamma(label: str) -> float | None:
        try:
            g = getattr(parse_policy(label), "gamma_ms", None)
        except PolicySpecError:
            return None
        return None if g is None else float(g)

    def candidate(label: str) -> Any:
        g = gamma(label) if ordered else None
        return label if g is None else g

    bounds = {r["policy"] for r in doc.get("policies", []) if r.get("bound")}
    episodes = [e for e in doc["episodes"] if e["policy"] not in bounds]

    def judge(rows: Sequence[Mapping[str, Any]]) -> dict[str, Any]:
        selected: dict[Any, list[float]] = {}
        for r in rows:
            selected.setdefault(candidate(r["policy"]), []).append(float(r["n_selected"]))
        position: dict[Any, float] | None = (
            {candidate(r["policy"]): _or_inf(gamma(r["policy"])) for r in rows}
            if ordered else None)
        got = optima(rows, metrics, candidate=lambda r: candidate(r["policy"]),
                     selects={c: float(np.mean(v)) for c, v in selected.items()},
                     ordered=ordered, position=position)
        return {m: o.to_dict() for m, o in got.items()}

    out = dict(doc)
    if "optima" in doc:  # delay: one optimum per delay
        out["optima"] = [{**row, "optimum": judge([e for e in episodes
                                                   if e["delay"] == row["delay"]])[metrics[0]]}
                         for row in doc["optima"]]
    else:
        out["optimum"] = judge(episodes)
    return out


def _or_inf(gamma: float | None) -> float:
    """A policy's Γ as a position on the Γ axis: a policy without one (all) sits at +∞."""
    return math.inf if gamma is None else gamma
