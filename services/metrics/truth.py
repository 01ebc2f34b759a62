"""The metrics service's ground truth: the held-out camera's recent frames by generation time
(:class:`TruthRing`), and each frame decoded and its dynamic mask made once
(:class:`TruthImages`): a truth frame is paired by the render of its decision time and by the
renders shown at its time, and is the earlier frame of the next two frames' masks. Pure: no bus,
no threads (the scoring thread alone calls them)."""

from __future__ import annotations

import bisect
from collections import OrderedDict
from dataclasses import dataclass

import numpy as np

from aoi3d.quality import DYNAMIC_FRAMES, dynamic_mask
from services.kit.codec import decode_image
from services.kit.pb import aoi3d_pb2 as pb
from services.kit.rejected import Rejected, RejectReason

__all__ = ["TruthFrame", "TruthImages", "TruthRing"]

_TIME_TOL_MS = 1e-6  # generation times this close to t count as "at t" (float round-off)
_KEPT = 64  # truth frames kept decoded (and dynamic masks kept): about 2 s of truth


@dataclass(frozen=True)
class TruthFrame:
    """A ground-truth frame of the held-out camera, image still encoded."""

    generation_ms: float
    scene_time_ms: float
    image: pb.Image


class TruthRing:
    """The most recent ground-truth frames, by generation time (not thread-safe)."""

    def __init__(self, capacity: int) -> None:
        if capacity < 1:
            raise ValueError(f"capacity must be >= 1, got {capacity}")
        self._capacity = capacity
        self._times: list[float] = []  # sorted generation times
        self._frames: dict[float, TruthFrame] = {}

    def __len__(self) -> int:
        return len(self._times)

    @property
    def newest_ms(self) -> float | None:
        """Generation time of the newest frame held (None when empty)."""
        return self._times[-1] if self._times else None

    def add(self, frame: TruthFrame) -> None:
        """Keep ``frame`` (a repeat of a generation time replaces it); evict the oldest."""
        if frame.generation_ms not in self._frames:
            bisect.insort(self._times, frame.generation_ms)
        self._frames[frame.generation_ms] = frame
        while len(self._times) > self._capacity:
            del self._frames[self._times.pop(0)]

    def pair(self, time_ms: float, period_ms: float) -> TruthFrame:
        """The frame generated at ``time_ms``, else the newest in [time_ms − period_ms,
        time_ms]; raises ``Rejected(RejectReason.NO_TRUTH)`` when there is none."""
        exact = self._frames.get(time_ms)
        if exact is not None:
            return exact
        i = bisect.bisect_right(self._times, time_ms + _TIME_TOL_MS) - 1
        if i >= 0 and time_ms - self._times[i] <= period_ms + _TIME_TOL_MS:
            return self._frames[self._times[i]]
        held = (f"holding {len(self)} frame(s) generated in [{self._times[0]:g}, "
                f"{self._times[-1]:g}] ms" if self._times else "holding no frame")
        raise Rejected(RejectReason.NO_TRUTH,
                       f"no ground-truth frame generated at t = {time_ms:g} ms or "
                       f"within {period_ms:g} ms before it ({held})")

    def before(self, generation_ms: float, period_ms: float, count: int
               ) -> list[TruthFrame] | None:
        """The frames generated at ``generation_ms`` − k·``period_ms``, k = 1..``count``:
        for each, the newest generated in (that time − period/2, that time + period/2];
        None when any of them is missing."""
        half = period_ms / 2.0
        frames = []
        for k in range(1, count + 1):
            target = generation_ms - k * period_ms
            i = bisect.bisect_right(self._times, target + half) - 1
            if i < 0 or self._times[i] <= target - half:
                return None
            frames.append(self._frames[self._times[i]])
        return frames


class TruthImages:
    """Truth frames of a :class:`TruthRing` decoded, and their dynamic masks, each made once
    and kept for the :data:`_KEPT` most recently used (a frame is known by identity, so a
    frame the ring replaced is never mistaken for its successor)."""

    def __init__(self, ring: TruthRing, period_ms: float) -> None:
        self._ring = ring
        self.period_ms = period_ms
        self._images: OrderedDict[int, tuple[TruthFrame, np.ndarray]] = OrderedDict()
        self._masks: OrderedDict[tuple[int, ...], tuple[tuple[TruthFrame, ...], np.ndarray]] = \
            OrderedDict()

    def decoded(self, frame: TruthFrame) -> np.ndarray:
        """``frame``'s image decoded, once per frame: a truth frame is paired by the render
        of its decision time and by renders shown at its time (:class:`Rejected` when it
        does not decode)."""
        key = id(frame)
        hit = self._images.get(key)
        if hit is not None and hit[0] is frame:
            self._images.move_to_end(key)
            return hit[1]
        image = decode_image(frame.image)
        self._images[key] = (frame, image)
        while len(self._images) > _KEPT:
            self._images.popitem(last=False)
        return image

    def mask(self, truth: TruthFrame) -> np.ndarray | None:
        """The dynamic mask of ``truth`` (:func:`aoi3d.quality.dynamic_mask` of it and the
        truth one to K periods before it, :meth:`TruthRing.before`), once per such set of
        frames; None when one is missing, undecodable or of another size."""
        frames = self._ring.before(truth.generation_ms, self.period_ms, DYNAMIC_FRAMES)
        if frames is None:
            return None
        key = (id(truth), *(id(f) for f in frames))
        hit = self._masks.get(key)
        if hit is not None and all(a is b for a, b in zip(hit[0], (truth, *frames),
                                                             strict=True)):
            return hit[1]
        now = self.decoded(truth)
        previous = []
        for frame in frames:
            try:
                image = self.decoded(frame)
            except Rejected:
                return None
            if image.shape != now.shape:
                return None
            previous.append(image)
        mask = dynamic_mask(now, previous)
        self._masks[key] = ((truth, *frames), mask)
        while len(self._masks) > _KEPT:
            self._masks.popitem(last=False)
        return mask
