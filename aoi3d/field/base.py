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

import math
from abc import ABC, abstractmethod
from collections.abc import Callable, Iterable, Iterator
from contextlib import contextmanager
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any

import numpy as np
import torch
from torch import nn

from aoi3d.field.background import latlong_background
from aoi3d.field.encodings import cell_index, grid_shape, vertex_coords
from aoi3d.field.rays import RayBundle
from aoi3d.field.render import RenderOptions, RenderResult, render_uniform

if TYPE_CHECKING:
    from aoi3d.field.optim import LazyAdam

__all__ = [
    "CoarseToFineConfig",
    "CoarseToFineField",
    "Field",
    "FieldConfig",
    "check_at_least",
    "check_positive",
    "check_schedule",
    "seeded",
]


@contextmanager
def seeded(seed: int) -> Iterator[None]:
    """Inside: torch's global generator seeded with ``seed``; after: its state as before (so
    a field's initial weights depend on its seed only)."""
    with torch.random.fork_rng(devices=[]):
        torch.manual_seed(seed)
        yield


# --- validation the configs share -----------------------------------------------------------
def check_at_least(cfg: Any, minimum: int, names: Iterable[str]) -> None:
    """``ValueError`` naming the first of the fields ``names`` of ``cfg`` below ``minimum``."""
    for name in names:
        if getattr(cfg, name) < minimum:
            raise ValueError(f"{name} must be >= {minimum}, got {getattr(cfg, name)}")


def check_positive(cfg: Any, names: Iterable[str]) -> None:
    """``ValueError`` naming the first of the fields ``names`` of ``cfg`` not > 0 (NaN too)."""
    for name in names:
        if not getattr(cfg, name) > 0:
            raise ValueError(f"{name} must be > 0, got {getattr(cfg, name)}")


def check_schedule(schedule: str, from_step: int, every: int, alpha: float) -> None:
    """Validate an empty-space schedule (``<schedule>_from_step``, ``<schedule>_every``,
    ``<schedule>_alpha``, e.g. ``occupancy`` or ``mask``); ``ValueError`` names the field."""
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
    ``num_threads`` (None: torch's default) and ``tune_malloc`` (raise glibc's mmap/trim
    thresholds so that per-step tensors reuse heap memory instead of fresh pages) are the
    process-wide settings a program that trains this field makes once, with
    :func:`aoi3d.field.process.configure_process`; the trainer's constructor makes none.
    ``appearance_slots``: rows of the per-image appearance table of fields that have one (the
    trainer maps each view's ``appearance_id`` — or its camera — to a row and recycles the
    least recently used row when more ids come; fields without embeddings ignore it).
    Background (every backend's, :mod:`aoi3d.field.background`): a lat-long map of
    ``background_size`` (rows, columns) around ``up_axis``, learned at ``lr_background``.

    ``age_weight_tau_ms``: the *weighted-sum* baseline of the follow-up paper (arXiv
    2509.17282): each ray's data terms (the colour MSE and the per-sample colour loss) are
    weighted by w = exp(−age/τ), the age being its image's (``TrainView.age_ms``, the AoI of
    the frame at the decision it trains for), and normalised over the batch, Σ w·e / Σ w, so
    that images of equal age give the plain loss. None (the default): the plain loss; every
    view may then lack an age.
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
    lr_background: float = 0.05
    background_size: tuple[int, int] = (64, 128)
    up_axis: int = 2
    age_weight_tau_ms: float | None = None

    def __post_init__(self) -> None:
        names = ("batch_rays", "samples_coarse", "samples_fine", "render_chunk_rays",
                 "appearance_slots")
        check_at_least(self, 1, names)
        check_at_least(self, 0, ("sample_rgb_loss", "opacity_loss"))
        tau = self.age_weight_tau_ms
        if tau is not None and (isinstance(tau, bool) or not isinstance(tau, int | float)
                                or not math.isfinite(tau) or tau <= 0):
            raise ValueError(f"age_weight_tau_ms must be a number > 0 or None, got {tau!r}")
        check_positive(self, ("lr_background",))
        if min(self.background_size) < 2:
            raise ValueError(f"background_size must be >= (2, 2), got {self.background_size}")
        if self.up_axis not in (0, 1, 2):
            raise ValueError(f"up_axis must be 0, 1 or 2, got {self.up_axis}")
        if not 0 <= self.explore_empty <= 1:
            raise ValueError(f"explore_empty must be in [0, 1], got {self.explore_empty}")
        if self.fine_from_step < 0:
            raise ValueError(f"fine_from_step must be >= 0, got {self.fine_from_step}")
        if self.num_threads is not None and self.num_threads < 1:
            raise ValueError(f"num_threads must be >= 1 or None, got {self.num_threads}")

    @property
    def takes_age(self) -> bool:
        """Whether the field this config builds takes each training ray's image age as an
        input (``RayBundle.age_ms``; the grid's timeliness embedding). Default: no."""
        return False

    @property
    def time_aware(self) -> bool:
        """Whether the field this config builds can be rendered at another time than the one
        it stands for (``FieldTrainer.render``'s ``ahead_ms``: the display time) and carried to
        a later one (``Field.advance``): the ``flow`` backend. Default: no, a static field
        shows the same scene at every time."""
        return False

    @property
    def uses_age(self) -> bool:
        """Whether training needs each view's age (``TrainView.age_ms``): the field takes it,
        or the loss is weighted by it (``age_weight_tau_ms``)."""
        return self.takes_age or self.age_weight_tau_ms is not None

    def ray_step(self, aabb: np.ndarray, step: int) -> float:
        """World distance between samples at training step ``step``."""
        diagonal = float(np.linalg.norm(aabb[1] - aabb[0]))
        n = self.samples_coarse if step < self.fine_from_step else self.samples_fine
        return diagonal / n

    def density_threshold(self, aabb: np.ndarray, alpha: float) -> float:
        """The density σ whose opacity 1 − exp(−σ·δ) at the fine ray step δ is ``alpha``
        (empty-space skipping keeps what is above it)."""
        return -math.log1p(-alpha) / self.ray_step(aabb, self.fine_from_step)

    def build(self, aabb: np.ndarray) -> Field:
        """The field this config describes, covering ``aabb`` (2, 3)."""
        raise NotImplementedError(f"{type(self).__name__} builds no field")


class Field(nn.Module, ABC):
    """Maps points inside the box to density and colour, and directions to the background.

    The built-in backends start with :meth:`_setup` (their config ``cfg``, the box buffer
    ``aabb`` and the lat-long background map ``env``), which the default :meth:`background`
    and :meth:`background_group` use.
    """

    cfg: FieldConfig
    aabb: torch.Tensor  # a buffer: the box (2, 3)
    env: nn.Parameter
    view_dependent: bool = True
    """Whether :meth:`query`'s colour depends on ``dirs``; False lets the uniform renderer
    skip gathering each sample's direction (it then passes any unit direction)."""

    def _setup(self, cfg: FieldConfig, aabb: np.ndarray) -> np.ndarray:
        """Keep ``cfg``, register the box (2, 3) as buffer ``aabb`` and create the background
        map ``env`` (rows, columns, 3) at zero; returns the box as float64."""
        self.cfg = cfg
        box = np.asarray(aabb, dtype=np.float64)
        self.register_buffer("aabb", torch.tensor(box, dtype=torch.float32))
        rows, cols = cfg.background_size
        self.env = nn.Parameter(torch.zeros(rows, cols, 3))
        return box

    @abstractmethod
    def query(self, points: torch.Tensor, dirs: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """Density σ ≥ 0 (P,) and colour in [0, 1] (P, 3) at world ``points`` seen along
        ``dirs`` (P, 3)."""

    def query_aged(self, points: torch.Tensor, dirs: torch.Tensor, age_ms: torch.Tensor
                   ) -> tuple[torch.Tensor, torch.Tensor]:
        """:meth:`query` for samples of images of age ``age_ms`` (P,): what the scene looked
        like that long before the time the field stands for. Only a field whose config
        ``takes_age`` is asked; the others take no age."""
        raise NotImplementedError(f"{type(self).__name__} takes no age input")

    def background(self, dirs: torch.Tensor) -> torch.Tensor:
        """Colour in [0, 1] (R, 3) of rays leaving the box with unit directions ``dirs``;
        default: the lat-long map ``env`` around ``cfg.up_axis``."""
        return latlong_background(self.env, dirs, self.cfg.up_axis)

    def background_group(self) -> dict[str, Any]:
        """The optimizer parameter group of the background map."""
        return {"params": [self.env], "lr": self.cfg.lr_background}

    @abstractmethod
    def param_groups(self) -> list[dict[str, Any]]:
        """Optimizer parameter groups (each with its ``lr``)."""

    def occupied(self, points: torch.Tensor) -> torch.Tensor | None:
        """Mask (P,) of the points that may have density (empty-space skipping); None keeps
        every point. Skipped points are treated as σ = 0."""
        return None

    def advance(self, dt_ms: float
                ) -> list[tuple[torch.Tensor, Callable[[torch.Tensor], torch.Tensor]]] | None:
        """Move the time the field stands for ``dt_ms`` later (a time-aware field, whose
        config is ``time_aware``, carries its parameters along its motion); returns each
        parameter changed with the map that changed it, for the optimizer's moments of it.
        Default: None, nothing changes (a static field stands for every time)."""
        return None

    def set_pivot(self, pivot_ms: float) -> None:
        """A time-aware field: the age its parameters stand for (the trainer sets it to the
        mean age of the views before training). Default: nothing (a static field)."""

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

    def train_step(self, rays: RayBundle, options: RenderOptions, target: torch.Tensor,
                   optimizer: LazyAdam) -> float | None:
        """Hook: one whole training step on ``rays`` and their ``target`` colours (R, 3) —
        render, the trainer's loss (:meth:`aoi3d.field.trainer.FieldTrainer.step`, unweighted),
        gradients and ``optimizer``'s update — done by the field itself, faster than the
        trainer's autograd step and equal to it up to float rounding; returns the step's
        colour MSE. None (default): nothing was done, not even a random draw; the trainer
        takes its autograd step."""
        return None

    def forget(self, changed: Any) -> list[tuple[torch.Tensor, torch.Tensor]] | None:
        """Hook: return the parameters where ``changed(points)`` (world points (P, 3) → bool
        (P,)) holds to their initial values; the (parameter, rows reset) pairs, for the
        optimizer's moments. Default: None, this field cannot forget a region."""
        return None

    def reset_appearance(self, rows: torch.Tensor) -> None:
        """Hook: the trainer gave appearance ``rows`` (int64) to new images; a field with
        per-image embeddings resets them to their initial value. Default: nothing."""


# --- backends on vertex grids refined coarse to fine ----------------------------------------
@dataclass(frozen=True)
class CoarseToFineConfig(FieldConfig):
    """A backend on vertex grids refined coarse to fine (``grid``, ``tensorf``):
    ``grid_sizes``: vertices along the longest box side at each stage (the other sides get the
    same voxel size); stage k + 1 starts at training step ``upsample_steps[k]``."""

    grid_sizes: tuple[int, ...] = (48, 96, 128)
    upsample_steps: tuple[int, ...] = (300, 1000)

    def __post_init__(self) -> None:
        super().__post_init__()
        sizes, steps = self.grid_sizes, self.upsample_steps
        if not sizes or min(sizes) < 2:
            raise ValueError(f"grid_sizes must be non-empty, each >= 2, got {sizes}")
        if len(steps) != len(sizes) - 1:
            raise ValueError(
                f"upsample_steps needs len(grid_sizes) - 1 = {len(sizes) - 1} entries, got {steps}"
            )
        if list(steps) != sorted(steps) or (steps and steps[0] < 1):
            raise ValueError(f"upsample_steps must be increasing and >= 1: {steps}")

    def stage(self, step: int) -> int:
        """Index into ``grid_sizes`` of the resolution used at training step ``step``."""
        return sum(1 for s in self.upsample_steps if step >= s)


class CoarseToFineField(Field):
    """A field on vertex grids spanning the box (vertices on its faces, cubic voxels) of
    ``shape`` vertices per axis, the stage of ``cfg.grid_sizes`` in force; :meth:`resize`
    resamples its grids when a stage begins (:meth:`_advance`, from ``on_step``)."""

    cfg: CoarseToFineConfig

    def _setup(self, cfg: FieldConfig, aabb: np.ndarray) -> np.ndarray:
        box = super()._setup(cfg, aabb)
        self._stage = 0
        self.shape = grid_shape(box, self.cfg.grid_sizes[0])
        return box

    @abstractmethod
    def resize(self, size: int) -> None:
        """Resample the grids to ``size`` vertices along the longest side; sets ``shape``."""

    def _advance(self, step: int) -> bool:
        """Resize when training step ``step`` begins a new stage; True when it did."""
        stage = self.cfg.stage(step)
        if stage == self._stage:
            return False
        self.resize(self.cfg.grid_sizes[stage])
        self._stage = stage
        return True

    def _coords(self, points: torch.Tensor) -> torch.Tensor:
        """World ``points`` (P, 3) in vertex units of the current grid."""
        return vertex_coords(points, self.aabb, self.shape)

    def _at_cells(self, cells: torch.Tensor | None, points: torch.Tensor) -> torch.Tensor | None:
        """Per-cell values ``cells`` (Π(n − 1),) of the current grid at world ``points`` (None
        stays None)."""
        if cells is None:
            return None
        index = cell_index(self._coords(points), [n - 1 for n in self.shape])
        return cells.index_select(0, index)
