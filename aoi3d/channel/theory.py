r"""Exact long-run statistics of one discrete D/G/1/0 camera link (what ``simulate`` estimates).

Model. Slots of T_s = 1 ms. A camera generates a frame every C slots (C = ``period_ms``). The
link holds at most one frame: a frame generated while the previous one is in flight is
dropped; an accepted frame with transmission time Y is delivered Ys = max(1, ceil(Y)) slots
after its generation. A frame generated at the very slot the previous one is delivered is
accepted. AoI at slot t is Δ(t) = t − U(t), with U(t) the generation slot of the newest frame
delivered at or before t.

Accepted frames. If frame i is accepted at g_i and delivered at d_i = g_i + Ys_i, the next
accepted frame is the first generated at or after d_i: g_{i+1} = g_i + K_i·C with
K_i = ceil(Ys_i / C) >= 1. The K_i are i.i.d., so the accepted frames form a renewal process
with mean gap C·E[K]. Of the K_i frames generated in [g_i, g_{i+1}) one is accepted, hence

    drop ratio = 1 − 1/E[K],        deliveries per second = 1000 / (C·E[K]).

AoI. Take the cycle between deliveries i and i+1, slots d_i … d_{i+1} − 1; its length is
d_{i+1} − d_i = K_i·C + Ys_{i+1} − Ys_i, with mean C·E[K]. During it U = g_i, so the AoI runs
through the consecutive integers a … b − 1 with

    a = Ys_i,    b = K_i·C + Ys_{i+1},    (a < b since K_i·C >= Ys_i and Ys_{i+1} >= 1)

where Ys_{i+1} is independent of (Ys_i, K_i). By the renewal-reward theorem the long-run
share of slots with AoI = v is E[1{a <= v < b}] / (C·E[K]), and since a < b always,
1{a <= v < b} = 1{a <= v} − 1{b <= v}. So the AoI's stationary distribution is

    P(Δ = v) = [P(Ys <= v) − P(K·C + Ys' <= v)] / (C·E[K]),   Ys' an independent copy of Ys,

the distribution of B = K·C + Ys' being the convolution of the law of K·C with that of Ys.
Equivalently P(Δ <= x) = E[max(0, min(b, x + 1) − a)] / (C·E[K]). The sum of the AoI over a
cycle is (b − a)(a + b − 1)/2; with E[b² − a²] = C²E[K²] + 2C·E[K]·E[Ys] and E[b − a] = C·E[K]:

    E[Δ] = C·E[K²] / (2·E[K]) + E[Ys] − 1/2.

Numerics. The law of Ys is P(Ys = 1) = F_Y(1), P(Ys = s) = F_Y(s) − F_Y(s − 1) for s >= 2,
truncated where the tail mass falls below ``tail`` (the rest is lumped into the last slot).
Percentiles are the smallest integer v with P(Δ <= v) >= q — the definition
``channel_statistics`` uses on simulated slots, so deterministic delays agree exactly.
"""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass
from typing import Any

import numpy as np
from scipy import signal

from aoi3d.channel.delay import DelayDistribution, parse_delay

DEFAULT_TAIL = 1e-12
MAX_SUPPORT_SLOTS = 10_000_000
_Q_TOL = 1e-9


@dataclass(frozen=True)
class ChannelTheory:
    """Long-run statistics of one link (per camera)."""

    delay_spec: str
    period_ms: int
    mean_delay_slots: float  # E[Ys]
    mean_periods: float  # E[K]: periods between accepted frames
    drop_ratio: float
    delivered_per_s: float
    mean_aoi_ms: float
    p50_aoi_ms: float
    p99_aoi_ms: float

    def to_dict(self) -> dict[str, Any]:
        return asdict(self)


def _check_period(period_ms: int) -> int:
    if isinstance(period_ms, bool) or not isinstance(period_ms, int | np.integer) or period_ms < 1:
        raise ValueError(f"period_ms must be an int >= 1, got {period_ms!r}")
    return int(period_ms)


def slot_delay_pmf(delay: DelayDistribution | str, tail: float = DEFAULT_TAIL) -> np.ndarray:
    """``pmf[s] = P(Ys = s)`` for s = 0 … S (pmf[0] = 0), tail mass beyond S below ``tail``."""
    dist = parse_delay(delay)
    if not 0.0 < tail < 1e-3:
        raise ValueError(f"tail must be in (0, 1e-3), got {tail}")
    top = dist.ppf(1.0 - tail)
    if not math.isfinite(top) or top > MAX_SUPPORT_SLOTS:
        raise ValueError(
            f"delay {dist.spec} has too heavy a tail for the numeric theory "
            f"(its {1 - tail} quantile is {top:.3g} ms > {MAX_SUPPORT_SLOTS} ms)"
        )
    size = max(1, math.ceil(top)) + 2
    cdf = dist.cdf(np.arange(size, dtype=np.float64))
    pmf = np.zeros(size)
    pmf[1] = cdf[1]
    pmf[2:] = np.diff(cdf[1:])
    pmf = np.clip(pmf, 0.0, None)
    pmf[-1] += max(0.0, 1.0 - pmf.sum())
    normed: np.ndarray = pmf / pmf.sum()
    return normed


def _convolve(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    if len(a) * len(b) <= 20_000_000:
        return np.convolve(a, b)
    conv: np.ndarray = np.clip(signal.fftconvolve(a, b), 0.0, None)
    return conv


def aoi_pmf(
    delay: DelayDistribution | str, period_ms: int, tail: float = DEFAULT_TAIL
) -> np.ndarray:
    """``pmf[v]`` = long-run share of slots with AoI v ms (v = 0, 1, …)."""
    period = _check_period(period_ms)
    ys_pmf = slot_delay_pmf(delay, tail)
    s = np.arange(len(ys_pmf))
    k = -(-s // period)
    mean_k = float(ys_pmf @ k)
    kc_pmf = np.bincount(k * period, weights=ys_pmf)
    b_pmf = _convolve(kc_pmf, ys_pmf)  # law of B = K·C + Ys'
    cdf_a = np.cumsum(np.pad(ys_pmf, (0, len(b_pmf) - len(ys_pmf))))
    cdf_b = np.cumsum(b_pmf)
    pmf: np.ndarray = np.clip(cdf_a - cdf_b, 0.0, None) / (period * mean_k)
    return pmf


def aoi_cdf(
    delay: DelayDistribution | str,
    period_ms: int,
    x_ms: float | np.ndarray,
    tail: float = DEFAULT_TAIL,
) -> np.ndarray:
    """P(Δ <= x): the long-run share of slots with AoI at most x ms."""
    cdf = np.minimum(np.cumsum(aoi_pmf(delay, period_ms, tail)), 1.0)
    x = np.floor(np.asarray(x_ms, dtype=np.float64))
    idx = np.clip(x, -1, len(cdf) - 1).astype(np.int64)
    return np.where(idx < 0, 0.0, cdf[np.maximum(idx, 0)])


def quantile_from_pmf(pmf: np.ndarray, q: float) -> float:
    """Smallest v with sum(pmf[:v+1]) >= q."""
    if not 0.0 < q <= 1.0:
        raise ValueError(f"quantile level must be in (0, 1], got {q}")
    cdf = np.cumsum(pmf)
    v = int(np.searchsorted(cdf, q - _Q_TOL, side="left"))
    return float(min(v, len(pmf) - 1))


def channel_theory(
    delay: DelayDistribution | str, period_ms: int, tail: float = DEFAULT_TAIL
) -> ChannelTheory:
    """Drop ratio, deliveries/s and mean/p50/p99 AoI of one link, from the derivation above."""
    dist = parse_delay(delay)
    period = _check_period(period_ms)
    ys_pmf = slot_delay_pmf(dist, tail)
    s = np.arange(len(ys_pmf), dtype=np.float64)
    k = np.ceil(s / period)
    mean_ys = float(ys_pmf @ s)
    mean_k = float(ys_pmf @ k)
    mean_k2 = float(ys_pmf @ (k * k))
    pmf = aoi_pmf(dist, period, tail)
    return ChannelTheory(
        delay_spec=dist.spec,
        period_ms=period,
        mean_delay_slots=mean_ys,
        mean_periods=mean_k,
        drop_ratio=1.0 - 1.0 / mean_k,
        delivered_per_s=1000.0 / (period * mean_k),
        mean_aoi_ms=period * mean_k2 / (2.0 * mean_k) + mean_ys - 0.5,
        p50_aoi_ms=quantile_from_pmf(pmf, 0.50),
        p99_aoi_ms=quantile_from_pmf(pmf, 0.99),
    )
