"""The switching gain G (issue 32, section 2): how much an adaptive threshold could gain over
the best single MAT Γ when the channel moves between regimes.

    G = mean over regimes of (best Γ for that regime) − (best single Γ across all regimes)

measured on the virtual clock (quick preset, seed-paired), over

- the stationary delays E[Y] ∈ {10, 20, 40, 60, 100, 150, 200} ms (``exp:``), Γ up to 300 ms;
- 10-s windows of the cellular traces in ``../shared/data/traces`` (``trace:``, each camera
  at its own phase inside the window, the frames' stored PNG sizes);

and against the per-decision oracle over the same Γ arms (at each scored decision the best of
the Γ's selections, scored with the truth — the bound of any threshold that switches per
decision). Every paired difference is a 95% Student-t interval over the seeds.

``python -m bench.switching run`` computes the missing episodes (the experiments' cache,
seed-major, so an interrupted run has covered every point with its first seeds);
``python -m bench.switching report [--json]`` reads whatever the cache holds, uses the seeds
complete for every point, and writes ``results/switching/switching.json``.

Episodes already computed by ``make science`` (``results/science/``: the delay sweep at
exp:20/60/100, Γ 40–160, seeds 20000–20005) are reused: each is re-planned here and its plan
checked to be the very one the science run keyed (same selections, same seed, dataset root
aside) before it enters this run's cache.
"""

from __future__ import annotations

import argparse
import dataclasses
import glob
import json
import math
import time
from pathlib import Path
from typing import Any

import numpy as np

from aoi3d.experiment.config import get_preset
from aoi3d.experiment.episode import EpisodeResult, plan_episode, plan_key
from aoi3d.experiment.sweep import Job, ResultCache, lpips_available, run_jobs
from aoi3d.policy import MatPolicy, PolicySpecError, kind_of
from aoi3d.scene import open_dataset
from aoi3d.stats import mean_ci95
from bench import common
from bench.common import ROOT

TRACES = ROOT.parent / "shared" / "data" / "traces"
OUT = ROOT / "results" / "switching"
CACHE = ROOT / "runs" / "experiments" / "cache"
SEED0 = 20000
MEANS_MS = (10, 20, 40, 60, 100, 150, 200)
GAMMAS = (40, 70, 100, 130, 160, 220, 300)
WINDOW_GAMMAS = (40, 70, 100, 160)
# 10-s windows of the traces at the experiments' frame sizes (stored PNGs, ~4.8 kB = 4
# packets): (trace, window start ms, one camera's mean transmission time in that window ms)
WINDOWS = (
    ("TMobile-LTE-short.up", 120_000, 2.5),   # the trace's 10th-percentile window
    ("Verizon-LTE-short.up", 40_000, 26.3),   # 90th percentile
    ("TMobile-UMTS-driving.up", 80_000, 137.9),  # 90th percentile
)
SCIENCE_MAIN_ROOT = "/work/main/data/turbine-rotor"  # where make science's episodes were keyed


def window_spec(name: str, start_ms: int) -> str:
    # cameras at their own phases inside the window (an episode lasts ~2.1 s)
    return f"trace:{TRACES / name},offset={start_ms},spread=7800"


def regimes() -> list[tuple[str, str, tuple[int, ...]]]:
    """(label, delay spec, Γ swept)."""
    out: list[tuple[str, str, tuple[int, ...]]] = [
        (f"E[Y]={m}", f"exp:{m}", GAMMAS) for m in MEANS_MS]
    if TRACES.is_dir():
        out += [(f"{n}@{s // 1000}s", window_spec(n, s), WINDOW_GAMMAS) for n, s, _ in WINDOWS]
    return out


def seed_science(cfg, ds, cache: ResultCache) -> int:
    """Put make science's episodes into this cache, each after checking its plan is ours."""
    lp = lpips_available(cfg)
    main = dataclasses.replace(ds, root=Path(SCIENCE_MAIN_ROOT))
    n = 0
    for path in glob.glob(str(ROOT / "results/science/*/results.json")):
        doc = json.loads(Path(path).read_text())
        for ep in doc.get("episodes", []):
            if family_kind(ep.get("policy", "")) != "mat":
                continue
            plan = plan_episode(cfg.with_(delay=ep["delay"]), ds, ep["policy"], ep["seed"])
            if plan_key(plan, main, lpips=lp) != ep["key"]:
                continue  # another config or code: not ours
            key = plan_key(plan, ds, lpips=lp)
            if key not in cache:
                cache.put(EpisodeResult.from_dict({**ep, "key": key}), b"")
                n += 1
    return n


def compute(seeds: int, processes: int) -> None:
    """``run``: the missing episodes into the experiments' cache."""
    preset = get_preset("quick")
    cfg = preset.episode
    ds = open_dataset(cfg.dataset)
    cache = ResultCache(CACHE)
    print(f"seeded {seed_science(cfg, ds, cache)} episodes from make science", flush=True)
    jobs = [Job(MatPolicy(g).spec, spec, s) for s in range(SEED0, SEED0 + seeds)
            for _, spec, gammas in regimes() for g in gammas]
    started = time.time()

    def progress(done: int, total: int) -> None:
        print(f"{time.strftime('%H:%M:%S')} {done}/{total} episodes computed "
              f"({time.time() - started:.0f} s)", flush=True)

    out = run_jobs(cfg, jobs, cache=cache, processes=processes, progress=progress, dataset=ds)
    print(f"done: {out.computed} computed, {out.cached} cached, {out.wall_s:.0f} s")


def family_kind(label: str) -> str | None:
    """The registered kind of a result's label (None for a label no kind reads)."""
    try:
        return kind_of(str(label)).kind
    except PolicySpecError:
        return None


# ------------------------------------------------------------------------------ the report
def ci95(x: np.ndarray) -> tuple[float, float]:
    """Mean and 95% half-width (:func:`aoi3d.stats.mean_ci95`)."""
    m = mean_ci95(np.asarray(x, dtype=np.float64).tolist())
    return m.mean, m.half


def collect(seeds: int, metric: str = "psnr_db") -> dict[str, Any]:
    """Q[regime][Γ][seed] (episode means) and D[regime][Γ][seed] (per scored decision)."""
    cfg = get_preset("quick").episode
    ds = open_dataset(cfg.dataset)
    cache = ResultCache(CACHE)
    lp = lpips_available(cfg)
    table: dict[str, dict[int, dict[int, EpisodeResult]]] = {}
    specs = {}
    for label, spec, gammas in regimes():
        specs[label] = spec
        table[label] = {}
        for g in gammas:
            table[label][g] = {}
            for s in range(SEED0, SEED0 + seeds):
                plan = plan_episode(cfg.with_(delay=spec), ds, MatPolicy(g).spec, s)
                hit = cache.get(plan_key(plan, ds, lpips=lp))
                if hit is not None:
                    table[label][g][s] = hit
    return {"table": table, "specs": specs}


def gain(table, labels: list[str], gammas: tuple[int, ...], seeds: list[int],
         metric: str = "psnr_db") -> dict[str, Any]:
    """G over ``labels`` (equal weights), paired by seed; and the per-decision oracle."""
    q = np.array([[[getattr(table[r][g][s], metric) for s in seeds] for g in gammas]
                  for r in labels])  # (R, Γ, S)
    mean_rg = q.mean(axis=2)
    single = int(np.argmax(mean_rg.mean(axis=0)))
    best = mean_rg.argmax(axis=1)  # per regime
    per_seed_g = np.mean([q[i, best[i]] - q[i, single] for i in range(len(labels))], axis=0)
    # leave-one-seed-out: choose Γ's on the other seeds, judge on the left-out one (no
    # winner's curse from picking and judging on the same seeds)
    loo = []
    for k in range(len(seeds)):
        keep = [j for j in range(len(seeds)) if j != k]
        m = q[:, :, keep].mean(axis=2)
        b1, br = int(np.argmax(m.mean(axis=0))), m.argmax(axis=1)
        loo.append(np.mean([q[i, br[i], k] - q[i, b1, k] for i in range(len(labels))]))
    # per-decision oracle over the Γ arms
    def decisions(r: str, g: int, s: int) -> np.ndarray:
        return np.array([getattr(e, metric) for e in table[r][g][s].epochs
                         if getattr(e, metric, None) is not None])
    oracle = np.array([[np.max(np.stack([decisions(r, g, s) for g in gammas]), axis=0).mean()
                        for s in seeds] for r in labels])  # (R, S)
    o_minus_single = (oracle - q[:, single, :]).mean(axis=0)
    o_minus_best = np.mean([oracle[i] - q[i, best[i]] for i in range(len(labels))], axis=0)
    regret = {labels[i]: {
        "best_gamma_ms": gammas[best[i]],
        "single_loses_db": ci95(q[i, best[i]] - q[i, single]),
        "curve_db": {gammas[j]: ci95(q[i, j]) for j in range(len(gammas))},
    } for i in range(len(labels))}
    return {"regimes": labels, "seeds": seeds, "gammas_ms": list(gammas),
            "best_single_gamma_ms": gammas[single],
            "G_db": ci95(per_seed_g), "G_leave_one_seed_out_db": ci95(np.array(loo)),
            "oracle_minus_single_db": ci95(o_minus_single),
            "oracle_minus_per_regime_best_db": ci95(o_minus_best),
            "per_regime": regret}


def report(seeds: int) -> dict[str, Any]:
    data = collect(seeds)
    table = data["table"]
    out: dict[str, Any] = {"specs": data["specs"], "sets": {}}
    labels = list(table)
    delays = [r for r in labels if r.startswith("E[Y]")]
    windows = [r for r in labels if not r.startswith("E[Y]")]

    def complete(rs: list[str], gammas: tuple[int, ...]) -> list[int]:
        return [s for s in range(SEED0, SEED0 + seeds)
                if all(s in table[r][g] for r in rs for g in gammas)]

    sets = {
        "all seven delays": (delays, GAMMAS),
        "20 and 100 ms": (["E[Y]=20", "E[Y]=100"], GAMMAS),
        "20, 60, 100 ms": (["E[Y]=20", "E[Y]=60", "E[Y]=100"], GAMMAS),
        "10 and 200 ms": (["E[Y]=10", "E[Y]=200"], GAMMAS),
        "20 and 100 ms, Γ ≤ 160 (the issue's first look)": (
            ["E[Y]=20", "E[Y]=100"], (40, 70, 100, 130, 160)),
        "trace windows": (windows, WINDOW_GAMMAS),
        "all seven delays, Γ of the windows": (delays, WINDOW_GAMMAS),
    }
    for name, (rs, gammas) in sets.items():
        if not rs:
            continue
        ss = complete(rs, gammas)
        if len(ss) < 2:
            out["sets"][name] = {"regimes": rs, "seeds": ss, "note": "fewer than 2 seeds"}
            continue
        out["sets"][name] = gain(table, rs, gammas, ss)
    return out


def _pm(x: tuple[float, float], signed: bool = True) -> str:
    m, h = x
    text = f"{m:+.2f}" if signed else f"{m:.2f}"
    return text + ("" if not math.isfinite(h) else f" ± {h:.2f}")


def markdown(result: dict[str, Any]) -> str:
    """The report's tables, as docs/experiments.md shows them."""
    lines = ["| regimes | seeds | best single Γ | G (dB) | G, leave-one-seed-out (dB) | "
             "per-decision oracle − single Γ (dB) | oracle − per-regime best Γ (dB) |",
             "|---|---|---|---|---|---|---|"]
    for name, r in result["sets"].items():
        if "G_db" not in r:
            continue
        lines.append(f"| {name} | {len(r['seeds'])} | {r['best_single_gamma_ms']} | "
                     f"{_pm(r['G_db'])} | {_pm(r['G_leave_one_seed_out_db'])} | "
                     f"{_pm(r['oracle_minus_single_db'])} | "
                     f"{_pm(r['oracle_minus_per_regime_best_db'])} |")
    lines.append("")
    for name in ("all seven delays", "trace windows"):
        r = result["sets"].get(name, {})
        if "per_regime" not in r:
            continue
        gammas = r["gammas_ms"]
        lines += ["", f"**{name}** (PSNR in dB, mean ± 95% CI over seeds "
                      f"{r['seeds'][0]}–{r['seeds'][-1]}; best single Γ "
                      f"{r['best_single_gamma_ms']}):", "",
                  "| regime | " + " | ".join(f"Γ {g}" for g in gammas)
                  + " | best Γ | single Γ loses (dB) |",
                  "|---|" + "---|" * (len(gammas) + 2)]
        for lab, pr in r["per_regime"].items():
            cells = []
            for g in gammas:
                m, _h = pr["curve_db"][g] if g in pr["curve_db"] else pr["curve_db"][str(g)]
                cell = f"{m:.2f}"
                cells.append(f"**{cell}**" if g == pr["best_gamma_ms"] else cell)
            lines.append(f"| {lab} | " + " | ".join(cells)
                         + f" | {pr['best_gamma_ms']} | {_pm(pr['single_loses_db'])} |")
    return "\n".join(lines) + "\n"


def run(seeds: int = 6) -> dict[str, Any]:
    """``report``: the result document from what the cache holds; writes
    ``results/switching/{switching.json,report.md}`` and returns the document."""
    result = report(seeds)
    OUT.mkdir(parents=True, exist_ok=True)
    (OUT / "switching.json").write_text(json.dumps(result, indent=1, default=str))
    (OUT / "report.md").write_text(markdown(result))
    return result


def print_summary(result: dict[str, Any]) -> None:
    for name, r in result["sets"].items():
        if "G_db" not in r:
            print(f"{name}: {r.get('note')}")
            continue
        g, gl = r["G_db"], r["G_leave_one_seed_out_db"]
        o1, o2 = r["oracle_minus_single_db"], r["oracle_minus_per_regime_best_db"]
        print(f"{name}: seeds {len(r['seeds'])}, best single Γ {r['best_single_gamma_ms']}; "
              f"G {g[0]:+.2f} ± {g[1]:.2f} dB (leave-one-seed-out {gl[0]:+.2f} ± {gl[1]:.2f}); "
              f"oracle − single {o1[0]:+.2f} ± {o1[1]:.2f}, oracle − per-regime best "
              f"{o2[0]:+.2f} ± {o2[1]:.2f}")
        for lab, pr in r["per_regime"].items():
            print(f"   {lab}: best Γ {pr['best_gamma_ms']}, single Γ loses "
                  f"{pr['single_loses_db'][0]:+.2f} ± {pr['single_loses_db'][1]:.2f} dB")


def parser() -> argparse.ArgumentParser:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("what", choices=("run", "report"),
                    help="run: compute the missing episodes; report: the result document")
    ap.add_argument("--seeds", type=int, default=6)
    ap.add_argument("--processes", "--workers", dest="processes", type=int, default=2)
    common.add_json_option(ap, help="report: print the result document as JSON")
    return ap


def main(argv: list[str] | None = None) -> None:
    args = parser().parse_args(argv)
    with common.progress_to_stderr(args.json):
        if args.what == "run":
            compute(args.seeds, args.processes)
            return
        result = run(args.seeds)
        print_summary(result)
    if args.json:
        common.print_json(result, default=str)


if __name__ == "__main__":
    main()
