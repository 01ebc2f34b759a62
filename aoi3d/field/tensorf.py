"""``tensorf``: the VM (vector–matrix) decomposition of a feature grid (TensoRF, Chen et al. 2022).

The density and appearance grids are never stored: a point's raw density is
Σ_m Σ_r P^σ_{m,r}(u_m, v_m) · L^σ_{m,r}(w_m) over the three plane/line pairs
m ∈ {(xy, z), (xz, y), (yz, x)} and ``density_components`` components each, sampled
bilinearly (planes) and linearly (lines); the appearance features are the
``3 · app_components`` products P^c_{m,r} · L^c_{m,r}, decoded to colour by a linear basis
(or a tiny MLP when ``decoder_hidden`` > 0) and a sigmoid. The scene is Lambertian, so the
colour does not depend on the ray direction. Density is σ = softplus(raw + shift) — the shift
makes the initial density ``init_density`` (a prototype with TensoRF's exp activation
diverged to NaN at grid learning rates ≥ 0.1).

Planes and lines span the box with vertices on its faces and cubic voxels (``grid_shape``);
they start coarse and are resampled (bilinear / linear) to the next of ``grid_sizes`` at
``upsample_steps`` (``on_step`` returns True: the trainer rebuilds the optimizer, as TensoRF
resets its learning rates there). The alpha mask: from ``mask_from_step``, every
``mask_every`` steps, the density is evaluated at every vertex of the current grid (exactly,
by outer products of planes and lines), and a cell is kept when a vertex within one cell of
it has an opacity 1 − exp(−σ·δ_fine) above ``mask_alpha``; ``occupied`` skips the others.
Rays leaving the box see the shared lat-long background. Lookups use ``row_gather``
(``embedding_bag`` forward, ``index_add_`` backward; the planes are small, so their gradient
stays dense).

Defaults, measured on the turbine (18 views, 1 CPU thread): a linear basis with 8/16
components and grids from 48 vertices stalled near 23 dB for hundreds of steps with some
initial seeds (fog that fits the training views, not the novel one); 4/8 components, a
64-unit MLP decoder, grid lr 0.1, grids from 64 vertices and 32 samples per diagonal for the
first 300 steps reached 29.3–31.2 dB at 400 steps on every seed tried, at 30–50k rays/s.
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
from aoi3d.field.encodings import (
    cell_index,
    corner_rows,
    grid_shape,
    linear_corners,
    resample,
    row_gather,
    vertex_coords,
)

__all__ = ["VM_MODES", "TensorfConfig", "TensorfField"]

VM_MODES = ((0, 1, 2), (0, 2, 1), (1, 2, 0))
"""(plane axis u, plane axis v, line axis w) of each of the three VM pairs."""


@dataclass(frozen=True)
class TensorfConfig(FieldConfig):
    """The VM-decomposition backend.

    ``grid_sizes``: vertices along the longest box side at each coarse-to-fine stage (cubic
    voxels); stage k + 1 starts at training step ``upsample_steps[k]``.
    ``density_components`` / ``app_components``: components per plane/line pair (R_σ, R_c).
    ``decoder_hidden``: 0 decodes colour with a linear basis (3·R_c → 3), else a tiny MLP with
    that many hidden units. ``init_scale``: standard deviation of the initial components.
    ``init_density``: σ everywhere at the start. Adam learning rates: ``lr_grid`` (planes and
    lines), ``lr_decoder``, ``lr_background``. Background: lat-long map of
    ``background_size`` around ``up_axis``. Alpha mask: see the module docstring
    (``mask_from_step``, ``mask_every``, ``mask_alpha``). ``init_seed`` seeds the initial
    components and decoder.
    """

    batch_rays: int = 1024
    samples_coarse: int = 32
    samples_fine: int = 160
    grid_sizes: tuple[int, ...] = (64, 96, 128)
    upsample_steps: tuple[int, ...] = (300, 1000)
    density_components: int = 4
    app_components: int = 8
    decoder_hidden: int = 64
    init_scale: float = 0.1
    init_density: float = 0.1
    lr_grid: float = 0.1
    lr_decoder: float = 0.01
    lr_background: float = 0.05
    background_size: tuple[int, int] = (64, 128)
    up_axis: int = 2
    mask_from_step: int = 100
    mask_every: int = 16
    mask_alpha: float = 1e-3
    init_seed: int = 0

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
        for name in ("density_components", "app_components"):
            if getattr(self, name) < 1:
                raise ValueError(f"{name} must be >= 1, got {getattr(self, name)}")
        if self.decoder_hidden < 0:
            raise ValueError(f"decoder_hidden must be >= 0, got {self.decoder_hidden}")
        for name in ("init_scale", "init_density", "lr_grid", "lr_decoder", "lr_background"):
            if not getattr(self, name) > 0:
                raise ValueError(f"{name} must be > 0, got {getattr(self, name)}")
        check_background_and_schedule(self.background_size, self.up_axis, "mask",
                                      self.mask_from_step, self.mask_every, self.mask_alpha)

    def stage(self, step: int) -> int:
        """Index into ``grid_sizes`` of the resolution used at training step ``step``."""
        return sum(1 for s in self.upsample_steps if step >= s)

    def build(self, aabb: np.ndarray) -> TensorfField:
        return TensorfField(self, aabb)


class TensorfField(Field):
    """Three plane/line pairs for density and appearance, a colour decoder, an alpha mask."""

    def __init__(self, cfg: TensorfConfig, aabb: np.ndarray) -> None:
        super().__init__()
        self.cfg = cfg
        box = np.asarray(aabb, dtype=np.float64)
        self.register_buffer("aabb", torch.tensor(box, dtype=torch.float32))
        self._stage = 0
        self.shape = grid_shape(box, cfg.grid_sizes[0])
        channels = cfg.density_components + cfg.app_components
        with torch.random.fork_rng(devices=[]):  # initial values from ``init_seed`` only
            torch.manual_seed(cfg.init_seed)
            self.planes = nn.ParameterList(
                nn.Parameter(cfg.init_scale * torch.randn(self.shape[u] * self.shape[v], channels))
                for u, v, _ in VM_MODES
            )
            self.lines = nn.ParameterList(
                nn.Parameter(cfg.init_scale * torch.randn(self.shape[w], channels))
                for _, _, w in VM_MODES
            )
            features = 3 * cfg.app_components
            if cfg.decoder_hidden:
                self.decoder: nn.Module = nn.Sequential(
                    nn.Linear(features, cfg.decoder_hidden),
                    nn.ReLU(),
                    nn.Linear(cfg.decoder_hidden, 3),
                )
            else:
                self.decoder = nn.Linear(features, 3)
        self.density_shift = math.log(math.expm1(cfg.init_density))
        rows, cols = cfg.background_size
        self.env = nn.Parameter(torch.zeros(rows, cols, 3))
        fine_step = cfg.ray_step(box, cfg.fine_from_step)
        self.sigma_min = -math.log1p(-cfg.mask_alpha) / fine_step
        self._mask: torch.Tensor | None = None  # (cells,) bool; None: skip nothing

    # --- the Field interface -------------------------------------------------------------
    def _features(self, points: torch.Tensor) -> list[torch.Tensor]:
        """Plane × line products of each VM pair at ``points``: three (P, R_σ + R_c)."""
        coords = vertex_coords(points, self.aabb, self.shape)
        axes = [linear_corners(coords[:, a], n) for a, n in enumerate(self.shape)]
        out = []
        shape = self.shape
        for m, (u, v, w) in enumerate(VM_MODES):
            plane_rows = corner_rows([axes[u], axes[v]], (shape[u], shape[v]))
            plane = row_gather(self.planes[m], *plane_rows)
            line = row_gather(self.lines[m], *corner_rows([axes[w]], (shape[w],)))
            out.append(plane * line)
        return out

    def density(self, points: torch.Tensor) -> torch.Tensor:
        """σ (P,) at ``points``."""
        return self.query(points, points)[0]

    def query(self, points: torch.Tensor, dirs: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        parts = self._features(points)
        rd = self.cfg.density_components
        raw = (parts[0][:, :rd] + parts[1][:, :rd] + parts[2][:, :rd]).sum(dim=1)
        app = torch.cat([p[:, rd:] for p in parts], dim=1)
        return F.softplus(raw + self.density_shift), torch.sigmoid(self.decoder(app))

    def background(self, dirs: torch.Tensor) -> torch.Tensor:
        return latlong_background(self.env, dirs, self.cfg.up_axis)

    def param_groups(self) -> list[dict[str, Any]]:
        return [
            {"params": [*self.planes, *self.lines], "lr": self.cfg.lr_grid},
            {"params": list(self.decoder.parameters()), "lr": self.cfg.lr_decoder},
            {"params": [self.env], "lr": self.cfg.lr_background},
        ]

    def occupied(self, points: torch.Tensor) -> torch.Tensor | None:
        if self._mask is None:
            return None
        cells = [n - 1 for n in self.shape]
        index = cell_index(vertex_coords(points, self.aabb, self.shape), cells)
        return self._mask.index_select(0, index)

    def on_step(self, step: int) -> bool:
        cfg = self.cfg
        stage = cfg.stage(step)
        resized = stage != self._stage
        if resized:
            self.upsample(cfg.grid_sizes[stage])
            self._stage = stage
        if step < cfg.mask_from_step:
            self._mask = None
        elif self._mask is None or (
            not resized and (step - cfg.mask_from_step) % cfg.mask_every == 0
        ):  # (``upsample`` rebuilt an existing mask)
            self.update_alpha_mask()
        return resized

    # --- the alpha mask -------------------------------------------------------------------
    @torch.no_grad()
    def vertex_density(self) -> torch.Tensor:
        """σ at every vertex of the current grid (X, Y, Z), from outer products of the
        density components of planes and lines."""
        rd = self.cfg.density_components
        raw = torch.zeros(self.shape, device=self.env.device)
        for m, (u, v, w) in enumerate(VM_MODES):
            plane = self.planes[m][:, :rd].view(self.shape[u], self.shape[v], rd)
            term = torch.einsum("uvr,wr->uvw", plane, self.lines[m][:, :rd])
            order = [0, 0, 0]
            order[u], order[v], order[w] = 0, 1, 2
            raw += term.permute(*order)
        return F.softplus(raw + self.density_shift)

    @torch.no_grad()
    def update_alpha_mask(self) -> None:
        """Keep the cells with a vertex within one cell above the opacity threshold."""
        dense = (self.vertex_density() > self.sigma_min).float()[None, None]
        cells = F.max_pool3d(dense, 2, stride=1)
        cells = F.max_pool3d(cells, 3, stride=1, padding=1)
        self._mask = cells.reshape(-1) > 0

    @property
    def alpha_mask(self) -> torch.Tensor | None:
        """Kept cells (X−1, Y−1, Z−1) bool, None before the mask is first built."""
        if self._mask is None:
            return None
        nx, ny, nz = self.shape
        return self._mask.view(nx - 1, ny - 1, nz - 1)

    # --- coarse to fine -------------------------------------------------------------------
    @torch.no_grad()
    def upsample(self, size: int) -> None:
        """Resample planes (bilinear) and lines (linear) to ``size`` vertices along the
        longest side (the function is kept up to interpolation) and rebuild the alpha mask
        on the new cells."""
        new_shape = grid_shape(self.aabb.cpu().numpy(), size)
        old = self.shape
        self.planes = nn.ParameterList(
            nn.Parameter(resample(p, (old[u], old[v]), (new_shape[u], new_shape[v])))
            for p, (u, v, _) in zip(self.planes, VM_MODES, strict=True)
        )
        self.lines = nn.ParameterList(
            nn.Parameter(resample(line, (old[w],), (new_shape[w],)))
            for line, (_, _, w) in zip(self.lines, VM_MODES, strict=True)
        )
        self.shape = new_shape
        if self._mask is not None:  # the mask follows the grid's cells
            self.update_alpha_mask()
