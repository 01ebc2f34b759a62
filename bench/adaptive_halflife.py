"""Choose the plug-in's half-life on the design traces only (issue 32: tune on some traces,
judge on others). No reconstruction: for each half-life, the plug-in runs over the links of a
design trace (every camera on its own subchannel at one phase, frames of the rotor scene's
PNG sizes, a decision every 30 ms) and its Γ is compared with the Γ it would take if it knew
the mean transmission time of the frames generated in the last second, Γ*(ȳ[t−1 s, t]) — the
tracking error, mean |Γ̂ − Γ*(ȳ)| in ms. Writes results/adaptive-halflife/results.json.

Design traces: TMobile-LTE-short.up and ATT-LTE-driving-2016.up (the held-out ones of
bench/adaptive.py are never read here).
"""

from __future__ import annotations

import argparse
import sys

import numpy as np

from aoi3d.experiment import get_preset
from aoi3d.experiment.episode import episode_links
from aoi3d.policy import PluginPolicy, decide
from aoi3d.policy.adaptive import load_gamma_curve
from aoi3d.scene import open_dataset
from bench import common
from bench.common import ROOT

DESIGN = ("TMobile-LTE-short.up", "ATT-LTE-driving-2016.up")
HALFLIVES = (250, 500, 1000, 2000, 3000, 5000, 10000)


def parser() -> argparse.ArgumentParser:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    common.add_json_option(ap)
    return ap


def run() -> dict | None:
    """Every half-life on the design traces; writes
    results/adaptive-halflife/results.json and returns its document (None, and a
    message, where the traces are absent)."""
    traces = ROOT.parent / "shared/data/traces"
    if not traces.is_dir():
        print(f"no traces at {traces}: nothing to tune")
        return None
    curve = load_gamma_curve()
    base = get_preset("quick").episode.with_(warmup_ms=0, scored_ms=60_000, lpips=False)
    ds = open_dataset(base.dataset)
    rows = []
    for name in DESIGN:
        for offset in (0, 30_000, 60_000):
            cfg = base.with_(delay=f"trace:{traces / name},spread=0,offset={offset}")
            links = episode_links(cfg, ds, 1)
            gen = np.concatenate(links.run.gen_ms)
            y = np.concatenate([d - g for g, d in zip(links.run.gen_ms, links.run.delivery_ms,
                                                      strict=True)])
            times = [t for t in cfg.decision_times_ms() if t >= 2000]
            target = []
            for t in times:
                m = (gen >= t - 1000) & (gen < t)
                target.append(curve(float(y[m].mean())) if m.any() else np.nan)
            target_arr = np.asarray(target)
            for h in HALFLIVES:
                pol = PluginPolicy(halflife_ms=h, curve=curve)
                feed = links.delivery_feed()
                got = []
                for t in cfg.decision_times_ms():
                    decide(pol, t, links.newest_ms, deliveries=feed)
                    if t >= 2000:
                        got.append(pol.gamma_ms)
                err = np.nanmean(np.abs(np.asarray(got) - target_arr))
                rows.append({"trace": name, "offset_ms": offset, "halflife_ms": h,
                             "tracking_error_ms": float(err)})
                print(f"{name} @{offset}: half-life {h:5d} ms → |Γ̂ − Γ*(ȳ)| {err:5.1f} ms",
                      flush=True)
    mean = {h: float(np.mean([r["tracking_error_ms"] for r in rows if r["halflife_ms"] == h]))
            for h in HALFLIVES}
    best = min(HALFLIVES, key=lambda h: mean[h])
    doc = {"command": "python bench/adaptive_halflife.py", "design_traces": list(DESIGN),
           "curve": curve.source, "mean_tracking_error_ms": mean, "best_halflife_ms": best,
           "rows": rows}
    common.write_json(common.RESULTS / "adaptive-halflife" / "results.json", doc, indent=1)
    print({h: round(v, 1) for h, v in mean.items()}, "best", best)
    return doc


def main(argv: list[str] | None = None) -> int:
    args = parser().parse_args(argv)
    with common.progress_to_stderr(args.json):
        doc = run()
    if args.json:
        common.print_json(doc, indent=1)
    return 0


if __name__ == "__main__":
    sys.exit(main())
