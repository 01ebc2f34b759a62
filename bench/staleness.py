"""Probe: what a frame's age and the number of views cost the novel view, on one scene.

The measurement behind the experiments' choice of scene (docs/experiments.md). For each case
(k views, age a frame periods) a fresh radiance field trains ``--steps`` steps on k training
cameras spread evenly over the rig, every one showing the scene a frames *before* the time
t0; it renders the held-out camera 0 and is scored against camera 0's frame *at* t0. Each case
is the mean over three times t0. No channel is involved: this isolates the two sides of the
tradeoff (views against staleness) that the MAT threshold trades.

    python -m bench.staleness --dataset data/turbine-rotor          # the experiments' scene
    python -m bench.staleness --dataset data/turbine                # the default (site) scene
    python -m bench.staleness --dataset data/turbine-rotor --cases 18:0,18:1,5:1,3:1

The datasets are made by ``aoi3d scene generate`` (``--framing rotor --rotor-rpm 6
--out data/turbine-rotor`` for the experiments' scene, which the experiment commands also
generate). Writes ``results/staleness-<dataset name>.json``.
"""

from __future__ import annotations

import argparse
import platform
import time
from pathlib import Path

import numpy as np

from aoi3d.field import FieldTrainer, TrainView, field_config
from aoi3d.field.process import configure_process
from aoi3d.lpips import load_lpips_fn, weights_path
from aoi3d.quality import RewardWeights, score
from aoi3d.scene import open_dataset
from bench import common

DEFAULT_CASES = "18:0,18:1,18:2,18:3,18:5,9:1,5:1,3:1,8:2"
TIMES = (30, 130, 230)
"""The frame indices t0 whose novel view is scored (the mean over them is reported)."""


def _cases(text: str) -> list[tuple[int, int]]:
    out = []
    for item in text.split(","):
        k, _, age = item.partition(":")
        out.append((int(k), int(age)))
    return out


def parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--dataset", type=Path, required=True)
    parser.add_argument("--steps", type=int, default=300, help="training steps per case")
    parser.add_argument("--cases", default=DEFAULT_CASES,
                        help="comma-separated VIEWS:AGE (age in frame periods)")
    parser.add_argument("--backend", default="grid")
    parser.add_argument("--threads", type=int, default=1)
    common.add_json_option(parser)
    return parser


def run(args: argparse.Namespace) -> dict:
    """Every case (``parser()``'s options); writes
    ``results/staleness-<dataset name>.json`` and returns its document."""
    configure_process(args.threads)
    ds = open_dataset(args.dataset)
    lpips_fn = load_lpips_fn() if weights_path("alex").exists() else None
    ids = list(ds.train_ids)
    rows = []
    for k, age in _cases(args.cases):
        if not 1 <= k <= len(ids) or age < 0 or age > min(TIMES):
            raise SystemExit(f"case {k}:{age}: views must be in 1..{len(ids)}, age in "
                             f"0..{min(TIMES)}")
        chosen = [ids[round(float(i))] for i in np.linspace(0, len(ids) - 1, k)]
        scores, train_s = [], 0.0
        for t0 in TIMES:
            trainer = FieldTrainer(field_config(args.backend), ds.aabb, seed=0)
            trainer.set_views([TrainView(ds.cameras[c], ds.frame(c, t0 - age)) for c in chosen])
            started = time.perf_counter()
            trainer.step(args.steps)
            train_s += time.perf_counter() - started
            q = score(trainer.render(ds.cameras[ds.heldout_id]),
                      ds.frame(ds.heldout_id, t0), RewardWeights(), lpips_fn)
            scores.append((q.psnr_db, q.ssim, np.nan if q.lpips is None else q.lpips))
        psnr, ssim, lpips = (float(v) for v in np.mean(scores, axis=0))
        rows.append({"views": k, "age_frames": age, "age_ms": 1000.0 * age / ds.fps,
                     "psnr_db": psnr, "ssim": ssim, "lpips": lpips, "train_s": train_s})
        print(f"{k:2d} views, {age} frame(s) old: PSNR {psnr:.2f} dB, SSIM {ssim:.3f}, "
              f"LPIPS {lpips:.3f}", flush=True)
    out = common.RESULTS / f"staleness-{args.dataset.name}.json"
    doc = {
        "benchmark": "staleness vs views", "dataset": str(args.dataset),
        "config_hash": ds.config_hash, "backend": args.backend, "steps": args.steps,
        "times": list(TIMES), "rows": rows,
        "machine": {"python": platform.python_version(), "threads": args.threads},
    }
    common.write_json(out, doc)
    print(f"written to {out}")
    return doc


def main(argv: list[str] | None = None) -> None:
    args = parser().parse_args(argv)
    with common.progress_to_stderr(args.json):
        doc = run(args)
    if args.json:
        common.print_json(doc)


if __name__ == "__main__":
    main()
