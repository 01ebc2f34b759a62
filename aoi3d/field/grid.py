"""``grid``: a dense voxel grid of density and colour (DVGO / Plenoxels style).

Each grid vertex holds a raw density and a raw RGB; a point's values are the trilinear
interpolation of its 8 neighbours, then σ = softplus(raw) and rgb = sigmoid(raw)
(post-activation, as DVGO: sharp surfaces at coarse resolution). Colour is per vertex, not
view-dependent: the turbine scene is Lambertian + ambient, so SH or an MLP would buy nothing
there. The grid spans the scene box
with vertices on its faces and cubic voxels; it starts coarse and is upsampled trilinearly at
``upsample_steps``. Rays that leave the box see a learned background, a lat-long environment
map of the ray direction sampled bilinearly (the scene outside the box depends on the
direction only).

The trilinear interpolation is the shared one of flat grids
(:func:`aoi3d.field.encodings.interpolate`: ``row_gather`` of the 8 corners, whose backward
scatters with ``index_add_`` into a row-sparse gradient). Measured with torch 2.13 on 2 CPU
cores, 200k samples on a 128×128×89 grid, forward + backward: a hand-written gather took
78 / 58 ms on 1 / 2 threads against 62 / 67 ms for ``grid_sample`` — on par; what pays is the
sparse gradient: ``LazyAdam`` then updates only the rows a batch reached, where a dense Adam
step over that grid costs 29 / 18 ms. On the CPU the query (interpolation and activations,
and its row-sparse gradient) runs fused in C where it can (:func:`aoi3d.field.native.grid_query`;
the code above is its reference and fallback); with the other fused kernels a 100-step
reconstruction takes about a third of the CPU time it took in torch (``bench/recon.py``). The
whole training step of this class runs in them without autograd (:meth:`DenseGridField.train_step`:
no graph, same gradients and random draws), another ~1.3× on that bench.

Timeliness embedding (``age_features`` = K > 0; the follow-up paper's baseline, arXiv
2509.17282: each image's AoI given to the scene model): the field also takes the age a of the
image a ray comes from (``RayBundle.age_ms``) and represents the scene a ms before the time
it stands for. A second table R of K × 4 raw values per vertex, on the same grid, is added
before the activations:

    raw(x, a) = G(x) + Σ_k φ_k(a) · R_k(x),   φ_k(a) = sin(k·π·min(a, A) / (2A)),

A = ``age_scale_ms``: a Fourier embedding of the age that is 0 at age 0, so G alone is the
scene at the decision's time — what a novel view renders (no age: age 0, the fused query) —
and R holds how older frames differ from it. R starts at 0 and trains with G; occupancy keeps
a voxel when G's density could reach the threshold with any age (|φ| ≤ 1). With the age
input ignored (every age 0, or K = 0) the field is the plain grid. Queries at an age run the
torch interpolation (the fused kernel has no age input).
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any

import numpy as np
import torch
import torch.nn.functional as F
from torch import nn

from aoi3d.field import native
from aoi3d.field.base import (
    CoarseToFineConfig,
    CoarseToFineField,
    check_positive,
    check_schedule,
)
from aoi3d.field.encodings import (
    cells_near,
    corner_rows,
    grid_shape,
    interpolate,
    linear_corners,
    resample,
    row_gather,
)
from aoi3d.field.rays import RayBundle
from aoi3d.field.render import RenderOptions, sample_kept

if TYPE_CHECKING:
    from aoi3d.field.optim import LazyAdam

__all__ = ["DenseGridField", "GridConfig"]


@dataclass(frozen=True)
class GridConfig(CoarseToFineConfig):
    """The dense grid backend.

    Coarse to fine: ``grid_sizes`` at ``upsample_steps`` (:class:`CoarseToFineConfig`).
    ``init_density`` is the initial σ everywhere (per world unit).
    Adam learning rate ``lr_grid`` (density and colour; the background's is inherited).
    Empty-space skipping: from step ``occupancy_from_step``, every ``occupancy_every`` steps,
    a voxel is kept when one of its corners has an opacity 1 − exp(−σ·δ_fine) above
    ``occupancy_alpha``, dilated by one voxel; samples in other voxels are skipped (σ = 0).
    Timeliness embedding: ``age_features`` K (0: off) Fourier features of the image's age over
    ``age_scale_ms`` (see the module).
    """

    init_density: float = 0.1
    lr_grid: float = 0.1
    occupancy_from_step: int = 100
    occupancy_every: int = 16
    occupancy_alpha: float = 1e-3
    age_features: int = 0
    age_scale_ms: float = 300.0

    def __post_init__(self) -> None:
        super().__post_init__()
        check_positive(self, ("init_density", "lr_grid", "age_scale_ms"))
        check_schedule("occupancy", self.occupancy_from_step, self.occupancy_every,
                       self.occupancy_alpha)
        k = self.age_features
        if isinstance(k, bool) or not isinstance(k, int) or k < 0:
            raise ValueError(f"age_features must be an int >= 0, got {k!r}")

    @property
    def takes_age(self) -> bool:
        """The timeliness embedding is on (``age_features`` > 0)."""
        return self.age_features > 0

    def build(self, aabb: np.ndarray) -> DenseGridField:
        return DenseGridField(self, aabb)


class DenseGridField(CoarseToFineField):
    """Density + RGB on a dense grid inside the box, lat-long background outside."""

    cfg: GridConfig
    view_dependent = False  # colour per vertex

    def __init__(self, cfg: GridConfig, aabb: np.ndarray) -> None:
        super().__init__()
        box = self._setup(cfg, aabb)
        raw_density = math.log(math.expm1(cfg.init_density))
        self._raw_density_init = raw_density
        table = torch.zeros(math.prod(self.shape), 4)
        table[:, 0] = raw_density
        self.grid = nn.Parameter(table)  # (vertices, 4): raw density, raw RGB
        # the timeliness embedding's residuals, (vertices, 4·K): feature k in columns 4k:4k+4
        self.age_grid = (nn.Parameter(torch.zeros(table.shape[0], 4 * cfg.age_features))
                         if cfg.age_features else None)
        sigma_min = cfg.density_threshold(box, cfg.occupancy_alpha)
        self._raw_density_min = math.log(math.expm1(sigma_min))
        self._occupancy: torch.Tensor | None = None  # (cells,) bool, None: skip nothing

    # --- the Field interface -------------------------------------------------------------
    def query(self, points: torch.Tensor, dirs: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        fused = native.grid_query(self.grid, points, self.aabb, self.shape)
        if fused is not None:
            return fused
        raw = interpolate(self.grid, self.shape, self._coords(points), sparse=True)
        return F.softplus(raw[:, 0]), torch.sigmoid(raw[:, 1:])

    def query_aged(self, points: torch.Tensor, dirs: torch.Tensor, age_ms: torch.Tensor
                   ) -> tuple[torch.Tensor, torch.Tensor]:
        """The scene ``age_ms`` (P,) before the field's time: G + Σ_k φ_k(age)·R_k, then the
        activations (see the module); the plain query without the embedding."""
        if self.age_grid is None:
            return self.query(points, dirs)
        coords = self._coords(points)
        axes = [linear_corners(coords[:, d], n) for d, n in enumerate(self.shape)]
        idx, w = corner_rows(axes, self.shape)
        raw = row_gather(self.grid, idx, w, True)
        residual = row_gather(self.age_grid, idx, w, True).view(-1, self.cfg.age_features, 4)
        raw = raw + (self.age_embedding(age_ms)[:, :, None] * residual).sum(dim=1)
        return F.softplus(raw[:, 0]), torch.sigmoid(raw[:, 1:])

    def age_embedding(self, age_ms: torch.Tensor) -> torch.Tensor:
        """φ(a) (P, K): sin(k·π·min(a, A)/(2A)), k = 1..K; 0 at age 0."""
        cfg = self.cfg
        a = age_ms.clamp(0.0, cfg.age_scale_ms) * (math.pi / (2.0 * cfg.age_scale_ms))
        k = torch.arange(1, cfg.age_features + 1, device=age_ms.device, dtype=age_ms.dtype)
        return torch.sin(a[:, None] * k[None, :])

    def train_step(self, rays: RayBundle, options: RenderOptions, target: torch.Tensor,
                   optimizer: LazyAdam) -> float | None:
        """The whole training step in the fused kernels, without autograd
        (:func:`aoi3d.field.native.grid_training_grads`), where they run and the rays carry no
        age (the timeliness embedding trains under autograd); for this class itself only: a
        subclass may render otherwise (its own ``render_rays``, ``query`` or ``background``),
        so it trains under autograd."""
        if (type(self) is not DenseGridField or rays.age_ms is not None
                or self.age_grid is not None
                or not native.grid_step_available(self.grid, self.env, rays.origins, target)):
            return None
        samples = sample_kept(self, rays, options)
        cfg = self.cfg
        mse, rows, values, grad_env = native.grid_training_grads(
            self.grid, self.aabb, self.shape, self.env, cfg.up_axis, samples.points,
            samples.deltas, samples.ray_index, rays.dirs, target, cfg.sample_rgb_loss,
            cfg.opacity_loss)
        optimizer.update(self.grid, (rows, values))
        optimizer.update(self.env, grad_env)
        return mse

    @torch.no_grad()
    def forget(self, changed: Callable[[torch.Tensor], torch.Tensor]
               ) -> list[tuple[torch.Tensor, torch.Tensor]]:
        """The vertices where ``changed`` holds back to their initial values: density
        ``init_density``, colour 0 (grey), no age residual (the background is kept)."""
        axes = [torch.linspace(0.0, 1.0, n, device=self.grid.device) for n in self.shape]
        unit = torch.stack(torch.meshgrid(*axes, indexing="ij"), dim=-1).reshape(-1, 3)
        points = self.aabb[0] + unit * (self.aabb[1] - self.aabb[0])
        rows = torch.as_tensor(changed(points), device=self.grid.device).reshape(-1)
        rows = rows.nonzero().reshape(-1)
        self.grid[rows, 0] = self._raw_density_init
        self.grid[rows, 1:] = 0.0
        found: list[tuple[torch.Tensor, torch.Tensor]] = [(self.grid, rows)]
        if self.age_grid is not None:
            self.age_grid[rows] = 0.0
            found.append((self.age_grid, rows))
        return found

    def param_groups(self) -> list[dict[str, Any]]:
        grids = [self.grid] if self.age_grid is None else [self.grid, self.age_grid]
        return [{"params": grids, "lr": self.cfg.lr_grid}, self.background_group()]

    def occupied(self, points: torch.Tensor) -> torch.Tensor | None:
        return self._at_cells(self._occupancy, points)

    def on_step(self, step: int) -> bool:
        resized = self._advance(step)
        cfg = self.cfg
        if step < cfg.occupancy_from_step:
            self._occupancy = None
        elif resized or (step - cfg.occupancy_from_step) % cfg.occupancy_every == 0:
            self.refresh_occupancy()
        return resized

    @torch.no_grad()
    def refresh_occupancy(self) -> None:
        """Recompute which voxels may hold density (see ``GridConfig``): a voxel is kept when a
        vertex within one voxel of it (4 vertices per axis) is above the threshold."""
        raw = self.grid[:, 0]
        if self.age_grid is not None:  # the largest density any age can give (|φ| ≤ 1)
            raw = raw + self.age_grid[:, 0::4].abs().sum(dim=1)
        dense = (raw > self._raw_density_min).view(*self.shape)
        self._occupancy = cells_near(dense).reshape(-1)

    # --- coarse to fine -------------------------------------------------------------------
    def resize(self, size: int) -> None:
        """Resample the grid trilinearly to ``size`` vertices along the longest side."""
        new_shape = grid_shape(self.aabb.cpu().numpy(), size)
        with torch.no_grad():
            self.grid = nn.Parameter(resample(self.grid, self.shape, new_shape))
            if self.age_grid is not None:
                self.age_grid = nn.Parameter(resample(self.age_grid, self.shape, new_shape))
        self.shape = new_shape
