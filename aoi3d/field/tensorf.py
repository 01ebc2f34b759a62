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

from aoi3d.field.base import (
    CoarseToFineConfig,
    CoarseToFineField,
    check_at_least,
    check_positive,
    check_schedule,
    seeded,
)
from aoi3d.field.encodings import (
    cells_near,
    corner_rows,
    grid_shape,
    linear_corners,
    resample,
    row_gather,
)

__all__ = ["VM_MODES", "TensorfConfig", "TensorfField"]

VM_MODES = ((0, 1, 2), (0, 2, 1), (1, 2, 0))
"""(plane axis u, plane axis v, line axis w) of each of the three VM pairs."""


@dataclass(frozen=True)
class TensorfConfig(CoarseToFineConfig):
    """The VM-decomposition backend.

    Coarse to fine: ``grid_sizes`` at ``upsample_steps`` (:class:`CoarseToFineConfig`).
    ``density_components`` / ``app_components``: components per plane/line pair (R_σ, R_c).
    ``decoder_hidden``: 0 decodes colour with a linear basis (3·R_c → 3), else a tiny MLP with
    that many hidden units. ``init_scale``: standard deviation of the initial components.
    ``init_density``: σ everywhere at the start. Adam learning rates: ``lr_grid`` (planes and
    lines), ``lr_decoder`` (the background's is inherited). Alpha mask: see the module docstring
    (``mask_from_step``, ``mask_every``, ``mask_alpha``). ``init_seed`` seeds the initial
    components and decoder.
    """

    batch_rays: int = 1024
    samples_coarse: int = 32
    samples_fine: int = 160
    grid_sizes: tuple[int, ...] = (64, 96, 128)
    density_components: int = 4
    app_components: int = 8
    decoder_hidden: int = 64
    init_scale: float = 0.1
    init_density: float = 0.1
    lr_grid: float = 0.1
    lr_decoder: float = 0.01
    mask_from_step: int = 100
    mask_every: int = 16
    mask_alpha: float = 1e-3
    init_seed: int = 0

    def __post_init__(self) -> None:
        super().__post_init__()
        check_at_least(self, 1, ("density_components", "app_components"))
        check_at_least(self, 0, ("decoder_hidden",))
        check_positive(self, ("init_scale", "init_density", "lr_grid", "lr_decoder"))
        check_schedule("mask", self.mask_from_step, self.mask_every, self.mask_alpha)

    def build(self, aabb: np.ndarray) -> TensorfField:
        return TensorfField(self, aabb)


class TensorfField(CoarseToFineField):
    """Three plane/line pairs for density and appearance, a colour decoder, an alpha mask."""

    cfg: TensorfConfig

    def __init__(self, cfg: TensorfConfig, aabb: np.ndarray) -> None:
        super().__init__()
        box = self._setup(cfg, aabb)
        channels = cfg.density_components + cfg.app_components
        with seeded(cfg.init_seed):  # initial values from ``init_seed`` only
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
        self.sigma_min = cfg.density_threshold(box, cfg.mask_alpha)
        self._mask: torch.Tensor | None = None  # (cells,) bool; None: skip nothing

    # --- the Field interface -------------------------------------------------------------
    def _features(self, points: torch.Tensor) -> list[torch.Tensor]:
        """Plane × line products of each VM pair at ``points``: three (P, R_σ + R_c)."""
        coords = self._coords(points)
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

    def param_groups(self) -> list[dict[str, Any]]:
        return [
            {"params": [*self.planes, *self.lines], "lr": self.cfg.lr_grid},
            {"params": list(self.decoder.parameters()), "lr": self.cfg.lr_decoder},
            self.background_group(),
        ]

    def occupied(self, points: torch.Tensor) -> torch.Tensor | None:
        return self._at_cells(self._mask, points)

    def on_step(self, step: int) -> bool:
        cfg = self.cfg
        resized = self._advance(step)
        if step < cfg.mask_from_step:
            self._mask = None
        elif self._mask is None or (
            not resized and (step - cfg.mask_from_step) % cfg.mask_every == 0
        ):  # (``resize`` rebuilt an existing mask)
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
        self._mask = cells_near(self.vertex_density() > self.sigma_min).reshape(-1)

    @property
    def alpha_mask(self) -> torch.Tensor | None:
        """Kept cells (X−1, Y−1, Z−1) bool, None before the mask is first built."""
        if self._mask is None:
            return None
        nx, ny, nz = self.shape
        return self._mask.view(nx - 1, ny - 1, nz - 1)

    # --- coarse to fine -------------------------------------------------------------------
    @torch.no_grad()
    def resize(self, size: int) -> None:
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
