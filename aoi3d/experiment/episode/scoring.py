"""Scoring a rendered decision of an episode (:func:`epoch_score`), against the truth frames
of the episode's dataset at channel times (:class:`Frames`): what the no-pool engine
(:mod:`.run`) and the pool's twin (:mod:`.pool`) share."""

from __future__ import annotations

import math
from dataclasses import replace

import numpy as np

from aoi3d.experiment.config import EpisodeConfig
from aoi3d.experiment.episode.plan import PlannedDecision
from aoi3d.experiment.episode.result import EpochScore
from aoi3d.field import TrainView
from aoi3d.field.carry import Reconstruction, RenderedDecision
from aoi3d.quality import DYNAMIC_FRAMES, LpipsFn, score
from aoi3d.scene import Camera, SceneDataset

__all__ = ["Frames", "epoch_score"]


class Frames:
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



def epoch_score(cfg: EpisodeConfig, d: PlannedDecision, rec: Reconstruction,
                rendered: RenderedDecision, frames: Frames, heldout: Camera,
                lpips_fn: LpipsFn | None, *, display_ms: float, loss: float) -> EpochScore:
    """The scores of one rendered decision: its render against the truth at its time, and
    what a viewer sees — the render shown at ``display_ms`` (its reconstruction done), scored
    against the truth then (a time-aware field rendered again at that scene time)."""
    image = rendered.image
    quality = score(image, frames.truth(d.eval_ms), cfg.reward, lpips_fn,
                    previous=frames.truth_before(d.eval_ms, cfg.period_ms))
    dyn = quality.dynamic
    assert dyn is not None  # score() was given the previous truth frames
    # a time-aware field is rendered again at the scene time of the truth shown then (a
    # static one shows the same image)
    shown_image = (rec.render_at(heldout, frames.content_ms(display_ms)
                                 - frames.content_ms(d.eval_ms))
                   if rec.trainer.cfg.time_aware else image)
    shown = score(shown_image, frames.truth(display_ms), cfg.reward, lpips_fn,
                  previous=frames.truth_before(display_ms, cfg.period_ms))
    return EpochScore(
        decision_ms=d.decision_ms, eval_ms=d.eval_ms, n_selected=len(d.cameras),
        aoi_used_ms=float(np.mean(d.aoi_ms)) if d.aoi_ms else math.nan,
        psnr_db=quality.psnr_db, ssim=quality.ssim, lpips=quality.lpips,
        reward=quality.reward, loss=loss, steps=rendered.steps,
        psnr_dynamic_db=dyn.psnr_db, ssim_dynamic=dyn.ssim, dynamic_fraction=dyn.fraction,
        display_ms=display_ms, psnr_display_db=shown.psnr_db, ssim_display=shown.ssim,
        lpips_display=shown.lpips, reward_display=shown.reward,
        psnr_dynamic_display_db=shown.dynamic.psnr_db if shown.dynamic else None,
    )
