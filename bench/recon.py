"""The per-decision reconstruction, timed: the project's unit of work (issue 23).

One reconstruction is what a live worker (carry ``fresh``) and the experiments' virtual
clock do per scored decision: ``FieldTrainer.reset`` → ``set_views`` of the views' frames at
t0 → ``step(steps)`` → ``render`` of the held-out camera, scored (PSNR) against the held-out
camera's frame at t0. Defaults are the live settings: the rotor scene
(:data:`aoi3d.experiment.config.EXPERIMENT_SCENE`), the ``grid`` backend, 6 training cameras
spread evenly over the rig, 100 steps of 1024 rays, 96×72 images, 1 torch thread; t0 cycles
through 60, 67, 74, 81 (frame indices). The reconstructions are seeded, so each t0 gives the
same PSNR every cycle; ``seconds_median`` is the median wall time of one reconstruction (all of
it: reset, views, training, render; not the dataset's decoding), ``psnr_db`` the mean PSNR.

    python -m bench.recon                      # the default workload, a line per reconstruction
    python -m bench.recon --json               # one JSON object
    python -m bench.recon --backend ngp --size 192x144 --threads 2 --json
    python -m bench.recon --backend tensorf --device cuda --json   # on a GPU
    python -m bench.recon --field flow --ages 1,2,3,4 --ahead 1 --json  # the time-aware field

``--field`` is ``--backend``'s other name (the time-aware ``flow`` is one more backend).
``--ages``: each chosen camera's frame is that many frames older than t0 (cycled over the
cameras; default 0: every frame at t0, which teaches a time-aware field no motion);
``--ahead``: the render is taken that many frames after t0 and scored against the truth then
(a display time; a static field shows the same image).

The dataset is generated when missing (as the experiment commands do): at 96×72 into
``data/turbine-rotor``, at another ``--size`` into ``data/turbine-rotor-<W>x<H>``.
"""

from __future__ import annotations

import argparse
import json
import statistics
import time
from dataclasses import replace
from pathlib import Path
from typing import Any

import numpy as np

from aoi3d.experiment.config import EXPERIMENT_DATASET, EXPERIMENT_SCENE
from aoi3d.field import FieldTrainer, TrainView, check_backend, field_config
from aoi3d.field.carry import Reconstruction, WarmStart
from aoi3d.field.process import configure_process
from aoi3d.quality import DYNAMIC_FRAMES, dynamic_mask, dynamic_score, psnr
from aoi3d.scene.write import ensure_dataset

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


def _ages(text: str) -> tuple[int, ...]:
    try:
        ages = tuple(int(a) for a in text.split(","))
    except ValueError:
        raise argparse.ArgumentTypeError(f"ages must be frame counts A,B,..., got {text!r}"
                                         ) from None
    if min(ages) < 0:
        raise argparse.ArgumentTypeError(f"ages must be >= 0, got {text!r}")
    return ages


class UsageError(ValueError):
    """Options that cannot run together (``main`` prints it as argparse's usage error)."""


def parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--backend", "--field", dest="backend", default="grid",
                        help="the field backend (aoi3d.field.BACKENDS; flow: time-aware)")
    parser.add_argument("--ages", type=_ages, default=(0,),
                        help="frame ages in frames, cycled over the cameras (default 0)")
    parser.add_argument("--ahead", type=int, default=0,
                        help="frames after t0 the render is taken and scored at (default 0)")
    parser.add_argument("--size", type=_size, default=(EXPERIMENT_SCENE.width,
                                                        EXPERIMENT_SCENE.height),
                        help="image size WxH (default: the experiments' scene, 96x72)")
    parser.add_argument("--steps", type=int, default=100,
                        help="training steps per reconstruction (warm: per warm start)")
    parser.add_argument("--carry", choices=("fresh", "warm"), default="fresh",
                        help="fresh: each reconstruction from nothing (default); warm: a "
                             "sequence of consecutive decisions, each started from the previous "
                             "one's model (the stream carry, aoi3d.field.carry), the first cold")
    parser.add_argument("--gap", type=int, default=1,
                        help="warm: frames between consecutive decisions (default 1)")
    parser.add_argument("--cold-steps", type=int, default=100,
                        help="warm: the budget of the first, cold, reconstruction")
    parser.add_argument("--focus", type=float, default=WarmStart.focus,
                        help="warm: share of each batch drawn from the changed pixels")
    parser.add_argument("--reset", action="store_true",
                        help="warm: reset the cells the change carve marks (a candidate that "
                             "lost: docs/performance.md, Streaming reconstruction)")
    parser.add_argument("--dilation", type=int, default=WarmStart.dilation_px,
                        help="warm: dilation of the change masks, pixels")
    parser.add_argument("--lr-scale", type=float, default=WarmStart.lr_scale,
                        help="warm: learning rates of a warm start times this")
    parser.add_argument("--no-hold", action="store_true",
                        help="warm: let the carried model's schedule run on (no hold)")
    parser.add_argument("--threads", type=int, default=1, help="torch threads")
    parser.add_argument("--views", type=int, default=6, help="training cameras, spread evenly")
    parser.add_argument("--repeats", type=int, default=None,
                        help=f"reconstructions (>= 5; fresh, default 8: t0 cycles through "
                             f"{TIMES}; warm, default 22: warm decisions at {TIMES[0]}, "
                             f"{TIMES[0]} + gap, ...)")
    parser.add_argument("--dataset", type=Path, default=None,
                        help="where the rotor scene at --size is (generated when missing)")
    parser.add_argument("--device", default="cpu",
                        help="torch device of the field: cpu (default), cuda or auto")
    parser.add_argument("--json", action="store_true", help="print one JSON object only")
    return parser


def run(args: argparse.Namespace) -> dict[str, Any]:
    """The measurement for ``parser()``'s options (``UsageError`` for options that cannot
    run); prints a line per reconstruction unless ``args.json``; returns the result."""
    if args.repeats is None:
        args.repeats = 8 if args.carry == "fresh" else 22
    if args.repeats < 5:
        raise UsageError("--repeats must be >= 5")
    if args.steps < 1:
        raise UsageError("--steps must be >= 1")
    if args.ahead < 0:
        raise UsageError("--ahead must be >= 0")
    try:
        check_backend(args.backend)
    except ValueError as err:
        raise UsageError(str(err)) from None
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
        raise UsageError(f"--views must be in 1..{len(ids)}")
    chosen = [ids[round(float(i))] for i in np.linspace(0, len(ids) - 1, args.views)]
    heldout = ds.cameras[ds.heldout_id]
    if args.carry == "fresh":
        sequence = [TIMES[i % len(TIMES)] for i in range(args.repeats)]
    else:  # the cold decision, then the warm ones
        if args.gap < 1:
            raise UsageError("--gap must be >= 1")
        sequence = [TIMES[0] + (k - 1) * args.gap for k in range(args.repeats + 1)]
    frame_ms = 1000.0 / ds.fps
    ages = [args.ages[i % len(args.ages)] for i in range(len(chosen))]
    if max(ages) > min(sequence):
        raise UsageError(f"--ages reach before the scene's first frame (t0 from {min(sequence)})")
    shown = [t0 + args.ahead for t0 in sequence]  # the truth a render is scored against
    frames = {t0: [TrainView(ds.cameras[c], ds.frame(c, t0 - a), age_ms=a * frame_ms)
                   for c, a in zip(chosen, ages, strict=True)] for t0 in sorted(set(sequence))}
    truths = {t: (ds.frame(ds.heldout_id, t),
                  dynamic_mask(ds.frame(ds.heldout_id, t),
                               [ds.frame(ds.heldout_id, t - k)
                                for k in range(1, DYNAMIC_FRAMES + 1)]))
              for t in sorted(set(shown))}

    from aoi3d.device import resolve_device

    try:
        device = resolve_device(args.device)
    except ValueError as err:
        raise UsageError(str(err)) from None
    trainer = FieldTrainer(field_config(args.backend), ds.aabb, device=device, seed=0)
    warm_start = WarmStart(cold_steps=args.cold_steps,
                           reset=args.reset, focus=args.focus, hold=not args.no_hold,
                           dilation_px=args.dilation, lr_scale=args.lr_scale)
    rec = Reconstruction(trainer, "stream", args.steps, warm_start)
    seconds, cpu_seconds, scores, dynamic, at_times, cold_seconds = [], [], [], [], [], []
    ahead_ms = args.ahead * frame_ms
    for i, t0 in enumerate(sequence):
        views = frames[t0]
        truth, mask = truths[t0 + args.ahead]
        started, cpu_started = time.perf_counter(), time.process_time()
        if args.carry == "fresh":
            trainer.reset()
            trainer.set_views(views)
            trainer.step(args.steps)
            image = trainer.render(heldout, ahead_ms=ahead_ms)
        else:
            image = rec.render_decision(heldout, views, time_ms=t0 * frame_ms).image
        elapsed = time.perf_counter() - started
        cpu = time.process_time() - cpu_started
        if args.carry == "warm" and args.ahead:  # the same model later (untimed: one render
            image = rec.render_at(heldout, ahead_ms)  # per reconstruction is timed)
        score = psnr(image, truth)
        dyn = dynamic_score(image, truth, mask).psnr_db
        assert dyn is not None, "the blades' mask is never empty"
        kind = "cold" if args.carry == "warm" and i == 0 else args.carry
        if kind == "cold":
            cold_seconds.append(elapsed)
        else:
            seconds.append(elapsed)
            cpu_seconds.append(cpu)
            scores.append(score)
            dynamic.append(dyn)
            if t0 in TIMES:
                at_times.append((score, dyn))
        if not args.json:
            print(f"t0 = {t0:3d} ({kind}): {elapsed:.3f} s, PSNR {score:.2f} dB, dynamic "
                  f"{dyn:.2f} dB", flush=True)
    result = {
        "seconds_median": round(statistics.median(seconds), 4),
        "cpu_seconds_median": round(statistics.median(cpu_seconds), 4),
        "psnr_db": round(float(np.mean(scores)), 3),
        "psnr_dynamic_db": round(float(np.mean(dynamic)), 3),
        "backend": args.backend,
        "size": [width, height],
        "steps": args.steps,
        "threads": args.threads,
        "views": args.views,
        "device": device,
        "carry": args.carry,
        "ages_frames": list(args.ages),
        "ahead_frames": args.ahead,
    }
    if args.carry == "warm":  # the scores at the fresh mode's t0s, paired with them
        result.update({
            "psnr_db_at_times": round(float(np.mean([a for a, _ in at_times])), 3),
            "psnr_dynamic_db_at_times": round(float(np.mean([b for _, b in at_times])), 3),
            "cold_seconds": round(cold_seconds[0], 4), "cold_steps": args.cold_steps,
            "gap_frames": args.gap, "focus": args.focus, "reset": args.reset,
            "hold": not args.no_hold, "dilation_px": args.dilation,
            "lr_scale": args.lr_scale,
        })
    return result


def main(argv: list[str] | None = None) -> None:
    ap = parser()
    args = ap.parse_args(argv)
    try:
        result = run(args)
    except UsageError as err:
        ap.error(str(err))
    if args.json:
        print(json.dumps(result))
    else:
        width, height = args.size
        n = args.repeats
        print(f"{args.backend}, {width}×{height}, {args.views} views, {args.steps} steps "
              f"({args.carry}), {args.threads} thread(s): {result['seconds_median']:.3f} s per "
              f"reconstruction (median of {n}), PSNR {result['psnr_db']:.2f} dB, "
              f"dynamic {result['psnr_dynamic_db']:.2f} dB")


if __name__ == "__main__":
    main()
