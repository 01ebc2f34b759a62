"""``LazyAdam``: Adam that accepts dense and row-sparse gradients in one optimizer.

A dense gradient gets the usual Adam update. A sparse COO gradient (rows of a table, as the
grid's trilinear gather produces) updates only the rows it names: their moments and values,
with the bias correction of the global step count — the lazy Adam of ``torch.optim.SparseAdam``
and of DVGO's masked Adam. Untouched rows keep their values and moments, so a step costs in
proportion to the rows a batch reaches, not to the size of the grid.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Iterable
from typing import Any

import torch

from aoi3d.field import native

__all__ = ["LazyAdam"]


def _unique_rows(grad: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Rows and values of a row-sparse gradient, summing duplicate rows only when there are
    any (autograd marks even a coalesced gradient uncoalesced; sorting it again is costly)."""
    rows = grad._indices()[0]
    if not grad.is_coalesced() and rows.numel() > 1 and not bool((rows[1:] > rows[:-1]).all()):
        grad = grad.coalesce()
        rows = grad._indices()[0]
    return rows, grad._values()


class LazyAdam(torch.optim.Optimizer):
    """Adam (Kingma & Ba 2015) with lazy row updates for sparse gradients."""

    def __init__(
        self,
        params: Iterable[torch.Tensor] | Iterable[dict[str, Any]],
        lr: float = 1e-3,
        betas: tuple[float, float] = (0.9, 0.99),
        eps: float = 1e-15,
    ) -> None:
        if not lr >= 0:
            raise ValueError(f"lr must be >= 0, got {lr}")
        if not (0 <= betas[0] < 1 and 0 <= betas[1] < 1):
            raise ValueError(f"betas must be in [0, 1), got {betas}")
        super().__init__(params, {"lr": lr, "betas": betas, "eps": eps})

    @torch.no_grad()
    def step(self, closure: Callable[[], float] | None = None) -> float | None:  # type: ignore[override]
        loss = None
        if closure is not None:
            with torch.enable_grad():
                loss = closure()
        for group in self.param_groups:
            for p in group["params"]:
                if p.grad is not None:
                    self._update(group, p, p.grad)
        return loss

    @torch.no_grad()
    def update(self, param: torch.Tensor,
               grad: torch.Tensor | tuple[torch.Tensor, torch.Tensor]) -> None:
        """One Adam step of ``param`` (one of this optimizer's) from ``grad`` given directly,
        not through ``param.grad``: a dense or sparse COO tensor as :meth:`step` takes, or
        ``(rows, values)`` of a row-sparse gradient (rows int64 (n,) of the 2-D ``param``,
        values (n, C)). For training steps that compute their gradients without autograd
        (``DenseGridField.train_step``); the result is :meth:`step`'s with that gradient."""
        for group in self.param_groups:
            if any(q is param for q in group["params"]):
                self._update(group, param, grad)
                return
        raise ValueError("update: the tensor is not a parameter of this optimizer")

    def _update(self, group: dict[str, Any], p: torch.Tensor,
                grad: torch.Tensor | tuple[torch.Tensor, torch.Tensor]) -> None:
        lr, (beta1, beta2), eps = group["lr"], group["betas"], group["eps"]
        state = self.state[p]
        if not state:
            state["step"] = 0
            state["exp_avg"] = torch.zeros_like(p)
            state["exp_avg_sq"] = torch.zeros_like(p)
        state["step"] += 1
        t = state["step"]
        step_size = lr / (1 - beta1**t)
        root_bias = math.sqrt(1 - beta2**t)
        m, v = state["exp_avg"], state["exp_avg_sq"]
        if isinstance(grad, tuple) or grad.is_sparse:
            rows, g = grad if isinstance(grad, tuple) else (grad._indices()[0], grad._values())
            # the kernel checks that the rows are unique (sorted) itself:
            if native.lazy_adam_rows(p, m, v, rows, g, beta1, beta2, step_size, root_bias, eps):
                return
            if isinstance(grad, tuple):
                grad = torch.sparse_coo_tensor(rows[None], g, p.shape, check_invariants=False)
            rows, g = _unique_rows(grad)
            m_rows = m.index_select(0, rows).lerp_(g, 1 - beta1)
            v_rows = v.index_select(0, rows).mul_(beta2).addcmul_(g, g, value=1 - beta2)
            m.index_copy_(0, rows, m_rows)
            v.index_copy_(0, rows, v_rows)
            denom = v_rows.sqrt_().div_(root_bias).add_(eps)
            p.index_add_(0, rows, m_rows.div_(denom).mul_(-step_size))
        elif not native.adam_dense(p, m, v, grad, beta1, beta2, step_size, root_bias, eps):
            m.lerp_(grad, 1 - beta1)
            v.mul_(beta2).addcmul_(grad, grad, value=1 - beta2)
            denom = v.sqrt().div_(root_bias).add_(eps)
            p.addcdiv_(m, denom, value=-step_size)
