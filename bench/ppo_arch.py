"""Benchmark: which PPO actor learns the frame selection within the 600-episode budget?

A cheap surrogate of the real reward (no radiance field) with the shape measured on the
experiments' scene (docs/ppo.md): 18 cameras, AoIs at decision epochs multiples of 30 ms; the
reward is 0.92, minus 0.012 per selected camera whose frame is stale (AoI ≥ 100 ms), minus
0.03 per fresh camera short of five, plus N(0, 0.04) noise (what the unobserved scene phase
adds). The best policy is the MAT rule Γ = 100 ms (0.92 on average); `all` scores ≈ 0.86.

Trains :class:`aoi3d.policy.ppo.learner.PPOLearner` with each actor (``mlp``, ``shared``)
for 38 updates of 16 episodes (= ``aoi3d ppo train --preset quick``) on three seeds and
reports the mean reward of the first and last three batches and of the trained deterministic
policy on 300 fresh episodes. Writes ``results/ppo_arch.json``. Run:
``python -m bench.ppo_arch`` (~1 min).
"""

from __future__ import annotations

import argparse
import platform
import time
from typing import Any

import numpy as np
import torch

from aoi3d.policy.ppo import Batch, PPOConfig
from aoi3d.policy.ppo.learner import PPOLearner
from bench import common

N, UPDATES, BATCH, SEEDS = 18, 38, 16, 3
HYPER: dict[str, Any] = {"lr": 1e-3, "minibatch_size": 8}


def sample_aoi(rng: np.random.Generator) -> np.ndarray:
    """AoIs at a decision epoch: whole frame periods (30 ms), mostly young."""
    return 30.0 * np.minimum(rng.geometric(0.35, N), 10)


def reward(aoi: np.ndarray, mask: np.ndarray, rng: np.random.Generator | None) -> float:
    fresh = aoi < 100.0
    n_fresh, n_stale = int((mask & fresh).sum()), int((mask & ~fresh).sum())
    r = 0.92 - 0.012 * n_stale - 0.03 * max(0, 5 - n_fresh)
    return r + (float(rng.normal(0.0, 0.04)) if rng is not None else 0.0)


def train_arch(arch: str, seed: int) -> dict[str, float]:
    """One actor trained on one seed: the mean rewards reported per actor."""
    rng = np.random.default_rng(seed)
    agent = PPOLearner(PPOConfig(n_cameras=N, seed=seed, arch=arch, **HYPER))
    batches = []
    for _ in range(UPDATES):
        obs, acts, logps, rewards = [], [], [], []
        for _ in range(BATCH):
            aoi = sample_aoi(rng)
            o = agent.observe(aoi)
            act = agent.sample(o)
            rewards.append(reward(aoi, act.action.astype(bool), rng))
            obs.append(o)
            acts.append(act.action)
            logps.append(act.logp)
        batches.append(float(np.mean(rewards)))
        agent.update(Batch(np.array(obs), np.array(acts), np.array(logps), np.array(rewards)))
    test = [sample_aoi(rng) for _ in range(300)]
    trained = [reward(a, agent.select(a), None) for a in test]
    return {"first_batches": float(np.mean(batches[:3])),
            "last_batches": float(np.mean(batches[-3:])),
            "trained_policy": float(np.mean(trained)),
            "mat100": float(np.mean([reward(a, a < 100.0, None) for a in test])),
            "all": float(np.mean([reward(a, np.ones(N, bool), None) for a in test]))}


def parser() -> argparse.ArgumentParser:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    common.add_json_option(ap)
    return ap


def run() -> dict:
    """Both actors on every seed; writes ``results/ppo_arch.json`` and returns its
    document."""
    torch.set_num_threads(1)
    started = time.perf_counter()
    out: dict[str, dict[str, float]] = {}
    for arch in ("mlp", "shared"):
        runs = [train_arch(arch, s) for s in range(SEEDS)]
        out[arch] = {k: float(np.mean([r[k] for r in runs])) for k in runs[0]}
        print(f"{arch:7s} " + "  ".join(f"{k} {v:.4f}" for k, v in out[arch].items()))
    doc = {"results": out, "updates": UPDATES, "batch": BATCH, "seeds": SEEDS, "hyper": HYPER,
           "wall_s": time.perf_counter() - started, "machine": platform.node()}
    common.write_json(common.RESULTS / "ppo_arch.json", doc, indent=1)
    return doc


def main(argv: list[str] | None = None) -> None:
    args = parser().parse_args(argv)
    with common.progress_to_stderr(args.json):
        doc = run()
    if args.json:
        common.print_json(doc, indent=1)


if __name__ == "__main__":
    main()
