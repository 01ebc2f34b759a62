"""Figures of a live sweep (matplotlib, Agg backend, as :mod:`aoi3d.experiment.figures`):
the curve per policy with the virtual clock's beside it, and each policy's last render beside
the truth of the same time."""

from __future__ import annotations

import io
import math
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import TYPE_CHECKING, Any

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt
import numpy as np
from PIL import Image

from aoi3d.live.summary import Measurement
from aoi3d.metric import BY_NAME, LIVE

if TYPE_CHECKING:
    from aoi3d.scene import SceneDataset

__all__ = ["ViewPair", "plot", "plot_views", "view_pairs"]

ViewPair = tuple[Measurement, dict[str, Any], np.ndarray]
"""A window, the Quality entry of its render, and the render (RGB)."""


def plot(results: Sequence[dict[str, Any]], sim: Mapping[str, Any] | None, path: Path,
         title: str) -> Path:
    """PSNR (full and dynamic), SSIM, LPIPS, reward and cameras used per policy, live with
    95% CIs, the virtual clock's curve beside it; the PSNR panel has the live PSNR at display
    time too."""
    panels = [*((m, BY_NAME[m].axis_label) for m in LIVE), ("cameras_used", "cameras used")]
    x = list(range(len(results)))
    labels = [r["policy"] for r in results]
    fig, axes = plt.subplots(2, 3, figsize=(13, 7), constrained_layout=True)
    for ax, (metric, label) in zip(axes.flat, panels, strict=True):
        means = [r[metric]["mean"] for r in results]
        if all(m is None for m in means):
            ax.text(0.5, 0.5, f"{label}: not measured", ha="center", va="center",
                    transform=ax.transAxes)
            ax.set_axis_off()
            continue
        y = [math.nan if m is None else m for m in means]
        err = [r[metric]["ci95"] or 0.0 for r in results]
        ax.errorbar(x, y, yerr=err, fmt="o-", capsize=4, label="live (95% CI)")
        if metric == "psnr_db":  # what a viewer saw: the PSNR at display time beside it
            shown = [r.get("psnr_display_db", {}).get("mean") for r in results]
            if any(v is not None for v in shown):
                ax.errorbar(x, [math.nan if v is None else v for v in shown],
                            yerr=[r["psnr_display_db"]["ci95"] or 0.0 for r in results],
                            fmt="^:", capsize=4, color="tab:orange",
                            label="live, at display time")
        if sim is not None:
            sy = [sim.get(p, {}).get(metric, {}).get("mean") for p in labels]
            if any(v is not None for v in sy):
                se = [sim.get(p, {}).get(metric, {}).get("ci95") or 0.0 for p in labels]
                ax.errorbar(x, [math.nan if v is None else v for v in sy], yerr=se,
                            fmt="s--", capsize=4, color="grey", label="virtual clock")
        ax.set_xticks(x, labels)
        ax.set_ylabel(label)
        ax.grid(alpha=0.3)
        if metric == "psnr_db":
            ax.legend(fontsize=8)
    fig.suptitle(title)
    fig.savefig(path, dpi=120)
    plt.close(fig)
    return path


def view_pairs(measurements: Sequence[Measurement]) -> list[ViewPair]:
    """Each policy's last render (of its last window) that the metrics service scored, with
    its Quality entry; none where a window has no render or its render was not scored."""
    last = {m.policy: m for m in measurements}  # the last window of each policy
    pairs = []
    for m in last.values():
        entry = next((q for q in m.qualities if q["decision_id"] == m.render_decision), None)
        if not m.render_png or entry is None:
            continue
        pairs.append((m, entry, np.asarray(Image.open(io.BytesIO(m.render_png)).convert("RGB"))))
    return pairs


def plot_views(pairs: Sequence[ViewPair], ds: SceneDataset, path: Path, title: str) -> Path:
    """The renders of :func:`view_pairs` (top) beside the ground truth of the same time
    (bottom: the held-out camera's frame at the scene time the metrics service paired each
    render with)."""
    fig, axes = plt.subplots(2, len(pairs), figsize=(3.2 * len(pairs), 5.2), squeeze=False,
                             constrained_layout=True)
    for col, (m, entry, image) in enumerate(pairs):
        truth = ds.frame(ds.heldout_id, ds.frame_index(entry["scene_time_ms"]))
        axes[0, col].imshow(image, interpolation="nearest")
        axes[0, col].set_title(f"{m.policy} (repeat {m.repeat + 1})\n"
                               f"{entry['psnr_db']:.1f} dB, {entry['n_views']} views", fontsize=9)
        axes[1, col].imshow(truth, interpolation="nearest")
        axes[1, col].set_title(f"truth, t = {entry['time_ms']:.0f} ms", fontsize=9)
        for ax in axes[:, col]:
            ax.set_axis_off()
    fig.suptitle(title)
    fig.savefig(path, dpi=120)
    plt.close(fig)
    return path
