"""The experiments' claims (docs/research.md; aoi3d.experiment.claims) hold on data built to
satisfy them and fail on data built to break them."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from aoi3d.experiment import claims
from aoi3d.experiment.optimum import optimum

SEEDS = range(20000, 20008)


def per_seed(curve: dict, rng_seed: int = 0, noise: float = 0.2) -> dict:
    rng = np.random.default_rng(rng_seed)
    shared = {s: rng.normal(0, 3.0) for s in SEEDS}
    return {g: {s: v + shared[s] + rng.normal(0, noise) for s in SEEDS} for g, v in curve.items()}


def tradeoff_doc(curves: dict[str, tuple[dict, float]]) -> dict:
    """A results.json of `experiment tradeoff` as far as the claims read it (JSON round trip,
    as bench/science.py reads it)."""
    selects = {g: (0.0 if g == 0.0 else 5.0) for g in PEAK}
    opt = {}
    for i, (m, (curve, k)) in enumerate(curves.items()):
        values = {g: {s: k * v for s, v in per.items()} for g, per in per_seed(curve, i).items()}
        opt[m] = optimum(values, metric=m, lower_is_better=m == "lpips",
                         selects=selects).to_dict()
    return json.loads(json.dumps({"meta": {"args": {"delay": "exp:60"}}, "optimum": opt}))


PEAK = {0.0: 12.0, 40.0: 22.0, 70.0: 26.0, 100.0: 27.0, 130.0: 26.0, 160.0: 25.0, "all": 24.0}
RISING = {0.0: 12.0, 40.0: 22.0, 70.0: 23.0, 100.0: 24.0, 130.0: 25.0, 160.0: 26.0, "all": 27.0}


def test_interior_and_agreement_hold_on_a_peak_and_fail_on_a_rise() -> None:
    good = tradeoff_doc({"psnr_db": (PEAK, 1.0), "ssim": (PEAK, 0.03),
                         "lpips": (PEAK, -0.01), "reward": (PEAK, 0.03)})
    assert claims.tradeoff_interior_optimum(good).holds
    assert claims.scores_agree_on_the_optimum(good).holds
    bad = tradeoff_doc({"psnr_db": (RISING, 1.0), "ssim": (PEAK, 0.03),
                        "lpips": (RISING, -0.01), "reward": (PEAK, 0.03)})
    verdict = claims.tradeoff_interior_optimum(bad)
    assert not verdict.holds and "best Γ = all" in verdict.evidence
    assert not claims.scores_agree_on_the_optimum(bad).holds  # LPIPS best at `all`
    # Γ = 0 (selects nothing) cannot make a rising curve look interior.
    assert claims.tradeoff_interior_optimum(bad).numbers["optimum"]["excluded"] == [0.0]


def test_the_dynamic_region_claim_reads_its_own_metric() -> None:
    # Full-image PSNR peaks while the blades' PSNR rises to `all`: the dynamic claim fails
    # on its own numbers, not on the full image's.
    doc = tradeoff_doc({"psnr_db": (PEAK, 1.0), "psnr_dynamic_db": (RISING, 1.0)})
    assert claims.tradeoff_interior_optimum(doc).holds
    verdict = claims.tradeoff_interior_optimum(doc, metric="psnr_dynamic_db")
    assert verdict.claim == "interior-psnr_dynamic_db" and not verdict.holds
    assert "dynamic-region PSNR" in verdict.statement
    flipped = tradeoff_doc({"psnr_db": (RISING, 1.0), "psnr_dynamic_db": (PEAK, 1.0)})
    assert claims.tradeoff_interior_optimum(flipped, metric="psnr_dynamic_db").holds


def delay_doc(peaks: dict[float, float]) -> dict:
    optima = []
    for i, (mean_delay, peak) in enumerate(peaks.items()):
        curve = {g: 27.0 - abs(g - peak) / 15.0 for g in (40.0, 70.0, 100.0, 130.0, 160.0)}
        opt = optimum(per_seed(curve, i, noise=0.3), ordered=True).to_dict()
        optima.append({"mean_delay_ms": mean_delay, "optimum": opt})
    return json.loads(json.dumps({"optima": optima}))


def test_growth_holds_when_the_peak_moves_up_and_fails_when_it_does_not() -> None:
    assert claims.optimal_gamma_grows_with_delay(delay_doc({20: 40, 60: 70, 100: 130})).holds
    assert not claims.optimal_gamma_grows_with_delay(delay_doc({20: 100, 100: 100})).holds
    assert not claims.optimal_gamma_grows_with_delay(delay_doc({20: 130, 100: 40})).holds
    # A best Γ that grows, but stays inside the other delay's optimum set, is not enough.
    close = delay_doc({20: 40, 100: 130})
    close["optima"][1]["optimum"]["members"].append(40.0)
    assert not claims.optimal_gamma_grows_with_delay(close).holds


def eval_doc(ppo_gain: float, *, equal: bool = True) -> dict:
    rng = np.random.default_rng(1)
    base = {"mat:70": 0.90, "mat:100": 0.91, "freshest:6": 0.88, "all": 0.84}
    episodes = []
    for s in range(1005000, 1005040):
        shared = rng.normal(0, 0.05)
        for p, v in base.items():
            episodes.append({"policy": p, "seed": s, "reward": v + shared + rng.normal(0, 0.005)})
        episodes.append({"policy": "ppo:x.pt", "seed": s,
                         "reward": 0.91 + ppo_gain + shared + rng.normal(0, 0.005)})
    return {"meta": {"policies": ["ppo:x.pt", *base], "equal_budget": equal,
                     "trained_steps_per_epoch": 100 if equal else 300,
                     "episode_config": {"steps_per_epoch": 100},
                     "seeds": list(range(1005000, 1005040))},
            "episodes": episodes}


def test_ppo_claims() -> None:
    tied = claims.ppo_reaches_best_mat(eval_doc(0.0))
    assert tied.holds and tied.numbers["best_mat"] == "mat:100"
    assert claims.ppo_reaches_best_mat(eval_doc(0.02)).holds
    worse = claims.ppo_reaches_best_mat(eval_doc(-0.02))
    assert not worse.holds and "significantly worse" in worse.evidence
    # Scored at another budget than it was trained for: the claim is not tested there.
    assert not claims.ppo_reaches_best_mat(eval_doc(0.02, equal=False)).holds
    assert claims.ppo_beats_all(eval_doc(0.0)).holds
    assert not claims.ppo_beats_all(eval_doc(-0.07)).holds


def test_selective_beats_all() -> None:
    values = per_seed({"all": 24.0, "mat:70": 26.0, "freshest:6": 25.8})
    doc = json.loads(json.dumps({"optimum": {"psnr_db": optimum(values, ordered=False)
                                             .to_dict()}}))
    assert claims.compare_selective_beats_all(doc).holds
    values = per_seed({"all": 26.5, "mat:70": 26.0, "freshest:6": 25.8})
    doc = json.loads(json.dumps({"optimum": {"psnr_db": optimum(values, ordered=False)
                                             .to_dict()}}))
    assert not claims.compare_selective_beats_all(doc).holds


def compare_doc(learned: float, oracle: float | None = None) -> dict:
    """A results.json of `experiment compare` with a learned policy ``learned`` dB above the
    best rule, three rules, `all` and (optionally) the PSNR oracle bound ``oracle`` dB above the
    best rule, as far as the claim reads it."""
    nominal = {"all": 24.0, "mat:100": 26.0, "freshest:6": 26.4, "wait:40": 25.0,
               "ppo:agent.pt": 26.4 + learned}
    values = per_seed(nominal)
    episodes = [{"policy": p, "seed": s, "psnr_db": v} for p, per in values.items()
                for s, v in per.items()]
    doc = {"meta": {"seed_list": list(SEEDS), "episode_config": {"steps_per_epoch": 300}},
           "policies": [{"policy": p, "bound": False} for p in values], "episodes": episodes}
    if oracle is not None:
        minus = {p: {"mean": 26.4 + oracle - v, "ci95": 0.1, "n": 8} for p, v in nominal.items()}
        doc["bound"] = {"oracle:rules:psnr_db": {"minus": {"psnr_db": minus}}}
    return json.loads(json.dumps(doc))


def test_learned_beats_best_rule() -> None:
    ahead = claims.learned_beats_best_rule(compare_doc(0.8, oracle=1.0))
    assert ahead.holds and ahead.numbers["best_rule"] == "freshest:6"
    assert "goal ≥ 0.5: met" in ahead.evidence and "within half the distance: yes" in ahead.evidence
    small = claims.learned_beats_best_rule(compare_doc(0.3, oracle=1.0))
    assert small.holds and "goal ≥ 0.5: not met" in small.evidence
    assert "within half the distance: no" in small.evidence
    tied = claims.learned_beats_best_rule(compare_doc(0.0))
    assert not tied.holds and "not significantly different" in tied.evidence
    assert "no oracle bound" in tied.evidence
    worse = claims.learned_beats_best_rule(compare_doc(-0.8))
    assert not worse.holds and "significantly worse" in worse.evidence
    doc = compare_doc(0.8)
    doc["policies"] = [r for r in doc["policies"] if not r["policy"].startswith("ppo:")]
    assert not claims.learned_beats_best_rule(doc).holds


REGIMES = "regimes:exp:20@3s,exp:150@3s"


def regimes_doc(adaptive_gain: float, switching: bool = True) -> dict:
    """A compare run on a two-regime schedule: per scored decision (every 600 ms from 900 ms),
    PSNR per MAT Γ — Γ 40 best in the fast regime, Γ 190 in the slow one (or one curve for
    both when not ``switching``) — a freshest and a wait rule, and an adaptive policy that
    takes each regime's best Γ plus ``adaptive_gain`` dB."""
    rng = np.random.default_rng(5)
    fast = {"mat:40": 27.0, "mat:100": 26.2, "mat:190": 24.0}
    slow = {"mat:40": 20.0, "mat:100": 24.5, "mat:190": 26.0} if switching else fast
    times = [900 + 600 * k for k in range(12)]
    episodes = []
    for s in SEEDS:
        offset = rng.normal(0, 2.0)
        rows: dict[str, list] = {p: [] for p in [*fast, "freshest:6", "wait:40",
                                                   "adaptive:plugin"]}
        for t in times:
            table = fast if (t % 6000) < 3000 else slow
            noise = rng.normal(0, 0.3)
            for p, v in table.items():
                rows[p].append(v + offset + noise + rng.normal(0, 0.1))
            rows["freshest:6"].append(23.0 + offset + noise)
            rows["wait:40"].append(22.0 + offset + noise)
            rows["adaptive:plugin"].append(max(table.values()) + adaptive_gain + offset + noise
                                           + rng.normal(0, 0.1))
        for p, vals in rows.items():
            episodes.append({"policy": p, "seed": s, "psnr_db": float(np.mean(vals)),
                             "epochs": [{"eval_ms": t, "psnr_db": v}
                                        for t, v in zip(times, vals, strict=True)]})
    names = list(dict.fromkeys(e["policy"] for e in episodes))
    return json.loads(json.dumps({
        "meta": {"seed_list": list(SEEDS), "args": {"delay": REGIMES},
                 "episode_config": {"steps_per_epoch": 100}},
        "policies": [{"policy": p, "bound": False} for p in names], "episodes": episodes}))


def test_a_fixed_gamma_loses_when_the_regimes_want_different_ones() -> None:
    v = claims.fixed_gamma_loses_under_changing_channel(regimes_doc(0.0))
    assert v.holds, v.evidence
    g = v.numbers["G"]
    assert g["best_per_regime"] == {"exp:20": "mat:40", "exp:150": "mat:190"}
    assert g["G"]["mean"] > 1.0 and "G = +" in v.evidence
    flat = claims.fixed_gamma_loses_under_changing_channel(regimes_doc(0.0, switching=False))
    assert not flat.holds and flat.numbers["G"]["G"]["mean"] == 0.0
    stationary = regimes_doc(0.0)
    stationary["meta"]["args"]["delay"] = "exp:60"
    assert not claims.fixed_gamma_loses_under_changing_channel(stationary).holds
    assert claims.regime_gain(stationary) is None


def test_the_adaptive_question_reports_g_and_the_oracle_either_way() -> None:
    yes = claims.adaptive_beats_best_rule(regimes_doc(0.3))
    assert yes.holds and yes.numbers["best_adaptive"] == "adaptive:plugin"
    assert yes.numbers["best_rule"] in ("mat:100", "mat:190")
    assert "goal ≥ 0.5 dB: met" in yes.evidence and "G = +" in yes.evidence
    assert "oracle over the rules at t" in yes.evidence
    assert yes.numbers["oracle_rules_at_t_minus_best_rule"]["mean"] > 1.0
    no = claims.adaptive_beats_best_rule(regimes_doc(-3.0, switching=False))
    assert not no.holds and "significantly worse" in no.evidence
    assert "goal ≥ 0.5 dB: not met" in no.evidence
    doc = regimes_doc(0.3)
    doc["policies"] = [r for r in doc["policies"] if not r["policy"].startswith("adaptive:")]
    assert not claims.adaptive_beats_best_rule(doc).holds


SCIENCE = Path(__file__).resolve().parents[3] / "results/science"


@pytest.mark.parametrize("name, ordered", [("tradeoff", True), ("delay", True),
                                           ("compare", False)])
def test_rederived_optimum_is_the_commands_own(name: str, ordered: bool) -> None:
    """Taken again from a recorded run's episodes, the optimum of a metric the command judged
    is exactly the command's (the bound of compare left out): so the display-time verdicts of
    `make science` use the same criterion as the decision-time ones."""
    doc = json.loads((SCIENCE / name / "results.json").read_text())
    metrics = ("psnr_db", "psnr_dynamic_db")
    again = claims.rederived(doc, metrics, ordered=ordered)
    if name == "delay":
        assert [r["optimum"] for r in again["optima"]] == [r["optimum"] for r in doc["optima"]]
    else:
        for m in metrics:
            assert again["optimum"][m] == doc["optimum"][m], m


def test_display_time_verdicts_use_the_display_scores() -> None:
    """at_display_time judges psnr_display_db (here: a copy of a recorded run whose display
    scores are its PSNR shifted per Γ so that the freshest Γ wins) and marks its verdicts."""
    from aoi3d.policy import parse_policy

    docs = {n: json.loads((SCIENCE / n / "results.json").read_text())
            for n in ("tradeoff", "delay", "compare")}
    for name, doc in docs.items():
        for e in doc["episodes"]:
            # display time: the later frames lose more; Γ = 40 ms (and in compare `all`,
            # which the criterion must then find best) far ahead of the rest
            best = (e["policy"] == "all" if name == "compare" else
                    getattr(parse_policy(e["policy"]), "gamma_ms", None) == 40.0)
            e["psnr_display_db"] = e["psnr_db"] - (0.0 if best else 10.0)
            e["psnr_dynamic_display_db"] = e["psnr_display_db"]
    verdicts = claims.at_display_time(docs["tradeoff"], docs["delay"], docs["compare"])
    assert [v.claim for v in verdicts] == [
        "interior-psnr_display_db@display", "interior-psnr_dynamic_display_db@display",
        "gamma-grows-with-delay@display", "selective-beats-all@display"]
    interior = verdicts[0]
    assert interior.numbers["optimum"]["best"] == 40.0
    assert "at display time" in interior.statement
    assert verdicts[2].holds is False  # Γ = 40 is best at every delay: it does not grow
    assert verdicts[3].holds is False and verdicts[3].numbers["optimum"]["best"] == "all"


def test_the_claims_read_a_typed_view_parsed_once() -> None:
    """A document is parsed once (aoi3d.experiment.results); a claim given the view or the
    dict says the same, and quotes the document's own numbers back."""
    import math

    from aoi3d.experiment.results import Difference, Results

    tradeoff = tradeoff_doc({"psnr_db": (PEAK, 1.0), "ssim": (PEAK, 0.03),
                             "lpips": (PEAK, -0.01), "reward": (PEAK, 0.03)})
    view = Results.parse(tradeoff)
    assert Results.parse(view) is view
    assert view.meta.delay == "exp:60" and view.optimum["psnr_db"].raw is tradeoff["optimum"][
        "psnr_db"]
    assert view.optimum["psnr_db"].best == 100.0 and view.optimum["psnr_db"].excluded == (0.0,)
    assert view.episodes == () and view.policies == () and view.optima == ()
    for claim in (claims.tradeoff_interior_optimum, claims.scores_agree_on_the_optimum):
        assert claim(view) == claim(tradeoff)
    compare = compare_doc(0.8, oracle=1.0)
    parsed = Results.parse(compare)
    assert parsed.per_seed("all", "psnr_db") == {
        e["seed"]: e["psnr_db"] for e in compare["episodes"] if e["policy"] == "all"}
    assert parsed.bound["oracle:rules:psnr_db"]["psnr_db"]["all"].ci95 == 0.1
    assert claims.learned_beats_best_rule(parsed) == claims.learned_beats_best_rule(compare)
    evaluation = eval_doc(0.0)
    assert claims.ppo_reaches_best_mat(Results.parse(evaluation)) == \
        claims.ppo_reaches_best_mat(evaluation)
    delay = delay_doc({20: 40, 60: 70, 100: 130})
    assert [o.mean_delay_ms for o in Results.parse(delay).optima] == [20, 60, 100]
    assert math.isnan(Difference.parse({"mean": None, "ci95": None}).mean)
    with pytest.raises(KeyError):
        _ = Results.parse({"meta": {}}).meta.seed_list
