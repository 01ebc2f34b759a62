"""The project's statistics, in one place: the 95% intervals and the one interior-maximum test.

* :func:`mean_ci95` — the mean of the finite values and the half-width of its 95% confidence
  interval (Student t, n − 1 degrees of freedom), as a :class:`MeanCI` (a named tuple; its
  :meth:`MeanCI.to_dict` is the ``{"mean", "ci95", "n"}`` the JSON outputs write).
* :func:`paired_difference` — ``a − b`` paired by seed (the experiments run every policy on
  the same seeds), with its 95% interval.
* :func:`welch_ci95` — the 95% interval of the difference of two *independent* means
  (Welch–Satterthwaite): the live pipeline's windows are different renders, not paired seeds.
* :func:`interior_maximum` — THE criterion for "the best lies strictly inside the sweep,
  beyond its uncertainty": both ends are significantly worse than the best. The virtual
  clock's optimum (:func:`aoi3d.experiment.optimum.optimum`, paired differences) and the live
  sweep's (:func:`aoi3d.experiment.optimum.unpaired_interior_maximum`, Welch differences) both
  decide with it; they differ only in how the difference to each end is measured.

Pure numpy/scipy; no other aoi3d module.
"""

from __future__ import annotations

import math
from collections.abc import Iterable, Mapping
from dataclasses import dataclass
from typing import Any, NamedTuple

import numpy as np
from scipy import stats

__all__ = ["LEVEL", "MeanCI", "PairedDifference", "interior_maximum", "mean_ci95",
           "paired_difference", "welch_ci95"]

LEVEL = 0.95
"""Confidence level of every interval of the project."""


class MeanCI(NamedTuple):
    """Mean, half-width of its 95% interval (NaN below two values) and the count of values."""

    mean: float
    half: float
    n: int

    def to_dict(self) -> dict[str, float | int | None]:
        """``{"mean", "ci95", "n"}``, None for what is undefined (JSON has no NaN)."""
        return {"mean": None if not math.isfinite(self.mean) else self.mean,
                "ci95": None if not math.isfinite(self.half) else self.half, "n": self.n}


def mean_ci95(values: Iterable[float | None]) -> MeanCI:
    """Mean, half-width of the 95% confidence interval (Student t) and the count of the
    finite values (None and NaN are left out); the half-width is NaN below two values."""
    arr = np.asarray([np.nan if v is None else v for v in values], dtype=np.float64)
    arr = arr[np.isfinite(arr)]
    n = int(arr.size)
    if n == 0:
        return MeanCI(math.nan, math.nan, 0)
    mean = float(arr.mean())
    if n < 2:
        return MeanCI(mean, math.nan, n)
    half = float(stats.t.ppf(0.975, n - 1) * arr.std(ddof=1) / math.sqrt(n))
    return MeanCI(mean, half, n)


def welch_ci95(a: MeanCI | Mapping[str, Any], b: MeanCI | Mapping[str, Any]) -> float | None:
    """Half-width of the 95% CI of ``mean(a) − mean(b)`` for two *independent* (unpaired)
    samples, each a :class:`MeanCI` or its :meth:`~MeanCI.to_dict` (Welch–Satterthwaite
    degrees of freedom); None when either lacks a CI."""
    a, b = _as_dict(a), _as_dict(b)
    if a.get("ci95") is None or b.get("ci95") is None or a["n"] < 2 or b["n"] < 2:
        return None
    # back from each half-width to its variance of the mean
    va = (a["ci95"] / stats.t.ppf(0.975, a["n"] - 1)) ** 2
    vb = (b["ci95"] / stats.t.ppf(0.975, b["n"] - 1)) ** 2
    if va + vb == 0:
        return 0.0
    dof = (va + vb) ** 2 / (va ** 2 / (a["n"] - 1) + vb ** 2 / (b["n"] - 1))
    return float(stats.t.ppf(0.975, dof) * math.sqrt(va + vb))


def _as_dict(x: MeanCI | Mapping[str, Any]) -> Mapping[str, Any]:
    return x.to_dict() if isinstance(x, MeanCI) else x


@dataclass(frozen=True)
class PairedDifference:
    """Mean of ``a − b`` over the seeds both have, the half-width of its confidence interval
    (NaN below two seeds) and the count of seeds."""

    mean: float
    half: float
    n: int

    @property
    def significant(self) -> bool:
        """Whether the interval excludes zero."""
        return math.isfinite(self.half) and abs(self.mean) > self.half

    def to_dict(self) -> dict[str, Any]:
        return {"mean": self.mean, "ci95": self.half, "n": self.n}


def paired_difference(a: Mapping[int, float], b: Mapping[int, float],
                      level: float = LEVEL) -> PairedDifference:
    """``a − b`` paired by seed (the keys), over the seeds where both are finite."""
    seeds = sorted(s for s in a.keys() & b.keys()
                   if math.isfinite(a[s]) and math.isfinite(b[s]))
    d = np.array([a[s] - b[s] for s in seeds], dtype=np.float64)
    n = int(d.size)
    if n == 0:
        return PairedDifference(math.nan, math.nan, 0)
    if n < 2:
        return PairedDifference(float(d[0]), math.nan, 1)
    half = float(stats.t.ppf(0.5 + level / 2, n - 1) * d.std(ddof=1) / math.sqrt(n))
    return PairedDifference(float(d.mean()), half, n)


def interior_maximum(best_minus_ends: Iterable[tuple[float, float | None]]) -> bool:
    """The one interior-maximum criterion: the best of an ordered sweep is an interior
    maximum beyond its uncertainty when *both* ends are significantly worse than it — for each
    end, the difference best − end, taken in the metric's better direction, exceeds the
    half-width of its 95% confidence interval (a finite one: an unknown interval never
    separates). A best at an end is never interior: its difference to itself is 0.

    ``best_minus_ends``: ``(difference, half-width)`` for the two ends."""
    ends = list(best_minus_ends)
    if len(ends) != 2:
        raise ValueError(f"a sweep has two ends, got {len(ends)}")
    return all(half is not None and math.isfinite(half) and diff > half for diff, half in ends)
