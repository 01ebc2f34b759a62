"""Volume rendering, exactly as in NeRF (Mildenhall et al. 2020, eq. 3):

    C(r) = Σ_i T_i (1 − exp(−σ_i δ_i)) c_i + T_N · c_bg(d),   T_i = exp(−Σ_{j<i} σ_j δ_j),

where T_N = exp(−Σ_j σ_j δ_j) is the transmittance left when the ray leaves the box and
c_bg(d) the background seen in the ray's direction.

Samples are packed (only those inside the box, ray after ray, in order along each ray), so a
ray may have any number of samples, none included. The exclusive prefix sums Σ_{j<i} σ_j δ_j
are one float64 cumulative sum over all samples minus the sum of the rays before.

:func:`render_uniform` is the default way a field renders rays (``Field.render_rays``): the
uniform sampler at a fixed world step, empty-space skipping, the field, this compositor.
Fields that sample otherwise (e.g. ``nerfacto``'s proposal sampling) override
``Field.render_rays`` and return the same :class:`RenderResult`, with their own loss terms in
``aux_loss``.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Protocol

import torch

from aoi3d.field import native
from aoi3d.field.rays import RayBundle, RaySamples, sample_uniform

__all__ = ["RenderOptions", "RenderResult", "SampledField", "render_uniform", "sample_kept",
           "volume_render"]


class SampledField(Protocol):
    """What :func:`render_uniform` asks of a field (every ``aoi3d.field.base.Field`` has
    it): which sample points are occupied, density and colour at points, the background,
    and whether the colour depends on the direction."""

    @property
    def view_dependent(self) -> bool: ...

    def occupied(self, points: torch.Tensor) -> torch.Tensor | None: ...

    def query(self, points: torch.Tensor, dirs: torch.Tensor
              ) -> tuple[torch.Tensor, torch.Tensor]: ...

    def query_aged(self, points: torch.Tensor, dirs: torch.Tensor, age_ms: torch.Tensor
                   ) -> tuple[torch.Tensor, torch.Tensor]: ...

    def background(self, dirs: torch.Tensor) -> torch.Tensor: ...


@dataclass(frozen=True)
class RenderResult:
    """Colour (R, 3) and final transmittance T_N (R,) of each ray; weights T_i·α_i (P,),
    colours (P, 3), ray (P,) and opacity α_i (P,) of each sample (for per-sample losses).

    ``aux_loss``: a scalar the field adds to the training loss (e.g. nerfacto's proposal and
    distortion losses, already weighted), or None; the trainer adds it as it is.
    """

    rgb: torch.Tensor
    transmittance: torch.Tensor
    weights: torch.Tensor
    sample_rgb: torch.Tensor
    ray_index: torch.Tensor
    opacity: torch.Tensor
    aux_loss: torch.Tensor | None = None


@dataclass(frozen=True)
class RenderOptions:
    """How the trainer asks a field to render one batch of rays.

    ``ray_step``: world distance between samples of the uniform sampler (the trainer's
    coarse-to-fine schedule, ``FieldConfig.ray_step``). ``jitter`` (R,) in [0, 1): stratified
    offsets of each ray's samples in training, None (midpoints) when rendering.
    ``explore``: fraction of skipped samples still trained on. ``generator``: the trainer's
    random stream, for any other random draw (keeps a seeded run deterministic). Whether the
    call is for training is the field's ``training`` flag (the trainer sets train/eval).
    """

    ray_step: float
    jitter: torch.Tensor | None = None
    explore: float = 0.0
    generator: torch.Generator | None = None


def volume_render(
    sigma: torch.Tensor,
    rgb: torch.Tensor,
    deltas: torch.Tensor,
    ray_index: torch.Tensor,
    background: torch.Tensor,
) -> RenderResult:
    """Composite packed samples over the background.

    ``sigma`` (P,) densities ≥ 0, ``rgb`` (P, 3) colours, ``deltas`` (P,) interval lengths,
    ``ray_index`` (P,) non-decreasing ray of each sample, ``background`` (R, 3) the colour of
    each ray's direction. Returns the colours of all R rays.
    """
    n_samples = sigma.shape[0]
    if deltas.shape != (n_samples,) or ray_index.shape != (n_samples,):
        raise ValueError(
            f"shapes disagree: sigma {tuple(sigma.shape)}, deltas {tuple(deltas.shape)}, "
            f"ray_index {tuple(ray_index.shape)}"
        )
    if rgb.shape != (n_samples, 3) or background.ndim != 2 or background.shape[1] != 3:
        raise ValueError(
            f"rgb must be (P, 3) and background (R, 3), got {tuple(rgb.shape)}, "
            f"{tuple(background.shape)}"
        )
    fused = native.volume_render(sigma, rgb, deltas, ray_index, background)
    if fused is not None:
        color, transmittance, weights, alpha = fused
        return RenderResult(color, transmittance, weights, rgb, ray_index, alpha)
    n_rays = background.shape[0]
    tau = sigma * deltas
    tau64 = tau.double()
    per_ray = tau64.new_zeros(n_rays).index_add_(0, ray_index, tau64)  # Σ_j σ_j δ_j of each ray
    rays_before = torch.cumsum(per_ray, 0) - per_ray
    # Σ_{j<i} σ_j δ_j within the ray of sample i:
    before = torch.cumsum(tau64, 0) - tau64 - rays_before.index_select(0, ray_index)
    alpha = -torch.expm1(-tau)
    weights = torch.exp(-before.clamp_min(0.0)).to(tau.dtype) * alpha
    transmittance = torch.exp(-per_ray).to(tau.dtype)
    color = rgb.new_zeros(n_rays, 3).index_add_(0, ray_index, weights[:, None] * rgb)
    color = color + transmittance[:, None] * background
    return RenderResult(color, transmittance, weights, rgb, ray_index, alpha)


def sample_kept(field: SampledField, rays: RayBundle, options: RenderOptions) -> RaySamples:
    """The uniform sampler's samples of ``rays`` at ``options.ray_step`` that the field does
    not skip as empty (``Field.occupied``); ``options.explore`` > 0 keeps that fraction of the
    skipped ones at random, drawn from ``options.generator``, so that density can grow again
    where new frames need it."""
    samples = sample_uniform(
        rays.origins, rays.dirs, rays.t_near, rays.t_far, options.ray_step, options.jitter
    )
    keep = field.occupied(samples.points)
    if keep is not None and options.explore > 0:
        lucky = (
            torch.rand(keep.shape, generator=options.generator, device=keep.device)
            < options.explore
        )
        keep = keep | lucky
    if keep is not None:
        samples = samples.select(keep)
    return samples


def render_uniform(field: SampledField, rays: RayBundle, options: RenderOptions
                   ) -> RenderResult:
    """The default renderer: sample the rays inside the box at ``options.ray_step``, skip
    empty space, query the field, composite over its background.

    The samples are :func:`sample_kept`'s. Appearance rows are not used. Rays with an age
    (``rays.age_ms``, given only to a field that takes it) are queried at their image's age
    (``query_aged``).
    """
    samples = sample_kept(field, rays, options)
    dirs = rays.dirs
    if field.view_dependent or dirs.shape[0] == 0:
        sample_dirs = dirs.index_select(0, samples.ray_index)
    else:  # the field does not read them: the first ray's, broadcast (a view, no copy)
        sample_dirs = dirs[:1].expand(samples.points.shape[0], 3)
    if rays.age_ms is None:
        sigma, rgb = field.query(samples.points, sample_dirs)
    else:
        age = rays.age_ms.index_select(0, samples.ray_index)
        sigma, rgb = field.query_aged(samples.points, sample_dirs, age)
    return volume_render(sigma, rgb, samples.deltas, samples.ray_index, field.background(dirs))
