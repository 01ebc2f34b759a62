"""The dynamic-region mask (:func:`aoi3d.quality.dynamic_mask`) on a real truth sequence.

For every generation slot t = 2C, 3C, … of one loop of the scene (C = ``--period-ms``, the
channel's frame period, 30 ms by default; scene offset 0), the mask of the held-out view is
built from the truth at t, t − C, …, t − K·C exactly as the experiments and the metrics
service build it, for several thresholds τ. Reported per τ: the mask's pixel fraction
(mean, min, max over the loop) and how well it matches the moving parts of the scene:

- *moving*: the pixels at t that differ (by more than 8/255 in some channel) from the loop's
  per-pixel median, the empty scene the rotor sweeps over — the blades at t;
- *recall*: the share of the moving pixels that the mask covers;
- *off*: the share of the mask farther than one pixel (3×3 square) from any pixel moving
  at t, t − C, …, t − K·C (the blades now and where they were, which the mask covers by
  construction): pixels that neither are rotor nor border it — noise, if τ were too low.

    python -m bench.dynamic_mask                               # data/turbine-rotor
    python -m bench.dynamic_mask --png runs/dynamic_mask.png   # and an overlay figure

Writes ``results/dynamic_mask.json``. Reads only the held-out camera's frames (≈ 10 s
on one core for the default 300-frame scene).
"""

from __future__ import annotations

import argparse
import json
import math
import sys
from pathlib import Path

import numpy as np
from scipy import ndimage

from aoi3d.quality import DYNAMIC_DILATION_PX, DYNAMIC_FRAMES, DYNAMIC_TAU, dynamic_mask
from aoi3d.scene import open_dataset
from bench import common

TAUS_255 = (2, 4, 8, 16, 24)
"""Thresholds compared, in 8-bit levels (τ = levels / 255)."""


def parser() -> argparse.ArgumentParser:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--dataset", type=Path, default=Path("data/turbine-rotor"))
    ap.add_argument("--period-ms", type=float, default=30.0, help="C, the frame period (ms).")
    ap.add_argument("--frames", type=int, default=DYNAMIC_FRAMES, help="K, earlier frames.")
    ap.add_argument("--png", type=Path, default=None, help="Also write an overlay figure.")
    ap.add_argument("--out", type=Path, default=Path("results/dynamic_mask.json"))
    common.add_json_option(ap)
    return ap


def main(argv: list[str] | None = None) -> int:
    ap = parser()
    args = ap.parse_args(argv)
    if args.period_ms <= 0 or args.frames < 1:
        ap.error("--period-ms must be > 0 and --frames >= 1")
    with common.progress_to_stderr(args.json):
        doc = run(args, argv)
    if args.json:
        common.print_json(doc, indent=1)
    return 0


def run(args: argparse.Namespace, argv: list[str] | None = None) -> dict:
    """Every threshold (``parser()``'s options; ``argv``, or this process's, is recorded as
    the command); writes ``args.out`` (and ``args.png``) and returns the result document."""

    ds = open_dataset(args.dataset)
    cam = ds.heldout_id
    cache: dict[int, np.ndarray] = {}

    def truth(t_ms: float) -> np.ndarray:
        k = ds.frame_index(t_ms)
        if k not in cache:
            cache[k] = ds.frame(cam, k)
        return cache[k]

    loop = np.stack([ds.frame(cam, k) for k in range(ds.n_frames)]).astype(np.int16)
    empty = np.median(loop, axis=0)
    slots = np.arange(args.frames, math.floor(ds.duration_ms / args.period_ms)) * args.period_ms
    square = np.ones((3, 3), dtype=bool)
    rows = []
    overlays = []
    for levels in TAUS_255:
        tau = levels / 255.0
        fractions, recalls, offs = [], [], []
        for i, t in enumerate(slots):
            now = truth(t)
            previous = [truth(t - k * args.period_ms) for k in range(1, args.frames + 1)]
            mask = dynamic_mask(now, previous, tau=tau)
            moving = _moving(now, empty)
            swept = moving.copy()
            for image in previous:
                swept |= _moving(image, empty)
            near = ndimage.binary_dilation(swept, structure=square)
            fractions.append(mask.mean())
            if moving.any():
                recalls.append((mask & moving).sum() / moving.sum())
            if mask.any():
                offs.append((mask & ~near).sum() / mask.sum())
            if args.png is not None and i in (20, 41, 100, 167):
                overlays.append((levels, now, mask))
        rows.append({
            "tau_255": levels, "tau": tau, "slots": len(slots),
            "fraction_mean": float(np.mean(fractions)), "fraction_min": float(np.min(fractions)),
            "fraction_max": float(np.max(fractions)),
            "recall_mean": float(np.mean(recalls)), "off_mean": float(np.mean(offs)),
        })
    doc = {
        "command": "python bench/dynamic_mask.py " + " ".join(argv or sys.argv[1:]),
        "dataset": str(args.dataset), "heldout_id": cam, "size": [ds.width, ds.height],
        "fps": ds.fps, "period_ms": args.period_ms, "frames_K": args.frames,
        "dilation_px": DYNAMIC_DILATION_PX, "default_tau_255": round(DYNAMIC_TAU * 255),
        "moving_fraction_mean": float(np.mean([_moving(truth(t), empty).mean() for t in slots])),
        "results": rows,
    }
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(json.dumps(doc, indent=1) + "\n")
    print(f"{args.dataset} camera {cam}: {len(slots)} slots, C = {args.period_ms:g} ms, "
          f"K = {args.frames}, dilation {DYNAMIC_DILATION_PX} px; moving pixels "
          f"{100 * doc['moving_fraction_mean']:.1f} % of the image on average")
    print(f"{'tau':>8} {'fraction mean':>14} {'min':>6} {'max':>6} {'recall':>7} {'off':>6}")
    for r in rows:
        mark = "  <- default" if r["tau_255"] == doc["default_tau_255"] else ""
        print(f"{r['tau_255']:>4}/255 {100 * r['fraction_mean']:>13.1f}% "
              f"{100 * r['fraction_min']:>5.1f}% {100 * r['fraction_max']:>5.1f}% "
              f"{100 * r['recall_mean']:>6.1f}% {100 * r['off_mean']:>5.1f}%{mark}")
    print(f"wrote {args.out}")
    if args.png is not None:
        _figure(overlays, args.png)
        print(f"wrote {args.png}")
    return doc


def _moving(image: np.ndarray, empty: np.ndarray) -> np.ndarray:
    """Pixels of ``image`` that differ from the empty scene by more than 8/255."""
    return np.abs(image.astype(np.int16) - empty).max(axis=2) > 8


def _figure(overlays: list[tuple[int, np.ndarray, np.ndarray]], path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    taus = sorted({lv for lv, _, _ in overlays})
    per = len(overlays) // len(taus)
    fig, axes = plt.subplots(per, len(taus) + 1, figsize=(2.2 * (len(taus) + 1), 1.8 * per),
                             squeeze=False, constrained_layout=True)
    for j, levels in enumerate(taus):
        items = [o for o in overlays if o[0] == levels]
        for i, (_, now, mask) in enumerate(items):
            if j == 0:
                axes[i][0].imshow(now)
                axes[i][0].set_title("truth", fontsize=8)
            shown = now.astype(np.float64) / 255.0
            shown[mask] = 0.3 * shown[mask] + 0.7 * np.array([1.0, 0.0, 0.0])
            axes[i][j + 1].imshow(shown)
            axes[i][j + 1].set_title(f"τ = {levels}/255: {100 * mask.mean():.1f} %", fontsize=8)
    for ax in axes.flat:
        ax.set_axis_off()
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=130)
    plt.close(fig)


if __name__ == "__main__":
    raise SystemExit(main())
