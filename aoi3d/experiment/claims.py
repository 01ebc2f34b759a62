"""The scientific claims of docs/research.md, each a test on the results of the experiment commands.

Every claim is stated here, before any run, as a function of the ``results.json`` (or
``eval.json``) the commands write — read once into the typed view of
:mod:`aoi3d.experiment.results`; every one uses the optimum criterion of
:mod:`aoi3d.experiment.optimum` (paired by seed). ``bench/science.py`` (``make science``)
runs the commands on seeds disjoint from those used while developing, applies these
functions and writes the verdicts. Pure: no I/O.
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from dataclasses import asdict, dataclass, field
from typing import Any

import numpy as np

from aoi3d.experiment.optimum import rederived
from aoi3d.experiment.results import Difference, Results
from aoi3d.metric import (
    BY_NAME,
    LPIPS,
    PSNR,
    PSNR_DISPLAY,
    PSNR_DYNAMIC_DISPLAY,
    REWARD,
    SSIM,
    names_of,
)
from aoi3d.policy import PolicyKind, kind_of
from aoi3d.stats import PairedDifference, paired_difference

__all__ = [
    "DISPLAY_METRIC",
    "Verdict",
    "adaptive_beats_best_rule",
    "at_display_time",
    "compare_selective_beats_all",
    "fixed_gamma_loses_under_changing_channel",
    "gamma_label",
    "learned_beats_best_rule",
    "metric_name",
    "optimal_gamma_grows_with_delay",
    "ppo_beats_all",
    "ppo_reaches_best_mat",
    "rederived",
    "regime_gain",
    "scores_agree_on_the_optimum",
    "tradeoff_interior_optimum",
]


@dataclass(frozen=True)
class Verdict:
    """One claim: its id, its statement, whether it held, and the numbers behind it."""

    claim: str
    statement: str
    holds: bool
    evidence: str
    numbers: dict[str, Any] = field(default_factory=dict)

    def to_dict(self) -> dict[str, Any]:
        return asdict(self)


def gamma_label(value: Any) -> str:
    """A candidate as the reports write it: Γ in ms (``40``), ``all`` for `all` or Γ = ∞, else
    the policy spec."""
    if value == "all" or (isinstance(value, float) and math.isinf(value)):
        return "all"
    try:
        return f"{float(value):g}"
    except (TypeError, ValueError):
        return str(value)


_g = gamma_label  # the short form the f-strings below use


def _set(members: Sequence[Any]) -> str:
    return "{" + ", ".join(_g(m) for m in members) + "}"


def _diff(d: Difference | Mapping[str, Any], digits: int = 2) -> str:
    d = d if isinstance(d, Difference) else Difference.parse(d)
    text = f"{d.mean:+.{digits}f}"
    if d.ci95 is not None and math.isfinite(d.ci95):
        text += f" ± {d.ci95:.{digits}f}"
    return text


def metric_name(metric: str) -> str:
    """A metric's name in words (``psnr_dynamic_db`` → ``dynamic-region PSNR``: its label in
    :mod:`aoi3d.metric`; ``the reward`` in a sentence); a name that is not a metric's as it is."""
    found = BY_NAME.get(metric)
    if found is None:
        return metric
    return f"the {found.label}" if found is REWARD else found.label


def _seeds(seeds: Sequence[int]) -> str:
    return f"{seeds[0]}–{seeds[-1]}" if len(seeds) > 1 else str(seeds[0])


def tradeoff_interior_optimum(tradeoff: Results | Mapping[str, Any], metric: str = "psnr_db"
                              ) -> Verdict:
    """At the tradeoff's delay, ``metric`` has an interior optimum: the optimum set holds
    neither the smallest Γ that selects frames nor `all` (Γ = ∞). With
    ``metric="psnr_dynamic_db"`` it is the claim that staleness costs most where the scene
    moves: on the blades too, neither the freshest frames alone nor every frame is best."""
    doc = Results.parse(tradeoff)
    opt = doc.optimum[metric]
    minus = opt.best_minus
    gaps = "; ".join(f"best − {_g(e)}: {_diff(minus[str(e)])}" for e in opt.ends
                     if str(e) in minus)
    return Verdict(
        claim=f"interior-{metric}",
        statement=(f"At {doc.meta.delay}, {metric_name(metric)} has an interior optimum in Γ: "
                   "neither the smallest Γ that selects frames nor `all` is in the optimum set"),
        holds=opt.interior,
        evidence=(f"best Γ = {_g(opt.best)}; optimum set {_set(opt.members)}; {gaps} "
                  f"(paired, seeds {_seeds(opt.seeds)}); left out (select nothing): "
                  f"{_set(opt.excluded)}"),
        numbers={"optimum": opt.raw})


def scores_agree_on_the_optimum(tradeoff: Results | Mapping[str, Any],
                                metrics: Sequence[str] = names_of((SSIM, LPIPS, REWARD))
                                ) -> Verdict:
    """SSIM, LPIPS and the reward each have an interior optimum, and each one's best Γ lies
    in the PSNR optimum set."""
    doc = Results.parse(tradeoff)
    psnr = doc.optimum[PSNR.name]
    parts = []
    holds = True
    for m in metrics:
        opt = doc.optimum.get(m)
        if opt is None:
            holds = False
            parts.append(f"{m}: not measured")
            continue
        inside = opt.best in psnr.members
        holds = holds and opt.interior and inside
        parts.append(f"{m}: best {_g(opt.best)}, set {_set(opt.members)}, "
                     f"{'interior' if opt.interior else 'not interior'}")
    return Verdict(
        claim="scores-agree",
        statement=("SSIM, LPIPS and the reward have interior optima too, at a Γ inside the "
                   "PSNR optimum set"),
        holds=holds, evidence=f"PSNR set {_set(psnr.members)}; " + "; ".join(parts),
        numbers={m: (o.raw if (o := doc.optimum.get(m)) is not None else None)
                 for m in metrics})


def optimal_gamma_grows_with_delay(delay: Results | Mapping[str, Any]) -> Verdict:
    """Between the smallest and the largest mean delay swept, the best Γ grows, and each
    delay's best Γ is significantly worse at the other delay (outside its optimum set)."""
    rows = sorted(Results.parse(delay).optima, key=lambda o: o.mean_delay_ms)
    lo, hi = rows[0].optimum, rows[-1].optimum
    grows = float(hi.best) > float(lo.best)
    apart = lo.best not in hi.members and hi.best not in lo.members
    sets = "; ".join(f"E[Y] = {o.mean_delay_ms:g} ms: best {_g(o.optimum.best)}, "
                     f"set {_set(o.optimum.members)}" for o in rows)
    at_lo = lo.best_minus.get(str(hi.best))
    at_hi = hi.best_minus.get(str(lo.best))
    gaps = (f"at {rows[0].mean_delay_ms:g} ms Γ {_g(lo.best)} − Γ {_g(hi.best)}: "
            f"{_diff(at_lo) if at_lo else '—'}; at {rows[-1].mean_delay_ms:g} ms "
            f"Γ {_g(hi.best)} − Γ {_g(lo.best)}: {_diff(at_hi) if at_hi else '—'}")
    return Verdict(
        claim="gamma-grows-with-delay",
        statement=(f"The optimal Γ grows with the mean delay: the best Γ at E[Y] = "
                   f"{rows[-1].mean_delay_ms:g} ms is larger than at "
                   f"{rows[0].mean_delay_ms:g} ms, and each is significantly worse at the "
                   "other delay"),
        holds=grows and apart,
        evidence=f"{sets}; {gaps} (dB, paired, seeds {_seeds(lo.seeds)})",
        numbers={"optima": [o.optimum.raw for o in rows]})


def compare_selective_beats_all(compare: Results | Mapping[str, Any], metric: str = "psnr_db"
                                ) -> Verdict:
    """Among the compared policies, `all` is significantly worse than the best."""
    opt = Results.parse(compare).optimum[metric]
    d = opt.best_minus.get("all")
    return Verdict(
        claim="selective-beats-all",
        statement=(f"Selecting frames beats training on every frame: `all` is significantly "
                   f"worse in {metric_name(metric)} than the best of the compared policies"),
        holds=d is not None and "all" not in opt.members,
        evidence=(f"best {opt.best}; not significantly worse: {_set(opt.members)}; "
                  f"best − all: {_diff(d) if d else '—'} (paired, seeds "
                  f"{_seeds(opt.seeds)})"),
        numbers={"optimum": opt.raw})


def _kind(label: str | Mapping[str, Any]) -> PolicyKind:
    """The registered kind of a result — its own JSON form (``policy_json``) where the result
    carries one, else its label — (:func:`aoi3d.policy.kind_of`): its name and family, read
    by the registry, never by the label's prefix."""
    return kind_of(label)


def _ppo_spec(evaluation: Results) -> str:
    return next(p for p in evaluation.meta.policies if _kind(p).kind == "ppo")


def ppo_reaches_best_mat(evaluation: Results | Mapping[str, Any], metric: str = "reward"
                         ) -> Verdict:
    """At the budget the agent was trained for, PPO is not significantly worse than the best
    MAT threshold evaluated beside it (it is in the optimum set of the evaluated policies or
    within the best MAT's)."""
    doc = Results.parse(evaluation)
    ppo = _ppo_spec(doc)
    mats = [p for p in doc.meta.policies if _kind(p).kind == "mat"]
    means = {p: sum(v := list(doc.per_seed(p, metric).values())) / len(v) for p in mats}
    best = max(mats, key=lambda p: means[p])
    d: PairedDifference = paired_difference(doc.per_seed(ppo, metric),
                                            doc.per_seed(best, metric))
    equal = doc.meta.equal_budget
    not_worse = not (d.significant and d.mean < 0)
    steps = doc.meta.steps_per_epoch
    verdict = ("significantly better" if d.significant and d.mean > 0 else
               "tied (not significantly different)" if not_worse else "significantly worse")
    return Verdict(
        claim="ppo-reaches-best-mat",
        statement=("At the budget it was trained for, the PPO agent is not significantly "
                   f"worse in {metric} than the best MAT threshold"),
        holds=equal and not_worse,
        evidence=(f"{steps} field steps (trained at "
                  f"{doc.meta.trained_steps_per_epoch}); best MAT {best}; "
                  f"PPO − {best}: {d.mean:+.4f} ± {d.half:.4f} over {d.n} seeds "
                  f"{_seeds(doc.meta.seeds)}: {verdict}"),
        numbers={"best_mat": best, "ppo_minus_best_mat": d.to_dict(), "equal_budget": equal})


def ppo_beats_all(evaluation: Results | Mapping[str, Any], metric: str = "reward"
                  ) -> Verdict:
    """PPO is significantly better than `all` (every frame) at its training budget."""
    doc = Results.parse(evaluation)
    ppo = _ppo_spec(doc)
    d = paired_difference(doc.per_seed(ppo, metric), doc.per_seed("all", metric))
    return Verdict(
        claim="ppo-beats-all",
        statement=f"The PPO agent is significantly better in {metric} than `all`",
        holds=doc.meta.equal_budget and d.significant and d.mean > 0,
        evidence=(f"PPO − all: {d.mean:+.4f} ± {d.half:.4f} over {d.n} seeds "
                  f"{_seeds(doc.meta.seeds)}"),
        numbers={"ppo_minus_all": d.to_dict()})


def _held_rule(label: str | Mapping[str, Any]) -> bool:
    """A fixed rule a learned policy is held against: every kind of the ``rule`` family but
    ``all``, the reference (MAT thresholds, freshest:k, wait:ω)."""
    entry = _kind(label)
    return entry.family == "rule" and entry.kind != "all"


def learned_beats_best_rule(compare: Results | Mapping[str, Any], metric: str = "psnr_db",
                            goal: float = 0.5) -> Verdict:
    """At the experiments' budget (the ``compare`` run's), the learned policy (``ppo:…``) is
    significantly better in ``metric`` than the best fixed rule run beside it (highest mean of
    MAT, freshest:k and wait:ω). The evidence also states the goal of issue 25 — ahead by at
    least ``goal`` and within half the distance from the best rule to the oracle bound
    (``oracle:rules:<metric>``, when it was run) — which the verdict does not require."""
    doc = Results.parse(compare)
    runs = {r.policy: r.own for r in doc.runs()}
    ppo = next((p for p, own in runs.items() if _kind(own).family == "learned"), None)
    rules = [p for p, own in runs.items() if _held_rule(own)]
    steps = doc.meta.steps_per_epoch
    statement = (f"At the experiments' budget, the learned policy is significantly better in "
                 f"{metric_name(metric)} than the best fixed rule (MAT, freshest:k, wait:ω)")
    if ppo is None or not rules:
        return Verdict("learned-beats-best-rule", statement, False,
                       "not tested: the compare run has no learned policy or no fixed rule")
    means = {p: float(np.mean(list(doc.per_seed(p, metric).values()))) for p in rules}
    best = max(rules, key=lambda p: means[p])
    d = paired_difference(doc.per_seed(ppo, metric), doc.per_seed(best, metric))
    holds = d.significant and d.mean > 0
    verdict = ("significantly better" if holds else "significantly worse"
               if d.significant else "not significantly different")
    numbers: dict[str, Any] = {"learned": ppo, "best_rule": best, "rule_means": means,
                               "learned_minus_best_rule": d.to_dict(), "steps": steps}
    evidence = (f"{steps} field steps; best rule {best}; learned − {best}: {d.mean:+.2f} ± "
                f"{d.half:.2f} over {d.n} seeds {_seeds(doc.meta.seed_list)}: {verdict}; "
                f"goal ≥ {goal:g}: {'met' if holds and d.mean >= goal else 'not met'}")
    bound = doc.bound.get(f"oracle:rules:{metric}")
    if bound is not None:
        to_rule, to_learned = bound[metric][best], bound[metric][ppo]
        half_way = to_learned.mean <= to_rule.mean / 2
        numbers.update(oracle_minus_best_rule=to_rule.raw, oracle_minus_learned=to_learned.raw)
        evidence += (f"; oracle bound (oracle:rules:{metric}) − {best}: {_diff(to_rule)}, "
                     f"− learned: {_diff(to_learned)}: within half the distance: "
                     f"{'yes' if half_way else 'no'}")
    else:
        evidence += "; no oracle bound in this run"
    return Verdict("learned-beats-best-rule", statement, holds, evidence, numbers)


# --- changing channels (issue 32) ------------------------------------------------------------
def _regime_of(delay: str) -> Any:
    """``t ↦ the regime in force`` of a regime schedule (``regimes:…``); None otherwise."""
    from aoi3d.channel import parse_channel

    channel = parse_channel(delay)
    regime_at = getattr(channel, "regime_at", None)
    return regime_at if callable(regime_at) and len(getattr(channel, "regimes", ())) > 1 \
        else None


def regime_gain(compare: Results | Mapping[str, Any], metric: str = "psnr_db"
                ) -> dict[str, Any] | None:
    """The switching gain G of a compare run on a regime schedule: over the MAT thresholds
    run, the best Γ of each regime (highest mean over the scored decisions taken while it was
    in force, all seeds) against the best single Γ (highest mean over every decision); per
    seed, the mean over the regimes of (its best Γ − the single Γ) on that regime's decisions;
    paired by seed. None when the run is not on a regime schedule or has no MAT rule."""
    doc = Results.parse(compare)
    delay = doc.meta.delay
    regime_at = _regime_of(delay) if delay else None
    mats = [r.policy for r in doc.runs() if _kind(r.policy).kind == "mat"]
    if regime_at is None or not mats:
        return None
    per = {m: doc.epochs(m, metric) for m in mats}
    seeds = sorted(set.intersection(*(set(v) for v in per.values())))
    regimes = sorted({regime_at(t) for m in mats for s in seeds for t, _ in per[m][s]})

    def mean_on(m: str, regime: str | None, seed: int | None = None) -> float:
        vals = [v for s in ([seed] if seed is not None else seeds) for t, v in per[m][s]
                if regime is None or regime_at(t) == regime]
        return float(np.mean(vals)) if vals else math.nan

    single = max(mats, key=lambda m: mean_on(m, None))
    best = {g: max(mats, key=lambda m: mean_on(m, g)) for g in regimes}
    gain = {s: float(np.nanmean([mean_on(best[g], g, s) - mean_on(single, g, s)
                                 for g in regimes])) for s in seeds}
    d = paired_difference(gain, {s: 0.0 for s in seeds})
    return {"delay": delay, "best_single": single, "best_per_regime": best,
            "single_minus_best_per_regime": {
                g: paired_difference({s: mean_on(single, g, s) for s in seeds},
                                     {s: mean_on(best[g], g, s) for s in seeds}).to_dict()
                for g in regimes},
            "G": d.to_dict(), "seeds": seeds}


def fixed_gamma_loses_under_changing_channel(compare: Results | Mapping[str, Any],
                                             metric: str = "psnr_db") -> Verdict:
    """Under a channel whose regimes change, every fixed Γ is significantly worse than the
    best Γ of each regime: the switching gain G (:func:`regime_gain`) is significantly above
    zero, paired by seed, and the regimes' best Γ differ."""
    g = regime_gain(compare, metric)
    statement = (f"Under a changing channel, a fixed Γ is significantly worse in "
                 f"{metric_name(metric)} than the best Γ of each regime (the switching gain G "
                 "over the regimes is significantly above zero)")
    if g is None:
        return Verdict("fixed-gamma-loses", statement, False,
                       "not tested: the run is not on a regime schedule with MAT rules")
    d = g["G"]
    apart = len(set(g["best_per_regime"].values())) > 1
    holds = math.isfinite(d["ci95"]) and d["mean"] > d["ci95"] and apart
    per = "; ".join(f"{r}: best {b}, {g['best_single']} − {b} "
                    f"{_diff(g['single_minus_best_per_regime'][r])}"
                    for r, b in g["best_per_regime"].items())
    return Verdict("fixed-gamma-loses", statement, holds,
                   f"{g['delay']}: best single Γ {g['best_single']}; {per}; G = {_diff(d)} dB "
                   f"(paired, seeds {_seeds(g['seeds'])})", {"G": g})


def adaptive_beats_best_rule(compare: Results | Mapping[str, Any], metric: str = "psnr_db",
                             goal: float = 0.5) -> Verdict:
    """On the compare run's changing channel, the best adaptive policy (``adaptive:…``, the
    highest mean) is significantly better in ``metric`` than the best fixed rule in
    hindsight (the MAT, freshest:k or wait:ω run beside it with the highest mean). Beside the
    verdict: the switching gain G (:func:`regime_gain`), the oracle over the rules that
    decide at t (per scored decision, the best of the MAT and freshest:k run: a lower bound of
    ``oracle:rules``), the oracle bound itself when it was run, and issue 32's goal (≥ ``goal``
    dB)."""
    doc = Results.parse(compare)
    names = [r.policy for r in doc.runs()]
    adaptive = [p for p in names if _kind(p).family == "adaptive"]
    rules = [p for p in names if _kind(p).family == "rule" and _kind(p).kind != "all"]
    statement = (f"On a changing channel, an adaptive policy is significantly better in "
                 f"{metric_name(metric)} than the best fixed rule in hindsight (MAT, "
                 "freshest:k, wait:ω)")
    if not adaptive or not rules:
        return Verdict("adaptive-beats-best-rule", statement, False,
                       "not tested: the compare run has no adaptive policy or no fixed rule")
    seed_means = {p: doc.per_seed(p, metric) for p in [*rules, *adaptive]}
    means = {p: float(np.mean(list(v.values()))) for p, v in seed_means.items()}
    best = max(rules, key=lambda p: means[p])
    ours = max(adaptive, key=lambda p: means[p])
    diffs = {p: paired_difference(seed_means[p], seed_means[best]) for p in adaptive}
    d = diffs[ours]
    holds = d.significant and d.mean > 0
    verdict = ("significantly better" if holds else "significantly worse"
               if d.significant else "not significantly different")
    at_t = [p for p in rules if _kind(p).kind != "wait"]
    per = {p: doc.epochs(p, metric) for p in at_t}
    seeds = sorted(set.intersection(*(set(v) for v in per.values()))) if per else []
    oracle = {s: float(np.mean(np.max([[v for _, v in per[p][s]] for p in at_t], axis=0)))
              for s in seeds}
    to_oracle = paired_difference(oracle, seed_means[best])
    g = regime_gain(doc, metric)
    evidence = (f"{doc.meta.delay}; best rule {best}; "
                + "; ".join(f"{p} − {best}: {diffs[p].mean:+.2f} ± {diffs[p].half:.2f}"
                            for p in adaptive)
                + f" over {d.n} seeds {_seeds(doc.meta.seed_list)}: {ours} "
                f"{verdict}; goal ≥ {goal:g} dB: "
                f"{'met' if holds and d.mean >= goal else 'not met'}; "
                f"G = {_diff(g['G']) if g else '— (not a regime schedule)'}; "
                f"oracle over the rules at t − {best}: {to_oracle.mean:+.2f} ± "
                f"{to_oracle.half:.2f}")
    numbers: dict[str, Any] = {
        "best_rule": best, "best_adaptive": ours, "means": means,
        "adaptive_minus_best_rule": {p: v.to_dict() for p, v in diffs.items()},
        "oracle_rules_at_t_minus_best_rule": to_oracle.to_dict(), "G": g}
    bound = doc.bound.get(f"oracle:rules:{metric}")
    if bound is not None:
        numbers["oracle_minus_best_rule"] = bound[metric][best].raw
        evidence += f"; oracle:rules:{metric} − {best}: {_diff(bound[metric][best])}"
    return Verdict("adaptive-beats-best-rule", statement, holds, evidence, numbers)


DISPLAY_METRIC = PSNR_DISPLAY.name
"""The display-time PSNR: the render against the truth at the time it is ready (its decision
time plus its compute, :meth:`aoi3d.experiment.config.EpisodeConfig.compute_ms`)."""


def at_display_time(tradeoff: Results | Mapping[str, Any], delay: Results | Mapping[str, Any],
                    compare: Results | Mapping[str, Any]) -> list[Verdict]:
    """The claims on PSNR, asked again of what a viewer sees: the same episodes judged by
    their display-time scores (``psnr_display_db``, ``psnr_dynamic_display_db``). Each
    verdict's id ends in ``@display``. The PPO claims are not asked: the agent learned the
    decision-time reward."""
    dyn = PSNR_DYNAMIC_DISPLAY.name

    def again(doc: Results | Mapping[str, Any], metrics: tuple[str, ...], ordered: bool
              ) -> Results:
        raw = doc.raw if isinstance(doc, Results) else doc
        return Results.parse(rederived(raw, metrics, ordered=ordered))

    t = again(tradeoff, (DISPLAY_METRIC, dyn), True)
    verdicts = [tradeoff_interior_optimum(t, DISPLAY_METRIC),
                tradeoff_interior_optimum(t, dyn) if dyn in t.optimum else None,
                optimal_gamma_grows_with_delay(again(delay, (DISPLAY_METRIC,), True)),
                compare_selective_beats_all(again(compare, (DISPLAY_METRIC,), False),
                                            DISPLAY_METRIC)]
    return [Verdict(f"{v.claim}@display", v.statement if "display time" in v.statement
                    else f"{v.statement} (at display time)", v.holds, v.evidence, v.numbers)
            for v in verdicts if v is not None]
