"""aoi3d/stats.py: the one home of the project's intervals and of the interior-maximum test."""

from __future__ import annotations

import math
import re
from pathlib import Path

import numpy as np
import pytest
from scipy import stats as sp

from aoi3d.stats import MeanCI, interior_maximum, mean_ci95, paired_difference, welch_ci95

ROOT = Path(__file__).resolve().parents[3]


def test_mean_ci95_is_student_t_over_the_finite_values() -> None:
    xs = [1.0, 2.0, 4.0, None, math.nan]
    got = mean_ci95(xs)
    lo, hi = sp.t.interval(0.95, 2, loc=np.mean([1, 2, 4]), scale=sp.sem([1, 2, 4]))
    assert got.n == 3 and got.mean == pytest.approx(7 / 3)
    assert got.half == pytest.approx((hi - lo) / 2)
    mean, half, n = got  # a named tuple: unpacks as before
    assert (mean, half, n) == tuple(got)
    assert mean_ci95([5.0]).to_dict() == {"mean": 5.0, "ci95": None, "n": 1}
    assert mean_ci95([]).to_dict() == {"mean": None, "ci95": None, "n": 0}


def test_welch_takes_either_form_and_needs_two_intervals() -> None:
    a, b = mean_ci95([1.0, 2.0, 3.0]), mean_ci95([2.0, 4.0, 6.0, 8.0])
    assert welch_ci95(a, b) == welch_ci95(a.to_dict(), b.to_dict()) > 0
    assert welch_ci95(a, MeanCI(1.0, math.nan, 1)) is None


def test_interior_maximum_needs_both_ends_beyond_their_interval() -> None:
    assert interior_maximum([(2.0, 1.0), (0.5, 0.4)])
    assert not interior_maximum([(2.0, 1.0), (0.5, 0.6)])  # one end not separated
    assert not interior_maximum([(0.0, 0.0), (3.0, 1.0)])  # the best is an end
    assert not interior_maximum([(2.0, None), (3.0, 1.0)])  # an unknown interval
    assert not interior_maximum([(2.0, math.nan), (3.0, 1.0)])
    with pytest.raises(ValueError):
        interior_maximum([(1.0, 0.1)])


def test_the_paired_criterion_is_the_same_test() -> None:
    """optimum()'s interior (the optimum set holds neither end) is interior_maximum on the
    paired differences best − end."""
    from aoi3d.experiment.optimum import optimum

    rng = np.random.default_rng(1)
    for _ in range(50):
        curve = rng.normal(0, 1, 4)
        values = {g: {s: curve[i] + rng.normal(0, 0.5) for s in range(4)}
                  for i, g in enumerate((40, 70, 100, "all"))}
        opt = optimum(values)
        by_set = not any(e in opt.members for e in opt.ends)
        assert opt.interior == by_set
        signed = {c: values[c] for c in values}
        d = [paired_difference(signed[opt.best], signed[e]) for e in opt.ends]
        assert opt.interior == interior_maximum((x.mean, x.half) for x in d)


def test_one_home_for_each_statistic() -> None:
    """No module but aoi3d/stats.py defines mean_ci95, welch_ci95 or an interval by hand."""
    offenders = []
    for path in [*ROOT.glob("aoi3d/**/*.py"), *ROOT.glob("bench/*.py"),
                 *ROOT.glob("services/**/*.py")]:
        if path.name == "stats.py" and path.parent.name == "aoi3d":
            continue
        text = path.read_text()
        if re.search(r"def (mean_ci95|welch_ci95|paired_difference|interior_maximum)\b|"
                     r"t\.ppf\(0\.975", text):
            offenders.append(str(path.relative_to(ROOT)))
    assert offenders == []
