"""The tradeoff at display time: MAT Γ × reconstruction steps on the virtual clock (issue 33).

Each scored decision's render is scored twice (:func:`aoi3d.experiment.run_plan`): against
the truth at its decision time (``psnr_db``) and against the truth once its reconstruction is
done (``psnr_display_db``: the decision time plus ``EpisodeConfig.compute_ms(steps)``, the
measured cost model at ``--time-scale``). The steps budget now trades fidelity for age. For
every (Γ, steps) of the grid, seeds ``--seed-offset`` … (paired: every cell sees the same
links), the quick preset's episode with the ``fresh`` carry; it writes the heat maps of both
metrics with their optimum, a CSV of the cells, and the paired difference (per seed) between
the display-time optimum and the best Γ at decision time, both read at display time.

    python -m bench.display_sweep                                  # the default grid
    python -m bench.display_sweep --gammas 40,70,130 --steps 25,100 --seeds 2

Results: ``results/streaming/display-sweep/`` (``cells.csv``, ``results.json``,
``display_sweep.png``); episodes are cached under ``runs/display-sweep-cache``.
"""

from __future__ import annotations

import argparse
import csv
import json
import sys
import time
from pathlib import Path
from typing import Any

import numpy as np

from aoi3d.experiment import ResultCache, get_preset, run_jobs
from aoi3d.experiment.sweep import Job, mean_ci95
from aoi3d.metric import (
    PSNR,
    PSNR_DISPLAY,
    PSNR_DYNAMIC,
    PSNR_DYNAMIC_DISPLAY,
    REWARD,
    REWARD_DISPLAY,
    names_of,
)
from aoi3d.policy import MatPolicy
from bench import common

ROOT = Path(__file__).resolve().parents[1]


def _ints(text: str) -> list[int]:
    return [int(v) for v in text.split(",") if v.strip()]


def parser() -> argparse.ArgumentParser:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--gammas", type=_ints, default=[40, 70, 100, 130, 160])
    ap.add_argument("--steps", type=_ints, default=[25, 50, 100, 200])
    ap.add_argument("--seeds", type=int, default=2)
    ap.add_argument("--seed-offset", type=int, default=300,
                    help="first seed (the science runs use 0…; these are fresh ones)")
    ap.add_argument("--delay", default="exp:60")
    ap.add_argument("--time-scale", type=float, default=0.1,
                    help="the live run's time scale the compute is charged at")
    ap.add_argument("--processes", "--workers", dest="processes", type=int, default=1)
    ap.add_argument("--out", type=Path,
                    default=ROOT / "results" / "streaming" / "display-sweep")
    ap.add_argument("--cache", type=Path, default=ROOT / "runs" / "display-sweep-cache")
    common.add_json_option(ap, help="print the whole result document (cells too) as JSON")
    return ap


def main(argv: list[str] | None = None) -> None:
    args = parser().parse_args(argv)
    with common.progress_to_stderr(args.json):
        doc = run(args, argv)
    if args.json:
        common.print_json(doc)


def run(args: argparse.Namespace, argv: list[str] | None = None) -> dict:
    """The Γ × steps grid (``parser()``'s options; ``argv``, or this process's, is recorded
    as the command); writes into ``args.out`` and returns the result document."""
    base = get_preset("quick").episode.with_(time_scale=args.time_scale, carry="fresh")
    seeds = list(range(args.seed_offset, args.seed_offset + args.seeds))
    started = time.perf_counter()
    cells: dict[tuple[int, int], list] = {}
    for steps in args.steps:
        cfg = base.with_(steps_per_epoch=steps)
        mats = [(MatPolicy(g), s) for g in args.gammas for s in seeds]
        jobs = [Job(mat.spec, args.delay, s) for mat, s in mats]
        out = run_jobs(cfg, jobs, cache=ResultCache(args.cache), processes=args.processes)
        for (mat, _), result in zip(mats, out.results, strict=True):
            cells.setdefault((int(mat.gamma_ms), steps), []).append(result)
        print(f"steps {steps}: {out.computed} computed, {out.cached} cached", flush=True)
    rows: list[dict[str, Any]] = []
    for (gamma, steps), results in sorted(cells.items()):
        row: dict[str, Any] = {"gamma_ms": gamma, "steps": steps, "n": len(results)}
        for metric in (*names_of((PSNR, PSNR_DISPLAY, PSNR_DYNAMIC, PSNR_DYNAMIC_DISPLAY, REWARD,
                               REWARD_DISPLAY)), "compute_ms"):
            mean, half, _ = mean_ci95(getattr(r, metric) for r in results)
            row[metric], row[f"{metric}_ci95"] = mean, half
        rows.append(row)
    best_display = max(rows, key=lambda r: r["psnr_display_db"])
    best_decision = max(rows, key=lambda r: r["psnr_db"])
    # paired by seed: the display-time optimum against the decision-time optimum's cell and
    # against the best Γ at decision time with the live budget (100 steps), both at display
    def per_seed(cell: dict, metric: str) -> dict[int, float]:
        return {r.seed: getattr(r, metric) for r in cells[(cell["gamma_ms"], cell["steps"])]}

    def paired(a: dict, b: dict, metric: str) -> dict:
        x, y = per_seed(a, metric), per_seed(b, metric)
        diff = [x[s] - y[s] for s in sorted(x) if s in y]
        mean, half, n = mean_ci95(diff)
        return {"mean": mean, "ci95": half, "n": n}

    for r in rows:  # every cell against the display-time optimum, paired by seed
        r["psnr_display_db_by_seed"] = per_seed(r, "psnr_display_db")
        if r is not best_display:
            diff = paired(best_display, r, "psnr_display_db")
            r["best_display_minus_this_db"], r["best_display_minus_this_ci95"] = (
                diff["mean"], diff["ci95"])
    live = [r for r in rows if r["steps"] == 100]
    best_live_decision = max(live, key=lambda r: r["psnr_db"]) if live else None
    doc = {
        "command": " ".join(["python", "bench/display_sweep.py", *(argv or sys.argv[1:])]),
        "delay": args.delay, "time_scale": args.time_scale, "seeds": seeds,
        "cost_model_ms": {"fixed": base.compute_fixed_ms, "per_step": base.compute_step_ms},
        "cells": rows,
        "best_at_display": {k: best_display[k] for k in ("gamma_ms", "steps")},
        "best_at_decision": {k: best_decision[k] for k in ("gamma_ms", "steps")},
        "display_best_minus_decision_best_at_display_db":
            paired(best_display, best_decision, "psnr_display_db"),
        "best_at_decision_100_steps": ({k: best_live_decision[k] for k in ("gamma_ms", "steps")}
                                       if best_live_decision else None),
        "display_best_minus_decision_best_100_steps_at_display_db":
            (paired(best_display, best_live_decision, "psnr_display_db")
             if best_live_decision else None),
        "wall_s": round(time.perf_counter() - started, 1),
    }
    args.out.mkdir(parents=True, exist_ok=True)
    with open(args.out / "cells.csv", "w", newline="") as fh:
        writer = csv.DictWriter(fh, fieldnames=list(rows[1] if len(rows) > 1 else rows[0]),
                                extrasaction="ignore")
        writer.writeheader()
        writer.writerows(rows)
    (args.out / "results.json").write_text(json.dumps(doc, indent=2) + "\n")
    figure(rows, args.gammas, args.steps, args.out / "display_sweep.png", doc)
    print(json.dumps({k: v for k, v in doc.items() if k != "cells"}, indent=2))
    return doc


def figure(rows: list[dict], gammas: list[int], steps: list[int], path: Path, doc: dict) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, 2, figsize=(10, 4), constrained_layout=True)
    for ax, metric, title in ((axes[0], "psnr_db", "PSNR at decision time (dB)"),
                              (axes[1], "psnr_display_db", "PSNR at display time (dB)")):
        grid = np.full((len(steps), len(gammas)), np.nan)
        for r in rows:
            grid[steps.index(r["steps"]), gammas.index(r["gamma_ms"])] = r[metric]
        im = ax.imshow(grid, origin="lower", aspect="auto", cmap="viridis")
        ax.set_xticks(range(len(gammas)), [str(g) for g in gammas])
        ax.set_yticks(range(len(steps)), [str(s) for s in steps])
        ax.set_xlabel("MAT threshold Γ (ms)")
        ax.set_ylabel("reconstruction steps")
        ax.set_title(title)
        for i in range(len(steps)):
            for j in range(len(gammas)):
                if np.isfinite(grid[i, j]):
                    ax.text(j, i, f"{grid[i, j]:.2f}", ha="center", va="center", fontsize=8,
                            color="white")
        bi, bj = np.unravel_index(np.nanargmax(grid), grid.shape)
        ax.add_patch(plt.Rectangle((bj - 0.5, bi - 0.5), 1, 1, fill=False, ec="red", lw=2))
        fig.colorbar(im, ax=ax)
    fig.suptitle(f"Γ × steps, {doc['delay']}, time scale {doc['time_scale']}, seeds "
                 f"{doc['seeds'][0]}–{doc['seeds'][-1]} (red: the optimum)")
    fig.savefig(path, dpi=110)
    plt.close(fig)


if __name__ == "__main__":
    main()
