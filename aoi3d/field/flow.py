"""``flow``: a time-aware (4-D) field — the dense grid at one reference time, carried to any
other time by a learned velocity field (issue 41).

Every other backend is static: a decision's frames carry different ages and the field
averages them, so a stale frame is wrong where the scene moved. Here a frame is information
about its own time. The field stands for the scene at a reference time t_ref (the decision's
time); the scene a ms earlier is the grid G (the ``grid`` backend's table, see
:mod:`aoi3d.field.grid`) read where the flow carries each point by then:

    S(x, a) = G(x + (a − p)·v(x)),

a first-order backward warp by a *steady* velocity field v (m/s): a coarse vertex grid of
``flow_size`` vertices along the longest box side, interpolated trilinearly, zero at the start
(so the untrained field is the static grid). Each training ray is read at its image's age a
(``TrainView.age_ms``, the AoI at the decision: ``RayBundle.age_ms``); a novel view at the
decision's time is a = 0, and at any other time t it is a = t_ref − t — the
display time t_ref + L is a = −L, a time no frame shows (:meth:`FieldTrainer.render`'s
``ahead_ms``). Ages are clipped to ±``flow_max_ms``. G itself stands for the age p, the
*pivot*: the mean age of the views the model first trains on (``FieldTrainer.set_views``
sets it before the first step), so that ages enter as differences from their mean.

v is learned with the grid, from how the frames of different ages disagree: a sample of an
image of age a reads G at x + (a − p)·v(x), so the loss moves v along G's spatial gradient,
times a − p.
Frames of one age say nothing about v (a·v is then an offset the grid absorbs); old frames
are what teaches it. Measured from the pivot, the ages cannot make v a shortcut that pulls
every old frame's samples towards density. A rotor at constant speed has v(x) = ω × (x − c),
linear in x, which trilinear interpolation represents exactly at any resolution; a
smoothness prior (``flow_smooth`` × the squared second differences of v, free for a linear
field) carries v into space no frame constrains — between the blades, where a blade will be.

Carrying the model to a later decision (the ``stream`` carry, :mod:`aoi3d.field.carry`):
:meth:`FlowField.advance` moves the reference time by dt, resampling the grid along the flow,
G'(x) = G(x − dt·v(x)) (semi-Lagrangian), and its Adam moments with it; v is kept.

Empty-space skipping tests the grid's occupancy at the warped points. On the CPU the step is
fused (:mod:`aoi3d.field.native_flow`: the sampler, the grid's query at the warped points, the
volume rendering, background and colour loss of the grid's fused step, then the velocity
grid's interpolation, the spatial gradient and its scatter); the torch code here is the
reference (the same gradients: a test) and the fallback.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Sequence
from dataclasses import dataclass, replace
from typing import TYPE_CHECKING, Any

import numpy as np
import torch
import torch.nn.functional as F
from torch import nn

from aoi3d.field import native_flow
from aoi3d.field.encodings import (
    corner_rows,
    grid_shape,
    linear_corners,
    row_gather,
    vertex_coords,
)
from aoi3d.field.grid import DenseGridField, GridConfig
from aoi3d.field.rays import RayBundle, RaySamples, sample_uniform
from aoi3d.field.render import RenderOptions, RenderResult, volume_render

if TYPE_CHECKING:
    from aoi3d.field.optim import LazyAdam

__all__ = ["FlowConfig", "FlowField", "trilinear"]


def trilinear(table: torch.Tensor, shape: Sequence[int], coords: torch.Tensor,
              sparse: bool = False) -> torch.Tensor:
    """The trilinear interpolation of a vertex grid stored flat (``table`` (Π shape, C),
    row-major) at ``coords`` (P, 3) in vertex units, differentiable with respect to the table
    (row-sparse gradient when ``sparse``) *and* to ``coords`` (the spatial derivative, zero
    where a coordinate is clamped to the grid)."""
    axes = [linear_corners(coords[:, d], n) for d, n in enumerate(shape)]
    idx, w = corner_rows(axes, shape)
    value = row_gather(table, idx, w.detach(), sparse)
    if not (coords.requires_grad and torch.is_grad_enabled()):
        return value
    rows = table.detach().index_select(0, idx.reshape(-1).long()).view(*idx.shape, -1)
    moving = (rows * w[..., None]).sum(0)  # the same value, differentiable in the weights only
    return value + (moving - moving.detach())


@dataclass(frozen=True)
class FlowConfig(GridConfig):
    """The time-aware grid: :class:`GridConfig`'s grid at the reference time, plus a velocity
    grid of ``flow_size`` vertices along the longest side (m/s, three columns and one unused:
    the kernels' four-float row), learned at ``lr_flow`` with the smoothness weight
    ``flow_smooth``; ages clipped to ±``flow_max_ms``. The timeliness embedding
    (``age_features``) is the other way to take the age: not both."""

    flow_size: int = 16
    lr_flow: float = 0.02
    flow_max_ms: float = 500.0
    flow_smooth: float = 0.01

    def __post_init__(self) -> None:
        super().__post_init__()
        n = self.flow_size
        if isinstance(n, bool) or not isinstance(n, int) or n < 2:
            raise ValueError(f"flow_size must be an int >= 2, got {n!r}")
        if not (math.isfinite(self.flow_smooth) and self.flow_smooth >= 0):
            raise ValueError(f"flow_smooth must be a finite number >= 0, got {self.flow_smooth}")
        for name in ("lr_flow", "flow_max_ms"):
            value = getattr(self, name)
            if isinstance(value, bool) or not isinstance(value, int | float) or not (
                    math.isfinite(value) and value > 0):
                raise ValueError(f"{name} must be a finite number > 0, got {value!r}")
        if self.age_features:
            raise ValueError("the flow field takes the age through its velocity field: "
                             f"age_features must be 0, got {self.age_features}")

    @property
    def takes_age(self) -> bool:
        """Every training ray is read at its image's age."""
        return True

    @property
    def time_aware(self) -> bool:
        return True

    def build(self, aabb: np.ndarray) -> FlowField:
        return FlowField(self, aabb)


class FlowField(DenseGridField):
    """The grid at the reference time and the velocity field that carries it (module doc)."""

    cfg: FlowConfig

    def __init__(self, cfg: FlowConfig, aabb: np.ndarray) -> None:
        super().__init__(cfg, aabb)
        self.flow_shape = grid_shape(np.asarray(aabb, dtype=np.float64), cfg.flow_size)
        self.flow = nn.Parameter(torch.zeros(math.prod(self.flow_shape), 4))
        self.pivot_ms = 0.0  # the grid stands for the scene pivot_ms before the reference time

    def set_pivot(self, pivot_ms: float) -> None:
        """The age the grid stands for (set before training: the mean age of the first
        views, so that v is taught by how frames differ in age, not by how old they are)."""
        if not math.isfinite(pivot_ms):
            raise ValueError(f"pivot_ms must be finite, got {pivot_ms}")
        self.pivot_ms = float(pivot_ms)

    # --- the flow ---------------------------------------------------------------------------
    def velocity(self, points: torch.Tensor) -> torch.Tensor:
        """v (P, 3), m/s, at world ``points`` (P, 3); differentiable in the velocity grid
        where gradients are on (else the fused kernel where it runs)."""
        if not (torch.is_grad_enabled() and self.flow.requires_grad):
            fused = native_flow.trilinear4(self.flow, points, self.aabb, self.flow_shape)
            if fused is not None:
                return fused[:, :3]
        coords = vertex_coords(points, self.aabb, self.flow_shape)
        return trilinear(self.flow, self.flow_shape, coords)[:, :3]

    def smoothness(self) -> torch.Tensor:
        """``flow_smooth`` × the mean squared second difference of the velocity grid along each
        axis: free for a linear field (a rigid rotation), it carries the velocity the frames
        teach into the space they say nothing about (between a rotor's blades: where a blade
        will be)."""
        v = self.flow[:, :3].view(*self.flow_shape, 3)
        total = v.new_zeros(())
        for axis, n in enumerate(self.flow_shape):
            if n >= 3:
                d2 = (v.narrow(axis, 2, n - 2) - 2.0 * v.narrow(axis, 1, n - 2)
                      + v.narrow(axis, 0, n - 2))
                total = total + (d2 * d2).mean()
        return self.cfg.flow_smooth * total

    def age_seconds(self, age_ms: torch.Tensor) -> torch.Tensor:
        """Ages (ms) from the pivot, clipped to ±``flow_max_ms``, in seconds."""
        limit = self.cfg.flow_max_ms
        return (age_ms - self.pivot_ms).clamp(-limit, limit) * 1e-3

    def warp(self, points: torch.Tensor, age_ms: torch.Tensor) -> torch.Tensor:
        """Where the grid is read for world ``points`` (P, 3) of images of age ``age_ms`` (P,):
        points + a·v(points), a the age from the pivot."""
        return self._warp(points, self.age_seconds(age_ms))

    def _warp(self, points: torch.Tensor, age_s: torch.Tensor) -> torch.Tensor:
        if not (torch.is_grad_enabled() and self.flow.requires_grad):
            fused = native_flow.warp(self.flow, points, age_s, self.aabb, self.flow_shape)
            if fused is not None:
                return fused
        return points + age_s[:, None] * self.velocity(points)

    def _canonical(self, warped: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """σ, rgb of the grid at ``warped`` points; under autograd, differentiable in the grid
        (row-sparse) and in the points."""
        if not (torch.is_grad_enabled() and warped.requires_grad):
            return self.query(warped, warped)  # the grid's colour ignores the direction
        raw = trilinear(self.grid, self.shape, self._coords(warped), sparse=True)
        return F.softplus(raw[:, 0]), torch.sigmoid(raw[:, 1:])

    def query_aged(self, points: torch.Tensor, dirs: torch.Tensor, age_ms: torch.Tensor
                   ) -> tuple[torch.Tensor, torch.Tensor]:
        """The scene ``age_ms`` (P,) before the reference time (negative: after it)."""
        return self._canonical(self.warp(points, age_ms))

    # --- rendering and training -------------------------------------------------------------
    def _samples(self, rays: RayBundle, options: RenderOptions
                 ) -> tuple[RaySamples, torch.Tensor, torch.Tensor]:
        """The uniform sampler's samples of ``rays`` (which carry ages), where they read the
        grid (warped), and their ages in seconds; samples whose warped point lies in skipped
        space are dropped (``options.explore`` keeps that fraction of them, as
        :func:`aoi3d.field.render.sample_kept` does)."""
        assert rays.age_ms is not None
        samples = sample_uniform(rays.origins, rays.dirs, rays.t_near, rays.t_far,
                                 options.ray_step, options.jitter)
        age_s = self.age_seconds(rays.age_ms).index_select(0, samples.ray_index)
        warped = self._warp(samples.points, age_s)
        keep = self.occupied(warped.detach())
        if keep is not None and options.explore > 0:
            lucky = (torch.rand(keep.shape, generator=options.generator, device=keep.device)
                     < options.explore)
            keep = keep | lucky
        if keep is not None:
            kept = keep.nonzero().squeeze(1)
            samples = samples.select(keep)
            warped, age_s = warped.index_select(0, kept), age_s.index_select(0, kept)
        return samples, warped, age_s

    def render_rays(self, rays: RayBundle, options: RenderOptions) -> RenderResult:
        """Rays without an age: the grid at the reference time (the grid's renderer, fused);
        with ages: each sample read at the warped point."""
        if rays.age_ms is None:
            if self.pivot_ms == 0.0:
                return super().render_rays(rays, options)
            rays = replace(rays, age_ms=rays.t_near.new_zeros(rays.n_rays))
        samples, warped, _ = self._samples(rays, options)
        sigma, rgb = self._canonical(warped)
        out = volume_render(sigma, rgb, samples.deltas, samples.ray_index,
                            self.background(rays.dirs))
        if self.training and self.cfg.flow_smooth > 0:
            out = replace(out, aux_loss=self.smoothness())
        return out

    def train_step(self, rays: RayBundle, options: RenderOptions, target: torch.Tensor,
                   optimizer: LazyAdam) -> float | None:
        """The whole step in the fused kernels (:func:`aoi3d.field.native_flow.
        flow_training_grads`) where they run; None (autograd trains) elsewhere, or for a
        subclass."""
        if (type(self) is not FlowField or rays.age_ms is None
                or not native_flow.usable(self.grid, self.flow, self.env, rays.origins, target)):
            return None
        with torch.no_grad():
            samples, warped, age_s = self._samples(rays, options)
        cfg = self.cfg
        mse, rows, values, grad_env, grad_flow = native_flow.flow_training_grads(
            self.grid, self.aabb, self.shape, self.flow, self.flow_shape, self.env, cfg.up_axis,
            samples.points, warped, age_s, samples.deltas, samples.ray_index, rays.dirs, target,
            cfg.sample_rgb_loss, cfg.opacity_loss, cfg.flow_smooth)
        optimizer.update(self.grid, (rows, values))
        optimizer.update(self.env, grad_env)
        optimizer.update(self.flow, grad_flow)
        return mse

    def param_groups(self) -> list[dict[str, Any]]:
        grid, background = super().param_groups()
        return [grid, {"params": [self.flow], "lr": self.cfg.lr_flow}, background]

    # --- moving the reference time ----------------------------------------------------------
    @torch.no_grad()
    def advance(self, dt_ms: float
                ) -> list[tuple[torch.Tensor, Callable[[torch.Tensor], torch.Tensor]]] | None:
        """Move the reference time ``dt_ms`` later: the grid resampled along the flow,
        G'(x) = G(x − dt·v(x)) (dt clipped to ±``flow_max_ms``); returns the grid and the
        resampling, for the optimizer's moments of it. None when dt is 0."""
        if not math.isfinite(dt_ms):
            raise ValueError(f"dt_ms must be finite, got {dt_ms}")
        if dt_ms == 0:
            return None
        axes = [torch.linspace(0.0, 1.0, n, device=self.grid.device) for n in self.shape]
        unit = torch.stack(torch.meshgrid(*axes, indexing="ij"), dim=-1).reshape(-1, 3)
        vertices = self.aabb[0] + unit * (self.aabb[1] - self.aabb[0])
        limit = self.cfg.flow_max_ms
        dt_s = min(max(float(dt_ms), -limit), limit) * 1e-3
        source = vertices - dt_s * self.velocity(vertices)

        def carry(table: torch.Tensor) -> torch.Tensor:
            fused = native_flow.trilinear4(table, source, self.aabb, self.shape)
            if fused is not None:
                return fused
            return trilinear(table.detach(), self.shape, self._coords(source))

        self.grid.copy_(carry(self.grid))
        if self._occupancy is not None:
            self.refresh_occupancy()
        return [(self.grid, carry)]
