"""Volume rendering, exactly as in NeRF (Mildenhall et al. 2020, eq. 3):

    C(r) = Σ_i T_i (1 − exp(−σ_i δ_i)) c_i + T_N · c_bg(d),   T_i = exp(−Σ_{j<i} σ_j δ_j),

where T_N = exp(−Σ_j σ_j δ_j) is the transmittance left when the ray leaves the box and
c_bg(d) the background seen in the ray's direction.

Samples are packed (only those inside the box, ray after ray, in order along each ray), so a
ray may have any number of samples, none included. The exclusive prefix sums Σ_{j<i} σ_j δ_j
are one float64 cumulative sum over all samples minus the sum of the rays before.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch

__all__ = ["RenderResult", "volume_render"]


@dataclass(frozen=True)
class RenderResult:
    """Colour (R, 3) and final transmittance T_N (R,) of each ray; weights T_i·α_i (P,),
    colours (P, 3) and ray (P,) of each sample (for per-sample losses)."""

    rgb: torch.Tensor
    transmittance: torch.Tensor
    weights: torch.Tensor
    sample_rgb: torch.Tensor
    ray_index: torch.Tensor
    opacity: torch.Tensor


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
