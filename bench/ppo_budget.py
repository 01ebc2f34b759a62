"""Benchmark: is the PPO quick preset's cheaper episode (100 field steps) a faithful proxy of
the experiments' 300?

Scores rule policies on the same one-decision episodes of ``aoi3d/FrameSelection-v0`` (the
experiment quick preset's episode config, ``steps_per_epoch`` 100 and 300) with
:func:`aoi3d.rl.evaluate.evaluate` on seeds 2,000,000+ (neither training nor held-out seeds), and
reports per budget the mean reward/PSNR/SSIM/LPIPS of each policy, their ranking, the
Spearman correlation of the two rankings, and the wall time of a computed episode.
Writes ``results/ppo_budget.json``. Run: ``python -m bench.ppo_budget [SEEDS]``
(10 seeds: about 5 minutes on 2 cores).
"""

from __future__ import annotations

import argparse
import time

import numpy as np
from scipy import stats

from aoi3d.experiment import get_preset
from aoi3d.experiment.report import machine
from aoi3d.rl.evaluate import evaluate
from bench import common

POLICIES = ("all", "mat:40", "mat:70", "mat:100", "mat:160", "freshest:6", "freshest:12")
BUDGETS = (100, 300)
SEED_BASE = 2_000_000


def parser() -> argparse.ArgumentParser:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("seeds", nargs="?", type=int, default=10, metavar="SEEDS",
                    help="episodes per policy and budget (default 10)")
    common.add_json_option(ap)
    return ap


def run(n_seeds: int = 10) -> dict:
    """Both budgets on ``n_seeds`` seeds; writes ``results/ppo_budget.json`` and returns
    its document."""
    seeds = [SEED_BASE + s for s in range(n_seeds)]
    base = get_preset("quick").episode
    doc: dict[str, object] = {"policies": POLICIES, "seeds": seeds, "machine": machine(),
                              "dataset": base.dataset, "budgets": {}}
    means: dict[int, list[float]] = {}
    for steps in BUDGETS:
        started = time.perf_counter()
        outcome = evaluate(POLICIES, base.with_(steps_per_epoch=steps), seeds, processes=2)
        walls = [r["wall_s"] for r in outcome.rows if not r["cached"]]
        means[steps] = [r["reward"] for r in outcome.summary]
        doc["budgets"][steps] = {  # type: ignore[index]
            "summary": outcome.summary, "wall_s": time.perf_counter() - started,
            "episode_wall_s_median": float(np.median(walls)), "episodes_computed": len(walls)}
        print(f"{steps} steps: median episode {np.median(walls):.2f} s")
        for r in outcome.summary:
            print(f"  {r['policy']:12s} reward {r['reward']:.4f} ± {r['reward_ci95']:.4f}  "
                  f"PSNR {r['psnr']:.2f}  SSIM {r['ssim']:.3f}  LPIPS {r['lpips']:.3f}  "
                  f"cameras {r['n_selected']:.1f}")
    rho = float(stats.spearmanr(means[BUDGETS[0]], means[BUDGETS[1]]).statistic)
    doc["spearman_reward"] = rho
    print(f"Spearman correlation of the policies' mean rewards, {BUDGETS}: {rho:.3f}")
    common.write_json(common.RESULTS / "ppo_budget.json", doc, indent=1, default=float)
    return doc


def main(argv: list[str] | None = None) -> None:
    args = parser().parse_args(argv)
    with common.progress_to_stderr(args.json):
        doc = run(args.seeds)
    if args.json:
        common.print_json(doc, indent=1, default=float)


if __name__ == "__main__":
    main()
