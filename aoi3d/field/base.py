"""What every radiance-field backend shares: its config's sampling/training part and the
``Field`` interface the trainer drives (nerfstudio style: a config dataclass builds its field).

A backend is a pair: ``XConfig(FieldConfig)`` with ``build(aabb) -> XField`` and
``XField(Field)``. Ray generation, the volume renderer and the training loop
(``FieldTrainer``) are common to all of them. The field owns how its rays are sampled and
rendered (nerfstudio's Model: sampling → field → rendering → losses) through
:meth:`Field.render_rays`; the default is the shared uniform sampler with empty-space skipping
(:func:`aoi3d.field.render.render_uniform`), which needs only ``query``/``background``/
``occupied``. A field that samples otherwise overrides ``render_rays`` and may return extra
loss terms in ``RenderResult.aux_loss``.
"""

from __future__ import annotations

from abc import ABC, abstractmethod
from dataclasses import dataclass
from typing import Any

import numpy as np
import torch
from torch import nn

from aoi3d.field.rays import RayBundle
from aoi3d.field.render import RenderOptions, RenderResult, render_uniform

__all__ = ["Field", "FieldConfig", "check_background_and_schedule"]


def check_background_and_schedule(background_size: tuple[int, int], up_axis: int,
                                  schedule: str, from_step: int, every: int,
                                  alpha: float) -> None:
    """Validate what the grid-like configs share: the background map's size and pole axis, and
    an empty-space schedule (``<schedule>_from_step``, ``<schedule>_every``,
    ``<schedule>_alpha``, e.g. ``occupancy`` or ``mask``); ``ValueError`` names the field."""
    if min(background_size) < 2:
        raise ValueError(f"background_size must be >= (2, 2), got {background_size}")
    if up_axis not in (0, 1, 2):
        raise ValueError(f"up_axis must be 0, 1 or 2, got {up_axis}")
    if from_step < 0 or every < 1:
        raise ValueError(f"{schedule}_from_step must be >= 0 and {schedule}_every >= 1, got "
                         f"{from_step}, {every}")
    if not 0 < alpha < 1:
        raise ValueError(f"{schedule}_alpha must be in (0, 1), got {alpha}")


@dataclass(frozen=True)
class FieldConfig:
    """Training and sampling settings common to every backend.

    Ray step: ``box diagonal / samples_coarse`` for the first ``fine_from_step`` steps, then
    ``box diagonal / samples_fine``. ``batch_rays`` random rays per step, Adam with
    ``adam_eps``. ``render_chunk_rays`` rays per chunk when rendering a whole view.

    Loss = MSE(C(r), C_gt) + ``sample_rgb_loss`` · Σ_i w_i ‖c_i − C_gt‖² (DVGO's per-point
    colour loss: fog must have the pixel's colour) + ``opacity_loss`` · Σ_i α_i (sparsity:
    clears free space that the data does not constrain, e.g. fog in front of the sky), both
    summed along a ray and averaged over rays (turbine, 15 s: +1.5 dB with 18 views, and
    the cleared sky lets empty-space skipping work; about even with 6 views).
    ``explore_empty``: fraction of the samples in
    skipped (empty) space still trained on, so that density can return where frames need it.
    ``num_threads`` sets ``torch.set_num_threads`` when the trainer is built on the CPU
    (process-wide; None leaves torch's default). ``tune_malloc`` raises glibc's mmap/trim
    thresholds on Linux CPU so that per-step tensors reuse heap memory instead of fresh pages.
    ``appearance_slots``: rows of the per-image appearance table of fields that have one (the
    trainer maps each view's ``appearance_id`` — or its camera — to a row and recycles the
    least recently used row when more ids come; fields without embeddings ignore it).
    """

    batch_rays: int = 1024
    samples_coarse: int = 64
    samples_fine: int = 160
    fine_from_step: int = 300
    adam_eps: float = 1e-15
    render_chunk_rays: int = 16384
    sample_rgb_loss: float = 0.01
    opacity_loss: float = 3e-3
    explore_empty: float = 0.02
    num_threads: int | None = None
    tune_malloc: bool = True
    appearance_slots: int = 64

    def __post_init__(self) -> None:
        for name in (
            "batch_rays",
            "samples_coarse",
            "samples_fine",
            "render_chunk_rays",
            "appearance_slots",
        ):
            if getattr(self, name) < 1:
                raise ValueError(f"{name} must be >= 1, got {getattr(self, name)}")
        for name in ("sample_rgb_loss", "opacity_loss"):
            if not getattr(self, name) >= 0:
                raise ValueError(f"{name} must be >= 0, got {getattr(self, name)}")
        if not 0 <= self.explore_empty <= 1:
            raise ValueError(f"explore_empty must be in [0, 1], got {self.explore_empty}")
        if self.fine_from_step < 0:
            raise ValueError(f"fine_from_step must be >= 0, got {self.fine_from_step}")
        if self.num_threads is not None and self.num_threads < 1:
            raise ValueError(f"num_threads must be >= 1 or None, got {self.num_threads}")

    def ray_step(self, aabb: np.ndarray, step: int) -> float:
        """World distance between samples at training step ``step``."""
        diagonal = float(np.linalg.norm(aabb[1] - aabb[0]))
        n = self.samples_coarse if step < self.fine_from_step else self.samples_fine
        return diagonal / n

    def build(self, aabb: np.ndarray) -> Field:
        """The field this config describes, covering ``aabb`` (2, 3)."""
        raise NotImplementedError(f"{type(self).__name__} builds no field")


class Field(nn.Module, ABC):
    """Maps points inside the box to density and colour, and directions to the background."""

    @abstractmethod
    def query(self, points: torch.Tensor, dirs: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """Density σ ≥ 0 (P,) and colour in [0, 1] (P, 3) at world ``points`` seen along
        ``dirs`` (P, 3)."""

    @abstractmethod
    def background(self, dirs: torch.Tensor) -> torch.Tensor:
        """Colour in [0, 1] (R, 3) of rays leaving the box with unit directions ``dirs``."""

    @abstractmethod
    def param_groups(self) -> list[dict[str, Any]]:
        """Optimizer parameter groups (each with its ``lr``)."""

    def occupied(self, points: torch.Tensor) -> torch.Tensor | None:
        """Mask (P,) of the points that may have density (empty-space skipping); None keeps
        every point. Skipped points are treated as σ = 0."""
        return None

    def on_step(self, step: int) -> bool:
        """Hook before training step ``step``; True when parameters were replaced (e.g. the
        grid was upsampled) and the optimizer must be rebuilt."""
        return False

    def render_rays(self, rays: RayBundle, options: RenderOptions) -> RenderResult:
        """Sample, query and composite ``rays``; in training (``self.training``) the result's
        ``aux_loss`` may carry this field's extra loss terms, which the trainer adds.

        Default: the shared uniform sampler at ``options.ray_step`` with empty-space skipping
        (``occupied``), ``query``, ``background``, the volume renderer; ``rays.appearance``
        is not used.
        """
        return render_uniform(self, rays, options)

    def reset_appearance(self, rows: torch.Tensor) -> None:
        """Hook: the trainer gave appearance ``rows`` (int64) to new images; a field with
        per-image embeddings resets them to their initial value. Default: nothing."""
