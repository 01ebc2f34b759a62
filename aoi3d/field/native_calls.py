"""The fused kernels' calls: tensors in, one C function of the loaded library (``lib``, from
:func:`aoi3d.field.native._lib`) called, tensors out. No loading and no torch fallback here:
:mod:`aoi3d.field.native` decides whether the kernels run and wraps these in autograd."""

from __future__ import annotations

import ctypes
import threading
from typing import Any

import torch


def ptr(t: torch.Tensor | None) -> int | None:
    return None if t is None else t.data_ptr()


WORKSPACE = threading.local()


def workspace(n_rows: int) -> tuple[torch.Tensor, torch.Tensor]:
    """This thread's zeroed scatter buffers of the grid's backward: dense (n_rows, 4) float32
    and touched (n_rows,) uint8, kept between calls (the kernel leaves them zero)."""
    cached = getattr(WORKSPACE, "buffers", None)
    if cached is None or cached[1].shape[0] != n_rows:
        cached = (torch.zeros(n_rows, 4), torch.zeros(n_rows, dtype=torch.uint8))
        WORKSPACE.buffers = cached
    return cached


def grid_forward(lib: ctypes.CDLL, table: torch.Tensor, points: torch.Tensor,
                  geometry: tuple[torch.Tensor, ...]) -> tuple[torch.Tensor, ...]:
    """σ (P,), rgb (P, 3) and dσ/d raw density (P,) of the grid's query (contiguous inputs)."""
    lo, factor, shape = geometry
    n = points.shape[0]
    sigma = points.new_empty(n)
    rgb = points.new_empty(n, 3)
    sigma_grad = points.new_empty(n)
    lib.grid_query_forward(table.data_ptr(), points.data_ptr(), n, lo.data_ptr(),
                           factor.data_ptr(), shape.data_ptr(), sigma.data_ptr(),
                           rgb.data_ptr(), sigma_grad.data_ptr())
    return sigma, rgb, sigma_grad


def grid_backward(lib: ctypes.CDLL, n_rows: int, points: torch.Tensor,
                   geometry: tuple[torch.Tensor, ...], grad_sigma: torch.Tensor | None,
                   grad_rgb: torch.Tensor | None, rgb: torch.Tensor,
                   sigma_grad: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """The table's row-sparse gradient: its rows (increasing) and values (rows, 4)."""
    lo, factor, shape = geometry
    dense, touched = workspace(n_rows)
    rows = torch.empty(n_rows, dtype=torch.int64)
    values = points.new_empty(n_rows, 4)
    count = lib.grid_query_backward(points.data_ptr(), points.shape[0], lo.data_ptr(),
                                    factor.data_ptr(), shape.data_ptr(), ptr(grad_sigma),
                                    ptr(grad_rgb), rgb.data_ptr(), sigma_grad.data_ptr(),
                                    n_rows, dense.data_ptr(), touched.data_ptr(),
                                    rows.data_ptr(), values.data_ptr())
    return rows[:count], values[:count]


GEOMETRY: dict[tuple[Any, ...], tuple[torch.Tensor, ...]] = {}


def grid_geometry(aabb: torch.Tensor, shape: tuple[int, ...]) -> tuple[torch.Tensor, ...]:
    """The kernel's view of a grid: box corner, vertex units per world unit (as
    :func:`aoi3d.field.encodings.vertex_coords` computes them) and shape; cached by value."""
    box = aabb.detach()
    key = (*box.reshape(-1).tolist(), *shape)
    cached = GEOMETRY.get(key)
    if cached is None:
        n1 = torch.tensor([n - 1 for n in shape], dtype=torch.float32)
        cached = (box[0].clone().contiguous(), (n1 / (box[1] - box[0])).contiguous(),
                  torch.tensor(shape, dtype=torch.int64))
        if len(GEOMETRY) > 64:
            GEOMETRY.clear()
        GEOMETRY[key] = cached
    return cached


def volume_forward(lib: ctypes.CDLL, sigma: torch.Tensor, rgb: torch.Tensor,
                    background: torch.Tensor, deltas: torch.Tensor,
                    ray_index: torch.Tensor) -> tuple[torch.Tensor, ...]:
    """Colour (R, 3), transmittance (R,), weights, alpha and the transmittance in front of
    each sample (P,) of packed samples (contiguous inputs)."""
    n, r = sigma.shape[0], background.shape[0]
    color = sigma.new_empty(r, 3)
    transmittance = sigma.new_empty(r)
    weights = sigma.new_empty(n)
    alpha = sigma.new_empty(n)
    before = sigma.new_empty(n)
    lib.volume_render_forward(sigma.data_ptr(), rgb.data_ptr(), deltas.data_ptr(),
                              ray_index.data_ptr(), n, background.data_ptr(), r,
                              color.data_ptr(), transmittance.data_ptr(), weights.data_ptr(),
                              alpha.data_ptr(), before.data_ptr())
    return color, transmittance, weights, alpha, before


def volume_backward(lib: ctypes.CDLL, saved: tuple[torch.Tensor, ...],
                     grads: tuple[torch.Tensor | None, ...]) -> tuple[torch.Tensor, ...]:
    """Gradients of σ (P,), rgb (P, 3) and the background (R, 3) from those of colour,
    transmittance, weights and alpha (contiguous or None); ``saved``: rgb, deltas, ray_index,
    background and :func:`volume_forward`'s transmittance, weights, alpha and before."""
    rgb, deltas, ray_index, background, transmittance, weights, alpha, before = saved
    n, r = weights.shape[0], background.shape[0]
    grad_sigma = weights.new_empty(n)
    grad_rgb = weights.new_empty(n, 3)
    grad_bg = weights.new_empty(r, 3)
    lib.volume_render_backward(rgb.data_ptr(), deltas.data_ptr(), ray_index.data_ptr(), n,
                               background.data_ptr(), r, transmittance.data_ptr(),
                               weights.data_ptr(), alpha.data_ptr(), before.data_ptr(),
                               *(ptr(g) for g in grads), grad_sigma.data_ptr(),
                               grad_rgb.data_ptr(), grad_bg.data_ptr())
    return grad_sigma, grad_rgb, grad_bg


def latlong_forward(lib: ctypes.CDLL, env: torch.Tensor, dirs: torch.Tensor,
                     up_axis: int) -> torch.Tensor:
    rows, cols = env.shape[:2]
    out = dirs.new_empty(dirs.shape[0], 3)
    lib.latlong_forward(env.data_ptr(), rows, cols, dirs.data_ptr(), dirs.shape[0], up_axis,
                        out.data_ptr())
    return out


def latlong_backward(lib: ctypes.CDLL, env_shape: tuple[int, ...], dirs: torch.Tensor,
                      up_axis: int, out: torch.Tensor, grad_out: torch.Tensor) -> torch.Tensor:
    grad_env = out.new_zeros(env_shape)
    lib.latlong_backward(env_shape[0], env_shape[1], dirs.data_ptr(), dirs.shape[0], up_axis,
                         out.data_ptr(), grad_out.data_ptr(), grad_env.data_ptr())
    return grad_env


def colour_error_backward(lib: ctypes.CDLL, colours: torch.Tensor, weights: torch.Tensor,
                           target: torch.Tensor, ray_index: torch.Tensor,
                           grad: float) -> tuple[torch.Tensor, torch.Tensor]:
    """Gradients of the colours (P, 3) and weights (P,) of ``grad`` · Σ_i w_i ‖c_i − t‖²."""
    grad_colours = torch.empty_like(colours)
    grad_weights = torch.empty_like(weights)
    lib.weighted_colour_error_backward(colours.data_ptr(), weights.data_ptr(),
                                       ray_index.data_ptr(), colours.shape[0], target.data_ptr(),
                                       grad, grad_colours.data_ptr(), grad_weights.data_ptr())
    return grad_colours, grad_weights


def trilinear4(lib: ctypes.CDLL, table: torch.Tensor, points: torch.Tensor,
               geometry: tuple[torch.Tensor, ...]) -> torch.Tensor:
    """(P, 4): the raw trilinear interpolation of ``table`` (N, 4) at world ``points``."""
    lo, factor, shape = geometry
    out = points.new_empty(points.shape[0], 4)
    lib.trilinear4_forward(table.data_ptr(), points.data_ptr(), points.shape[0], lo.data_ptr(),
                           factor.data_ptr(), shape.data_ptr(), out.data_ptr())
    return out


def trilinear4_scatter(lib: ctypes.CDLL, n_rows: int, points: torch.Tensor,
                       geometry: tuple[torch.Tensor, ...], g: torch.Tensor) -> torch.Tensor:
    """(n_rows, 4): the dense gradient of a table from that of its interpolation ``g`` (P, 4)
    at ``points``."""
    lo, factor, shape = geometry
    out = points.new_zeros(n_rows, 4)
    lib.trilinear4_scatter(points.data_ptr(), points.shape[0], lo.data_ptr(), factor.data_ptr(),
                           shape.data_ptr(), g.data_ptr(), out.data_ptr())
    return out


def flow_grid_backward(lib: ctypes.CDLL, table: torch.Tensor, points: torch.Tensor,
                       geometry: tuple[torch.Tensor, ...], grad_sigma: torch.Tensor,
                       grad_rgb: torch.Tensor, rgb: torch.Tensor, sigma_grad: torch.Tensor,
                       age_s: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """:func:`grid_backward` (the table's row-sparse gradient: rows, values) and, from the same
    corners, the loss's gradient with respect to each point times ``age_s`` (P, 4; column 3
    zero): the flow backend's velocity gradient at the points."""
    lo, factor, shape = geometry
    n_rows = table.shape[0]
    dense, touched = workspace(n_rows)
    rows = torch.empty(n_rows, dtype=torch.int64)
    values = points.new_empty(n_rows, 4)
    at_points = points.new_empty(points.shape[0], 4)
    count = lib.flow_grid_backward(points.data_ptr(), points.shape[0], lo.data_ptr(),
                                   factor.data_ptr(), shape.data_ptr(), grad_sigma.data_ptr(),
                                   grad_rgb.data_ptr(), rgb.data_ptr(), sigma_grad.data_ptr(),
                                   table.data_ptr(), age_s.data_ptr(), n_rows, dense.data_ptr(),
                                   touched.data_ptr(), rows.data_ptr(), values.data_ptr(),
                                   at_points.data_ptr())
    return rows[:count], values[:count], at_points


def flow_warp(lib: ctypes.CDLL, flow: torch.Tensor, points: torch.Tensor, age_s: torch.Tensor,
              geometry: tuple[torch.Tensor, ...]) -> torch.Tensor:
    """(P, 3): points + age_s · v(points), v the velocity grid ``flow`` (N, 4) interpolated."""
    lo, factor, shape = geometry
    out = points.new_empty(points.shape[0], 3)
    lib.flow_warp(flow.data_ptr(), points.data_ptr(), age_s.data_ptr(), points.shape[0],
                  lo.data_ptr(), factor.data_ptr(), shape.data_ptr(), out.data_ptr())
    return out


def flow_smooth_grad(lib: ctypes.CDLL, flow: torch.Tensor, shape: tuple[int, ...],
                     scale: torch.Tensor, grad: torch.Tensor) -> None:
    """``grad`` (N, 4) += the gradient of the velocity grid's smoothness term, ``scale`` (3,)
    float32: 2·weight / entries of each axis's second differences."""
    dims = torch.tensor(shape, dtype=torch.int64)
    lib.flow_smooth_grad(flow.data_ptr(), dims.data_ptr(), scale.data_ptr(), grad.data_ptr())
