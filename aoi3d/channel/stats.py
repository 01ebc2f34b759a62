"""Time-average statistics of a ``ChannelRun``: AoI over slots, drops, delivery rate.

AoI statistics are over the slots from each link's first delivery to the end of the run
(before it the AoI is unknown). Between deliveries i and i+1 (slots d_i … d_{i+1} − 1) the AoI
runs through d_i − g_i … d_{i+1} − 1 − g_i, so the count of slots at each AoI value is a
difference array over these segments — exact, and linear in the number of deliveries rather
than slots. Percentiles are of that distribution (the smallest AoI whose cumulative share of
slots reaches q, the same definition ``theory`` uses).
"""

from __future__ import annotations

from typing import Any

import numpy as np

from aoi3d.channel.batch import ChannelRun

_Q_TOL = 1e-9


def aoi_slot_counts(run: ChannelRun) -> list[np.ndarray]:
    """Per link, ``counts[v]`` = number of slots in [first delivery, duration) with AoI v ms."""
    out: list[np.ndarray] = []
    end = run.duration_ms
    for g, d in zip(run.gen_ms, run.delivery_ms, strict=True):
        m = int(np.searchsorted(d, end))  # deliveries inside the run
        if m == 0:
            out.append(np.zeros(0, dtype=np.int64))
            continue
        g, d = g[:m], d[:m]
        seg_end = np.append(d[1:], end)
        lo = d - g  # AoI at the delivery slot
        hi = seg_end - g  # one past the AoI just before the next delivery
        size = int(hi.max()) + 1
        diff = np.bincount(lo, minlength=size) - np.bincount(hi, minlength=size)
        out.append(np.cumsum(diff)[:-1].astype(np.int64))
    return out


def quantile_from_counts(counts: np.ndarray, q: float) -> float | None:
    """Smallest value v with (slots at AoI <= v) / (all slots) >= q; None if no slots."""
    total = counts.sum()
    if total == 0:
        return None
    cum = np.cumsum(counts) / total
    return float(np.searchsorted(cum, q - _Q_TOL, side="left"))


def _aoi_summary(counts: np.ndarray) -> dict[str, Any]:
    total = int(counts.sum())
    if total == 0:
        return {"aoi_slots": 0, "mean_aoi_ms": None, "p50_aoi_ms": None, "p99_aoi_ms": None}
    values = np.arange(len(counts), dtype=np.float64)
    return {
        "aoi_slots": total,
        "mean_aoi_ms": float(values @ counts / total),
        "p50_aoi_ms": quantile_from_counts(counts, 0.50),
        "p99_aoi_ms": quantile_from_counts(counts, 0.99),
    }


def _flow(offered: int, dropped: int, delivered: int, duration_s: float) -> dict[str, Any]:
    return {
        "offered": offered,
        "dropped": dropped,
        "delivered": delivered,
        "drop_ratio": dropped / offered if offered else None,
        "delivered_per_s": delivered / duration_s,
    }


def channel_statistics(run: ChannelRun) -> dict[str, Any]:
    """JSON-ready statistics of a run, overall and per link (``per_camera``).

    Keys: ``mean_aoi_ms``, ``p50_aoi_ms``, ``p99_aoi_ms`` (over slots from the first delivery
    on; None when nothing was delivered), ``drop_ratio`` (dropped / offered),
    ``delivered_per_s`` (per link; the overall value is the mean over links),
    ``offered``, ``dropped``, ``delivered`` (counts; overall = sums), ``aoi_slots`` (slots
    the AoI statistics cover). Overall only: ``n_cameras``, ``total_delivered_per_s``.
    Per link: ``link`` (index), ``phase_ms``, ``first_delivery_ms``.
    """
    duration_s = run.duration_ms / 1000.0
    counts = aoi_slot_counts(run)
    offered, dropped, delivered = run.offered, run.dropped, run.delivered
    first = run.first_delivery_ms
    per_camera: list[dict[str, Any]] = []
    for i, c in enumerate(counts):
        entry: dict[str, Any] = {
            "link": i,
            "phase_ms": int(run.phase_ms[i]),
            "first_delivery_ms": None if np.isnan(first[i]) else int(first[i]),
        }
        entry.update(_aoi_summary(c))
        entry.update(_flow(int(offered[i]), int(dropped[i]), int(delivered[i]), duration_s))
        per_camera.append(entry)
    size = max((len(c) for c in counts), default=0)
    pooled = np.zeros(size, dtype=np.int64)
    for c in counts:
        pooled[: len(c)] += c
    overall: dict[str, Any] = {"n_cameras": run.n_cameras}
    overall.update(_aoi_summary(pooled))
    overall.update(
        _flow(int(offered.sum()), int(dropped.sum()), int(delivered.sum()), duration_s)
    )
    overall["total_delivered_per_s"] = overall["delivered_per_s"]
    overall["delivered_per_s"] = overall["total_delivered_per_s"] / run.n_cameras
    overall["per_camera"] = per_camera
    return overall
