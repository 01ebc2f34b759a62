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

The trilinear interpolation is a hand-written gather whose backward scatters with
``index_add_`` into a row-sparse gradient. Measured with torch 2.13 on 2 CPU cores, 200k
samples on a 128×128×89 grid, forward + backward: 78 / 58 ms on 1 / 2 threads against
62 / 67 ms for ``grid_sample`` — on par; what pays is the sparse gradient: ``LazyAdam`` then
updates only the rows a batch reached, where a dense Adam step over that grid costs
29 / 18 ms.
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

__all__ = ["DenseGridField", "GridConfig", "grid_shape", "trilinear"]


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


def grid_shape(aabb: np.ndarray, size: int) -> tuple[int, int, int]:
    """Vertices per axis: ``size`` along the longest side, cubic voxels, at least 2 per axis."""
    extent = np.asarray(aabb[1], dtype=np.float64) - np.asarray(aabb[0], dtype=np.float64)
    voxel = float(extent.max()) / (size - 1)
    return tuple(max(2, round(float(e) / voxel) + 1) for e in extent)  # type: ignore[return-value]


class _Gather(torch.autograd.Function):
    """out[p] = Σ_k w[p, k] · table[idx[p, k]].

    The backward returns a row-sparse COO gradient: the rows the batch touched, each summed
    with ``index_add_`` into a compact buffer (cache-friendly, and ``LazyAdam`` then updates
    only those rows).
    """

    @staticmethod
    def forward(ctx: Any, table: torch.Tensor, idx: torch.Tensor, w: torch.Tensor) -> torch.Tensor:
        ctx.save_for_backward(idx, w)
        ctx.n_rows = table.shape[0]
        rows = table.index_select(0, idx.reshape(-1)).view(*idx.shape, table.shape[1])
        return torch.bmm(w[:, None, :], rows).squeeze(1)

    @staticmethod
    def backward(ctx: Any, grad_out: torch.Tensor) -> tuple[torch.Tensor, None, None]:
        idx, w = ctx.saved_tensors
        n_rows, channels = ctx.n_rows, grad_out.shape[1]
        flat = idx.reshape(-1)
        touched = torch.zeros(n_rows, dtype=torch.bool, device=flat.device)
        touched[flat] = True
        rows = touched.nonzero().squeeze(1)  # sorted, unique
        position = torch.empty(n_rows, dtype=torch.long, device=flat.device)
        position[rows] = torch.arange(rows.shape[0], device=flat.device)
        contrib = (w[..., None] * grad_out[:, None, :]).reshape(-1, channels)
        values = grad_out.new_zeros(rows.shape[0], channels).index_add_(0, position[flat], contrib)
        grad = torch.sparse_coo_tensor(
            rows[None], values, (n_rows, channels), is_coalesced=True, check_invariants=False
        )
        return grad, None, None


def trilinear(
    table: torch.Tensor, shape: tuple[int, int, int], coords: torch.Tensor
) -> torch.Tensor:
    """Trilinear interpolation of a grid stored flat, channels last.

    ``table`` (X·Y·Z, C), vertex (i, j, k) at row (i·Y + j)·Z + k; ``coords`` (P, 3) in vertex
    units, clamped to the grid. Returns (P, C), differentiable with respect to ``table``.
    """
    nx, ny, nz = shape
    hi = torch.tensor([nx - 1, ny - 1, nz - 1], device=coords.device, dtype=coords.dtype)
    c = torch.minimum(coords.clamp_min(0.0), hi)
    base = torch.minimum(c.floor(), hi - 1)
    f = c - base
    b = base.long()
    row = (b[:, 0] * ny + b[:, 1]) * nz + b[:, 2]
    offsets = torch.tensor(
        [0, 1, nz, nz + 1, ny * nz, ny * nz + 1, ny * nz + nz, ny * nz + nz + 1],
        device=coords.device,
    )
    idx = row[:, None] + offsets[None, :]
    g = 1.0 - f
    wx = torch.stack([g[:, 0], f[:, 0]], dim=1)
    wy = torch.stack([g[:, 1], f[:, 1]], dim=1)
    wz = torch.stack([g[:, 2], f[:, 2]], dim=1)
    w = (wx[:, :, None, None] * wy[:, None, :, None] * wz[:, None, None, :]).reshape(-1, 8)
    return _Gather.apply(table, idx, w)


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
    def _coords(self, points: torch.Tensor) -> torch.Tensor:
        """World points → vertex units (0 … n−1 along each axis)."""
        scale = torch.tensor([n - 1 for n in self.shape], device=points.device, dtype=points.dtype)
        return (points - self.aabb[0]) * (scale / (self.aabb[1] - self.aabb[0]))

    def query(self, points: torch.Tensor, dirs: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        raw = trilinear(self.grid, self.shape, self._coords(points))
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
        nx, ny, nz = self.shape
        cells = torch.tensor([nx - 2, ny - 2, nz - 2], device=points.device)
        c = torch.minimum(self._coords(points).floor().long().clamp_min(0), cells)
        index = (c[:, 0] * (ny - 1) + c[:, 1]) * (nz - 1) + c[:, 2]
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
            c = self.grid.shape[1]
            vol = self.grid.detach().T.reshape(1, c, *self.shape)
            vol = F.interpolate(vol, size=new_shape, mode="trilinear", align_corners=True)
            self.grid = nn.Parameter(vol.reshape(c, -1).T.contiguous())
        self.shape = new_shape
