"""``ngp``: a multiresolution hash encoding and a tiny MLP (Instant-NGP, Müller et al. 2022).

A point's feature vector is the shared hash encoding
(:class:`aoi3d.field.encodings.HashEncoding`, ``"packed"`` layout: each level's vertex grid
covers the box, coarse levels stored densely, finer ones hashed, levels back to back in one
table) of ``n_levels`` resolutions growing geometrically from ``base_resolution`` to
``max_resolution`` cells along the longest box side. A tiny MLP maps the features to a raw
density and geometry features, σ = softplus(raw + shift) (the shift makes the initial
density ``init_density``), and a second one maps those (and, when ``view_dependent``, an SH
encoding of the ray direction) to the colour. Empty space is skipped with an occupancy grid:
every ``occupancy_every`` steps a random part of its cells is probed at a random point each,
every cell's density estimate decays by ``occupancy_decay`` and takes the maximum with its
new probe (Instant-NGP's EMA), and a cell is kept while its estimate gives an opacity above
``occupancy_alpha`` at the fine ray step. The trainer's opacity loss clears the initial fog,
so skipping starts to pay within a few dozen steps. Rays that leave the box see the lat-long
background shared with ``grid``.

The table lookup is ``encodings.row_gather`` (``embedding_bag`` forward, ``index_add_``
backward for 4 features). Its gradient is dense by default: with 8 levels × 2^16 rows most
hashed rows are touched by every batch, and the row-sparse gradient + ``LazyAdam``
(``sparse_grad=True``, the ``grid`` backend's trick) measured slower here (315 against 365
steps in 30 CPU-seconds, 1 thread). The CPU cost is the 8 × ``n_levels`` rows per sample,
hence the defaults: 512 rays a step, 32 then 128 samples per box diagonal, occupancy from
step 30 (each measured better on the turbine at 5–30 s than 1024 rays, 64/160 samples, step
100).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

import numpy as np
import torch
import torch.nn.functional as F
from torch import nn

from aoi3d.field.base import (
    Field,
    FieldConfig,
    check_at_least,
    check_positive,
    check_schedule,
    seeded,
)
from aoi3d.field.encodings import HashEncoding, cell_index, spherical_harmonics

__all__ = ["NgpConfig", "NgpField"]

@dataclass(frozen=True)
class NgpConfig(FieldConfig):
    """The hash-grid backend.

    Encoding: ``n_levels`` levels of ``features`` features each, a table of
    2^``log2_table_size`` rows per hashed level, resolutions from ``base_resolution`` to
    ``max_resolution`` cells along the longest box side; table entries start uniform in
    ±``init_scale``; ``sparse_grad`` makes the table's gradient row-sparse (for
    ``LazyAdam``). MLPs: ``hidden`` units, one hidden layer each; ``geo_features`` features
    pass from the density MLP to the colour MLP, which also sees a degree-2 SH encoding of
    the ray direction when ``view_dependent`` (no gain measured: the scene is Lambertian);
    without ``colour_mlp`` the density MLP outputs the colour itself. ``init_seed`` seeds the
    initial weights. ``init_density``: σ everywhere at the start. Adam learning rates:
    ``lr_table``, ``lr_mlp`` (the background's is inherited). Occupancy grid: cubic cells,
    ``occupancy_size`` along the longest side, first built at step ``occupancy_from_step``
    (all cells probed), then every ``occupancy_every`` steps a random ``occupancy_fraction``
    of them; threshold ``occupancy_alpha`` on 1 − exp(−σ·δ_fine).
    """

    batch_rays: int = 512
    samples_coarse: int = 32
    samples_fine: int = 128
    n_levels: int = 8
    features: int = 4
    log2_table_size: int = 16
    base_resolution: int = 16
    max_resolution: int = 256
    init_scale: float = 1e-4
    sparse_grad: bool = False
    hidden: int = 64
    geo_features: int = 15
    colour_mlp: bool = True
    view_dependent: bool = False
    init_seed: int = 0
    init_density: float = 0.1
    lr_table: float = 0.05
    lr_mlp: float = 0.001
    occupancy_size: int = 64
    occupancy_from_step: int = 30
    occupancy_every: int = 16
    occupancy_fraction: float = 0.25
    occupancy_decay: float = 0.95
    occupancy_alpha: float = 1e-3

    def __post_init__(self) -> None:
        super().__post_init__()
        check_at_least(self, 1, ("n_levels", "features", "hidden", "geo_features",
                                 "occupancy_size"))
        check_positive(self, ("init_scale", "init_density", "lr_table", "lr_mlp"))
        if not 4 <= self.log2_table_size <= 30:
            raise ValueError(f"log2_table_size must be in [4, 30], got {self.log2_table_size}")
        if not 2 <= self.base_resolution <= self.max_resolution:
            raise ValueError(
                "need 2 <= base_resolution <= max_resolution, got "
                f"{self.base_resolution}, {self.max_resolution}"
            )
        if self.view_dependent and not self.colour_mlp:
            raise ValueError("view_dependent needs the colour MLP (colour_mlp=True)")
        if not 0 < self.occupancy_fraction <= 1 or not 0 <= self.occupancy_decay <= 1:
            raise ValueError(
                "occupancy_fraction must be in (0, 1] and occupancy_decay in [0, 1], got "
                f"{self.occupancy_fraction}, {self.occupancy_decay}"
            )
        check_schedule("occupancy", self.occupancy_from_step, self.occupancy_every,
                       self.occupancy_alpha)

    def build(self, aabb: np.ndarray) -> NgpField:
        return NgpField(self, aabb)


# --- the field --------------------------------------------------------------------------------
class NgpField(Field):
    """Hash encoding + tiny MLPs inside the box, occupancy grid, lat-long background."""

    cfg: NgpConfig
    cell_size: torch.Tensor  # buffers: the occupancy cells' edge (3,), their density estimate
    density_estimate: torch.Tensor

    def __init__(self, cfg: NgpConfig, aabb: np.ndarray) -> None:
        super().__init__()
        box = self._setup(cfg, aabb)
        with seeded(cfg.init_seed):  # initial weights from ``init_seed`` only
            self.encoding = HashEncoding(
                box,
                cfg.n_levels,
                cfg.features,
                cfg.log2_table_size,
                cfg.base_resolution,
                cfg.max_resolution,
                init_scale=cfg.init_scale,
                sparse_grad=cfg.sparse_grad,
            )
            outputs = 1 + (cfg.geo_features if cfg.colour_mlp else 3)
            self.density_mlp = nn.Sequential(
                nn.Linear(self.encoding.out_features, cfg.hidden),
                nn.ReLU(),
                nn.Linear(cfg.hidden, outputs),
            )
            colour_in = cfg.geo_features + (9 if cfg.view_dependent else 0)
            self.colour_mlp = (
                nn.Sequential(nn.Linear(colour_in, cfg.hidden), nn.ReLU(), nn.Linear(cfg.hidden, 3))
                if cfg.colour_mlp
                else None
            )
        self.density_shift = math.log(math.expm1(cfg.init_density))
        # The occupancy grid: cubic cells, a density estimate per cell.
        extent = box[1] - box[0]
        cell = float(extent.max()) / cfg.occupancy_size
        self.occupancy_shape = tuple(max(1, math.ceil(float(e) / cell - 1e-9)) for e in extent)
        self.register_buffer("cell_size", torch.full((3,), cell, dtype=torch.float32))
        self.register_buffer("density_estimate", torch.zeros(math.prod(self.occupancy_shape)))
        self.sigma_min = cfg.density_threshold(box, cfg.occupancy_alpha)
        self._occupancy: torch.Tensor | None = None  # (cells,) bool; None: skip nothing
        self._probe_generator: torch.Generator | None = None

    # --- the Field interface -------------------------------------------------------------
    def density(self, points: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """σ (P,) and the geometry features (P, geo_features) at ``points``."""
        out = self.density_mlp(self.encoding(points))
        return F.softplus(out[:, 0] + self.density_shift), out[:, 1:]

    def query(self, points: torch.Tensor, dirs: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        sigma, geo = self.density(points)
        if self.colour_mlp is None:
            return sigma, torch.sigmoid(geo)
        if self.cfg.view_dependent:
            geo = torch.cat([geo, spherical_harmonics(dirs, 3)], dim=1)
        return sigma, torch.sigmoid(self.colour_mlp(geo))

    def param_groups(self) -> list[dict[str, Any]]:
        mlp = list(self.density_mlp.parameters())
        if self.colour_mlp is not None:
            mlp += list(self.colour_mlp.parameters())
        return [
            {"params": [self.encoding.table], "lr": self.cfg.lr_table},
            {"params": mlp, "lr": self.cfg.lr_mlp},
            self.background_group(),
        ]

    def occupied(self, points: torch.Tensor) -> torch.Tensor | None:
        if self._occupancy is None:
            return None
        return self._occupancy.index_select(0, self._cell_index(points))

    def on_step(self, step: int) -> bool:
        cfg = self.cfg
        if step < cfg.occupancy_from_step:
            self._occupancy = None
        elif self._occupancy is None:
            self.update_occupancy(fraction=1.0)
        elif (step - cfg.occupancy_from_step) % cfg.occupancy_every == 0:
            self.update_occupancy(cfg.occupancy_fraction)
        return False

    # --- the occupancy grid ---------------------------------------------------------------
    def _cell_index(self, points: torch.Tensor) -> torch.Tensor:
        return cell_index((points - self.aabb[0]) / self.cell_size, self.occupancy_shape)

    @property
    def occupancy(self) -> torch.Tensor | None:
        """Occupied cells (X, Y, Z) bool, None before the grid is first built."""
        if self._occupancy is None:
            return None
        return self._occupancy.view(self.occupancy_shape)

    @torch.no_grad()
    def update_occupancy(self, fraction: float = 1.0) -> None:
        """Probe a random ``fraction`` of the cells at a random point each, decay every cell's
        density estimate and keep the maximum with the probes; cells whose estimate gives an
        opacity above ``occupancy_alpha`` are occupied."""
        device = self.density_estimate.device
        if self._probe_generator is None or self._probe_generator.device != device:
            self._probe_generator = torch.Generator(device=device)
            self._probe_generator.manual_seed(0x6E6770)
        gen = self._probe_generator
        n_cells = self.density_estimate.shape[0]
        if fraction >= 1.0:
            cells = torch.arange(n_cells, device=device)
        else:
            count = max(1, round(fraction * n_cells))
            cells = torch.randint(n_cells, (count,), generator=gen, device=device)
        _, ny, nz = self.occupancy_shape
        ijk = torch.stack([cells // (ny * nz), cells // nz % ny, cells % nz], dim=1)
        jitter = torch.rand(cells.shape[0], 3, generator=gen, device=device)
        points = self.aabb[0] + (ijk.to(jitter.dtype) + jitter) * self.cell_size
        points = torch.minimum(points, self.aabb[1])
        sigma = torch.cat([self.density(p)[0] for p in points.split(65536)])
        estimate = self.density_estimate.mul_(self.cfg.occupancy_decay)
        estimate.scatter_reduce_(0, cells, sigma, reduce="amax")
        self._occupancy = estimate > self.sigma_min
