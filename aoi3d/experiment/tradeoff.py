"""The tradeoff along a MAT sweep: its policies (:class:`MatSweep`), the points of the curve
(:func:`tradeoff_rows`), the best Γ (:func:`best_gamma`), the optimum set per metric paired by
seed (:func:`sweep_optima`), a delay's row of the optimal-Γ-vs-delay table
(:func:`delay_optimum_row`) and the renders beside the truth (:func:`view_grid`): what
``aoi3d experiment tradeoff``, ``views``, ``delay`` and ``compare`` compute and write."""

from __future__ import annotations

import math
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
from PIL import Image

from aoi3d.experiment.episode import EpisodeResult
from aoi3d.experiment.optimum import Optimum, optima, sign_of
from aoi3d.experiment.sweep import Job, ResultCache, SweepOutcome, aggregate
from aoi3d.metric import AT_DECISION
from aoi3d.numbers import format_number
from aoi3d.policy import AllPolicy, MatPolicy, Policy
from aoi3d.scene import SceneDataset

__all__ = ["OPTIMUM_METRICS", "MatSweep", "best_gamma", "delay_optimum_row", "sweep_optima",
           "tradeoff_rows", "view_grid"]

OPTIMUM_METRICS = AT_DECISION
"""Metrics an optimum can be taken over: the scores at the decision's time,
:data:`aoi3d.metric.AT_DECISION` (their direction: :mod:`aoi3d.metric`); ``*_dynamic*``: over
the dynamic region (:mod:`aoi3d.quality`)."""


@dataclass(frozen=True)
class MatSweep:
    """A MAT sweep's policies, by the label their results carry: ``MatPolicy(Γ)`` for each Γ,
    then ``AllPolicy`` (the reference, at Γ = ∞). Γ is read from the policy objects built
    here, never parsed back out of a label."""

    policies: dict[str, Policy]

    @classmethod
    def of(cls, gammas: Sequence[float]) -> MatSweep:
        built: list[Policy] = [MatPolicy(float(g)) for g in gammas]
        built.append(AllPolicy())
        return cls({p.spec: p for p in built})

    def gamma(self, label: str) -> float | None:
        """Γ (ms) of the sweep's policy ``label``; None for the reference."""
        return self.policies[label].gamma_ms

    def candidate(self, label: str) -> Any:
        """A tradeoff candidate: Γ in ms for a MAT point, else the label (``all``)."""
        gamma = self.gamma(label)
        return label if gamma is None else gamma

    def position(self) -> dict[Any, float]:
        """Where each candidate lies along the sweep: Γ, and ∞ for the reference."""
        return {self.candidate(label): math.inf if p.gamma_ms is None else p.gamma_ms
                for label, p in self.policies.items()}

    def jobs(self, delays: Sequence[str], seeds: Sequence[int]) -> list[Job]:
        return [Job(label, d, s) for s in seeds for d in delays for label in self.policies]


def tradeoff_rows(results: Sequence[EpisodeResult], sweep: MatSweep
                  ) -> tuple[list[dict[str, Any]], dict[str, Any] | None]:
    """The sweep's points (:func:`~aoi3d.experiment.sweep.aggregate` rows with ``gamma_ms``
    first, by Γ) and the reference's row (None without one)."""
    rows = aggregate(results)
    points = []
    reference = None
    for row in rows:
        gamma = sweep.gamma(row["policy"])
        if gamma is None:
            reference = row
        else:
            points.append({"gamma_ms": gamma, **row})
    points.sort(key=lambda r: r["gamma_ms"])
    return points, reference


def best_gamma(points: Sequence[dict[str, Any]], metric: str = "psnr_db") -> float:
    """The swept Γ with the best mean ``metric`` (highest; lowest for a lower-is-better one,
    LPIPS)."""
    sign = sign_of(metric)
    values = np.array([np.nan if p[metric] is None else sign * p[metric] for p in points],
                      float)
    if not np.isfinite(values).any():
        raise RuntimeError(f"no finite {metric} in the sweep")
    return float(points[int(np.nanargmax(values))]["gamma_ms"])


def sweep_optima(results: Sequence[EpisodeResult], *, sweep: MatSweep | None = None
                 ) -> dict[str, Optimum]:
    """Per metric of :data:`OPTIMUM_METRICS`, :func:`aoi3d.experiment.optimum.optima` over the
    policies of ``results`` (one delay), paired by seed: the points of a MAT ``sweep`` (its
    candidates are Γ, ordered along it), or, without one, policies by their label
    (unordered)."""
    label: Callable[[str], Any] = sweep.candidate if sweep is not None else str

    selects: dict[Any, list[float]] = {}
    for r in results:
        selects.setdefault(label(r.policy), []).append(float(r.n_selected))
    rows = [{"candidate": label(r.policy), "seed": r.seed,
             **{m: getattr(r, m) for m in OPTIMUM_METRICS}} for r in results]
    return optima(rows, OPTIMUM_METRICS, candidate=lambda row: row["candidate"],
                  selects={c: float(np.mean(v)) for c, v in selects.items()},
                  ordered=sweep is not None,
                  position=sweep.position() if sweep is not None else None)


def delay_optimum_row(delay: str, mean_delay_ms: float, results: Sequence[EpisodeResult],
                      points: Sequence[dict[str, Any]], sweep: MatSweep, metric: str
                      ) -> dict[str, Any]:
    """One delay's row of ``aoi3d experiment delay``: per metric of :data:`OPTIMUM_METRICS`
    the best Γ, its mean and CI, the optimum set's span and whether it is interior (the
    chosen ``metric`` unsuffixed, with its whole :class:`Optimum` as ``optimum``; the others
    suffixed ``_<metric>``); ``results`` and ``points`` are that delay's."""
    row: dict[str, Any] = {"delay": delay, "mean_delay_ms": mean_delay_ms, "metric": metric}
    for name, opt in sweep_optima(results, sweep=sweep).items():
        by_gamma = {p["gamma_ms"]: p for p in points}
        span = opt.range_of() or (math.nan, math.nan)
        suffix = "" if name == metric else f"_{name}"
        row.update({f"best_gamma_ms{suffix}": opt.best,
                    f"best{suffix or '_value'}": by_gamma[opt.best][name],
                    f"best_ci95{suffix}": by_gamma[opt.best][f"{name}_ci95"],
                    f"optimum_min_ms{suffix}": span[0],
                    f"optimum_max_ms{suffix}": span[1],
                    f"interior{suffix}": opt.interior})
        if name == metric:
            row["optimum"] = opt.to_dict()
    return row


def view_grid(outcome: SweepOutcome, sweep: MatSweep, seeds: Sequence[int], ds: SceneDataset,
              cache: ResultCache, out: Path
              ) -> tuple[list[list[tuple[str, np.ndarray]]], list[str]]:
    """``aoi3d experiment views``' figure rows, one per seed of ``seeds``: the truth at the
    episode's last scored decision, then each policy's render of it (copied from ``cache`` to
    ``out/view_seed<seed>_<policy>.png``; earlier ones there are removed first), each with its
    label; and the names of the files written."""
    grid: list[list[tuple[str, np.ndarray]]] = []
    saved = []
    for old in out.glob("view_seed*.png"):  # renders of an earlier run of this folder
        old.unlink()
    for seed in seeds:
        members = [(r, p, k) for r, p, k in zip(outcome.results, outcome.plans, outcome.keys,
                                                strict=True) if r.seed == seed]
        plan = members[0][1]
        last = [d for d in plan.decisions if d.scored][-1]
        truth_index = ds.frame_index(last.eval_ms + plan.scene_offset_ms)
        row = [(f"truth, t = {last.eval_ms} ms", ds.frame(ds.heldout_id, truth_index))]
        for result, _, key in members:
            png = cache.render_png(key)
            if png is None:
                raise RuntimeError(f"render of {result.policy} missing from the cache ({key})")
            name = out / f"view_seed{seed}_{result.policy.replace(':', '')}.png"
            name.write_bytes(png)
            saved.append(name.name)
            image = np.asarray(Image.open(name).convert("RGB"))
            score = result.epochs[-1]
            gamma = sweep.gamma(result.policy)
            label = "all" if gamma is None else f"Γ = {format_number(gamma)} ms"
            row.append((f"{label}\n{score.psnr_db:.1f} dB, {score.n_selected} cams", image))
        grid.append(row)
    return grid, saved
