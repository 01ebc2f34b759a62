"""Figures of the experiments (matplotlib, Agg backend: no display needed).

Each function takes the rows :func:`aoi3d.experiment.sweep.aggregate` produces (``<metric>``
and ``<metric>_ci95`` per row) and writes one PNG.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt
import numpy as np

from aoi3d.metric import LPIPS, METRICS, PSNR, PSNR_DYNAMIC, SSIM, names_of

__all__ = ["plot_compare", "plot_delay", "plot_tradeoff", "plot_views"]

_PANELS = (
    *((m.name, m.axis_label) for m in METRICS if not m.display),
    ("n_selected", "cameras used"),
    ("aoi_used_ms", "AoI of the used frames (ms)"),
)
"""The tradeoff figure's panels, in order (two rows of four): the scores at the decision's
time (:data:`aoi3d.metric.AT_DECISION`; ``dynamic-region``: over the pixels that moved,
:func:`aoi3d.quality.dynamic_mask`), then what the episodes selected."""
_PSNRS = names_of((PSNR, PSNR_DYNAMIC))


def _values(rows: Sequence[dict[str, Any]], metric: str) -> tuple[np.ndarray, np.ndarray]:
    mean = np.array([np.nan if r.get(metric) is None else r[metric] for r in rows], float)
    half = np.array([np.nan if r.get(f"{metric}_ci95") is None else r[f"{metric}_ci95"]
                     for r in rows], float)
    return mean, half


def _band(ax: Any, x: np.ndarray, mean: np.ndarray, half: np.ndarray, **kw: Any) -> None:
    line = ax.plot(x, mean, marker="o", ms=3, **kw)[0]
    ok = np.isfinite(half)
    if ok.any():
        ax.fill_between(x[ok], (mean - half)[ok], (mean + half)[ok], alpha=0.2,
                        color=line.get_color(), lw=0)


def plot_tradeoff(rows: Sequence[dict[str, Any]], path: Path, *, title: str,
                  reference: dict[str, Any] | None = None) -> Path:
    """Fig. 4: each metric against the MAT Γ (``gamma_ms`` of each row), mean and 95% band —
    the full-image scores on top, the dynamic-region PSNR and SSIM below them;
    ``reference`` (e.g. the policy ``all``) is drawn as a dashed line."""
    rows = sorted(rows, key=lambda r: r["gamma_ms"])
    x = np.array([r["gamma_ms"] for r in rows], float)
    fig, axes = plt.subplots(2, 4, figsize=(17, 7), constrained_layout=True)
    for ax, (metric, label) in zip(axes.flat, _PANELS, strict=True):
        mean, half = _values(rows, metric)
        if not np.isfinite(mean).any():
            ax.text(0.5, 0.5, f"{label}: not available", ha="center", va="center",
                    transform=ax.transAxes)
            ax.set_axis_off()
            continue
        _band(ax, x, mean, half, label="MAT Γ")
        if reference is not None and reference.get(metric) is not None:
            value = float(reference[metric])
            if math.isfinite(value):
                ax.axhline(value, ls="--", color="grey", lw=1, label=reference.get("policy", ""))
        if metric in _PSNRS and np.isfinite(mean).any():
            best = int(np.nanargmax(mean))
            ax.axvline(x[best], ls=":", color="k", lw=1, label=f"best Γ = {x[best]:g} ms")
        ax.set_xlabel("MAT Γ (ms)")
        ax.set_ylabel(label)
        ax.grid(alpha=0.3)
        if metric in _PSNRS:
            ax.legend(fontsize=8)
    fig.suptitle(title)
    fig.savefig(path, dpi=120)
    plt.close(fig)
    return path


def plot_views(images: Sequence[Sequence[tuple[str, np.ndarray]]], path: Path, *,
               title: str) -> Path:
    """Fig. 5: rows of (label, H×W×3 image) — typically the truth, then the novel view for
    several Γ — in one grid."""
    n_rows = len(images)
    n_cols = max(len(r) for r in images)
    h, w = images[0][0][1].shape[:2]
    scale = 2.2 / max(h, w) * 1.3
    fig, axes = plt.subplots(n_rows, n_cols, squeeze=False, constrained_layout=True,
                             figsize=(n_cols * w * scale + 0.4, n_rows * (h * scale + 0.5)))
    for i, row in enumerate(images):
        for j in range(n_cols):
            ax = axes[i][j]
            ax.set_axis_off()
            if j < len(row):
                label, image = row[j]
                ax.imshow(np.clip(image, 0, 255 if image.dtype == np.uint8 else 1.0),
                          interpolation="nearest")
                ax.set_title(label, fontsize=8)
    fig.suptitle(title, fontsize=10)
    fig.savefig(path, dpi=150)
    plt.close(fig)
    return path


def plot_delay(optima: Sequence[dict[str, Any]], curves: Sequence[dict[str, Any]], path: Path,
               *, title: str, metric: str = "psnr_db") -> Path:
    """Fig. 6: the optimal Γ against the mean delay E[Y] (left; the bar spans the optimum
        set, the Γ not significantly worse than the best by :mod:`aoi3d.experiment.optimum`),
    and ``metric`` against Γ for each delay (right)."""
    fig, (left, right) = plt.subplots(1, 2, figsize=(12, 4.5), constrained_layout=True)
    ey = np.array([o["mean_delay_ms"] for o in optima], float)
    best = np.array([o["best_gamma_ms"] for o in optima], float)
    lo = np.array([o["optimum_min_ms"] for o in optima], float)
    hi = np.array([o["optimum_max_ms"] for o in optima], float)
    left.errorbar(ey, best, yerr=[best - lo, hi - best], marker="o", capsize=3)
    left.set_xlabel("mean delay E[Y] (ms)")
    left.set_ylabel(f"optimal MAT Γ (ms), by {dict(_PANELS)[metric]}")
    left.grid(alpha=0.3)
    for delay in dict.fromkeys(c["delay"] for c in curves):
        rows = sorted((c for c in curves if c["delay"] == delay), key=lambda r: r["gamma_ms"])
        x = np.array([r["gamma_ms"] for r in rows], float)
        mean, half = _values(rows, metric)
        _band(right, x, mean, half, label=delay)
    right.set_xlabel("MAT Γ (ms)")
    right.set_ylabel(dict(_PANELS)[metric])
    right.grid(alpha=0.3)
    right.legend(fontsize=8)
    fig.suptitle(title)
    fig.savefig(path, dpi=120)
    plt.close(fig)
    return path


def plot_compare(rows: Sequence[dict[str, Any]], path: Path, *, title: str) -> Path:
    """The policies side by side: mean and 95% interval of each metric."""
    names = [r["policy"] for r in rows]
    fig, axes = plt.subplots(1, 6, figsize=(19, 3.8), constrained_layout=True)
    panels = (*names_of((PSNR, PSNR_DYNAMIC, SSIM, LPIPS)), "n_selected", "aoi_used_ms")
    labels = dict(_PANELS)
    for ax, metric in zip(axes, panels, strict=True):
        mean, half = _values(rows, metric)
        if not np.isfinite(mean).any():
            ax.text(0.5, 0.5, f"{labels[metric]}: not available", ha="center", va="center",
                    transform=ax.transAxes)
            ax.set_axis_off()
            continue
        ax.bar(range(len(names)), np.nan_to_num(mean), yerr=np.nan_to_num(half), capsize=3,
               color="tab:blue", alpha=0.8)
        ax.set_xticks(range(len(names)), names, rotation=30, ha="right", fontsize=8)
        ax.set_ylabel(labels[metric])
        finite = mean[np.isfinite(mean)]
        if metric in (*_PSNRS, SSIM.name) and finite.size:
            span = float(finite.max() - finite.min()) or 1.0
            ax.set_ylim(float(finite.min()) - span, float(finite.max()) + span)
        else:
            ax.set_ylim(bottom=0.0)
        ax.grid(alpha=0.3, axis="y")
    fig.suptitle(title)
    fig.savefig(path, dpi=120)
    plt.close(fig)
    return path
