"""Rays of a camera, their intersection with the scene box, and the uniform ray sampler.

Shared by every field backend: a ray is an origin and a unit direction in world
coordinates; samples are taken at a fixed world step inside the scene AABB only (outside the
box the scene depends on the ray direction alone and is the field's background). A
:class:`RayBundle` is what a field's ``render_rays`` receives: rays, their chord through the
box and, in training, the appearance row of the image each ray comes from and, for a field
that takes it, that image's age.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np
import torch

from aoi3d.field import native

if TYPE_CHECKING:
    from aoi3d.scene.camera import Camera

__all__ = ["RayBundle", "RaySamples", "as_aabb", "camera_rays", "ray_aabb", "sample_uniform"]


def as_aabb(aabb: np.ndarray | torch.Tensor | list[list[float]]) -> np.ndarray:
    """``aabb`` as a float64 (2, 3) array [min, max]; raises ``ValueError`` when degenerate."""
    box = np.asarray(aabb.cpu() if isinstance(aabb, torch.Tensor) else aabb, dtype=np.float64)
    if box.shape != (2, 3):
        raise ValueError(f"aabb must have shape (2, 3) [min, max], got {box.shape}")
    if not np.isfinite(box).all() or not (box[1] > box[0]).all():
        raise ValueError(f"aabb must be finite with max > min on every axis, got {box.tolist()}")
    return box


def camera_rays(camera: Camera, device: torch.device | str = "cpu") -> tuple[torch.Tensor, ...]:
    """The camera's rays through pixel centres, flattened row-major: origins, dirs (H·W, 3)."""
    origins, dirs = camera.rays()
    o = torch.from_numpy(np.ascontiguousarray(origins, dtype=np.float32)).reshape(-1, 3)
    d = torch.from_numpy(np.ascontiguousarray(dirs, dtype=np.float32)).reshape(-1, 3)
    if o.shape[0] != camera.width * camera.height:
        raise ValueError(
            f"camera.rays() gave {o.shape[0]} rays for a {camera.width}×{camera.height} camera"
        )
    return o.to(device), d.to(device)


def ray_aabb(
    origins: torch.Tensor, dirs: torch.Tensor, aabb: torch.Tensor
) -> tuple[torch.Tensor, torch.Tensor]:
    """Slab test: entry and exit distances ``t_near, t_far`` (R,) of each ray through the box.

    ``t_near`` is clamped at 0 (an origin inside the box enters at once). A ray misses the box
    exactly when ``t_far <= t_near``; then both are returned as they are (the caller masks).
    """
    eps = 1e-12
    safe = torch.where(dirs.abs() < eps, torch.full_like(dirs, eps), dirs)
    inv = 1.0 / safe
    t0 = (aabb[0] - origins) * inv
    t1 = (aabb[1] - origins) * inv
    t_near = torch.minimum(t0, t1).amax(dim=-1).clamp_min(0.0)
    t_far = torch.maximum(t0, t1).amin(dim=-1)
    return t_near, t_far


@dataclass(frozen=True)
class RayBundle:
    """R rays: ``origins``, unit ``dirs`` (R, 3), box entry/exit ``t_near``, ``t_far`` (R,)
    (a ray misses the box when ``t_far <= t_near``) and ``appearance`` (R,) int64: the row of
    each ray's training image in the field's appearance table (see
    ``FieldConfig.appearance_slots``), or None for a novel view (fields with per-image
    embeddings then use their neutral one). ``age_ms`` (R,) float: the age of each ray's
    training image (its AoI at the decision it trains for), given only to a field that takes
    it (``FieldConfig.takes_age``: the grid's timeliness embedding); None for a novel view,
    which is the scene at age 0.
    """

    origins: torch.Tensor
    dirs: torch.Tensor
    t_near: torch.Tensor
    t_far: torch.Tensor
    appearance: torch.Tensor | None = None
    age_ms: torch.Tensor | None = None

    def __post_init__(self) -> None:
        n = self.origins.shape[0]
        if self.origins.shape != (n, 3) or self.dirs.shape != (n, 3):
            raise ValueError(
                f"origins and dirs must be (R, 3), got {tuple(self.origins.shape)}, "
                f"{tuple(self.dirs.shape)}"
            )
        shapes = [self.t_near.shape, self.t_far.shape]
        for extra in (self.appearance, self.age_ms):
            if extra is not None:
                shapes.append(extra.shape)
        if any(s != (n,) for s in shapes):
            raise ValueError(f"t_near, t_far, appearance and age_ms must be ({n},), got {shapes}")

    @property
    def n_rays(self) -> int:
        return self.origins.shape[0]

    def __getitem__(self, index: slice | torch.Tensor) -> RayBundle:
        """The rays at ``index`` (a slice, or an int64 tensor of ray numbers)."""

        def pick(x: torch.Tensor) -> torch.Tensor:
            return x[index] if isinstance(index, slice) else x.index_select(0, index)

        appearance = None if self.appearance is None else pick(self.appearance)
        age = None if self.age_ms is None else pick(self.age_ms)
        return RayBundle(
            pick(self.origins), pick(self.dirs), pick(self.t_near), pick(self.t_far), appearance,
            age,
        )


@dataclass(frozen=True)
class RaySamples:
    """Samples of R rays, packed: only samples inside the box, ray after ray, in order along
    each ray. ``points`` (P, 3) world positions, ``deltas`` (P,) the length of each sample's
    interval, ``ray_index`` (P,) the ray each sample belongs to (non-decreasing), ``n_rays`` R.
    """

    points: torch.Tensor
    deltas: torch.Tensor
    ray_index: torch.Tensor
    n_rays: int

    def select(self, keep: torch.Tensor) -> RaySamples:
        """The samples where the boolean mask ``keep`` (P,) is true (order is kept)."""
        kept = keep.nonzero().squeeze(1)
        return RaySamples(
            self.points.index_select(0, kept),
            self.deltas.index_select(0, kept),
            self.ray_index.index_select(0, kept),
            self.n_rays,
        )


def sample_uniform(
    origins: torch.Tensor,
    dirs: torch.Tensor,
    t_near: torch.Tensor,
    t_far: torch.Tensor,
    step: float,
    jitter: torch.Tensor | None = None,
) -> RaySamples:
    """One sample per interval ``[t_near + i·step, t_near + (i+1)·step]`` clipped to ``t_far``.

    The sample sits at the interval's midpoint, or at fraction ``jitter`` (R,) of it in
    training (stratified sampling). ``deltas`` are the clipped interval lengths, so they add
    up to the chord length of the ray through the box; rays that miss the box get no samples.
    """
    if step <= 0:
        raise ValueError(f"ray step must be > 0, got {step}")
    n_rays = origins.shape[0]
    chord = (t_far - t_near).clamp_min(0.0)
    max_chord = float(chord.max()) if n_rays else 0.0
    n_steps = max(1, int(np.ceil(max_chord / step)))
    fused = native.sample_uniform(origins, dirs, t_near, t_far, step, n_steps, jitter)
    if fused is not None:
        points, deltas, ray_index = fused
        return RaySamples(points, deltas, ray_index, n_rays)
    start = torch.arange(n_steps, device=origins.device, dtype=origins.dtype) * step  # (S,)
    remaining = chord[:, None] - start[None, :]  # (R, S)
    flat = (remaining > 0).view(-1).nonzero().squeeze(1)
    ray = torch.div(flat, n_steps, rounding_mode="floor")
    deltas = remaining.view(-1).index_select(0, flat).clamp_max(step)
    frac = 0.5 if jitter is None else jitter.index_select(0, ray)
    t = t_near.index_select(0, ray) + start.index_select(0, flat - ray * n_steps) + frac * deltas
    points = torch.addcmul(origins.index_select(0, ray), dirs.index_select(0, ray), t[:, None])
    return RaySamples(points, deltas, ray, n_rays)
