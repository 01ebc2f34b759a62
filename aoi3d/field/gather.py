"""``row_gather``: weighted sums of rows of a parameter table, the lookup under the ``ngp`` hash
encoding and the ``tensorf`` planes and lines.

The forward is ``embedding_bag`` (the fastest weighted gather on the CPU; int32 row numbers
are twice as fast as int64); the backward scatters with ``index_add_`` (int64: int32 takes a
slow path there), corner by corner, into a dense gradient or, on request, a row-sparse one
over the rows the batch touched (for ``LazyAdam``). Inputs are corner-major, (K, M): each
corner's rows and weights are one contiguous vector, which the CPU vectorises.
Measured with torch 2.13 on one CPU thread, 36k points × 8 levels × 8 corners, 4 features:
forward 14 ms, backward 66 ms, where a (P, K)-major layout with broadcast products took
92 ms backward and autograd through ``embedding_bag`` far longer (its dense backward sorts).
"""

from __future__ import annotations

from typing import Any

import torch
import torch.nn.functional as F

__all__ = ["row_gather"]


class _RowGather(torch.autograd.Function):
    """out[m] = Σ_k w[k, m] · table[idx[k, m]] (corner-major inputs: each ``idx[k]`` and
    ``w[k]`` is one contiguous vector, which the CPU vectorises); the gradient for ``table`` is
    dense, or row-sparse (COO over the rows the batch touched) when ``sparse``."""

    @staticmethod
    def forward(
        ctx: Any, table: torch.Tensor, idx: torch.Tensor, w: torch.Tensor, sparse: bool
    ) -> torch.Tensor:
        ctx.save_for_backward(idx, w)
        ctx.n_rows, ctx.sparse = table.shape[0], sparse
        # embedding_bag is the fastest weighted gather on the CPU (int32 indices: 2× int64).
        return F.embedding_bag(
            idx.T.contiguous(), table, per_sample_weights=w.T.contiguous(), mode="sum"
        )

    @staticmethod
    def backward(ctx: Any, grad_out: torch.Tensor) -> tuple[torch.Tensor, None, None, None]:
        idx, w = ctx.saved_tensors
        n_rows, channels = ctx.n_rows, grad_out.shape[1]
        rows_of = idx.long()  # index_add_ takes a slow path with int32 indices
        if ctx.sparse:
            touched = torch.zeros(n_rows, dtype=torch.bool, device=idx.device)
            touched[rows_of.view(-1)] = True
            rows = touched.nonzero().squeeze(1)  # sorted, unique
            position = torch.empty(n_rows, dtype=torch.long, device=idx.device)
            position[rows] = torch.arange(rows.shape[0], device=idx.device)
            rows_of = position[rows_of]
            n_out = rows.shape[0]
        else:
            n_out = n_rows
        values = grad_out.new_zeros(n_out, channels)
        for k in range(idx.shape[0]):
            values.index_add_(0, rows_of[k], grad_out * w[k, :, None])
        if not ctx.sparse:
            return values, None, None, None
        grad = torch.sparse_coo_tensor(
            rows[None], values, (n_rows, channels), is_coalesced=True, check_invariants=False
        )
        return grad, None, None, None


def row_gather(
    table: torch.Tensor, idx: torch.Tensor, w: torch.Tensor, sparse: bool = False
) -> torch.Tensor:
    """Weighted sums of table rows: ``table`` (N, C), ``idx`` (K, M) int32/int64 row numbers,
    ``w`` (K, M) weights → (M, C), out[m] = Σ_k w[k, m] · table[idx[k, m]]. The gradient for
    ``table`` is row-sparse when ``sparse`` (for ``LazyAdam``), else dense."""
    if idx.shape != w.shape or idx.ndim != 2:
        raise ValueError(f"idx and w must be (K, M), got {tuple(idx.shape)}, {tuple(w.shape)}")
    return _RowGather.apply(table, idx, w, sparse)
