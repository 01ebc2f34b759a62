"""The ``flow`` backend's fused kernels (``_native_flow.c``, built into the library of
:mod:`aoi3d.field.native`), with the same fallbacks: where the kernels cannot run, callers run
the torch code of :mod:`aoi3d.field.flow`.

- :func:`trilinear4` — a four-column vertex grid interpolated trilinearly, raw (the canonical
  grid resampled along the flow).
- :func:`warp` — sample points moved by their age times the velocity grid at them.
- :func:`flow_training_grads` — one training step of the flow field without autograd: the
  grid's fused step (:func:`aoi3d.field.native.grid_render_grads`) at the warped points, then
  one pass over the grid's corners for both the grid's row-sparse gradient and the loss's
  gradient with respect to each warped point (the interpolation's spatial derivative) times
  the sample's age, scattered into the velocity grid.
"""

from __future__ import annotations

import math

import torch

from aoi3d.field import native
from aoi3d.field.native_calls import (
    flow_grid_backward,
    flow_smooth_grad,
    grid_geometry,
    trilinear4_scatter,
)
from aoi3d.field.native_calls import flow_warp as _flow_warp
from aoi3d.field.native_calls import trilinear4 as _trilinear4

__all__ = ["flow_training_grads", "trilinear4", "usable", "warp"]


def usable(*tensors: torch.Tensor) -> bool:
    """Whether the kernels run on these tensors (float32 on the CPU, the library built)."""
    return native.grid_step_available(*tensors)


def trilinear4(table: torch.Tensor, points: torch.Tensor, aabb: torch.Tensor,
               shape: tuple[int, int, int]) -> torch.Tensor | None:
    """(P, 4): the raw trilinear interpolation of ``table`` (N, 4), a vertex grid of ``shape``
    spanning ``aabb``, at world ``points`` (P, 3), without gradient; None where the kernel
    cannot (the caller runs :func:`aoi3d.field.flow.trilinear`)."""
    if not usable(table, points, aabb) or table.ndim != 2 or table.shape[1] != 4:
        return None
    lib = native._lib()
    assert lib is not None
    return _trilinear4(lib, table.detach().contiguous(), points.detach().contiguous(),
                       grid_geometry(aabb, tuple(shape)))


def warp(flow: torch.Tensor, points: torch.Tensor, age_s: torch.Tensor, aabb: torch.Tensor,
         shape: tuple[int, int, int]) -> torch.Tensor | None:
    """(P, 3): ``points`` + ``age_s`` (P,) · v(points), v the first three columns of the
    velocity grid ``flow`` (N, 4) of ``shape`` spanning ``aabb``, without gradient; None where
    the kernel cannot."""
    if not usable(flow, points, age_s, aabb) or flow.ndim != 2 or flow.shape[1] != 4:
        return None
    lib = native._lib()
    assert lib is not None
    return _flow_warp(lib, flow.detach().contiguous(), points.detach().contiguous(),
                      age_s.detach().contiguous(), grid_geometry(aabb, tuple(shape)))


def flow_training_grads(table: torch.Tensor, aabb: torch.Tensor, shape: tuple[int, int, int],
                        flow: torch.Tensor, flow_shape: tuple[int, int, int],
                        env: torch.Tensor, up_axis: int, points: torch.Tensor,
                        warped: torch.Tensor, age_s: torch.Tensor, deltas: torch.Tensor,
                        ray_index: torch.Tensor, dirs: torch.Tensor, target: torch.Tensor,
                        sample_rgb_loss: float, opacity_loss: float, flow_smooth: float = 0.0
                        ) -> tuple[float, torch.Tensor, torch.Tensor, torch.Tensor,
                                   torch.Tensor]:
    """One training step of the ``flow`` backend, as its torch code computes it under autograd
    (:meth:`aoi3d.field.flow.FlowField.render_rays` and the trainer's loss, with the velocity
    grid's smoothness term of weight ``flow_smooth``), without autograd.

    The samples sit at ``points`` (P, 3) in the frames' time; ``warped`` = points +
    ``age_s``·v(points) are where the canonical grid ``table`` is read (``age_s`` (P,): each
    sample's age from the pivot in seconds, clipped; v: the velocity grid ``flow`` (M, 4),
    columns 0–2, of ``flow_shape``). Returns the MSE, the grid's row-sparse gradient (rows,
    values), the background's dense gradient and the velocity grid's dense gradient (M, 4;
    column 3 zero). Check :func:`usable` first.
    """
    lib = native._lib()
    assert lib is not None
    parts = native.grid_render_grads(table, aabb, shape, env, up_axis, warped, deltas,
                                     ray_index, dirs, target, sample_rgb_loss, opacity_loss)
    rows, values, g_velocity = flow_grid_backward(
        lib, table.detach().contiguous(), parts.points, parts.geometry, parts.grad_sigma,
        parts.grad_rgb, parts.rgb, parts.sigma_grad, age_s.contiguous())
    grad_flow = trilinear4_scatter(lib, flow.shape[0], points.detach().contiguous(),
                                   grid_geometry(aabb, tuple(flow_shape)), g_velocity)
    if flow_smooth > 0:
        entries = [max(0, n - 2) * 3 * math.prod(flow_shape) // n for n in flow_shape]
        scale = torch.tensor([2.0 * flow_smooth / e if e else 0.0 for e in entries])
        flow_smooth_grad(lib, flow.detach().contiguous(), tuple(flow_shape), scale, grad_flow)
    return parts.mse, rows, values, parts.grad_env, grad_flow
