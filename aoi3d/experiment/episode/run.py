"""Stage 2 of an episode: train, render and score its plan (:func:`run_plan`)."""

from __future__ import annotations

import io
import math
import time
from collections.abc import Callable
from dataclasses import replace

import numpy as np
from PIL import Image

from aoi3d.experiment.episode.plan import (
    EpisodePlan,
    PlannedDecision,
    decision_budget,
    render_budget,
)
from aoi3d.experiment.episode.result import EpisodeResult, EpochScore, episode_result
from aoi3d.field import FieldTrainer, TrainView, field_config
from aoi3d.field.carry import Reconstruction, WarmStart
from aoi3d.field.process import configure_process
from aoi3d.quality import DYNAMIC_FRAMES, LpipsFn, score
from aoi3d.scene import SceneDataset, to_uint8


class _Frames:
    """Decoded frames of the dataset at channel times (scene time = channel time + offset).

    Keeps one :class:`TrainView` per camera — its newest — so that the trainer's per-view
    pixel cache hits while a camera's frame does not change, and memory stays bounded.
    """

    def __init__(self, dataset: SceneDataset, offset_ms: int) -> None:
        self.ds = dataset
        self.offset_ms = offset_ms
        self._views: dict[int, tuple[int, TrainView]] = {}

    def index(self, time_ms: float) -> int:
        """The scene frame shown at channel time ``time_ms``."""
        return self.ds.frame_index(time_ms + self.offset_ms)

    def content_ms(self, time_ms: float) -> float:
        """The scene time of the frame shown at channel time ``time_ms``, not looped: the
        frames are 1000/fps ms apart, so it trails ``time_ms`` + offset by up to a frame."""
        return math.floor((time_ms + self.offset_ms) * self.ds.fps / 1000.0 + 1e-9
                          ) * 1000.0 / self.ds.fps

    def view(self, camera_id: int, gen_ms: int, eval_ms: int, content: bool = False
             ) -> TrainView:
        """Camera ``camera_id``'s frame generated at ``gen_ms``, used for time ``eval_ms``
        (its age, ``eval_ms − gen_ms``, is what the age-aware trainers read; ``content``: the
        age between the scene times the two frames show instead, what a time-aware field
        reads — a real camera's timestamp is its frame's scene time)."""
        k = self.index(gen_ms)
        age = (self.content_ms(eval_ms) - self.content_ms(gen_ms) if content
               else float(eval_ms - gen_ms))
        held = self._views.get(camera_id)
        if held is None or held[0] != k:
            held = (k, TrainView(self.ds.cameras[camera_id], self.ds.frame(camera_id, k),
                                 age_ms=age))
            self._views[camera_id] = held
        elif held[1].age_ms != age:  # the same frame, older: its pixels are shared
            held = (k, replace(held[1], age_ms=age))
            self._views[camera_id] = held
        return held[1]

    def truth(self, time_ms: float) -> np.ndarray:
        """The held-out camera's frame at ``time_ms``: the ground truth of the novel view."""
        return self.ds.frame(self.ds.heldout_id, self.index(time_ms))

    def truth_before(self, time_ms: float, period_ms: int) -> list[np.ndarray]:
        """The truth at ``time_ms`` − k·``period_ms``, k = 1..K: what the dynamic mask
        compares the truth at ``time_ms`` with."""
        return [self.truth(time_ms - k * period_ms) for k in range(1, DYNAMIC_FRAMES + 1)]


def run_plan(
    plan: EpisodePlan,
    dataset: SceneDataset,
    *,
    key: str = "",
    lpips_fn: LpipsFn | None = None,
    on_render: Callable[[PlannedDecision, np.ndarray], None] | None = None,
) -> tuple[EpisodeResult, bytes]:
    """Train, render and score the plan; returns the result and the PNG of the last render.

    ``on_render(decision, image)`` sees every scored render (float32 H×W×3 in [0, 1]).
    """
    cfg = plan.config
    started = time.perf_counter()
    trainer = FieldTrainer(field_config(cfg.backend, **cfg.field), dataset.aabb,
                           device=cfg.device, seed=plan.seed)
    rec = Reconstruction(trainer, cfg.carry, render_budget(cfg),
                         WarmStart(cold_steps=cfg.steps_per_epoch))
    frames = _Frames(dataset, plan.scene_offset_ms)
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
        image = rendered.image
        quality = score(image, frames.truth(d.eval_ms), cfg.reward, lpips_fn,
                        previous=frames.truth_before(d.eval_ms, cfg.period_ms))
        dyn = quality.dynamic
        assert dyn is not None  # score() was given the previous truth frames
        # what a viewer sees: the render once its compute is done, against the truth then
        display_ms = d.eval_ms + cfg.compute_ms(rendered.render_steps)
        # a time-aware field is rendered again at the scene time of the truth shown then (a
        # static one shows the same image)
        shown_image = (rec.render_at(heldout, frames.content_ms(display_ms)
                                     - frames.content_ms(d.eval_ms))
                       if time_aware else image)
        shown = score(shown_image, frames.truth(display_ms), cfg.reward, lpips_fn,
                      previous=frames.truth_before(display_ms, cfg.period_ms))
        epochs.append(EpochScore(
            decision_ms=d.decision_ms, eval_ms=d.eval_ms, n_selected=len(d.cameras),
            aoi_used_ms=float(np.mean(d.aoi_ms)) if d.aoi_ms else math.nan,
            psnr_db=quality.psnr_db, ssim=quality.ssim, lpips=quality.lpips,
            reward=quality.reward, loss=float(loss), steps=rendered.steps,
            psnr_dynamic_db=dyn.psnr_db, ssim_dynamic=dyn.ssim, dynamic_fraction=dyn.fraction,
            display_ms=display_ms, psnr_display_db=shown.psnr_db, ssim_display=shown.ssim,
            lpips_display=shown.lpips, reward_display=shown.reward,
            psnr_dynamic_display_db=shown.dynamic.psnr_db if shown.dynamic else None,
        ))
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
