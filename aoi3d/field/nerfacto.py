"""``nerfacto``: nerfstudio's nerfacto design, scaled for a small CPU.

A model that owns its sampling (it overrides :meth:`Field.render_rays`):

1. **Proposal sampling** (mip-NeRF 360 / nerfacto). Each ray's chord through the box is cut
   into ``proposal_samples[0]`` uniform bins (one stratified jitter per ray in training);
   a tiny density-only hash grid — the proposal network — gives their weights
   w_i = T_i (1 − exp(−σ_i δ_i)); the next bins are drawn from that histogram by inverse-CDF
   (PDF) resampling (:func:`sample_pdf`), where the weight concentrates. With more proposal
   networks this repeats; the last resampling gives ``fine_samples`` bins for the field.
   Early on the proposal weights are annealed towards uniform (w^a, a: 0 → 1 over
   ``proposal_anneal_steps``), so the first steps sample the whole chord.
2. **The field**: the shared multiresolution hash encoding
   (:class:`aoi3d.field.encodings.HashEncoding`, ``"aligned"`` layout: a table of
   2^``log2_table_size`` rows per level, small levels dense on cubes padded to a power of
   two) and a small MLP giving density
   (exp, initial σ ≈ ``init_density``) and geometry features; a colour MLP reads those, the
   view direction (real spherical harmonics, :func:`~aoi3d.field.encodings.spherical_harmonics`)
   and the per-image **appearance embedding**.
3. **Losses** (``RenderResult.aux_loss``): the interlevel (proposal, histogram) loss
   (:func:`interlevel_loss`), which teaches each proposal network to bound the field's
   weights (the field's weights and bins are detached: the loss trains the proposal networks
   only, and nothing else trains them), and the distortion loss (:func:`distortion_loss`) on
   the field's weights. The trainer adds its own MSE and ``sample_rgb_loss``.
4. **Background**: a lat-long map of the ray direction only (as ``grid``), composited with the
   transmittance left when the ray leaves the box.

Appearance embeddings: a fixed table of ``FieldConfig.appearance_slots`` rows, indexed by the
rows the trainer assigns per stable image key (``RayBundle.appearance``), initialised at zero.
A novel view (``appearance`` None) uses the **mean of the rows trained so far**: the colour
head has only ever seen trained embeddings, and their mean is the centre of that set — the
best guess for the lighting of an unseen camera (nerfstudio's default,
``use_average_appearance_embedding``). Zero would be equivalent only while every row is still
at its initial value; unused rows are left out of the mean so they do not pull it to zero.

Scaled for a 2-core CPU. Measured on the 96×72 turbine, 18 views, PSNR of held-out camera 0
at 5/15/30/60 s of process CPU time on one thread (torch 2.13, machine shared, ±0.5 dB):
nerfstudio's proportions (64 proposal samples through 5 levels × 2 features, 24 field
samples, 1024 rays) 23.2/26.0/29.3/32.2 dB at 8.8k rays/s, render 0.7–1.9 s; 48 → 16 samples
with a 4 × 1 proposal grid 24.3/29.0/32.0/33.7 at 16k rays/s; then 512 rays and 32 → 16
samples 25.7/30.4/32.3/33.4; + distortion loss 0.002 26.1/29.7/32.6/33.7; + the trainer's
``sample_rgb_loss`` 0.01 (these defaults) 27.1/31.8/33.0/33.4 at 15–16k rays/s, render
0.16–0.2 s. Without appearance embeddings +0.5–0.9 dB (this scene has no per-camera exposure
changes to explain). No better: lr 2e-2, a 32-wide colour MLP, 2^15 tables, 512 cells with
2^17 tables, 256-ray batches (stall at 31.6 dB), ``opacity_loss`` 1e-3 (−1.2 dB at 30 s),
annealing over 100 or 1000 steps (within noise).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

import numpy as np
import torch
import torch.nn.functional as F
from torch import nn

from aoi3d.field.base import Field, FieldConfig, check_at_least, check_positive
from aoi3d.field.encodings import HashEncoding, spherical_harmonics
from aoi3d.field.rays import RayBundle
from aoi3d.field.render import RenderOptions, RenderResult, volume_render

__all__ = [
    "NerfactoConfig",
    "NerfactoField",
    "distortion_loss",
    "interlevel_loss",
    "sample_pdf",
    "weights_from_density",
]


@dataclass(frozen=True)
class NerfactoConfig(FieldConfig):
    """The nerfacto backend.

    Field: ``levels`` hash levels of ``features_per_level`` features, resolutions growing
    geometrically from ``base_resolution`` to ``max_resolution`` (cells along the longest box
    side), tables of 2^``log2_table_size`` rows (a level with fewer vertices is stored
    densely); a density MLP with ``hidden_dim`` units gives σ and ``geo_features`` features;
    the colour MLP (``color_hidden_dim`` units, two hidden layers) reads them with the view
    direction's spherical harmonics of ``direction_sh_levels`` bands (0: none) and an
    appearance embedding of ``appearance_dim`` (0: none). ``init_density``: σ at the start.

    Proposal sampling: ``proposal_samples[k]`` bins go through proposal network k (the first
    uniformly placed), ``fine_samples`` bins through the field; each proposal network is a
    hash grid of ``proposal_levels`` × ``proposal_features`` up to
    ``proposal_max_resolutions[k]`` cells with a ``proposal_hidden_dim`` MLP.
    ``histogram_padding`` is added to the weights before resampling;
    ``proposal_anneal_steps``/``proposal_anneal_slope``: the annealing of the proposal weights
    (nerfstudio's schedule). Losses: ``interlevel_loss_weight`` × the proposal loss,
    ``distortion_loss_weight`` × the distortion loss (0: off).

    Learning rates (Adam): ``lr_field`` (hash table and MLPs), ``lr_proposal``,
    ``lr_appearance`` (the background's is inherited). The inherited uniform-sampler
    settings (``samples_coarse``, ``samples_fine``, ``fine_from_step``, ``explore_empty``) are
    not used by this backend.
    """

    levels: int = 8
    features_per_level: int = 2
    log2_table_size: int = 16
    base_resolution: int = 16
    max_resolution: int = 256
    hidden_dim: int = 64
    geo_features: int = 15
    color_hidden_dim: int = 64
    direction_sh_levels: int = 2
    appearance_dim: int = 8
    init_density: float = 0.1
    proposal_samples: tuple[int, ...] = (32,)
    fine_samples: int = 16
    proposal_levels: int = 4
    proposal_features: int = 1
    proposal_log2_table_size: int = 14
    proposal_base_resolution: int = 16
    proposal_max_resolutions: tuple[int, ...] = (128,)
    proposal_hidden_dim: int = 16
    histogram_padding: float = 0.01
    proposal_anneal_steps: int = 300
    proposal_anneal_slope: float = 10.0
    interlevel_loss_weight: float = 1.0
    distortion_loss_weight: float = 0.002
    lr_field: float = 1e-2
    lr_proposal: float = 1e-2
    lr_appearance: float = 1e-2
    batch_rays: int = 512
    opacity_loss: float = 0.0

    def __post_init__(self) -> None:
        super().__post_init__()
        at_least_1 = ("levels", "features_per_level", "base_resolution", "hidden_dim",
                      "color_hidden_dim", "fine_samples", "proposal_levels", "proposal_features",
                      "proposal_base_resolution", "proposal_hidden_dim")
        check_at_least(self, 1, at_least_1)
        check_at_least(self, 0, ("geo_features", "appearance_dim", "proposal_anneal_steps",
                                 "interlevel_loss_weight", "distortion_loss_weight"))
        check_positive(self, ("init_density", "lr_field", "lr_proposal", "lr_appearance"))
        for name in ("log2_table_size", "proposal_log2_table_size"):
            if not 4 <= getattr(self, name) <= 24:
                raise ValueError(f"{name} must be in [4, 24], got {getattr(self, name)}")
        if self.max_resolution < self.base_resolution:
            raise ValueError(
                f"max_resolution {self.max_resolution} < base_resolution {self.base_resolution}"
            )
        if not 0 <= self.direction_sh_levels <= 4:
            raise ValueError(f"direction_sh_levels must be in 0..4, got {self.direction_sh_levels}")
        if not self.proposal_samples or min(self.proposal_samples) < 1:
            raise ValueError(
                f"proposal_samples must be non-empty, each >= 1, got {self.proposal_samples}"
            )
        if (
            len(self.proposal_max_resolutions) != len(self.proposal_samples)
            or min(self.proposal_max_resolutions) < self.proposal_base_resolution
        ):
            raise ValueError(
                "proposal_max_resolutions needs one entry >= proposal_base_resolution per "
                f"proposal network ({len(self.proposal_samples)}), got "
                f"{self.proposal_max_resolutions}"
            )
        if not self.histogram_padding >= 0 or not self.proposal_anneal_slope >= 1:
            raise ValueError(
                "histogram_padding must be >= 0 and proposal_anneal_slope >= 1, got "
                f"{self.histogram_padding}, {self.proposal_anneal_slope}"
            )

    def anneal_exponent(self, step: int) -> float:
        """Exponent a of the proposal weights w^a used for resampling at training ``step``."""
        if self.proposal_anneal_steps == 0:
            return 1.0
        x = min(max(step / self.proposal_anneal_steps, 0.0), 1.0)
        b = self.proposal_anneal_slope
        return (b * x) / ((b - 1) * x + 1)

    def build(self, aabb: np.ndarray) -> NerfactoField:
        return NerfactoField(self, aabb)


# --- building blocks ---------------------------------------------------------------------------
class _TruncExp(torch.autograd.Function):
    """exp(x) whose gradient uses exp(min(x, 15)) (Instant-NGP's trunc_exp: no overflow)."""

    @staticmethod
    def forward(ctx: Any, x: torch.Tensor) -> torch.Tensor:
        ctx.save_for_backward(x)
        return torch.exp(x)

    @staticmethod
    def backward(ctx: Any, grad: torch.Tensor) -> torch.Tensor:
        (x,) = ctx.saved_tensors
        return grad * torch.exp(x.clamp_max(15.0))


def _trunc_exp(x: torch.Tensor) -> torch.Tensor:
    return _TruncExp.apply(x)


def weights_from_density(sigma: torch.Tensor, deltas: torch.Tensor) -> torch.Tensor:
    """Volume-rendering weights w_i = T_i (1 − exp(−σ_i δ_i)) of dense samples (R, N)."""
    tau = sigma * deltas
    before = torch.cumsum(tau, dim=-1) - tau
    return torch.exp(-before) * -torch.expm1(-tau)


def sample_pdf(
    edges: torch.Tensor,
    weights: torch.Tensor,
    n_samples: int,
    jitter: torch.Tensor | None = None,
    padding: float = 0.01,
) -> torch.Tensor:
    """Inverse-CDF resampling of a piecewise-constant histogram: ``n_samples`` new bins.

    ``edges`` (R, N+1) sorted bin edges, ``weights`` (R, N) ≥ 0 (``padding`` is added to
    each, so empty histograms give uniform bins). Returns the edges (R, n_samples+1) of the new
    bins, sorted, within [edges[:, 0], edges[:, -1]], denser where the weights are: the
    quantiles u_k = (k + j)/(n_samples+1), k = 0..n_samples, of the histogram, with ``jitter``
    j (R,) in [0, 1) (stratified, training) or 0.5 (None). Not differentiable (detached).
    """
    if edges.shape[-1] != weights.shape[-1] + 1 or edges.shape[:-1] != weights.shape[:-1]:
        raise ValueError(
            f"edges must be (R, N+1) for weights (R, N), got {tuple(edges.shape)}, "
            f"{tuple(weights.shape)}"
        )
    if n_samples < 1:
        raise ValueError(f"n_samples must be >= 1, got {n_samples}")
    edges, weights = edges.detach(), weights.detach()
    w = weights + padding
    total = w.sum(dim=-1, keepdim=True)
    w = w + F.relu(1e-5 - total) / w.shape[-1]  # all-zero rows (padding 0): uniform
    pdf = w / w.sum(dim=-1, keepdim=True)
    cdf = torch.cat([torch.zeros_like(pdf[:, :1]), torch.cumsum(pdf, dim=-1).clamp_max(1.0)], -1)
    m = n_samples + 1
    k = torch.arange(m, device=edges.device, dtype=edges.dtype)
    j = 0.5 if jitter is None else jitter[:, None]
    u = ((k[None, :] + j) / m).expand(edges.shape[0], m).contiguous()
    above = torch.searchsorted(cdf.contiguous(), u, right=True).clamp_max(cdf.shape[-1] - 1)
    below = (above - 1).clamp_min(0)
    cdf0, cdf1 = cdf.gather(-1, below), cdf.gather(-1, above)
    e0, e1 = edges.gather(-1, below), edges.gather(-1, above)
    span = cdf1 - cdf0
    t = torch.where(span > 0, (u - cdf0) / span.clamp_min(1e-12), torch.zeros_like(u)).clamp(0, 1)
    return e0 + t * (e1 - e0)


def _outer(
    starts: torch.Tensor,
    ends: torch.Tensor,
    env_starts: torch.Tensor,
    env_ends: torch.Tensor,
    env_weights: torch.Tensor,
) -> torch.Tensor:
    """Σ of ``env_weights`` over the envelope bins that overlap each bin [starts, ends]."""
    n_env = env_weights.shape[-1]
    cum = torch.cat([torch.zeros_like(env_weights[:, :1]), torch.cumsum(env_weights, -1)], -1)
    lo = torch.searchsorted(env_starts.contiguous(), starts.contiguous(), right=True) - 1
    lo = lo.clamp(0, n_env - 1)
    hi = torch.searchsorted(env_ends.contiguous(), ends.contiguous(), right=True)
    hi = hi.clamp(0, n_env - 1)
    return cum[:, 1:].gather(-1, hi) - cum[:, :-1].gather(-1, lo)


def interlevel_loss(
    edges: torch.Tensor,
    weights: torch.Tensor,
    proposal_edges: torch.Tensor,
    proposal_weights: torch.Tensor,
) -> torch.Tensor:
    """mip-NeRF 360's proposal loss: mean over bins of max(0, w − bound)² / (w + ε), where
    bound is the proposal weight summed over the proposal bins overlapping each field bin.

    ``edges`` (R, N+1) and ``weights`` (R, N) of the field are detached (the field is not
    pulled towards the proposal); the gradient reaches ``proposal_weights`` (R, M) only. Zero
    when the proposal's weights bound the field's everywhere.
    """
    e, w = edges.detach(), weights.detach()
    bound = _outer(
        e[:, :-1], e[:, 1:], proposal_edges[:, :-1], proposal_edges[:, 1:], proposal_weights
    )
    return torch.mean(F.relu(w - bound) ** 2 / (w + 1e-7))


def distortion_loss(edges: torch.Tensor, weights: torch.Tensor) -> torch.Tensor:
    """mip-NeRF 360's distortion loss Σ_ij w_i w_j |m_i − m_j| + ⅓ Σ_i w_i² δ_i, mean over rays
    (``edges`` (R, N+1) normalised along each ray, e.g. to [0, 1]; ``weights`` (R, N))."""
    mid = 0.5 * (edges[:, 1:] + edges[:, :-1])
    width = edges[:, 1:] - edges[:, :-1]
    wm = weights * mid
    w_before = torch.cumsum(weights, -1) - weights
    wm_before = torch.cumsum(wm, -1) - wm
    pairs = 2.0 * (weights * (mid * w_before - wm_before)).sum(-1)
    own = (weights**2 * width).sum(-1) / 3.0
    return (pairs + own).mean()


def _mlp(n_in: int, hidden: int, n_out: int, layers: int) -> nn.Sequential:
    """``layers`` hidden ReLU layers; weights uninitialised until :func:`_init_mlp`."""
    mods: list[nn.Module] = []
    for i in range(layers):
        mods += [nn.utils.skip_init(nn.Linear, n_in if i == 0 else hidden, hidden), nn.ReLU()]
    mods.append(nn.utils.skip_init(nn.Linear, hidden if layers else n_in, n_out))
    return nn.Sequential(*mods)


class _ProposalNetwork(nn.Module):
    """Density only: a small hash grid and a one-hidden-layer MLP."""

    def __init__(
        self, cfg: NerfactoConfig, aabb: np.ndarray, max_resolution: int, gen: torch.Generator
    ) -> None:
        super().__init__()
        self.encoding = HashEncoding(
            aabb, cfg.proposal_levels, cfg.proposal_features, cfg.proposal_log2_table_size,
            cfg.proposal_base_resolution, max_resolution, layout="aligned", generator=gen)
        self.mlp = _mlp(self.encoding.out_features, cfg.proposal_hidden_dim, 1, 1)
        self.log_init_density = math.log(cfg.init_density)

    def forward(self, points: torch.Tensor) -> torch.Tensor:
        raw = self.mlp(self.encoding(points)).squeeze(-1)
        return _trunc_exp(raw + self.log_init_density)


# --- the field -------------------------------------------------------------------------------
class NerfactoField(Field):
    """Hash-grid field with proposal sampling, per-image appearance and a direction-only
    background; renders its own rays (see the module)."""

    cfg: NerfactoConfig
    appearance_used: torch.Tensor  # a buffer: the appearance rows trained so far

    def __init__(self, cfg: NerfactoConfig, aabb: np.ndarray) -> None:
        super().__init__()
        box = self._setup(cfg, aabb)
        gen = torch.Generator().manual_seed(0)  # the module's init (torch's global RNG untouched)
        self.encoding = HashEncoding(
            box, cfg.levels, cfg.features_per_level, cfg.log2_table_size, cfg.base_resolution,
            cfg.max_resolution, layout="aligned", generator=gen)
        self.density_mlp = _mlp(
            self.encoding.out_features, cfg.hidden_dim, 1 + cfg.geo_features, 1
        )
        n_dir = cfg.direction_sh_levels**2
        self.color_mlp = _mlp(
            cfg.geo_features + n_dir + cfg.appearance_dim, cfg.color_hidden_dim, 3, 2
        )
        for mlp in (self.density_mlp, self.color_mlp):
            _init_mlp(mlp, gen)
        proposals = [_ProposalNetwork(cfg, box, r, gen) for r in cfg.proposal_max_resolutions]
        for p in proposals:
            _init_mlp(p.mlp, gen)
        self.proposals = nn.ModuleList(proposals)
        self.appearance = nn.Parameter(torch.zeros(cfg.appearance_slots, cfg.appearance_dim))
        self.register_buffer("appearance_used", torch.zeros(cfg.appearance_slots, dtype=torch.bool))
        self.log_init_density = math.log(cfg.init_density)
        self._step = 0

    # --- the Field interface -------------------------------------------------------------
    def _field(
        self, points: torch.Tensor, dirs: torch.Tensor, embedding: torch.Tensor | None
    ) -> tuple[torch.Tensor, torch.Tensor]:
        """σ (P,) and colour (P, 3) with appearance ``embedding`` (P, dim) or (dim,)."""
        h = self.density_mlp(self.encoding(points))
        sigma = _trunc_exp(h[:, 0] + self.log_init_density)
        inputs = [h[:, 1:], spherical_harmonics(dirs, self.cfg.direction_sh_levels)]
        if self.cfg.appearance_dim:
            if embedding is None:
                embedding = self.neutral_appearance()
            if embedding.ndim == 1:
                embedding = embedding.expand(points.shape[0], -1)
            inputs.append(embedding)
        rgb = torch.sigmoid(self.color_mlp(torch.cat(inputs, dim=-1)))
        return sigma, rgb

    def query(self, points: torch.Tensor, dirs: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """The field at ``points`` with the neutral appearance."""
        return self._field(points, dirs, None)

    def param_groups(self) -> list[dict[str, Any]]:
        cfg = self.cfg
        groups = [
            {
                "params": [
                    self.encoding.table,
                    *self.density_mlp.parameters(),
                    *self.color_mlp.parameters(),
                ],
                "lr": cfg.lr_field,
            },
            {"params": list(self.proposals.parameters()), "lr": cfg.lr_proposal},
            self.background_group(),
        ]
        if cfg.appearance_dim:
            groups.append({"params": [self.appearance], "lr": cfg.lr_appearance})
        return groups

    def on_step(self, step: int) -> bool:
        self._step = step
        return False

    @torch.no_grad()
    def reset_appearance(self, rows: torch.Tensor) -> None:
        self.appearance.index_fill_(0, rows, 0.0)
        self.appearance_used.index_fill_(0, rows, False)

    def neutral_appearance(self) -> torch.Tensor:
        """The embedding of a novel view: the mean of the rows trained so far (zero before)."""
        used = self.appearance_used
        if not bool(used.any()):
            return self.appearance.new_zeros(self.cfg.appearance_dim)
        return self.appearance[used].mean(dim=0)

    # --- sampling and rendering ----------------------------------------------------------
    def render_rays(self, rays: RayBundle, options: RenderOptions) -> RenderResult:
        """Proposal sampling → field → volume rendering; in training, ``aux_loss`` holds the
        interlevel (and distortion) losses."""
        cfg = self.cfg
        background = self.background(rays.dirs)
        hit = (rays.t_far > rays.t_near).nonzero().squeeze(1)
        origins, dirs = rays.origins.index_select(0, hit), rays.dirs.index_select(0, hit)
        near = rays.t_near.index_select(0, hit)[:, None]
        chord = (rays.t_far.index_select(0, hit) - rays.t_near.index_select(0, hit))[:, None]
        n_hit = hit.shape[0]
        training = self.training
        generator = options.generator

        # Uniform bins over the chord, one stratified offset per ray (s in [0, 1] along it).
        n0 = cfg.proposal_samples[0]
        k = torch.arange(n0 + 1, device=origins.device, dtype=origins.dtype)
        s_edges = (k / n0).expand(n_hit, n0 + 1)
        jitter = options.jitter.index_select(0, hit)[:, None] if options.jitter is not None else 0.5
        s_points = (k[:-1] + jitter) / n0
        proposal_levels: list[tuple[torch.Tensor, torch.Tensor]] = []
        exponent = cfg.anneal_exponent(self._step) if training else 1.0
        for level, proposal in enumerate(self.proposals):
            n = s_points.shape[-1]
            x = origins[:, None, :] + dirs[:, None, :] * (near + s_points * chord)[..., None]
            sigma = proposal(x.reshape(-1, 3)).view(n_hit, n)
            w = weights_from_density(sigma, (s_edges[:, 1:] - s_edges[:, :-1]) * chord)
            proposal_levels.append((s_edges, w))
            n_next = (
                cfg.proposal_samples[level + 1]
                if level + 1 < len(self.proposals)
                else cfg.fine_samples
            )
            resample_jitter = (
                torch.rand(n_hit, generator=generator, device=origins.device) if training else None
            )
            sample_w = w.detach() ** exponent if exponent != 1.0 else w.detach()
            s_edges = sample_pdf(s_edges, sample_w, n_next, resample_jitter, cfg.histogram_padding)
            s_points = 0.5 * (s_edges[:, 1:] + s_edges[:, :-1])

        n_fine = cfg.fine_samples
        deltas = (s_edges[:, 1:] - s_edges[:, :-1]) * chord  # (H, n_fine)
        points = origins[:, None, :] + dirs[:, None, :] * (near + s_points * chord)[..., None]
        ray_index = hit.repeat_interleave(n_fine)
        sample_dirs = dirs.repeat_interleave(n_fine, dim=0)
        embedding = None
        if cfg.appearance_dim and rays.appearance is not None:
            rows = rays.appearance.index_select(0, hit)
            if training:
                with torch.no_grad():
                    self.appearance_used.index_fill_(0, rows, True)
            embedding = self.appearance.index_select(0, rows).repeat_interleave(n_fine, dim=0)
        sigma, rgb = self._field(points.reshape(-1, 3), sample_dirs, embedding)
        out = volume_render(sigma, rgb, deltas.reshape(-1), ray_index, background)
        if not (training and torch.is_grad_enabled()):
            return out
        weights = out.weights.view(n_hit, n_fine)
        aux = (
            sum(
                (interlevel_loss(s_edges, weights, e, w) for e, w in proposal_levels),
                start=weights.new_zeros(()),
            )
            * cfg.interlevel_loss_weight
        )
        if cfg.distortion_loss_weight > 0:
            aux = aux + cfg.distortion_loss_weight * distortion_loss(s_edges, weights)
        return RenderResult(
            out.rgb, out.transmittance, out.weights, out.sample_rgb, out.ray_index, out.opacity, aux
        )


def _init_mlp(mlp: nn.Sequential, gen: torch.Generator) -> None:
    """Kaiming-uniform weights, zero biases, drawn from ``gen`` (deterministic per config)."""
    with torch.no_grad():
        for m in mlp:
            if isinstance(m, nn.Linear):
                bound = math.sqrt(6.0 / m.in_features)
                m.weight.uniform_(-bound, bound, generator=gen)
                m.bias.zero_()
