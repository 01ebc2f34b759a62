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
step over that grid costs 29 / 18 ms.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

import numpy as np
import torch
import torch.nn.functional as F
from torch import nn

from aoi3d.field.background import latlong_background
from aoi3d.field.base import Field, FieldConfig, check_background_and_schedule
from aoi3d.field.encodings import cell_index, grid_shape, interpolate, resample, vertex_coords

__all__ = ["DenseGridField", "GridConfig"]


@dataclass(frozen=True)
class GridConfig(FieldConfig):
    """The dense grid backend.

    ``grid_sizes``: vertices along the longest box side at each coarse-to-fine stage (the
    other sides get the same voxel size); stage k+1 starts at training step
    ``upsample_steps[k]``. ``init_density`` is the initial σ everywhere (per world unit).
    Adam learning rates: ``lr_grid`` (density and colour), ``lr_background``.
    ``background_size`` = (rows, columns) of the lat-long background map; ``up_axis`` is the
    world axis of its pole (zenith). Empty-space skipping: from step ``occupancy_from_step``,
    every ``occupancy_every`` steps, a voxel is kept when one of its corners has an opacity
    1 − exp(−σ·δ_fine) above ``occupancy_alpha``, dilated by one voxel; samples in other
    voxels are skipped (σ = 0).
    """

    grid_sizes: tuple[int, ...] = (48, 96, 128)
    upsample_steps: tuple[int, ...] = (300, 1000)
    init_density: float = 0.1
    lr_grid: float = 0.1
    lr_background: float = 0.05
    background_size: tuple[int, int] = (64, 128)
    up_axis: int = 2
    occupancy_from_step: int = 100
    occupancy_every: int = 16
    occupancy_alpha: float = 1e-3

    def __post_init__(self) -> None:
        super().__post_init__()
        if not self.grid_sizes or min(self.grid_sizes) < 2:
            raise ValueError(f"grid_sizes must be non-empty, each >= 2, got {self.grid_sizes}")
        if len(self.upsample_steps) != len(self.grid_sizes) - 1:
            raise ValueError(
                f"upsample_steps needs len(grid_sizes) - 1 = {len(self.grid_sizes) - 1} entries, "
                f"got {self.upsample_steps}"
            )
        if list(self.upsample_steps) != sorted(self.upsample_steps) or (
            self.upsample_steps and self.upsample_steps[0] < 1
        ):
            raise ValueError(f"upsample_steps must be increasing and >= 1: {self.upsample_steps}")
        if not self.init_density > 0:
            raise ValueError(f"init_density must be > 0, got {self.init_density}")
        check_background_and_schedule(self.background_size, self.up_axis, "occupancy",
                                      self.occupancy_from_step, self.occupancy_every,
                                      self.occupancy_alpha)

    def stage(self, step: int) -> int:
        """Index into ``grid_sizes`` of the resolution used at training step ``step``."""
        return sum(1 for s in self.upsample_steps if step >= s)

    def build(self, aabb: np.ndarray) -> DenseGridField:
        return DenseGridField(self, aabb)


def _dilate_cells(vertices: torch.Tensor, axis: int) -> torch.Tensor:
    """Along ``axis``: n vertex flags → n − 1 cell flags, cell c = any(vertices c−1 … c+2)."""
    n = vertices.shape[axis]
    if n <= 3:
        any_ = vertices.any(dim=axis, keepdim=True)
        return torch.cat([any_] * (n - 1), dim=axis)
    inner = vertices.narrow(axis, 0, n - 3)
    for i in range(1, 4):
        inner = inner | vertices.narrow(axis, i, n - 3)
    first = vertices.narrow(axis, 0, 3).any(dim=axis, keepdim=True)
    last = vertices.narrow(axis, n - 3, 3).any(dim=axis, keepdim=True)
    return torch.cat([first, inner, last], dim=axis)


class DenseGridField(Field):
    """Density + RGB on a dense grid inside the box, lat-long background outside."""

    def __init__(self, cfg: GridConfig, aabb: np.ndarray) -> None:
        super().__init__()
        self.cfg = cfg
        box = torch.as_tensor(np.asarray(aabb, dtype=np.float64), dtype=torch.float32)
        self.register_buffer("aabb", box)
        self._stage = 0
        self.shape = grid_shape(np.asarray(aabb), cfg.grid_sizes[0])
        raw_density = math.log(math.expm1(cfg.init_density))
        table = torch.zeros(math.prod(self.shape), 4)
        table[:, 0] = raw_density
        self.grid = nn.Parameter(table)  # (vertices, 4): raw density, raw RGB
        rows, cols = cfg.background_size
        self.env = nn.Parameter(torch.zeros(rows, cols, 3))
        fine_step = cfg.ray_step(np.asarray(aabb), cfg.fine_from_step)
        sigma_min = -math.log1p(-cfg.occupancy_alpha) / fine_step
        self._raw_density_min = math.log(math.expm1(sigma_min))
        self._occupancy: torch.Tensor | None = None  # (cells,) bool, None: skip nothing

    # --- the Field interface -------------------------------------------------------------
    def query(self, points: torch.Tensor, dirs: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        coords = vertex_coords(points, self.aabb, self.shape)
        raw = interpolate(self.grid, self.shape, coords, sparse=True)
        return F.softplus(raw[:, 0]), torch.sigmoid(raw[:, 1:])

    def background(self, dirs: torch.Tensor) -> torch.Tensor:
        return latlong_background(self.env, dirs, self.cfg.up_axis)

    def param_groups(self) -> list[dict[str, Any]]:
        return [
            {"params": [self.grid], "lr": self.cfg.lr_grid},
            {"params": [self.env], "lr": self.cfg.lr_background},
        ]

    def occupied(self, points: torch.Tensor) -> torch.Tensor | None:
        if self._occupancy is None:
            return None
        cells = [n - 1 for n in self.shape]
        index = cell_index(vertex_coords(points, self.aabb, self.shape), cells)
        return self._occupancy.index_select(0, index)

    def on_step(self, step: int) -> bool:
        stage = self.cfg.stage(step)
        resized = stage != self._stage
        if resized:
            self.resize(self.cfg.grid_sizes[stage])
            self._stage = stage
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
        dense = (self.grid[:, 0] > self._raw_density_min).view(*self.shape)
        for axis in range(3):
            dense = _dilate_cells(dense, axis)
        self._occupancy = dense.reshape(-1)

    # --- coarse to fine -------------------------------------------------------------------
    def resize(self, size: int) -> None:
        """Resample the grid trilinearly to ``size`` vertices along the longest side."""
        new_shape = grid_shape(self.aabb.cpu().numpy(), size)
        with torch.no_grad():
            self.grid = nn.Parameter(resample(self.grid, self.shape, new_shape))
        self.shape = new_shape
