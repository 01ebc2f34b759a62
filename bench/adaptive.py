"""Adaptive Γ against every fixed rule in hindsight on changing channels (issue 32 §3).

For each channel and seed, every policy runs the same episode on the virtual clock, decided
step by step (:func:`aoi3d.experiment.adaptive.run_stepwise`: the fresh carry, one
reconstruction per scored decision, every reconstruction cached by its selection so that the
policies share them): the fixed rules (MAT over a Γ grid, freshest:k, wait:ω), the adaptive
policies (``adaptive:plugin``, ``adaptive:bandit``) and, per scored decision, the best of the
rules that decide at t (the MAT grid and freshest:k: an oracle over the evaluated rules, a
lower bound on ``oracle:rules``). The fixed rules run first, as one parallel batch; the
adaptive policies then mostly hit the cache.

Channels: ``trace:<file>,spread=<S>,offset=<ms>`` — every camera on its own subchannel of
the same trace, within ``--spread-ms`` S of one phase (S = 0: identical links; S = 2000: the
cameras share the slow changes of the radio conditions, not the fast ones), the phase drawn
per seed, so the seeds see different stretches of the trace; and optionally a regime
schedule (``--regimes``). The traces are read from ``--traces-dir``
(``../shared/data/traces``); the script says so and stops where it is absent.

Statistics (paired by seed): per channel, each policy's mean PSNR with its 95% interval; the
paired difference of each adaptive policy to the best fixed rule *in hindsight on that
channel* (the fixed rule with the highest mean there, chosen after the fact); pooled over the
channels, the same against the best single fixed rule across them; and the switching gain G
over the channel's delay regimes (each scored decision binned by the mean transmission time
of the frames generated within ±1.5 s of it; the best MAT Γ per bin against the best single
MAT Γ, paired by seed) beside the per-decision oracle.

Writes ``<out>/results.json`` (every episode, its per-decision PSNR and Γ, the tables, the
command) and prints the tables. The Γ*(E[Y]) curve the plug-in uses is
``aoi3d/policy/gamma_curve.json`` (``bench/adaptive_curve.sh``).
"""

from __future__ import annotations

import argparse
import math
import sys
import time
from dataclasses import replace
from pathlib import Path
from typing import Any

import numpy as np

from aoi3d.experiment import ResultCache, get_preset, plan_episode, run_plans
from aoi3d.experiment.adaptive import run_stepwise
from aoi3d.experiment.episode import episode_links
from aoi3d.policy import MatPolicy, kind_of, parse_policy
from aoi3d.scene import open_dataset
from aoi3d.stats import mean_ci95, paired_difference
from bench import common
from bench.common import ROOT

GAMMAS = (40, 70, 100, 130, 160, 190, 220, 250, 280)
FRESHEST = (6, 12)
WAITS = (40,)
ADAPTIVE = ("adaptive:plugin", "adaptive:bandit", "adaptive:bandit:8:40/100/190")
DELAY_BINS_MS = (0.0, 30.0, 60.0, 100.0, 200.0, math.inf)


def fixed_rules(gammas: tuple[int, ...] = GAMMAS) -> list[str]:
    return ([MatPolicy(g).spec for g in gammas] + [f"freshest:{k}" for k in FRESHEST]
            + [f"wait:{w}" for w in WAITS])


def trace_length_ms(path: Path) -> int:
    last = path.read_text().split()[-1]
    return int(last)


def channel_spec(kind: str, arg: str, seed: int, span_ms: int, traces: Path,
                 spread_ms: int = 0) -> str:
    """The channel of one seed: a trace at a phase drawn from the seed (each camera within
    ``spread_ms`` after it), or a fixed spec."""
    if kind == "trace":
        path = traces / arg
        rng = np.random.default_rng(np.random.SeedSequence(seed, spawn_key=(0xAD,)))
        offset = int(rng.integers(0, max(1, trace_length_ms(path) - span_ms - spread_ms)))
        return f"trace:{path},spread={spread_ms},offset={offset}"
    return arg


def window_delay_ms(links: Any, t_ms: int, half_ms: int = 1500) -> float:
    """Mean transmission time of the frames generated within ±``half_ms`` of ``t_ms``."""
    ys = []
    for g, d in zip(links.run.gen_ms, links.run.delivery_ms, strict=True):
        m = (g >= t_ms - half_ms) & (g < t_ms + half_ms)
        ys.append(d[m] - g[m])
    y = np.concatenate(ys)
    return float(y.mean()) if y.size else math.nan


def parser() -> argparse.ArgumentParser:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--heldout", default="Verizon-LTE-short.up,Verizon-EVDO-driving.up",
                    help="trace files judged on (never used for design)")
    ap.add_argument("--regimes", default="", help="a regime schedule run beside the traces")
    ap.add_argument("--traces-dir", type=Path, default=ROOT.parent / "shared/data/traces")
    ap.add_argument("--spread-ms", type=int, default=0,
                    help="each camera's phase within this many ms after the seed's (0: every "
                         "camera at the same phase: identical links)")
    ap.add_argument("--seeds", type=int, default=4)
    ap.add_argument("--seed-offset", type=int, default=30000)
    ap.add_argument("--steps", type=int, default=100)
    ap.add_argument("--score-every", type=int, default=20)
    ap.add_argument("--scored-ms", type=int, default=7200)
    ap.add_argument("--gammas", default=",".join(map(str, GAMMAS)))
    ap.add_argument("--adaptive", default=",".join(ADAPTIVE))
    ap.add_argument("--processes", "--workers", dest="processes", type=int, default=2)
    ap.add_argument("--cache", type=Path, default=ROOT / "runs/adaptive-cache")
    ap.add_argument("--out", type=Path, default=ROOT / "results/adaptive")
    ap.add_argument("--dataset", default=None)
    common.add_json_option(ap)
    return ap


def run(args: argparse.Namespace, command: str = "python -m bench.adaptive") -> dict[str, Any]:
    """The study for ``parser()``'s options; writes ``<out>/results.json`` and returns it."""

    channels: list[tuple[str, str, str]] = []  # (label, kind, arg)
    names = [n for n in args.heldout.split(",") if n]
    if names and not args.traces_dir.is_dir():
        print(f"no traces at {args.traces_dir}: the trace channels are skipped (get mahimahi "
              "traces: see docs)")
        names = []
    channels += [(n, "trace", n) for n in names]
    if args.regimes:
        channels.append((args.regimes, "spec", args.regimes))
    gammas = tuple(int(g) for g in args.gammas.split(","))
    rules = fixed_rules(gammas)
    adaptive = [p for p in args.adaptive.split(",") if p]
    preset = get_preset("quick")
    base = preset.episode.with_(steps_per_epoch=args.steps, lpips=False,
                                score_every=args.score_every, scored_ms=args.scored_ms)
    if args.dataset:
        base = base.with_(dataset=args.dataset)
    ds = open_dataset(base.dataset)
    cache = ResultCache(args.cache)
    seeds = list(range(args.seed_offset, args.seed_offset + args.seeds))
    span = base.end_ms + 100
    started = time.perf_counter()
    counts = {"computed": 0, "cached": 0}

    def evaluate(plans: Any) -> Any:
        out = run_plans(plans, cache=cache, processes=args.processes, dataset=ds)
        counts["computed"] += out.computed
        counts["cached"] += out.cached
        return out.results

    # 1. the fixed rules' one-decision plans, all channels and seeds in one parallel batch
    batch = []
    setups = {}
    for label, kind, arg in channels:
        for seed in seeds:
            cfg = base.with_(delay=channel_spec(kind, arg, seed, span, args.traces_dir,
                                                args.spread_ms))
            setups[(label, seed)] = cfg
            for rule in rules:
                wait = parse_policy(rule).wait_ms
                links = episode_links(cfg, ds, seed, wait_ms=wait)
                plan = plan_episode(cfg, ds, rule, seed, links=links)
                for d in plan.decisions:
                    if d.scored:
                        batch.append(replace(plan, decisions=(d,)))
    print(f"{len(channels)} channel(s) × {len(seeds)} seeds; {len(batch)} rule decisions "
          f"to score", flush=True)
    done = [0]

    def progress(k: int, n: int) -> None:
        if k and (k % 20 == 0 or k == n):
            print(f"  {k}/{n} reconstructions ({time.perf_counter() - started:.0f} s)",
                  flush=True)
        done[0] = k

    out = run_plans(batch, cache=cache, processes=args.processes, dataset=ds, progress=progress)
    counts["computed"] += out.computed
    counts["cached"] += out.cached

    # 2. every policy, step by step (the rules from the cache; the adaptive ones mostly)
    episodes: list[dict[str, Any]] = []
    for label, _kind, _arg in channels:
        for seed in seeds:
            cfg = setups[(label, seed)]
            links = episode_links(cfg, ds, seed)
            for pol in [*rules, *adaptive]:
                (ep,) = run_stepwise(cfg, ds, pol, [seed], evaluate)
                scored = [d for d in ep.plan.decisions if d.scored]
                gam = [g for d, g in zip(ep.plan.decisions, ep.gamma_ms, strict=True)
                       if d.scored]
                episodes.append({
                    "channel": label, "delay": cfg.delay, "seed": seed, "policy": pol,
                    "psnr_db": ep.result.psnr_db, "n_selected": ep.result.n_selected,
                    "epochs_psnr_db": [e.psnr_db for e in ep.result.epochs],
                    "decision_ms": [d.decision_ms for d in scored],
                    "gamma_ms": gam,
                    "window_delay_ms": [window_delay_ms(links, d.decision_ms)
                                        for d in scored],
                })
            print(f"  {label} seed {seed}: done ({time.perf_counter() - started:.0f} s)",
                  flush=True)

    analysis = analyse(episodes, channels, seeds, rules, adaptive, gammas)
    doc = {"command": command,
           "heldout": names, "regimes": args.regimes or None, "seeds": seeds,
           "episode_config": base.to_dict(), "rules": rules, "adaptive": adaptive,
           "reconstructions": counts, "wall_s": round(time.perf_counter() - started, 1),
           "analysis": analysis, "episodes": episodes}
    common.write_json(args.out / "results.json", doc, indent=1, default=float)
    print_tables(analysis)
    print(f"\n{counts}; {doc['wall_s']} s; {args.out / 'results.json'}")
    return doc


def main(argv: list[str] | None = None) -> int:
    args = parser().parse_args(argv)
    command = "python -m bench.adaptive " + " ".join(sys.argv[1:] if argv is None else argv)
    with common.progress_to_stderr(args.json):
        doc = run(args, command.strip())
    if args.json:
        common.print_json(doc, indent=1, default=float)
    return 0


def _d(diff: Any) -> dict[str, float]:
    return {"mean": diff.mean, "ci95": diff.half, "n": diff.n}


def analyse(episodes: list[dict[str, Any]], channels: list[tuple[str, str, str]],
            seeds: list[int], rules: list[str], adaptive: list[str],
            gammas: tuple[int, ...]) -> dict[str, Any]:
    by = {(e["channel"], e["policy"], e["seed"]): e for e in episodes}
    out: dict[str, Any] = {"channels": {}}
    decide_at_t = [r for r in rules if kind_of(r).kind != "wait"]
    mats = [MatPolicy(g).spec for g in gammas]
    pooled: dict[str, dict[tuple[str, int], float]] = {}
    for label, _k, _a in channels:
        per = {p: {s: by[(label, p, s)]["psnr_db"] for s in seeds}
               for p in [*rules, *adaptive]}
        for p, v in per.items():
            pooled.setdefault(p, {}).update({(label, s): x for s, x in v.items()})
        # the oracle over the rules deciding at t, per scored decision
        oracle = {}
        for s in seeds:
            rows = np.array([by[(label, r, s)]["epochs_psnr_db"] for r in decide_at_t])
            oracle[s] = float(rows.max(axis=0).mean())
        pooled.setdefault("oracle", {}).update({(label, s): x for s, x in oracle.items()})
        means = {p: float(np.mean(list(v.values()))) for p, v in per.items()}
        best_rule = max(rules, key=lambda p: means[p])
        rows_out = []
        for p in [*rules, *adaptive, "oracle"]:
            v = oracle if p == "oracle" else per[p]
            m = mean_ci95(v.values())
            rows_out.append({"policy": p, "psnr_db": m.mean, "ci95": m.half,
                             "minus_best_rule": _d(paired_difference(v, per[best_rule]))})
        out["channels"][label] = {
            "best_rule": best_rule, "rows": rows_out,
            "adaptive_minus_best_rule": {p: _d(paired_difference(per[p], per[best_rule]))
                                         for p in adaptive},
            "oracle_minus_best_rule": _d(paired_difference(oracle, per[best_rule])),
            "G": switching_gain([by[(label, m, s)] for m in mats for s in seeds], mats, seeds),
            "gamma_trace": {p: {str(s): by[(label, p, s)]["gamma_ms"] for s in seeds}
                            for p in adaptive},
            "window_delay_ms": {str(s): by[(label, mats[0], s)]["window_delay_ms"]
                                for s in seeds},
        }
    # pooled over the channels: units (channel, seed)
    units = sorted(next(iter(pooled.values())).keys())
    key = {u: i for i, u in enumerate(units)}
    flat = {p: {key[u]: x for u, x in v.items()} for p, v in pooled.items()}
    means = {p: float(np.mean(list(flat[p].values()))) for p in rules}
    best_single = max(rules, key=lambda p: means[p])
    out["pooled"] = {
        "units": [list(u) for u in units], "best_single_rule": best_single,
        "rule_means": means,
        "adaptive_minus_best_single_rule": {p: _d(paired_difference(flat[p], flat[best_single]))
                                            for p in adaptive},
        "oracle_minus_best_single_rule": _d(paired_difference(flat["oracle"],
                                                              flat[best_single])),
        "G": switching_gain([e for e in episodes if e["policy"] in mats], mats, seeds,
                            pooled=True),
    }
    return out


def switching_gain(eps: list[dict[str, Any]], mats: list[str], seeds: list[int],
                   pooled: bool = False) -> dict[str, Any]:
    """G over delay regimes: every scored decision binned by its window's mean transmission
    time; per bin the MAT Γ with the best mean PSNR; G = per seed (channel, seed when pooled)
    the mean over its decisions of PSNR(best Γ of the bin) − PSNR(best single Γ), paired."""
    rows = []  # (unit, bin, mat, psnr)
    for e in eps:
        unit = (e["channel"], e["seed"]) if pooled else e["seed"]
        for y, q in zip(e["window_delay_ms"], e["epochs_psnr_db"], strict=True):
            b = int(np.digitize(y, DELAY_BINS_MS[1:-1])) if math.isfinite(y) else -1
            rows.append((unit, b, e["policy"], q))
    if not rows:
        return {}
    bins = sorted({r[1] for r in rows})
    mean = {}
    for b in bins:
        for m in mats:
            v = [r[3] for r in rows if r[1] == b and r[2] == m]
            mean[(b, m)] = float(np.mean(v)) if v else -math.inf
    overall = {m: float(np.mean([r[3] for r in rows if r[2] == m])) for m in mats}
    single = max(mats, key=lambda m: overall[m])
    best = {b: max(mats, key=lambda m: mean[(b, m)]) for b in bins}
    units = sorted({r[0] for r in rows}, key=str)
    per_unit_best: dict[Any, list[float]] = {u: [] for u in units}
    per_unit_single: dict[Any, list[float]] = {u: [] for u in units}
    for u, b, m, q in rows:
        if m == best[b]:
            per_unit_best[u].append(q)
        if m == single:
            per_unit_single[u].append(q)
    idx = {u: i for i, u in enumerate(units)}
    a = {idx[u]: float(np.mean(v)) for u, v in per_unit_best.items() if v}
    c = {idx[u]: float(np.mean(v)) for u, v in per_unit_single.items() if v}
    lo = [DELAY_BINS_MS[b] for b in bins]
    return {"best_single": single,
            "bins": [{"from_ms": lo[i], "best": best[b],
                      "decisions": sum(1 for r in rows if r[1] == b and r[2] == mats[0])}
                     for i, b in enumerate(bins)],
            "G": _d(paired_difference(a, c))}


def print_tables(analysis: dict[str, Any]) -> None:
    for label, ch in analysis["channels"].items():
        print(f"\n== {label}: best fixed rule in hindsight {ch['best_rule']}")
        for r in ch["rows"]:
            d = r["minus_best_rule"]
            print(f"  {r['policy']:32s} {r['psnr_db']:7.2f} ± {r['ci95']:.2f}   "
                  f"− best rule {d['mean']:+.2f} ± {d['ci95']:.2f}")
        g = ch["G"]
        if g:
            print(f"  G over delay bins: {g['G']['mean']:+.2f} ± {g['G']['ci95']:.2f} "
                  f"(best single {g['best_single']}; bins {g['bins']})")
    p = analysis["pooled"]
    print(f"\n== pooled: best single fixed rule {p['best_single_rule']}")
    for k, d in p["adaptive_minus_best_single_rule"].items():
        print(f"  {k:32s} − best single rule {d['mean']:+.2f} ± {d['ci95']:.2f}")
    d = p["oracle_minus_best_single_rule"]
    print(f"  {'oracle (rules at t)':32s} − best single rule {d['mean']:+.2f} ± {d['ci95']:.2f}")
    if p["G"]:
        print(f"  G pooled: {p['G']['G']['mean']:+.2f} ± {p['G']['G']['ci95']:.2f}")


if __name__ == "__main__":
    sys.exit(main())
