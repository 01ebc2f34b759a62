"""Age of Information at the edge server.

For camera n, U_n(t) is the generation time of the newest frame delivered by t and the AoI is
Δ_n(t) = t − U_n(t). Before a camera's first delivery its AoI is unknown: NaN here (null in
JSON), never 0. A frame delivered at slot d counts from t = d on, so deliver frames when they
arrive and read ``aoi_ms(t)`` at the decision time t.
"""

from __future__ import annotations

import math
import threading
from collections.abc import Iterable

import numpy as np


class AoITracker:
    """Newest delivered generation time per camera, in ``camera_ids`` order. Thread-safe."""

    def __init__(self, camera_ids: Iterable[int]) -> None:
        ids = tuple(camera_ids)
        for cid in ids:
            if isinstance(cid, bool) or not isinstance(cid, int | np.integer):
                raise TypeError(f"camera ids must be ints, got {cid!r}")
        if len(set(ids)) != len(ids):
            raise ValueError(f"camera ids must be unique, got {list(ids)}")
        self._ids = tuple(int(c) for c in ids)
        self._index = {cid: i for i, cid in enumerate(self._ids)}
        self._newest = np.full(len(ids), np.nan)
        self._deliveries = np.zeros(len(ids), dtype=np.int64)
        self._lock = threading.Lock()

    @property
    def camera_ids(self) -> tuple[int, ...]:
        return self._ids

    def index(self, camera_id: int) -> int:
        """Position of ``camera_id`` in the AoI vector; ``KeyError`` for an unknown camera."""
        try:
            return self._index[camera_id]
        except KeyError:
            raise KeyError(
                f"unknown camera id {camera_id!r}; tracked ids: {list(self._ids)}"
            ) from None

    def deliver(self, camera_id: int, gen_ms: float) -> bool:
        """Record a delivered frame of ``camera_id`` generated at ``gen_ms``.

        Keeps the newest (U_n never goes back); returns whether this frame became the newest.
        """
        gen = float(gen_ms)
        if not math.isfinite(gen):
            raise ValueError(f"generation time must be finite, got {gen_ms!r}")
        i = self.index(camera_id)
        with self._lock:
            self._deliveries[i] += 1
            current = self._newest[i]
            if math.isnan(current) or gen > current:
                self._newest[i] = gen
                return True
            return False

    @property
    def newest_ms(self) -> np.ndarray:
        """U_n per camera (float64 copy, ``camera_ids`` order); NaN = nothing delivered yet."""
        with self._lock:
            return self._newest.copy()

    @property
    def deliveries(self) -> np.ndarray:
        """Frames delivered per camera so far (int64 copy), stale ones included."""
        with self._lock:
            return self._deliveries.copy()

    def aoi_ms(self, t_ms: float) -> np.ndarray:
        """Δ_n(t) = t − U_n in ms (float64, ``camera_ids`` order); NaN = unknown."""
        t = float(t_ms)
        if not math.isfinite(t):
            raise ValueError(f"time must be finite, got {t_ms!r}")
        return t - self.newest_ms

    def reset(self) -> None:
        """Forget every delivery (all AoIs unknown again)."""
        with self._lock:
            self._newest.fill(np.nan)
            self._deliveries.fill(0)

    def __len__(self) -> int:
        return len(self._ids)

    def __repr__(self) -> str:
        return f"AoITracker(camera_ids={list(self._ids)})"
