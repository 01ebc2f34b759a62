"""The optimum criterion (aoi3d.experiment.optimum) on data whose answer is known by
construction: paired by seed, ends judged, Γ that select nothing left out."""

from __future__ import annotations

import math

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from scipy import stats

from aoi3d.experiment.optimum import (
    LOWER_IS_BETTER,
    optima,
    optimum,
    paired_difference,
    sign_of,
)

GAMMAS = [40.0, 70.0, 100.0, 130.0, 160.0, "all"]


def sweep(curve: dict, seeds: int = 8, *, seed_sd: float = 3.0, noise_sd: float = 0.2,
          rng_seed: int = 0) -> dict:
    """values[Γ][seed] = curve[Γ] + a per-seed effect shared by every Γ (the channel draw
    and scene phase of the seed) + a little independent noise."""
    rng = np.random.default_rng(rng_seed)
    shared = rng.normal(0.0, seed_sd, seeds)
    return {g: {s: curve[g] + shared[s] + rng.normal(0.0, noise_sd) for s in range(seeds)}
            for g in curve}


def test_a_peak_built_in_is_found_and_is_interior() -> None:
    curve = dict(zip(GAMMAS, [22.0, 26.0, 27.0, 26.0, 25.0, 24.0], strict=True))
    values = sweep(curve)
    opt = optimum(values)
    assert opt.best == 100.0 and opt.members == (100.0,)
    assert opt.ends == (40.0, "all") and opt.interior
    assert opt.range_of() == (100.0, 100.0)
    # The seed effect (sd 3 dB) hides the 1 dB steps from unpaired bands; pairing does not.
    a, b = list(values[100.0].values()), list(values[70.0].values())
    assert stats.ttest_ind(a, b).pvalue > 0.05
    assert stats.ttest_rel(a, b).pvalue < 0.05


def test_a_monotone_curve_is_not_interior() -> None:
    curve = dict(zip(GAMMAS, [22.0, 24.0, 25.0, 26.0, 27.0, 28.0], strict=True))
    opt = optimum(sweep(curve))
    assert opt.best == "all" and not opt.interior


def test_a_flat_top_gives_a_range_and_an_end_in_it_is_not_interior() -> None:
    curve = dict(zip(GAMMAS, [22.0, 27.0, 27.0, 27.0, 25.0, 24.0], strict=True))
    opt = optimum(sweep(curve, noise_sd=0.3))
    assert set(opt.members) == {70.0, 100.0, 130.0} and opt.range_of() == (70.0, 130.0)
    assert opt.interior
    tied_end = dict(curve, all=27.0)
    assert not optimum(sweep(tied_end, noise_sd=0.3)).interior


def test_thresholds_that_select_nothing_are_left_out() -> None:
    curve = {0.0: 30.0, 40.0: 24.0, 70.0: 27.0, 100.0: 25.0, "all": 23.0}
    values = sweep(curve)
    selects = {0.0: 0.0, 40.0: 2.5, 70.0: 6.0, 100.0: 9.0, "all": 18.0}
    opt = optimum(values, selects=selects)
    assert opt.excluded == (0.0,) and 0.0 not in opt.to_best
    assert opt.best == 70.0 and opt.ends == (40.0, "all") and opt.interior
    # Without the selection counts Γ = 0 would have won (a broken render scoring high).
    assert optimum(values).best == 0.0
    with pytest.raises(ValueError, match="selects a frame"):
        optimum({0.0: {0: 1.0, 1: 2.0}}, selects={0.0: 0.0})


def test_lower_is_better_and_unordered_policies() -> None:
    lpips = {"all": {0: 0.20, 1: 0.22, 2: 0.21}, "mat:70": {0: 0.10, 1: 0.12, 2: 0.11},
             "freshest:6": {0: 0.11, 1: 0.12, 2: 0.12}}
    opt = optimum(lpips, metric="lpips", lower_is_better=True, ordered=False)
    assert opt.best == "mat:70" and "all" not in opt.members
    assert opt.ends == () and not opt.interior
    assert opt.to_best["all"].mean == pytest.approx(0.10) and opt.to_best["all"].significant


def test_the_direction_is_stated_once_and_optima_applies_it_per_metric() -> None:
    # stated once, in aoi3d/metric.py's table: LPIPS at the decision's and at display time
    assert {"lpips", "lpips_display"} == LOWER_IS_BETTER
    assert sign_of("lpips") == sign_of("lpips_display") == -1.0 and sign_of("ssim") == 1.0
    means = (("all", 20.0, 0.30), ("mat:70", 22.0, 0.20), ("wait:40", 21.0, 0.25))
    rows = [{"policy": p, "seed": s, "psnr": psnr + 0.1 * s, "lpips": lp + 0.01 * s, "ssim": None}
            for s in range(3) for p, psnr, lp in means]
    out = optima(rows, ("psnr", "lpips", "ssim"), ordered=False)
    assert set(out) == {"psnr", "lpips"}  # no finite SSIM: left out
    assert out["psnr"].best == "mat:70" and out["lpips"].best == "mat:70"  # lowest LPIPS
    # the default direction is the metric's: the same as saying it
    lp = {p: {r["seed"]: r["lpips"] for r in rows if r["policy"] == p} for p in ("all", "mat:70")}
    assert (optimum(lp, metric="lpips", ordered=False).best
            == optimum(lp, metric="lpips", lower_is_better=True, ordered=False).best == "mat:70")


def test_one_seed_decides_nothing_and_seeds_are_paired() -> None:
    opt = optimum({40.0: {3: 1.0}, 70.0: {3: 5.0}, 100.0: {3: 2.0}})
    assert opt.best == 70.0 and set(opt.members) == {40.0, 70.0, 100.0} and not opt.interior
    # Only the seeds every candidate has are used.
    opt = optimum({40.0: {1: 1.0, 2: 1.1, 3: 9.0}, 70.0: {1: 2.0, 2: 2.1}})
    assert opt.seeds == (1, 2)
    nan = optimum({40.0: {1: math.nan, 2: 1.0, 3: 1.2}, 70.0: {1: 5.0, 2: 2.0, 3: 2.1}})
    assert nan.seeds == (2, 3)


@settings(max_examples=60, deadline=None)
@given(st.lists(st.floats(-5, 5), min_size=3, max_size=6),
       st.integers(2, 12), st.floats(0.0, 10.0), st.integers(0, 2**32 - 1))
def test_properties(levels: list[float], seeds: int, seed_sd: float, rng_seed: int) -> None:
    curve = {float(10 * (i + 1)): v for i, v in enumerate(levels)}
    values = sweep(curve, seeds, seed_sd=seed_sd, noise_sd=0.5, rng_seed=rng_seed)
    opt = optimum(values)
    assert opt.best in opt.members and set(opt.members) <= set(curve)
    means = {g: np.mean(list(v.values())) for g, v in values.items()}
    assert means[opt.best] == max(means.values())
    # A per-seed offset common to every candidate changes nothing: differences are paired.
    shift = np.random.default_rng(rng_seed).normal(0, 100, seeds)
    shifted = {g: {s: v + shift[s] for s, v in per.items()} for g, per in values.items()}
    again = optimum(shifted)
    assert again.best == opt.best and again.members == opt.members
    # Flipping the sign with lower_is_better gives the same answer.
    flipped = {g: {s: -v for s, v in per.items()} for g, per in values.items()}
    assert optimum(flipped, lower_is_better=True).members == opt.members
    # A member is exactly a candidate whose paired test against the best is not significant
    # in the best's favour (scipy's paired t test as the reference).
    for g in curve:
        if g == opt.best:
            continue
        a = [values[opt.best][s] for s in range(seeds)]
        b = [values[g][s] for s in range(seeds)]
        p = stats.ttest_rel(a, b).pvalue
        if math.isfinite(p) and abs(p - 0.05) > 1e-6:
            assert (g in opt.members) == (p > 0.05), (g, p)


def test_paired_difference_matches_scipy() -> None:
    a = {0: 1.0, 1: 2.5, 2: 3.0, 3: 4.2}
    b = {0: 0.5, 1: 2.0, 2: 3.1, 3: 3.0, 9: 100.0}
    d = paired_difference(a, b)
    res = stats.ttest_rel([1.0, 2.5, 3.0, 4.2], [0.5, 2.0, 3.1, 3.0])
    lo, hi = res.confidence_interval()
    assert d.n == 4 and d.mean == pytest.approx((lo + hi) / 2)
    assert d.half == pytest.approx((hi - lo) / 2)
    assert math.isnan(paired_difference({0: 1.0}, {0: 2.0}).half)
