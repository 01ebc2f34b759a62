"""Write the plug-in policy's Γ*(E[Y]) curve (aoi3d/policy/gamma_curve.json) from the delay
sweep of ``bench/adaptive_curve.sh`` (``results/adaptive-gamma-curve/results.json``).

Per mean delay, the best Γ is the one with the highest mean PSNR over the sweep's seeds. With
few seeds the best Γ is noisy, so the curve is made nondecreasing in E[Y] (the claim
`make science` holds: the optimal Γ grows with the delay) by pooling adjacent violators; the
raw best Γ and its optimum set are kept beside each point.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

from bench import common

ROOT = common.ROOT
SWEEP = common.RESULTS / "adaptive-gamma-curve" / "results.json"


def pool_adjacent_violators(values: list[float]) -> list[float]:
    """The nondecreasing sequence closest (least squares) to ``values``."""
    blocks: list[list[float]] = []  # [sum, count]
    for v in values:
        blocks.append([v, 1.0])
        while len(blocks) > 1 and blocks[-2][0] / blocks[-2][1] > blocks[-1][0] / blocks[-1][1]:
            s, c = blocks.pop()
            blocks[-1][0] += s
            blocks[-1][1] += c
    out: list[float] = []
    for s, c in blocks:
        out += [s / c] * int(c)
    return out


def parser() -> argparse.ArgumentParser:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("sweep", nargs="?", type=Path, default=SWEEP, metavar="RESULTS_JSON",
                    help="the delay sweep's results.json (default: "
                         "results/adaptive-gamma-curve/results.json)")
    common.add_json_option(ap, help="print the curve as JSON")
    return ap


def run(src: Path = SWEEP) -> dict:
    """The curve from the sweep at ``src``; writes aoi3d/policy/gamma_curve.json and returns
    it."""
    doc = json.loads(src.read_text())
    rows = sorted(doc["optima"], key=lambda o: o["mean_delay_ms"])
    raw = [float(o["best_gamma_ms"]) for o in rows]
    smooth = pool_adjacent_violators(raw)
    meta = doc["meta"]
    curve = {
        "what": ("Γ*(E[Y]): the MAT threshold with the highest mean PSNR against the mean "
                 "transmission time of an exponential channel; quick preset, a fresh model per "
                 "scored decision, 100 field steps, no LPIPS, the rotor scene; made "
                 "nondecreasing (pool adjacent violators) over the raw best Γ"),
        "command": "bench/adaptive_curve.sh && python bench/adaptive_curve.py "
                   "(aoi3d experiment delay --preset quick --steps-per-epoch 100 --no-lpips "
                   f"--delays {','.join(meta['args']['delays'])} "
                   f"--gammas {','.join(str(g) for g in meta['args']['gammas_ms'])} "
                   f"--seeds {len(meta['seed_list'])} --seed-offset {meta['seed_list'][0]})",
        "seeds": meta["seed_list"],
        "points": [{"mean_delay_ms": o["mean_delay_ms"], "gamma_ms": g,
                    "best_gamma_ms": o["best_gamma_ms"],
                    "optimum_set": o["optimum"]["members"]}
                   for o, g in zip(rows, smooth, strict=True)],
    }
    (ROOT / "aoi3d/policy/gamma_curve.json").write_text(json.dumps(curve, indent=1) + "\n")
    return curve


def main(argv: list[str] | None = None) -> int:
    args = parser().parse_args(argv)
    curve = run(args.sweep)
    if args.json:
        common.print_json(curve, indent=1)
        return 0
    for p in curve["points"]:
        print(f"E[Y] {p['mean_delay_ms']:6g} ms: best Γ {p['best_gamma_ms']:g} → "
              f"{p['gamma_ms']:g} (set {p['optimum_set']})")
    print(f"wrote {ROOT / 'aoi3d/policy/gamma_curve.json'}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
