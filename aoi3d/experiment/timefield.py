"""Issue 41's question: what a time-aware field does to the timeliness–fidelity tradeoff.

The static grid against the time-aware ``flow`` field (:mod:`aoi3d.field.flow`), on the
virtual clock, on the same seeds and episodes: MAT Γ swept (``aoi3d experiment tradeoff``),
scored at decision time and at display time, whole image and dynamic region, at two links.
Stated here, before any run, as data (the arms) and as functions of the tradeoff command's
``results.json`` (the analysis, the verdict); ``bench/timefield.py`` runs it and
``make science`` asks it on the unseen seeds. Pure: no I/O but the figure.

**Equal CPU seconds.** A flow step costs :data:`FLOW_STEP_COST` grid steps (measured, see
there), so each static arm of B steps has a time-aware twin of B / cost steps: the same CPU
seconds per render. The twin's compute model charges the same ratio per step
(``compute_step_ms``), so both are shown at the same display time.

**The arms**, three CPU levels: the paper's per-decision reconstruction (``fresh``) at 50 and
100 grid steps (the budgets where the display-time optimum lies, docs/experiments.md, "Does
the tradeoff survive at display time?"), and the streaming warm start (``stream``, issue 33)
at 25 grid steps per warm start after a cold start of 100.

**The goal** (:func:`goal`): at display time, the time-aware field beats the best static
configuration by at least 1 dB in dynamic-region PSNR at equal CPU seconds per render. The
best static configuration is the (arm, Γ) of the highest mean; the time-aware field may spend
as much CPU per render, no more: it takes the best (arm, Γ) among the twins of the static
arms that cost no more than that one (:attr:`Arm.cost`, grid steps per render over an
episode, a stream arm's cold start included); the difference is paired by seed, and the goal
holds when its mean is ≥ 1 dB and its 95% interval excludes 0. The twin at the same level is
reported beside it.
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np

from aoi3d.experiment.claims import Verdict
from aoi3d.experiment.config import COMPUTE_STEP_MS, get_preset
from aoi3d.experiment.optimum import rederived
from aoi3d.metric import PSNR, PSNR_DISPLAY, PSNR_DYNAMIC, PSNR_DYNAMIC_DISPLAY, names_of
from aoi3d.policy import kind_of
from aoi3d.stats import paired_difference

__all__ = ["ARMS", "DELAYS", "DISPLAY", "FLOW_STEP_COST", "GAMMAS", "GOAL_DB", "METRICS",
           "Arm", "analyse", "describe", "goal", "parameters", "per_seed", "plot", "public",
           "static_psnr", "twin"]

FLOW_STEP_COST = 1.55
"""CPU seconds of a ``flow`` reconstruction's step over a ``grid`` step: 1.52–1.55 for the
training (minimum and median of 12–20 interleaved reconstructions of 33 and 100 steps, 9
views of frames 1–4 frames old, one thread), 1.54 with the render, on the 2-core machine
busy with other jobs. ``bench/timefield.py`` measures every arm's CPU seconds per render
again on each run and reports them beside the verdict."""
GOAL_DB = 1.0
"""The margin the goal asks for (dB of dynamic-region PSNR at display time)."""
DELAYS = ("exp:60", "exp:100")
"""The link of the paper's tradeoff and a slower one."""
GAMMAS = (40, 70, 100, 130, 160)
"""MAT Γ (ms) swept; `all` is the tradeoff command's reference."""
DISPLAY = PSNR_DYNAMIC_DISPLAY.name
"""The goal's metric: dynamic-region PSNR against the truth when the render is shown."""
METRICS = names_of((PSNR, PSNR_DYNAMIC, PSNR_DISPLAY, PSNR_DYNAMIC_DISPLAY))
"""Decision time and display time, whole image and dynamic region."""


@dataclass(frozen=True)
class Arm:
    """One configuration of the field: ``backend`` and ``carry``, ``steps`` per render (a
    warm start's for ``stream``, after a cold start of ``cold_steps``), at CPU level
    ``level`` (the static arm's name at that level)."""

    backend: str
    carry: str
    steps: int
    level: str
    cold_steps: int | None = None

    @property
    def name(self) -> str:
        return f"{self.backend}-{self.carry}-{self.steps}"

    @property
    def time_aware(self) -> bool:
        return self.backend == "flow"

    @property
    def cost(self) -> float:
        """CPU per render in grid steps, over an episode of the quick preset (its scored
        decisions: a stream arm's first is its cold start)."""
        n = get_preset("quick").episode.scored_decisions
        steps = (self.steps if self.cold_steps is None
                 else (self.cold_steps + (n - 1) * self.steps) / n)
        return steps * (FLOW_STEP_COST if self.time_aware else 1.0)

    def options(self) -> list[str]:
        """The options of ``aoi3d experiment tradeoff`` that make this arm."""
        out = ["--field", self.backend, "--carry", self.carry, "--steps-per-epoch",
               str(self.cold_steps if self.cold_steps is not None else self.steps)]
        if self.cold_steps is not None:
            out += ["--set", f"render_steps={self.steps}"]
        if self.time_aware:
            out += ["--set", f"compute_step_ms={COMPUTE_STEP_MS * FLOW_STEP_COST:g}"]
        return out


def twin(arm: Arm) -> Arm:
    """The time-aware arm at the same CPU seconds per render."""
    cold = None if arm.cold_steps is None else round(arm.cold_steps / FLOW_STEP_COST)
    return Arm("flow", arm.carry, round(arm.steps / FLOW_STEP_COST), arm.level, cold)


_STATIC = (Arm("grid", "fresh", 50, "fresh@50"), Arm("grid", "fresh", 100, "fresh@100"),
           Arm("grid", "stream", 25, "stream@25", 100))
ARMS: tuple[Arm, ...] = tuple(a for s in _STATIC for a in (s, twin(s)))
"""Each static arm, then its time-aware twin."""


def _label(policy: str) -> str:
    """A tradeoff row's Γ label: ``"70"`` for ``mat:70``, the spec itself otherwise."""
    return policy.partition(":")[2] if kind_of(policy).kind == "mat" else policy


def per_seed(doc: Mapping[str, Any], metric: str) -> dict[str, dict[int, float]]:
    """``metric`` of every episode of a tradeoff ``results.json``: Γ label (``"40"``,
    ``"all"``) → seed → value (NaN where missing)."""
    out: dict[str, dict[int, float]] = {}
    for e in doc["episodes"]:
        v = e.get(metric)
        out.setdefault(_label(e["policy"]), {})[int(e["seed"])] = (
            math.nan if v is None else float(v))
    return out


def static_psnr(doc: Mapping[str, Any]) -> dict[str, dict[int, float]]:
    """PSNR over the pixels that did not move, at decision time, per Γ and seed: each scored
    decision's from its whole-image and dynamic-region MSE and the dynamic fraction f,
    MSE_static = (MSE − f·MSE_dyn) / (1 − f), the PSNRs averaged over the decisions."""
    out: dict[str, dict[int, float]] = {}
    for e in doc["episodes"]:
        values = []
        for ep in e.get("epochs", []):
            f, dyn = ep["dynamic_fraction"], ep["psnr_dynamic_db"]
            mse = 10.0 ** (-ep["psnr_db"] / 10.0)
            if dyn is not None and f < 1.0:
                mse = (mse - f * 10.0 ** (-dyn / 10.0)) / (1.0 - f)
            values.append(-10.0 * math.log10(mse) if mse > 0 else math.nan)
        out.setdefault(_label(e["policy"]), {})[int(e["seed"])] = (
            float(np.mean(values)) if values else math.nan)
    return out


def _mean(values: Mapping[int, float]) -> float:
    finite = [v for v in values.values() if math.isfinite(v)]
    return float(np.mean(finite)) if finite else math.nan


def _best(values: Mapping[str, Mapping[int, float]]) -> str:
    return max(values, key=lambda g: _mean(values[g]))


def analyse(docs: Mapping[str, Mapping[str, Mapping[str, Any]]]) -> dict[str, Any]:
    """The question's numbers from ``docs[delay][arm name]``, the tradeoff ``results.json``
    of every arm at every delay: per delay and arm, each Γ's means of :data:`METRICS` and the
    static-region PSNR, the optimum per metric (the commands' criterion, ``rederived``), the
    best Γ; per CPU level, the time-aware arm's best Γ minus the static arm's, paired; what
    the display time gives back (display − decision, each arm at its best Γ)."""
    out: dict[str, Any] = {}
    for delay, by_arm in docs.items():
        arms: dict[str, Any] = {}
        for arm in ARMS:
            doc = by_arm.get(arm.name)
            if doc is None:
                continue
            judged = rederived(doc, METRICS, ordered=True)["optimum"]
            values = {m: per_seed(doc, m) for m in METRICS}
            values["psnr_static_db"] = static_psnr(doc)
            gammas = list(values[METRICS[0]])
            arms[arm.name] = {
                "arm": arm.name, "backend": arm.backend, "carry": arm.carry,
                "steps": arm.steps, "cold_steps": arm.cold_steps, "level": arm.level,
                "cost": round(arm.cost, 2),
                "seeds": sorted({s for v in values[DISPLAY].values() for s in v}),
                "rows": [{"gamma": g, **{m: _mean(values[m][g]) for m in values}}
                         for g in gammas],
                "best": {m: _best(values[m]) for m in values},
                "optimum": {m: {k: judged[m][k] for k in ("members", "interior", "best")}
                            for m in METRICS},
                "display_gain": paired_difference(
                    values["psnr_display_db"][_best(values["psnr_display_db"])],
                    values["psnr_db"][_best(values["psnr_display_db"])]).to_dict(),
                "_values": values,
            }
        levels = {}
        for arm in ARMS:
            if arm.time_aware or arm.name not in arms:
                continue
            other = twin(arm)
            if other.name not in arms:
                continue
            a, b = arms[other.name], arms[arm.name]
            levels[arm.level] = {
                m: {"time_aware": a["best"][m], "static": b["best"][m],
                    **paired_difference(a["_values"][m][a["best"][m]],
                                        b["_values"][m][b["best"][m]]).to_dict()}
                for m in (*METRICS, "psnr_static_db")}
        out[delay] = {"arms": arms, "levels": levels}
    return out


def goal(analysis: Mapping[str, Any], delay: str) -> Verdict:
    """The issue's goal at ``delay`` (see the module): the best static (arm, Γ) at display
    time in dynamic-region PSNR against the time-aware arm at its CPU level, at its best Γ."""
    arms = analysis[delay]["arms"]
    static = [a for a in arms.values() if a["backend"] == "grid"]
    statement = (f"at display time, at {delay}, the time-aware field beats the best static "
                 f"configuration by ≥ {GOAL_DB:g} dB in dynamic-region PSNR at equal CPU "
                 "seconds per render")
    if not static:
        return Verdict(f"time-aware-beats-static@{delay}", statement, False, "no static arm")

    def top(a: Mapping[str, Any]) -> float:
        return _mean(a["_values"][DISPLAY][a["best"][DISPLAY]])

    best = max(static, key=top)
    level_cost = {a["level"]: a["cost"] for a in static}
    allowed = [a for a in arms.values() if a["backend"] == "flow"
               and level_cost.get(a["level"], math.inf) <= best["cost"]]
    if not allowed:
        return Verdict(f"time-aware-beats-static@{delay}", statement, False,
                       f"no time-aware arm within {best['arm']}'s CPU")
    pair = max(allowed, key=top)
    twin_arm = next((a for a in allowed if a["level"] == best["level"]), None)
    s_g, t_g = best["best"][DISPLAY], pair["best"][DISPLAY]
    d = paired_difference(pair["_values"][DISPLAY][t_g], best["_values"][DISPLAY][s_g])
    holds = d.mean >= GOAL_DB and d.significant
    evidence = (f"best static: {best['arm']} at Γ = {s_g} ({top(best):.2f} dB, "
                f"{best['cost']:g} grid steps per render); best time-aware within that CPU: "
                f"{pair['arm']} at Γ = {t_g} ({top(pair):.2f} dB, {pair['cost']:g}); paired "
                f"difference {d.mean:+.2f} ± {d.half:.2f} dB over {d.n} seeds")
    numbers: dict[str, Any] = {"static": {"arm": best["arm"], "gamma": s_g},
                               "time_aware": {"arm": pair["arm"], "gamma": t_g},
                               "difference": d.to_dict()}
    if twin_arm is not None and twin_arm is not pair:
        g = twin_arm["best"][DISPLAY]
        t = paired_difference(twin_arm["_values"][DISPLAY][g], best["_values"][DISPLAY][s_g])
        evidence += (f"; its twin at the same level, {twin_arm['arm']} at Γ = {g}: "
                     f"{t.mean:+.2f} ± {t.half:.2f} dB")
        numbers["twin"] = {"arm": twin_arm["arm"], "gamma": g, "difference": t.to_dict()}
    return Verdict(f"time-aware-beats-static@{delay}", statement, bool(holds), evidence, numbers)


def public(analysis: Mapping[str, Any]) -> dict[str, Any]:
    """:func:`analyse`'s result without the per-seed values (for JSON)."""
    return {delay: {"arms": {k: {kk: vv for kk, vv in a.items() if kk != "_values"}
                             for k, a in d["arms"].items()}, "levels": d["levels"]}
            for delay, d in analysis.items()}


def plot(analysis: Mapping[str, Any], path: Any) -> Any:
    """Both tradeoff curves at every delay (columns): dynamic-region PSNR and PSNR at
    display time (rows) against Γ, each arm a line — static grey/blue, time-aware orange/red,
    one line style per CPU level; the decision-time dynamic-region PSNR dotted, thin."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    delays = list(analysis)
    fig, axes = plt.subplots(2, len(delays), figsize=(6 * len(delays), 7.5), squeeze=False,
                             constrained_layout=True)
    styles = {"fresh@50": ":", "fresh@100": "-", "stream@25": "--"}
    colours = {"grid": "tab:blue", "flow": "tab:orange"}
    for col, delay in enumerate(delays):
        for arm in analysis[delay]["arms"].values():
            rows = arm["rows"]
            x = [_position(r["gamma"]) for r in rows]
            order = np.argsort(x)
            xs = [x[i] for i in order]
            for row, metric in enumerate((DISPLAY, "psnr_display_db")):
                axes[row][col].plot(xs, [rows[i][metric] for i in order], marker="o", ms=3,
                                    color=colours[arm["backend"]],
                                    ls=styles.get(arm["level"], "-"), label=arm["arm"])
        for row, label in enumerate(("dynamic-region PSNR at display time (dB)",
                                     "PSNR at display time (dB)")):
            ax = axes[row][col]
            ax.set_xticks([*GAMMAS, _position("all")])
            ax.set_xticklabels([*(str(g) for g in GAMMAS), "all"])
            ax.set_xlabel("MAT Γ (ms)")
            ax.set_ylabel(label)
            ax.set_title(f"{delay}")
            ax.grid(alpha=0.3)
        axes[0][col].legend(fontsize=8)
    fig.suptitle("static grid (blue) against the time-aware flow field (orange), "
                 "equal CPU seconds per render at each line style")
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path


def _position(gamma: str) -> float:
    """Where a Γ label is drawn: Γ in ms, `all` one step past the largest."""
    return float(gamma) if gamma != "all" else GAMMAS[-1] + 40.0


def parameters(counts: Mapping[str, int]) -> str:
    """A line on the fields' sizes: parameters per backend (``counts``)."""
    return ", ".join(f"{k}: {v:,} parameters ({v * 4 / 1024:.0f} KiB)" for k, v in counts.items())


def describe(arms: Sequence[Arm] = ARMS) -> list[str]:
    """One line per arm: its name, CPU level and options."""
    return [f"{a.name} ({a.level}): {' '.join(a.options())}" for a in arms]
