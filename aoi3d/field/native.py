"""Fused CPU kernels for the hot path of a reconstruction, with the torch code as fallback.

A reconstruction (100 steps of 1024 rays on the rotor scene, about 23k samples a step) is
made of many small torch operations; on the CPU each costs its dispatch and a pass over
memory, and the grid backend's step was ~28 ms, mostly in the trilinear gather's backward
(8 ``index_add_`` of 4 columns and the row-sparse bookkeeping), ``LazyAdam``'s row updates
and the volume renderer's float64 prefix sums. Two fused kernels in C
(``_native.c``) do the same work in one pass each:

- :func:`grid_query` — the ``grid`` backend's query: trilinear interpolation of its table,
  softplus and sigmoid; backward straight into the table's row-sparse gradient.
- :func:`volume_render` — NeRF's compositing of packed samples
  (:func:`aoi3d.field.render.volume_render`), forward and backward.

With the uniform sampler, the lat-long background, the per-sample colour loss and
``LazyAdam``'s updates fused too, what was left of a step was autograd's own bookkeeping
(graph, saved tensors, sparse gradient tensors; a third of the step): the ``grid`` backend
therefore takes its whole training step through these kernels without autograd
(:func:`grid_training_grads`, called by ``DenseGridField.train_step``), the gradients the
autograd path computes, from the same random draws.

The ``flow`` backend's kernels (``_native_flow.c``, included by ``_native.c``: one library)
are called through :mod:`aoi3d.field.native_flow`; :func:`grid_render_grads` is the part of the
grid's step they share.

The source is compiled at first use with the system C compiler (``$CC``, else ``cc`` or
``gcc``; ``-O3``, no Python or torch headers, a fraction of a second) into
``$AOI3D_CACHE/native`` (default ``~/.cache/aoi3d/native``, else the temporary directory),
named by the hash of the source and flags, and loaded with ctypes. Where there is no
compiler, or ``AOI3D_NATIVE=0``, or the tensors are not float32 on the CPU, or a gradient
is asked of something the kernels do not differentiate, the callers use their torch code:
same results up to float rounding order. :func:`available` says which path runs.
"""

from __future__ import annotations

import ctypes
import hashlib
import logging
import os
import shutil
import subprocess
import tempfile
from pathlib import Path
from typing import Any, NamedTuple

import torch

from aoi3d.atomic import atomic_path
from aoi3d.field.native_calls import (
    colour_error_backward,
    grid_backward,
    grid_forward,
    grid_geometry,
    latlong_backward,
    latlong_forward,
    ptr,
    volume_backward,
    volume_forward,
)

__all__ = ["GridRenderGrads", "adam_dense", "available", "grid_query", "grid_render_grads",
           "grid_step_available", "grid_training_grads",
           "latlong_background", "lazy_adam_rows", "sample_uniform", "volume_render",
           "weighted_colour_error"]

log = logging.getLogger(__name__)

_SOURCE = Path(__file__).with_name("_native.c")
_INCLUDED = (Path(__file__).with_name("_native_flow.c"),)
"""Files ``_native.c`` includes (their bytes are part of the library's name)."""
_FLAGS = ("-O3", "-fno-trapping-math", "-fno-math-errno", "-ffp-contract=off", "-std=c99",
          "-fPIC", "-shared")
_LIB: ctypes.CDLL | None = None
_TRIED = False

_P = ctypes.c_void_p
_I = ctypes.c_int64
_SIGNATURES: dict[str, tuple[Any, list[Any]]] = {
    "grid_query_forward": (None, [_P, _P, _I, _P, _P, _P, _P, _P, _P]),
    "grid_query_backward": (_I, [_P, _I, _P, _P, _P, _P, _P, _P, _P, _I, _P, _P, _P, _P]),
    "volume_render_forward": (None, [_P, _P, _P, _P, _I, _P, _I, _P, _P, _P, _P, _P]),
    "volume_render_backward": (None, [_P, _P, _P, _I, _P, _I, _P, _P, _P, _P, _P, _P, _P,
                                      _P, _P, _P, _P]),
    "lazy_adam_rows": (_I, [_P, _P, _P, _P, _P, _I, _I, ctypes.c_float, ctypes.c_float,
                              ctypes.c_float, ctypes.c_float, ctypes.c_float]),
    "adam_dense": (None, [_P, _P, _P, _P, _I, ctypes.c_float, ctypes.c_float, ctypes.c_float,
                          ctypes.c_float, ctypes.c_float]),
    "weighted_colour_error_forward": (ctypes.c_double, [_P, _P, _P, _I, _P]),
    "weighted_colour_error_backward": (None, [_P, _P, _P, _I, _P, ctypes.c_float, _P, _P]),
    "latlong_forward": (None, [_P, _I, _I, _P, _I, _I, _P]),
    "latlong_backward": (None, [_I, _I, _P, _I, _I, _P, _P, _P]),
    "sample_uniform_count": (_I, [_P, _P, _I, ctypes.c_float, _I, _P]),
    "sample_uniform_fill": (None, [_P, _P, _P, _P, _P, _I, ctypes.c_float, _P, _P, _P, _P]),
    "trilinear4_forward": (None, [_P, _P, _I, _P, _P, _P, _P]),
    "trilinear4_scatter": (None, [_P, _I, _P, _P, _P, _P, _P]),
    "flow_grid_backward": (_I, [_P, _I, _P, _P, _P, _P, _P, _P, _P, _P, _P, _I, _P, _P, _P, _P,
                                _P]),
    "flow_warp": (None, [_P, _P, _P, _I, _P, _P, _P, _P]),
    "flow_smooth_grad": (None, [_P, _P, _P, _P]),
}


def _cache_dirs() -> list[Path]:
    env = os.environ.get("AOI3D_CACHE")
    dirs = [Path(env) / "native"] if env else []
    dirs.append(Path.home() / ".cache" / "aoi3d" / "native")
    dirs.append(Path(tempfile.gettempdir()) / f"aoi3d-native-{os.getuid()}")
    return dirs


def _compiler() -> str | None:
    for name in (os.environ.get("CC"), "cc", "gcc"):
        if name and (path := shutil.which(name)):
            return path
    return None


def _build() -> ctypes.CDLL | None:
    source = _SOURCE.read_bytes() + b"".join(p.read_bytes() for p in _INCLUDED)
    digest = hashlib.sha256(source + " ".join(_FLAGS).encode()).hexdigest()[:16]
    name = f"aoi3d_native-{digest}.so"
    for folder in _cache_dirs():
        lib_path = folder / name
        if not lib_path.exists():
            cc = _compiler()
            if cc is None:
                log.info("no C compiler: the torch fallback of aoi3d.field.native runs")
                return None
            try:
                with atomic_path(lib_path) as tmp:  # concurrent builders agree
                    subprocess.run([cc, *_FLAGS, "-o", str(tmp), str(_SOURCE), "-lm"],
                                   check=True, capture_output=True, timeout=120)
            except (OSError, subprocess.SubprocessError) as exc:
                log.info("could not build %s in %s (%s)", name, folder, exc)
                continue
        try:
            lib = ctypes.CDLL(str(lib_path))
        except OSError as exc:
            log.info("could not load %s (%s)", lib_path, exc)
            continue
        for fn, (restype, argtypes) in _SIGNATURES.items():
            getattr(lib, fn).restype = restype
            getattr(lib, fn).argtypes = argtypes
        return lib
    return None


def _lib() -> ctypes.CDLL | None:
    global _LIB, _TRIED
    if not _TRIED:
        _TRIED = True
        if os.environ.get("AOI3D_NATIVE", "1") != "0":
            try:
                _LIB = _build()
            except Exception as exc:  # never worse than the torch path
                log.warning("aoi3d.field.native disabled: %s", exc)
                _LIB = None
    return _LIB


def available() -> bool:
    """Whether the fused kernels are compiled and loaded (else the torch code runs)."""
    return _lib() is not None


def _usable(*tensors: torch.Tensor) -> bool:
    return all(t.device.type == "cpu" and t.dtype == torch.float32 for t in tensors) and (
        _lib() is not None
    )


# --- the grid's query ------------------------------------------------------------------------


class _GridQuery(torch.autograd.Function):
    @staticmethod
    def forward(ctx: Any, table: torch.Tensor, points: torch.Tensor, lo: torch.Tensor,
                factor: torch.Tensor, shape: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        lib = _lib()
        assert lib is not None
        sigma, rgb, sigma_grad = grid_forward(lib, table, points, (lo, factor, shape))
        ctx.save_for_backward(points, lo, factor, shape, rgb, sigma_grad)
        ctx.n_rows = table.shape[0]
        return sigma, rgb

    @staticmethod
    def backward(ctx: Any, grad_sigma: torch.Tensor | None,
                 grad_rgb: torch.Tensor | None) -> tuple[Any, ...]:
        lib = _lib()
        assert lib is not None
        points, lo, factor, shape, rgb, sigma_grad = ctx.saved_tensors
        n_rows = ctx.n_rows
        gs = None if grad_sigma is None else grad_sigma.contiguous()
        gc = None if grad_rgb is None else grad_rgb.contiguous()
        rows, values = grid_backward(lib, n_rows, points, (lo, factor, shape), gs, gc, rgb,
                                      sigma_grad)
        grad = torch.sparse_coo_tensor(rows[None], values, (n_rows, 4), is_coalesced=True,
                                       check_invariants=False)
        return grad, None, None, None, None


def grid_query(table: torch.Tensor, points: torch.Tensor, aabb: torch.Tensor,
               shape: tuple[int, int, int]) -> tuple[torch.Tensor, torch.Tensor] | None:
    """σ = softplus and rgb = sigmoid of the trilinear interpolation of ``table`` (N, 4) — a
    vertex grid of ``shape`` spanning ``aabb`` (2, 3), row-major — at world ``points`` (P, 3),
    with a row-sparse gradient for ``table``; None where the kernels cannot (the caller runs
    its torch code: :func:`aoi3d.field.encodings.interpolate` and the activations)."""
    if not _usable(table, points, aabb) or table.ndim != 2 or table.shape[1] != 4:
        return None
    if points.requires_grad or len(shape) != 3:
        return None
    table = table if table.is_contiguous() else table.contiguous()
    return _GridQuery.apply(table, points.contiguous(), *grid_geometry(aabb, tuple(shape)))


# --- volume rendering -----------------------------------------------------------------------


class _VolumeRender(torch.autograd.Function):
    @staticmethod
    def forward(ctx: Any, sigma: torch.Tensor, rgb: torch.Tensor, background: torch.Tensor,
                deltas: torch.Tensor, ray_index: torch.Tensor) -> tuple[torch.Tensor, ...]:
        lib = _lib()
        assert lib is not None
        color, transmittance, weights, alpha, before = volume_forward(
            lib, sigma, rgb, background, deltas, ray_index)
        ctx.save_for_backward(rgb, deltas, ray_index, background, transmittance, weights, alpha,
                              before)
        return color, transmittance, weights, alpha

    @staticmethod
    def backward(ctx: Any, g_color: torch.Tensor | None, g_trans: torch.Tensor | None,
                 g_weights: torch.Tensor | None, g_alpha: torch.Tensor | None) -> tuple[Any, ...]:
        lib = _lib()
        assert lib is not None
        grads = tuple(None if g is None else g.contiguous()
                      for g in (g_color, g_trans, g_weights, g_alpha))
        grad_sigma, grad_rgb, grad_bg = volume_backward(lib, ctx.saved_tensors, grads)
        return grad_sigma, grad_rgb, grad_bg, None, None


def volume_render(sigma: torch.Tensor, rgb: torch.Tensor, deltas: torch.Tensor,
                  ray_index: torch.Tensor, background: torch.Tensor
                  ) -> tuple[torch.Tensor, ...] | None:
    """Colour (R, 3), transmittance (R,), weights (P,) and opacity (P,) of packed samples, as
    :func:`aoi3d.field.render.volume_render` computes them (shapes checked there); None where
    the kernels cannot (then that function's torch code runs)."""
    if not _usable(sigma, rgb, deltas, background) or ray_index.dtype != torch.int64:
        return None
    if deltas.requires_grad or ray_index.device.type != "cpu":
        return None
    return _VolumeRender.apply(sigma.contiguous(), rgb.contiguous(), background.contiguous(),
                               deltas.contiguous(), ray_index.contiguous())


# --- the background ---------------------------------------------------------------------------


class _LatLong(torch.autograd.Function):
    @staticmethod
    def forward(ctx: Any, env: torch.Tensor, dirs: torch.Tensor, up_axis: int) -> torch.Tensor:
        lib = _lib()
        assert lib is not None
        out = latlong_forward(lib, env, dirs, up_axis)
        ctx.save_for_backward(dirs, out)
        ctx.env_shape, ctx.up_axis = tuple(env.shape), up_axis
        return out

    @staticmethod
    def backward(ctx: Any, grad_out: torch.Tensor) -> tuple[Any, ...]:
        lib = _lib()
        assert lib is not None
        dirs, out = ctx.saved_tensors
        return (latlong_backward(lib, ctx.env_shape, dirs, ctx.up_axis, out,
                                  grad_out.contiguous()), None, None)


def latlong_background(env: torch.Tensor, dirs: torch.Tensor,
                       up_axis: int) -> torch.Tensor | None:
    """:func:`aoi3d.field.background.latlong_background` fused; None where the kernel cannot
    (then its torch code runs)."""
    if not _usable(env, dirs) or dirs.requires_grad or env.ndim != 3 or env.shape[2] != 3:
        return None
    return _LatLong.apply(env.contiguous(), dirs.contiguous(), int(up_axis))


# --- the per-sample colour loss ---------------------------------------------------------------


class _WeightedColourError(torch.autograd.Function):
    @staticmethod
    def forward(ctx: Any, colours: torch.Tensor, weights: torch.Tensor, target: torch.Tensor,
                ray_index: torch.Tensor) -> torch.Tensor:
        lib = _lib()
        assert lib is not None
        total = lib.weighted_colour_error_forward(colours.data_ptr(), weights.data_ptr(),
                                                  ray_index.data_ptr(), colours.shape[0],
                                                  target.data_ptr())
        ctx.save_for_backward(colours, weights, target, ray_index)
        return colours.new_tensor(total)

    @staticmethod
    def backward(ctx: Any, grad: torch.Tensor) -> tuple[Any, ...]:
        lib = _lib()
        assert lib is not None
        colours, weights, target, ray_index = ctx.saved_tensors
        return (*colour_error_backward(lib, colours, weights, target, ray_index, float(grad)),
                None, None)


def weighted_colour_error(colours: torch.Tensor, weights: torch.Tensor, target: torch.Tensor,
                          ray_index: torch.Tensor) -> torch.Tensor:
    """Σ_i w_i ‖c_i − target[ray_i]‖² (a scalar): samples' ``colours`` (P, 3) and ``weights``
    (P,), their rays ``ray_index`` (P,) and the rays' ``target`` colours (R, 3) (no gradient
    for the target). Fused where the kernel can, else the same in torch."""
    tensors = (colours, weights, target)
    if (_usable(*tensors) and ray_index.dtype == torch.int64 and ray_index.device.type == "cpu"
            and not target.requires_grad and colours.ndim == 2 and colours.shape[1] == 3):
        return _WeightedColourError.apply(colours.contiguous(), weights.contiguous(),
                                          target.contiguous(), ray_index.contiguous())
    err = ((colours - target.index_select(0, ray_index)) ** 2).sum(dim=1)
    return (weights * err).sum()


# --- LazyAdam ---------------------------------------------------------------------------------
def lazy_adam_rows(param: torch.Tensor, exp_avg: torch.Tensor, exp_avg_sq: torch.Tensor,
                   rows: torch.Tensor, values: torch.Tensor, beta1: float, beta2: float,
                   step_size: float, root_bias: float, eps: float) -> bool:
    """:class:`aoi3d.field.optim.LazyAdam`'s update of ``rows`` (int64) of the 2-D ``param``
    and its moments from the gradient ``values`` (rows, C), in place; False (nothing done)
    where the kernel cannot — rows not strictly increasing (duplicates to sum first), tensors
    it does not take: the caller runs its torch code."""
    tensors = (param, exp_avg, exp_avg_sq, values)
    if not _usable(*tensors) or param.ndim != 2 or rows.dtype != torch.int64:
        return False
    if values.shape != (rows.shape[0], param.shape[1]):
        return False
    if not all(t.is_contiguous() for t in (param, exp_avg, exp_avg_sq)):
        return False
    lib = _lib()
    assert lib is not None
    values = values.contiguous()
    rows = rows.contiguous()
    return bool(lib.lazy_adam_rows(param.data_ptr(), exp_avg.data_ptr(), exp_avg_sq.data_ptr(),
                                   rows.data_ptr(), values.data_ptr(), rows.shape[0],
                                   param.shape[1], beta1, beta2, step_size, root_bias, eps))


def adam_dense(param: torch.Tensor, exp_avg: torch.Tensor, exp_avg_sq: torch.Tensor,
               grad: torch.Tensor, beta1: float, beta2: float, step_size: float,
               root_bias: float, eps: float) -> bool:
    """:class:`aoi3d.field.optim.LazyAdam`'s update of a parameter from a dense gradient, in
    place; False (nothing done) where the kernel cannot: the caller runs its torch code."""
    tensors = (param, exp_avg, exp_avg_sq, grad)
    if not _usable(*tensors) or not all(t.is_contiguous() for t in tensors):
        return False
    if not param.shape == exp_avg.shape == exp_avg_sq.shape == grad.shape:
        return False
    lib = _lib()
    assert lib is not None
    lib.adam_dense(param.data_ptr(), exp_avg.data_ptr(), exp_avg_sq.data_ptr(), grad.data_ptr(),
                   param.numel(), beta1, beta2, step_size, root_bias, eps)
    return True


# --- the uniform sampler --------------------------------------------------------------------
def sample_uniform(origins: torch.Tensor, dirs: torch.Tensor, t_near: torch.Tensor,
                   t_far: torch.Tensor, step: float, n_steps: int,
                   jitter: torch.Tensor | None) -> tuple[torch.Tensor, ...] | None:
    """points (P, 3), deltas (P,), ray_index (P,) of :func:`aoi3d.field.rays.sample_uniform`
    (``n_steps`` intervals at most per ray, as it computes them), the same numbers; None where
    the kernel cannot (then its torch code runs)."""
    tensors = [origins, dirs, t_near, t_far] + ([] if jitter is None else [jitter])
    if not _usable(*tensors) or any(t.requires_grad for t in tensors):
        return None
    lib = _lib()
    assert lib is not None
    o, d, tn, tf = (t.contiguous() for t in (origins, dirs, t_near, t_far))
    jit = None if jitter is None else jitter.contiguous()
    n_rays = o.shape[0]
    counts = torch.empty(n_rays, dtype=torch.int64)
    total = lib.sample_uniform_count(tn.data_ptr(), tf.data_ptr(), n_rays, step, n_steps,
                                     counts.data_ptr())
    points = o.new_empty(total, 3)
    deltas = o.new_empty(total)
    ray_index = torch.empty(total, dtype=torch.int64)
    lib.sample_uniform_fill(o.data_ptr(), d.data_ptr(), tn.data_ptr(), tf.data_ptr(), ptr(jit),
                            n_rays, step, counts.data_ptr(), points.data_ptr(),
                            deltas.data_ptr(), ray_index.data_ptr())
    return points, deltas, ray_index


# --- the grid's training step, without autograd ----------------------------------------------
def grid_step_available(*tensors: torch.Tensor) -> bool:
    """Whether :func:`grid_training_grads` can run on these tensors (float32 on the CPU, the
    kernels built): the grid's training step is then fused (``DenseGridField.train_step``)."""
    return _usable(*tensors)


def grid_training_grads(table: torch.Tensor, aabb: torch.Tensor, shape: tuple[int, int, int],
                        env: torch.Tensor, up_axis: int, points: torch.Tensor,
                        deltas: torch.Tensor, ray_index: torch.Tensor, dirs: torch.Tensor,
                        target: torch.Tensor, sample_rgb_loss: float, opacity_loss: float
                        ) -> tuple[float, torch.Tensor, torch.Tensor, torch.Tensor]:
    """One training step of the ``grid`` backend — query, background, volume rendering, loss
    and backward — as the kernels above do them under autograd, without autograd's graph (on
    the CPU a reconstruction's steps are small and autograd's bookkeeping is a third of their
    time).

    Inputs: the grid's ``table`` (N, 4), box and ``shape``; the background map ``env``; the
    packed samples (``points``, ``deltas``, ``ray_index``) of R rays with unit ``dirs`` (R, 3)
    and ``target`` colours (R, 3). The loss is the trainer's
    (:meth:`aoi3d.field.trainer.FieldTrainer.step`, without the age-weighted variant):

        MSE(C(r), C_gt) + sample_rgb_loss · Σ_i w_i ‖c_i − C_gt‖² / R + opacity_loss · Σ_i α_i / R

    Returns the MSE (float), the table's row-sparse gradient (rows increasing, values
    (rows, 4)) and the background's dense gradient. Check :func:`grid_step_available` first.
    """
    lib = _lib()
    assert lib is not None
    parts = grid_render_grads(table, aabb, shape, env, up_axis, points, deltas, ray_index,
                              dirs, target, sample_rgb_loss, opacity_loss)
    rows, values = grid_backward(lib, table.shape[0], parts.points, parts.geometry,
                                  parts.grad_sigma, parts.grad_rgb, parts.rgb, parts.sigma_grad)
    return parts.mse, rows, values, parts.grad_env


class GridRenderGrads(NamedTuple):
    """What :func:`grid_render_grads` computes: the batch's MSE, the gradients of the loss
    with respect to each sample's σ (P,) and colour (P, 3) and to the background map, and
    what the table's backward needs (the points, the kernel's geometry of the grid, the
    samples' colours and dσ/d raw density)."""

    mse: float
    grad_sigma: torch.Tensor
    grad_rgb: torch.Tensor
    grad_env: torch.Tensor
    points: torch.Tensor
    geometry: tuple[torch.Tensor, ...]
    rgb: torch.Tensor
    sigma_grad: torch.Tensor


def grid_render_grads(table: torch.Tensor, aabb: torch.Tensor, shape: tuple[int, int, int],
                      env: torch.Tensor, up_axis: int, points: torch.Tensor,
                      deltas: torch.Tensor, ray_index: torch.Tensor, dirs: torch.Tensor,
                      target: torch.Tensor, sample_rgb_loss: float, opacity_loss: float
                      ) -> GridRenderGrads:
    """:func:`grid_training_grads` up to the table's backward: query, background, volume
    rendering, loss, and the loss's gradients with respect to the samples' σ and colour and
    to the background map (the ``flow`` backend goes on from them to its velocity grid).
    Check :func:`grid_step_available` first."""
    lib = _lib()
    assert lib is not None
    table, env, points, deltas, ray_index, dirs, target = (
        t.detach().contiguous() for t in (table, env, points, deltas, ray_index, dirs, target))
    geometry = grid_geometry(aabb, tuple(shape))
    n_rays = dirs.shape[0]
    sigma, rgb, sigma_grad = grid_forward(lib, table, points, geometry)
    background = latlong_forward(lib, env, dirs, up_axis)
    color, transmittance, weights, alpha, before = volume_forward(
        lib, sigma, rgb, background, deltas, ray_index)
    diff = color - target
    mse = float(torch.mean(diff * diff))
    g_color = diff * (2.0 / max(diff.numel(), 1))  # d MSE / d colour
    g_weights = None
    g_sample_rgb = None
    if sample_rgb_loss > 0:
        g_sample_rgb, g_weights = colour_error_backward(lib, rgb, weights, target, ray_index,
                                                         sample_rgb_loss / n_rays)
    g_alpha = (weights.new_full(weights.shape, opacity_loss / n_rays) if opacity_loss > 0
               else None)
    saved = (rgb, deltas, ray_index, background, transmittance, weights, alpha, before)
    grad_sigma, grad_rgb, grad_bg = volume_backward(lib, saved,
                                                     (g_color, None, g_weights, g_alpha))
    if g_sample_rgb is not None:
        grad_rgb += g_sample_rgb
    grad_env = latlong_backward(lib, tuple(env.shape), dirs, up_axis, background, grad_bg)
    return GridRenderGrads(mse, grad_sigma, grad_rgb, grad_env, points, geometry, rgb,
                           sigma_grad)
