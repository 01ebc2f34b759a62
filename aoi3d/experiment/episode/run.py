"""Stage 2 of an episode: train, render and score its plan (:func:`run_plan`)."""

from __future__ import annotations

import io
import math
import time
from collections.abc import Callable

import numpy as np
from PIL import Image

from aoi3d.experiment.episode.plan import (
    EpisodePlan,
    PlannedDecision,
    decision_budget,
    render_budget,
)
from aoi3d.experiment.episode.pool import run_pool_plan
from aoi3d.experiment.episode.result import EpisodeResult, EpochScore, episode_result
from aoi3d.experiment.episode.scoring import Frames, epoch_score
from aoi3d.field import FieldTrainer, field_config
from aoi3d.field.carry import Reconstruction, WarmStart
from aoi3d.field.process import configure_process
from aoi3d.quality import LpipsFn
from aoi3d.scene import SceneDataset, to_uint8


def run_plan(
    plan: EpisodePlan,
    dataset: SceneDataset,
    *,
    key: str = "",
    lpips_fn: LpipsFn | None = None,
    on_render: Callable[[PlannedDecision, np.ndarray], None] | None = None,
) -> tuple[EpisodeResult, bytes]:
    """Train, render and score the plan; returns the result and the PNG of the last render.
    With ``pool_workers`` ≥ 1 the pool's twin runs it (:func:`.pool.run_pool_plan`).

    ``on_render(decision, image)`` sees every scored render (float32 H×W×3 in [0, 1]).
    """
    cfg = plan.config
    if cfg.pool_workers:
        result, _, image = run_pool_plan(plan, dataset, key=key, lpips_fn=lpips_fn,
                                         on_render=on_render)
        return result, _png(image)
    started = time.perf_counter()
    trainer = FieldTrainer(field_config(cfg.backend, **cfg.field), dataset.aabb,
                           device=cfg.device, seed=plan.seed)
    rec = Reconstruction(trainer, cfg.carry, render_budget(cfg),
                         WarmStart(cold_steps=cfg.steps_per_epoch))
    frames = Frames(dataset, plan.scene_offset_ms)
    time_aware = trainer.cfg.time_aware  # trained at its frames' times, shown at display time
    heldout = dataset.cameras[dataset.heldout_id]
    epochs: list[EpochScore] = []
    last_image: np.ndarray | None = None
    loss = math.nan
    for d in plan.decisions:
        # the time a carried model moves to (a time-aware one: the scene time shown then)
        model_ms = frames.content_ms(d.eval_ms) if time_aware else d.eval_ms
        if d.train:
            rec.set_views([frames.view(c, g, d.eval_ms, time_aware)
                           for c, g in zip(d.cameras, d.gen_ms, strict=True)], model_ms)
            loss = rec.train(cfg.steps_per_epoch)
        if not d.scored:
            continue
        budget = decision_budget(cfg, d)
        if budget != rec.render_steps:
            rec.set_carry(cfg.carry, budget)
        rendered = rec.render_decision(heldout, time_ms=model_ms)
        if rendered.render_steps:
            loss = rendered.loss
        display_ms = d.eval_ms + cfg.compute_ms(rendered.render_steps)
        rec.ready(frames.content_ms(display_ms) if time_aware else display_ms)
        epoch = epoch_score(cfg, d, rec, rendered, frames, heldout, lpips_fn,
                            display_ms=display_ms, loss=float(loss))
        epochs.append(epoch)
        image = rendered.image
        last_image = image
        if on_render is not None:
            on_render(d, image)
    result = episode_result(plan, epochs, key=key, wall_s=time.perf_counter() - started)
    return result, _png(last_image)


def _png(image: np.ndarray | None) -> bytes:
    if image is None:
        return b""
    buf = io.BytesIO()
    Image.fromarray(to_uint8(image)).save(buf, "PNG")
    return buf.getvalue()


def set_torch_threads(threads: int) -> None:
    """Torch intra-op threads of this process (workers of a sweep use 1 each by default)."""
    if threads < 1:
        raise ValueError(f"threads must be >= 1, got {threads}")
    configure_process(threads)
