"""The per-decision reconstruction, timed: the project's unit of work (issue 23).

One reconstruction is what the live trainer (carry ``fresh``) and the experiments' virtual
clock do per scored decision: ``FieldTrainer.reset`` → ``set_views`` of the views' frames at
t0 → ``step(steps)`` → ``render`` of the held-out camera, scored (PSNR) against the held-out
camera's frame at t0. Defaults are the live settings: the rotor scene
(:data:`aoi3d.experiment.config.EXPERIMENT_SCENE`), the ``grid`` backend, 6 training cameras
spread evenly over the rig, 100 steps of 1024 rays, 96×72 images, 1 torch thread; t0 cycles
through 60, 67, 74, 81 (frame indices). The reconstructions are seeded, so each t0 gives the
same PSNR every cycle; ``seconds_median`` is the median wall time of one reconstruction (all of
it: reset, views, training, render; not the dataset's decoding), ``psnr_db`` the mean PSNR.

    python bench/recon.py                      # the default workload, a line per reconstruction
    python bench/recon.py --json               # one JSON object
    python bench/recon.py --backend ngp --size 192x144 --threads 2 --json
    python bench/recon.py --backend tensorf --device cuda --json   # on a GPU

The dataset is generated when missing (as the experiment commands do): at 96×72 into
``data/turbine-rotor``, at another ``--size`` into ``data/turbine-rotor-<W>x<H>``.
"""

from __future__ import annotations

import argparse
import json
import statistics
import sys
import time
from dataclasses import replace
from pathlib import Path

import numpy as np

from aoi3d.experiment.config import EXPERIMENT_DATASET, EXPERIMENT_SCENE
from aoi3d.field import FieldTrainer, TrainView, field_config
from aoi3d.field.process import configure_process
from aoi3d.quality import psnr
from aoi3d.scene.dataset import ensure_dataset

TIMES = (60, 67, 74, 81)
"""The frame indices t0 of the reconstructions, cycled."""


def _size(text: str) -> tuple[int, int]:
    w, _, h = text.lower().partition("x")
    try:
        size = int(w), int(h)
    except ValueError:
        raise argparse.ArgumentTypeError(f"size must be WxH, got {text!r}") from None
    if min(size) < 1:
        raise argparse.ArgumentTypeError(f"size must be positive, got {text!r}")
    return size


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--backend", default="grid")
    parser.add_argument("--size", type=_size, default=(EXPERIMENT_SCENE.width,
                                                        EXPERIMENT_SCENE.height),
                        help="image size WxH (default: the experiments' scene, 96x72)")
    parser.add_argument("--steps", type=int, default=100, help="training steps per reconstruction")
    parser.add_argument("--threads", type=int, default=1, help="torch threads")
    parser.add_argument("--views", type=int, default=6, help="training cameras, spread evenly")
    parser.add_argument("--repeats", type=int, default=8,
                        help=f"reconstructions (>= 5; t0 cycles through {TIMES})")
    parser.add_argument("--dataset", type=Path, default=None,
                        help="where the rotor scene at --size is (generated when missing)")
    parser.add_argument("--device", default="cpu",
                        help="torch device of the field: cpu (default), cuda or auto")
    parser.add_argument("--json", action="store_true", help="print one JSON object only")
    args = parser.parse_args(argv)
    if args.repeats < 5:
        parser.error("--repeats must be >= 5")
    if args.steps < 1:
        parser.error("--steps must be >= 1")
    configure_process(args.threads)

    width, height = args.size
    scene = EXPERIMENT_SCENE
    default_size = (scene.width, scene.height) == (width, height)
    if not default_size:
        scene = replace(scene, width=width, height=height)
    path = args.dataset or Path(EXPERIMENT_DATASET if default_size
                                else f"{EXPERIMENT_DATASET}-{width}x{height}")
    ds = ensure_dataset(path, scene)
    ids = list(ds.train_ids)
    if not 1 <= args.views <= len(ids):
        parser.error(f"--views must be in 1..{len(ids)}")
    chosen = [ids[round(float(i))] for i in np.linspace(0, len(ids) - 1, args.views)]
    heldout = ds.cameras[ds.heldout_id]
    frames = {t0: ([TrainView(ds.cameras[c], ds.frame(c, t0)) for c in chosen],
                   ds.frame(ds.heldout_id, t0)) for t0 in TIMES}

    from aoi3d.device import resolve_device

    try:
        device = resolve_device(args.device)
    except ValueError as err:
        parser.error(str(err))
    trainer = FieldTrainer(field_config(args.backend), ds.aabb, device=device, seed=0)
    seconds, scores = [], []
    for i in range(args.repeats):
        t0 = TIMES[i % len(TIMES)]
        views, truth = frames[t0]
        started = time.perf_counter()
        trainer.reset()
        trainer.set_views(views)
        trainer.step(args.steps)
        image = trainer.render(heldout)
        seconds.append(time.perf_counter() - started)
        scores.append(psnr(image, truth))
        if not args.json:
            print(f"t0 = {t0:3d}: {seconds[-1]:.3f} s, PSNR {scores[-1]:.2f} dB", flush=True)
    result = {
        "seconds_median": round(statistics.median(seconds), 4),
        "psnr_db": round(float(np.mean(scores)), 3),
        "backend": args.backend,
        "size": [width, height],
        "steps": args.steps,
        "threads": args.threads,
        "views": args.views,
        "device": device,
    }
    if args.json:
        print(json.dumps(result))
    else:
        print(f"{args.backend}, {width}×{height}, {args.views} views, {args.steps} steps, "
              f"{args.threads} thread(s): {result['seconds_median']:.3f} s per reconstruction "
              f"(median of {args.repeats}), PSNR {result['psnr_db']:.2f} dB")


if __name__ == "__main__":
    sys.exit(main())
