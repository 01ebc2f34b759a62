"""Which per-camera features say which frame helps? (issue 25, item 3: features by measurement)

The greedy oracle (``oracle:greedy:psnr_db``, docs/experiments.md "The greedy search") tried,
at each of its rounds, every camera not yet chosen on top of the same base selection: a
controlled measurement of each camera's marginal value. This script replays that search from
the experiment cache (no reconstruction is computed when the cache holds them: the command in
docs/experiments.md filled ``runs/experiments/oracle-cache``) and asks, for every round, how
well a per-camera model predicts the candidates' PSNR from one feature set or another.

The target is the candidate's PSNR minus the mean of its round (the base selection's level
removed). Per candidate camera c at decision epoch t:

- ``aoi``: its AoI Δ_c(t) / 300 ms and its square (the AoI-only agent's state);
- ``id``: the camera's identity, one-hot (what the shipped agent's learned embedding can
  express for one fixed rig);
- ``pose``: its geometry against the held-out view, fixed per rig: the angle between the
  optical axes and the distance between the centres, and the angle's square;
- ``delay``: the channel delay of its newest frame (delivery − generation), the time since
  that delivery, and whether a newer frame of c is in flight at t;
- ``overlap``: the smallest angle between c's axis and the axis of a camera already in the
  base selection (π when it is empty): how much of c's view is covered already.

Each model is a ridge regression fitted with one decision left out at a time (leave-one-
decision-out, so no decision is scored by a model that saw it). Reported: the out-of-fold R²
and the **regret**: at each round, the PSNR of the best candidate minus the PSNR of the one
the model ranks first (dB, mean over rounds) — what choosing by that model would give up at
that round. Rounds of one candidate are skipped. Two references: a random pick (the mean
candidate) and the AoI rule's pick (the youngest frame). All of it three times: over every
round, over the first (which single camera), and over the later rounds (which camera to add
to a selection: the regime of a policy that picks 5–9 cameras).

    python -m bench.state_features          # results/state-features.json, a table
    python -m bench.state_features --json   # the document on stdout
"""

from __future__ import annotations

import argparse
import math
import sys
from dataclasses import replace
from pathlib import Path
from typing import Any

import numpy as np

from aoi3d.experiment import ResultCache, get_preset
from aoi3d.experiment.oracle import search_oracle
from aoi3d.experiment.sweep import open_dataset, run_plans
from aoi3d.policy.ppo.obs import pose_features
from bench import common
from bench.common import ROOT

FEATURE_SETS = {
    "aoi": ("aoi",),
    "aoi + id": ("aoi", "id"),
    "aoi + pose": ("aoi", "pose"),
    "aoi + pose + delay": ("aoi", "pose", "delay"),
    "aoi + pose + overlap": ("aoi", "pose", "overlap"),
    "aoi + pose + overlap + delay": ("aoi", "pose", "overlap", "delay"),
}


def geometry(ds, ids):
    """Per training camera: the pose features of the agent (angle to the held-out camera's
    axis / π, distance / the largest; :func:`aoi3d.policy.ppo.obs.pose_features`) and the unit
    optical axes (for overlaps)."""
    c2w = np.stack([ds.cameras[i].c2w for i in ids])
    pose = pose_features(c2w, ds.cameras[ds.heldout_id].c2w)
    axes = -c2w[:, :3, 2] / np.linalg.norm(c2w[:, :3, 2], axis=1, keepdims=True)
    return pose[:, 0], pose[:, 1], axes


def collect(args):
    """Every greedy candidate (its decision, selection and PSNR), the oracle's episodes, the
    episode config, the dataset and how many reconstructions were computed."""
    cfg = replace(get_preset("quick").episode, steps_per_epoch=args.steps,
                  dataset=str(ROOT / "data" / "turbine-rotor"))
    ds = open_dataset(cfg.dataset)
    cache = ResultCache(args.cache)
    rows: list[dict] = []
    computed = 0

    def evaluate(plans):
        nonlocal computed
        out = run_plans(plans, cache=cache, processes=args.processes, dataset=ds)
        computed += out.computed
        for plan, res in zip(plans, out.results, strict=True):
            mask = np.array([c == "1" for c in plan.policy.split(":", 1)[1]])
            rows.append({"seed": plan.seed, "t_ms": plan.decisions[0].decision_ms,
                         "mask": mask, "psnr": res.epochs[0].psnr_db})
        return out.results

    episodes = search_oracle(cfg, ds, "oracle:greedy:psnr_db", args.seeds, evaluate,
                             lpips=cfg.lpips)
    return rows, episodes, cfg, ds, computed


def features(rows, cfg, ds) -> tuple[list[dict], list[str]]:
    """Candidates as (decision, round, camera, target, feature dict)."""
    from aoi3d.experiment.episode import episode_links, train_ids

    ids = train_ids(cfg, ds)
    n = len(ids)
    angle, dist, axes = geometry(ds, ids)
    links = {}
    # group the candidates of one round: same decision, same base (mask minus one camera)
    by_decision: dict[tuple[int, int], list[dict]] = {}
    for r in rows:
        by_decision.setdefault((r["seed"], r["t_ms"]), []).append(r)
    samples: list[dict[str, Any]] = []
    for (seed, t), cands in by_decision.items():
        if seed not in links:
            links[seed] = episode_links(cfg, ds, seed)
        run = links[seed].run
        aoi = run.aoi_ms(t)
        delay = np.full(n, np.nan)
        since = np.full(n, np.nan)
        inflight = np.zeros(n)
        for c, (g, d) in enumerate(zip(run.gen_ms, run.delivery_ms, strict=True)):
            k = int(np.searchsorted(d, t, side="right")) - 1
            if k >= 0:
                delay[c], since[c] = d[k] - g[k], t - d[k]
            inflight[c] = float(k + 1 < len(g) and g[k + 1] <= t)
        # rounds: candidates with the same number of cameras share a base
        for size in sorted({int(r["mask"].sum()) for r in cands}):
            group = [r for r in cands if int(r["mask"].sum()) == size]
            bases: dict[bytes, list[tuple[int, float]]] = {}
            for r in group:
                for c in np.flatnonzero(r["mask"]).tolist():
                    base = r["mask"].copy()
                    base[c] = False
                    bases.setdefault(base.tobytes(), []).append((int(c), r["psnr"]))
            # the round's base is the one every candidate of the round shares
            base_key, members = max(bases.items(), key=lambda kv: len(kv[1]))
            if len(members) < 2:
                continue
            base = np.frombuffer(base_key, dtype=bool)
            mean = float(np.mean([p for _, p in members]))
            for c, p in members:
                others = np.flatnonzero(base)
                overlap = (float(np.min(np.arccos(np.clip(axes[others] @ axes[c], -1, 1))))
                           if len(others) else math.pi)
                samples.append({
                    "decision": f"{seed}:{t}", "round": size, "camera": c, "psnr": p,
                    "y": p - mean,
                    "aoi": [aoi[c] / 300.0, (aoi[c] / 300.0) ** 2],
                    "id": list(np.eye(n)[c]),
                    "pose": [angle[c], angle[c] ** 2, dist[c]],
                    "delay": [delay[c] / 300.0, since[c] / 300.0, inflight[c]],
                    "overlap": [overlap, overlap ** 2],
                })
    return samples, sorted({s["decision"] for s in samples})


def evaluate_set(samples, decisions, feats, ridge=1e-2) -> dict:
    """Leave-one-decision-out ridge fit: out-of-fold R² and the per-round regret."""
    x = np.array([[v for f in feats for v in s[f]] for s in samples])
    y = np.array([s["y"] for s in samples])
    dec = np.array([s["decision"] for s in samples])
    pred = np.zeros_like(y)
    for d in decisions:
        test = dec == d
        train = ~test
        mu, sd = x[train].mean(0), x[train].std(0) + 1e-9
        a = np.c_[np.ones(train.sum()), (x[train] - mu) / sd]
        w = np.linalg.solve(a.T @ a + ridge * np.eye(a.shape[1]), a.T @ y[train])
        pred[test] = np.c_[np.ones(test.sum()), (x[test] - mu) / sd] @ w
    r2 = 1.0 - float(np.sum((y - pred) ** 2) / np.sum((y - y.mean()) ** 2))
    return {"r2": r2, **_regret(samples, decisions, pred)}


def _regret(samples, decisions, score) -> dict:
    """Per round: the best candidate's PSNR minus that of the one ranked first by ``score``."""
    y = np.array([s["y"] for s in samples])
    regrets = [float(np.max(y[m]) - y[m][np.argmax(score[m])])
               for m in _rounds(samples, decisions)]
    return {"regret_db": float(np.mean(regrets)), "rounds": len(regrets),
            "top1": float(np.mean([r == 0.0 for r in regrets]))}


def study(samples, decisions) -> dict:
    """Every feature set on these candidates, with two references: a random pick (the mean
    candidate) and the AoI rule (the youngest frame)."""
    y = np.array([s["y"] for s in samples])
    random = _regret(samples, decisions, np.zeros_like(y))
    rounds = list(_rounds(samples, decisions))  # the expectations of a uniform pick:
    random["regret_db"] = float(np.mean([np.max(y[m]) - np.mean(y[m]) for m in rounds]))
    random["top1"] = float(np.mean([1.0 / m.sum() for m in rounds]))
    youngest = _regret(samples, decisions, -np.array([s["aoi"][0] for s in samples]))
    return {"candidates": len(samples), "random_pick": random, "youngest_frame": youngest,
            "feature_sets": {name: evaluate_set(samples, decisions, feats)
                             for name, feats in FEATURE_SETS.items()}}


def _rounds(samples, decisions):
    """A mask over ``samples`` per round of each decision."""
    dec = np.array([s["decision"] for s in samples])
    rnd = np.array([s["round"] for s in samples])
    for d in decisions:
        for r in np.unique(rnd[dec == d]):
            yield (dec == d) & (rnd == r)


def parser() -> argparse.ArgumentParser:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seeds", type=int, nargs="+", default=[50000, 50001])
    ap.add_argument("--steps", type=int, default=300)
    ap.add_argument("--cache", type=Path, default=ROOT / "runs" / "experiments" / "oracle-cache")
    ap.add_argument("--processes", "--workers", dest="processes", type=int, default=1)
    ap.add_argument("--out", type=Path, default=ROOT / "results" / "state-features.json")
    common.add_json_option(ap)
    return ap


def run(seeds: list[int], steps: int = 300, cache: Path = ROOT / "runs" / "experiments" /
        "oracle-cache", processes: int = 1, out: Path | None = None,
        command: str = "python -m bench.state_features") -> dict[str, Any]:
    """The study; writes its document to ``out`` (when given) and returns it."""
    rows, _, cfg, ds, computed = collect(argparse.Namespace(seeds=seeds, steps=steps,
                                                            cache=cache, processes=processes))
    samples, decisions = features(rows, cfg, ds)
    parts = {
        "every round": samples,
        "the first round (one camera alone)": [s for s in samples if s["round"] == 1],
        "the later rounds (a camera added to a selection)": [s for s in samples
                                                             if s["round"] > 1],
    }
    doc = {"command": command, "seeds": seeds, "steps_per_epoch": steps,
           "decisions": len(decisions), "candidates": len(samples),
           "reconstructions_computed": computed,
           "parts": {name: study(part, decisions) for name, part in parts.items()}}
    if out is not None:
        common.write_json(out, doc, indent=1)
    return doc


def print_table(doc: dict[str, Any]) -> None:
    print(f"{doc['candidates']} candidates at {doc['decisions']} decisions "
          f"({doc['reconstructions_computed']} reconstructions computed)")
    for name, part in doc["parts"].items():
        print(f"\n{name}: {part['candidates']} candidates, {part['random_pick']['rounds']} "
              f"rounds")
        print(f"  {'model':30s} {'R² (out of fold)':>17s} {'regret dB':>10s} {'top-1':>6s}")
        for ref in ("random_pick", "youngest_frame"):
            r = part[ref]
            print(f"  {ref.replace('_', ' '):30s} {'':>17s} {r['regret_db']:10.3f} "
                  f"{r['top1']:6.2f}")
        for fname, r in part["feature_sets"].items():
            print(f"  {fname:30s} {r['r2']:17.3f} {r['regret_db']:10.3f} {r['top1']:6.2f}")


def main(argv: list[str] | None = None) -> None:
    args = parser().parse_args(argv)
    command = "python -m bench.state_features " + " ".join(
        sys.argv[1:] if argv is None else argv)
    with common.progress_to_stderr(args.json):
        doc = run(args.seeds, args.steps, args.cache, args.processes, args.out,
                  command=command.strip())
        print_table(doc)
    if args.json:
        common.print_json(doc, indent=1)


if __name__ == "__main__":
    main()
