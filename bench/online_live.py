"""Benchmark: does the live scheduler's PPO agent learn online? (issue 25, item 4)

Starts one pipeline, ``aoi3d up --sites 3 --workers K``, on its own ports: three sites of the
same scene and channel model (each site's link delays are its own draw of the same
distribution, its camera phase its own), the worker pool rendering for all three, and puts

- ``site1``: the shipped agent (``models/ppo/quick/final.pt``, copied into
  ``runs/online-live/``), learning online (``learn: true``);
- ``site2``: an untrained agent of the same architecture and hyper-parameters (a fresh
  ``PPOLearner``, seed ``--scratch-seed``), learning online; both learners' online
  checkpoints are written beside them in ``runs/online-live/``;
- ``site3``: the best fixed rule (``--rule``, default ``mat:100``: the best rule by reward at
  the agent's 100-step budget in ``make science``'s ``ppo eval`` and in the live policy
  measurement of issue 25, item 5).

Then, for ``--minutes`` wall minutes, every ``--poll-s`` it reads each site's scored renders
(the metrics service's ``/sites/<site>/quality``) and each learner's state (the scheduler's
``/sites/<site>/policy``). Every render's reward closes one online episode of its site's
learner, so the rewards it reads are what the learners learn from.

Writes into ``--out`` (default ``results/online-live``): ``qualities.csv`` (every scored
render: site, the wall seconds of its decision since the policies were put — sim time over
the time scale —, decision, reward, PSNR, SSIM, LPIPS, dynamic-region PSNR, views),
``learners.csv`` (each poll: episodes learned, updates, entropy, the latest batch's mean
reward), ``run.json`` (the command, policies, the machine's load, the learners' last state),
``summary.json`` (per site and per ``--window-min`` window the mean reward ± 95 % CI; per
site the first window and the last two against the rule's site, Welch, since the sites'
channels are independent draws) and ``online_live.png`` (reward and PSNR against wall time,
a trailing mean per site), which docs/ppo.md shows. ``--from-csv`` redoes the last two from
the first ones.

    python -m bench.online_live --minutes 60          # the issue's hour
    python -m bench.online_live --minutes 3 --out /tmp/online-smoke
    python -m bench.online_live --from-csv           # summary and figure again
"""

from __future__ import annotations

import argparse
import csv
import json
import os
import shutil
import sys
import time
from pathlib import Path
from typing import Any

import httpx

from aoi3d.metric import LPIPS, PSNR, PSNR_DYNAMIC, REWARD, SSIM, names_of
from aoi3d.stats import mean_ci95, welch_ci95
from aoi3d_cli.pipeline import Pipeline
from bench import common
from bench.ports import BENCH_BLOCKS

ROOT = common.ROOT
PORTS = BENCH_BLOCKS["online_live"]  # apart from `make up` and bench/scale.py (bench/ports.py)
PIPE = Pipeline(PORTS, timeout_s=60.0)
"""This bench's pipeline (:class:`aoi3d_cli.pipeline.Pipeline`): its URLs."""
SHIPPED = ROOT / "models" / "ppo" / "quick" / "final.pt"
DEFAULT_DATASET = ROOT / "data" / "turbine-rotor"
SITES = ("site1", "site2", "site3")
HTTP = httpx.Client(timeout=60)
FIELDS = ["site", "wall_s", "decision_id", "time_ms",
          *names_of((REWARD, PSNR, SSIM, LPIPS, PSNR_DYNAMIC)), "n_views"]
PLOTTED = names_of((REWARD, PSNR))
COMPARED = names_of((REWARD, PSNR, PSNR_DYNAMIC))


def scratch_checkpoint(path: Path, seed: int) -> None:
    """An untrained agent with the shipped agent's architecture and PPO settings."""
    from aoi3d.policy.ppo.checkpoint import Checkpoint
    from aoi3d.policy.ppo.config import PPOConfig
    from aoi3d.policy.ppo.learner import PPOLearner

    shipped = Checkpoint.read(SHIPPED)
    PPOLearner(PPOConfig.from_dict({**shipped.config, "seed": seed})).save(path)


def wait_up(up: Pipeline, workers: int, timeout_s: float) -> None:
    up.wait(
        "the pipeline ready (see runs/bench-online/latest/)",
        lambda: len(HTTP.get(PORTS.url("dispatcher", "/workers")).json()["workers"]) == workers
        and all(HTTP.get(PORTS.url(s, "/readyz")).status_code == 200
                for s in ("scheduler", "metrics", "dispatcher")),
        timeout_s, every_s=1.0)


def put_policy(site: str, body: dict[str, Any]) -> dict[str, Any]:
    resp = HTTP.put(PIPE.url("scheduler", "/policy", site=site), json=body)
    if resp.status_code >= 400:
        raise SystemExit(f"PUT {site} policy {body}: {resp.status_code} {resp.text[:300]}")
    return resp.json()


def windows(rows: list[dict[str, Any]], window_s: float) -> list[dict[str, Any]]:
    out: list[dict[str, Any]] = []
    if not rows:
        return out
    end = max(r["wall_s"] for r in rows)
    k = 0
    while k * window_s < end:
        sel = [r["reward"] for r in rows if k * window_s <= r["wall_s"] < (k + 1) * window_s]
        out.append({"from_min": k * window_s / 60, "to_min": (k + 1) * window_s / 60,
                    "reward": mean_ci95(sel).to_dict()})
        k += 1
    return out


def plot(rows_by_site: dict[str, list[dict[str, Any]]], labels: dict[str, str], path: Path,
         smooth_s: float) -> None:
    """Reward and PSNR of every scored render against wall time, with a trailing moving mean
    over ``smooth_s``."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    import numpy as np

    fig, axes = plt.subplots(2, 1, figsize=(8, 6.4), dpi=120, sharex=True)
    for (site, rows), colour in zip(rows_by_site.items(), ("C0", "C1", "C2"), strict=False):
        if not rows:
            continue
        t = np.array([r["wall_s"] for r in rows]) / 60.0
        for ax, key in zip(axes, PLOTTED, strict=True):
            v = np.array([r[key] for r in rows])
            ax.scatter(t, v, s=2, alpha=0.12, color=colour)
            mean = np.array([v[(t >= ti - smooth_s / 60) & (t <= ti)].mean() for ti in t])
            ax.plot(t, mean, lw=1.8, color=colour, label=f"{labels[site]} ({len(rows)} renders)")
    axes[0].set_ylabel("reward per scored render")
    axes[1].set_ylabel("PSNR (dB)")
    axes[1].set_xlabel("wall time since the policies were put (min)")
    axes[0].set_title(f"Online learning, live (lines: mean over the last {smooth_s / 60:g} min)")
    for ax, key in zip(axes, PLOTTED, strict=True):
        ax.grid(alpha=0.3)
        vals = np.concatenate([[r[key] for r in rs] for rs in rows_by_site.values() if rs])
        ax.set_ylim(np.percentile(vals, 1), np.percentile(vals, 99.5))
    axes[0].legend(fontsize=8, loc="lower right")
    fig.tight_layout()
    fig.savefig(path)
    plt.close(fig)


def parser() -> argparse.ArgumentParser:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--minutes", type=float, default=60.0, help="wall minutes to measure")
    ap.add_argument("--workers", type=int, default=2, help="reconstruction workers")
    ap.add_argument("--time-scale", type=float, default=0.1)
    ap.add_argument("--rule", default="mat:100", help="the fixed rule of site3")
    ap.add_argument("--scratch-seed", type=int, default=1)
    ap.add_argument("--poll-s", type=float, default=30.0)
    ap.add_argument("--window-min", type=float, default=10.0)
    ap.add_argument("--dataset", type=Path, default=DEFAULT_DATASET)
    ap.add_argument("--ready-timeout-s", type=float, default=300.0)
    ap.add_argument("--out", type=Path, default=common.RESULTS / "online-live")
    ap.add_argument("--from-csv", action="store_true",
                    help="only summarise: summary.json and the figure from --out's "
                         "qualities.csv and run.json")
    common.add_json_option(ap, help="print the result document (summary.json) as JSON")
    return ap


def run(args: argparse.Namespace) -> dict[str, Any]:
    """The hour (``parser()``'s options), or with ``args.from_csv`` only its summary; writes
    into ``args.out`` and returns the result document (summary.json's)."""
    if args.from_csv:
        return summarise(args.out.resolve(), args.window_min)

    from aoi3d.policy import parse_policy

    out = args.out.resolve()
    out.mkdir(parents=True, exist_ok=True)
    agents = ROOT / "runs" / "online-live"  # the scheduler loads agents from runs/ or models/
    agents.mkdir(parents=True, exist_ok=True)
    shutil.copyfile(SHIPPED, agents / "shipped.pt")
    scratch_checkpoint(agents / "scratch.pt", args.scratch_seed)
    policies = {
        "site1": {"kind": "ppo", "checkpoint": str(agents / "shipped.pt"), "learn": True,
                  "save_to": str(agents / "shipped.online.pt")},
        "site2": {"kind": "ppo", "checkpoint": str(agents / "scratch.pt"), "learn": True,
                  "save_to": str(agents / "scratch.online.pt")},
        "site3": parse_policy(args.rule).to_json(),
    }
    labels = {"site1": "shipped agent, learning", "site2": "untrained agent, learning",
              "site3": f"{args.rule} (fixed rule)"}

    log_dir = ROOT / "runs" / "bench-online"
    load_before = os.getloadavg()
    up = PIPE.start([
        "--dataset", str(args.dataset), "--time-scale", str(args.time_scale),
        "--workers", str(args.workers), "--sites", str(len(SITES))], run_id="online",
        log_dir=log_dir, cwd=ROOT)
    seen: dict[str, dict[int, dict[str, Any]]] = {s: {} for s in SITES}
    learners: list[dict[str, Any]] = []
    try:
        wait_up(up, args.workers, args.ready_timeout_s)
        first_id, first_ms = {}, {}
        for site, body in policies.items():
            put_policy(site, body)
        t0 = time.monotonic()
        for site in SITES:  # renders of decisions taken before the PUT are not counted
            d = HTTP.get(PIPE.url("scheduler", "/decision", site=site)).json()
            first_id[site], first_ms[site] = d["decision_id"], d["time_ms"]
        print(f"policies put; measuring {args.minutes:g} min -> {out}", flush=True)
        while (now := time.monotonic() - t0) < args.minutes * 60:
            time.sleep(min(args.poll_s, max(0.1, args.minutes * 60 - now)))
            wall = time.monotonic() - t0
            for site in SITES:
                hist = HTTP.get(PIPE.url("metrics", "/quality", site=site),
                                params={"limit": 1000}).json()["history"]
                for q in hist:
                    if q["decision_id"] > first_id[site] and q["decision_id"] not in seen[site]:
                        # the decision's epoch on the wall clock (sim ms / time scale)
                        at = (q["time_ms"] - first_ms[site]) / 1000 / args.time_scale
                        seen[site][q["decision_id"]] = {**q, "wall_s": round(at, 2)}
                pol = HTTP.get(PIPE.url("scheduler", "/policy", site=site)).json()
                online = pol.get("online") or {}
                learners.append({"site": site, "wall_s": round(wall, 1),
                                 "scored": len(seen[site]),
                                 **{k: online.get(k) for k in (
                                     "episodes_learned", "agent_episodes", "updates", "entropy",
                                     "mean_reward", "unscored", "expired")}})
            print(f"{wall / 60:5.1f} min: " + ", ".join(
                f"{s} {len(seen[s])} renders" for s in SITES), flush=True)
        pool = HTTP.get(PORTS.url("dispatcher", "/workers")).json()
    finally:
        up.stop(120)

    rows_by_site = {s: sorted(seen[s].values(), key=lambda q: q["decision_id"]) for s in SITES}
    with open(out / "qualities.csv", "w", newline="") as fh:
        w = csv.DictWriter(fh, fieldnames=FIELDS, extrasaction="ignore")
        w.writeheader()
        for site, rows in rows_by_site.items():
            w.writerows({**r, "site": site} for r in rows)
    with open(out / "learners.csv", "w", newline="") as fh:
        w = csv.DictWriter(fh, fieldnames=list(learners[0]))
        w.writeheader()
        w.writerows(learners)
    meta = {"command": " ".join(["python", "bench/online_live.py", *sys.argv[1:]]),
            "minutes": args.minutes, "workers": args.workers, "time_scale": args.time_scale,
            "policies": {s: {"label": labels[s], **policies[s]} for s in SITES},
            "load_before": [round(x, 2) for x in load_before],
            "load_after": [round(x, 2) for x in os.getloadavg()],
            "pool_lost": pool.get("lost"),
            "last_learner": {s: next((x for x in reversed(learners) if x["site"] == s), None)
                             for s in SITES}}
    (out / "run.json").write_text(json.dumps(meta, indent=1) + "\n")
    return summarise(out, args.window_min)


def main(argv: list[str] | None = None) -> None:
    args = parser().parse_args(argv)
    with common.progress_to_stderr(args.json):
        summary = run(args)
    if args.json:
        common.print_json(summary, indent=1)


def summarise(out: Path, window_min: float) -> dict[str, Any]:
    """summary.json and online_live.png from ``out``'s qualities.csv and run.json: per site
    and ``window_min`` window the mean reward ± 95 % CI; per site the first window and the
    last two against the rule's site (Welch: the sites' channels are independent draws)."""
    run = json.loads((out / "run.json").read_text())
    rows_by_site: dict[str, list[dict[str, Any]]] = {s: [] for s in SITES}
    with open(out / "qualities.csv", newline="") as fh:
        for r in csv.DictReader(fh):
            rows_by_site[r["site"]].append(
                {k: (float(v) if v not in ("", None) else None) for k, v in r.items()
                 if k != "site"})
    window_s = window_min * 60
    end_s = max(r["wall_s"] for rows in rows_by_site.values() for r in rows)
    spans = {"first": (0.0, window_s), "last": (end_s - 2 * window_s, end_s + 1)}

    def stats(rows: list[dict[str, Any]], lo: float, hi: float) -> dict[str, Any]:
        sel = [r for r in rows if lo <= r["wall_s"] < hi]
        return {key: mean_ci95([r[key] for r in sel]).to_dict()
                for key in (*COMPARED, "n_views")}

    rule = SITES[-1]
    sites = {}
    for s, rows in rows_by_site.items():
        spans_s = {name: stats(rows, lo, hi) for name, (lo, hi) in spans.items()}
        against = {name: {key: {"difference": v[key]["mean"] - spans_rule[key]["mean"],
                                "ci95": welch_ci95(v[key], spans_rule[key])}
                          for key in COMPARED}
                   for name, v in spans_s.items()
                   for spans_rule in [stats(rows_by_site[rule], *spans[name])]}
        sites[s] = {"label": run["policies"][s]["label"], "renders": len(rows),
                    "reward": mean_ci95([r["reward"] for r in rows]).to_dict(),
                    "windows": windows(rows, window_s), "spans": spans_s,
                    "minus_rule": against if s != rule else None,
                    "last_learner": run["last_learner"][s]}
    summary = {**{k: v for k, v in run.items() if k != "last_learner"},
               "spans_s": spans, "sites": sites}
    (out / "summary.json").write_text(json.dumps(summary, indent=1) + "\n")
    labels = {s: run["policies"][s]["label"] for s in SITES}
    plot(rows_by_site, labels, out / "online_live.png", smooth_s=min(600.0, window_s))
    for s, d in sites.items():
        last = d["spans"]["last"]["reward"]
        line = (f"{s} ({d['label']}): {d['renders']} renders; reward first "
                f"{d['spans']['first']['reward']['mean']:.4f}, last {2 * window_min:g} min "
                f"{last['mean']:.4f} ± {last['ci95']:.4f}")
        if d["minus_rule"]:
            m = d["minus_rule"]["last"]["reward"]
            line += f"; minus the rule {m['difference']:+.4f} ± {m['ci95']:.4f}"
        print(line)
    return summary

if __name__ == "__main__":
    main()
