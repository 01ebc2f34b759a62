"""Arrivals at the scheduler (see :mod:`services.recorder.replay`): when each recorded frame
counted for the scheduler's decisions — its delivery stamp, or the first decision that knew it
— and U(s) from them; and the frames a replayed job is given."""

from __future__ import annotations

import bisect
import math
from collections import defaultdict
from collections.abc import Callable, Iterable, Sequence
from dataclasses import dataclass

import numpy as np

from services.kit.pb import aoi3d_pb2 as pb
from services.recorder.recording import SiteRecord

__all__ = ["TOL_MS", "Arrival", "Arrivals", "arrivals", "job_frames"]

TOL_MS = 1e-6


@dataclass(frozen=True)
class Arrival:
    camera_id: int
    generation_ms: float
    arrival_ms: float
    frame: pb.Frame | None
    """None: a frame the scheduler knew from before the recording (no pixels)."""


class Arrivals:
    """U(s) from the frames that had arrived at the scheduler by s, per camera."""

    def __init__(self, camera_ids: Sequence[int], items: Iterable[Arrival]) -> None:
        self.camera_ids = tuple(camera_ids)
        by_cam: dict[int, list[Arrival]] = defaultdict(list)
        for a in items:
            by_cam[a.camera_id].append(a)
        self._times: dict[int, list[float]] = {}
        self._newest: dict[int, list[float]] = {}  # running max of generation time
        self._frames: dict[tuple[int, float], Arrival] = {}
        for cam, lst in by_cam.items():
            lst.sort(key=lambda a: a.arrival_ms)
            self._times[cam] = [a.arrival_ms for a in lst]
            self._newest[cam] = list(np.maximum.accumulate([a.generation_ms for a in lst]))
            for a in lst:
                self._frames.setdefault((cam, a.generation_ms), a)
        self.late = 0

    def newest_at(self, s_ms: float) -> np.ndarray:
        out = np.full(len(self.camera_ids), np.nan)
        for i, cam in enumerate(self.camera_ids):
            times = self._times.get(cam)
            if times:
                k = bisect.bisect_right(times, s_ms) - 1
                if k >= 0:
                    out[i] = self._newest[cam][k]
        return out

    def frame(self, camera_id: int, generation_ms: float) -> Arrival | None:
        return self._frames.get((camera_id, generation_ms))


def _snap(value: float, candidates: list[float]) -> float:
    k = bisect.bisect_left(candidates, value - 1e-3)
    if k < len(candidates) and abs(candidates[k] - value) <= 1e-3:
        return candidates[k]
    return value


def arrivals(rec: SiteRecord) -> Arrivals:
    """Each delivered frame's arrival at the scheduler (see the module docstring)."""
    if not rec.decisions:
        raise ValueError("the recording holds no decision")
    camera_ids = list(rec.decisions[0].camera_ids)
    gens: dict[int, list[float]] = defaultdict(list)
    for fr in rec.deliveries:
        gens[fr.camera_id].append(fr.generation_ms)
    for cam in gens:
        gens[cam].sort()
    times = [d.time_ms for d in rec.decisions]
    # U_rec(s) per decision and camera, snapped onto the recorded generation times
    known = []
    for d in rec.decisions:
        row = {}
        for cam, aoi in zip(d.camera_ids, d.aoi_ms, strict=True):
            if not math.isnan(aoi):
                row[cam] = _snap(d.time_ms - aoi, gens.get(cam, []))
        known.append(row)
    items: list[Arrival] = []
    late = 0
    for fr in rec.deliveries:
        cam, g, t_del = fr.camera_id, fr.generation_ms, fr.delivery_ms
        first = k = bisect.bisect_left(times, t_del)  # the first decision at or after it
        while k < len(times) and known[k].get(cam, -math.inf) < g - TOL_MS:
            k += 1
        if first == len(times) or k == first:
            arrival = t_del  # on time (or after the last decision)
        elif k < len(times):
            arrival, late = times[k], late + 1  # reached the scheduler after decision k-1
        else:
            arrival = math.inf  # no later decision knew it: it never counted
        items.append(Arrival(cam, g, arrival, fr))
    # what the scheduler knew at the first decision without a recorded frame behind it
    initial = known[0]
    recorded = {(fr.camera_id, fr.generation_ms) for fr in rec.deliveries}
    for cam, g in initial.items():
        if (cam, g) not in recorded:
            items.append(Arrival(cam, g, -math.inf, None))
    out = Arrivals(camera_ids, items)
    out.late = late
    return out


def job_frames(selected: Sequence[tuple[int, float]], used: Sequence[float] | None,
                arr: Arrivals, used_cameras: Sequence[int] = (),
                has_pixels: Callable[[pb.Frame], bool] = lambda f: bool(f.image.data),
                ) -> list[pb.Frame] | None:
    """The frames of a selection (those the live job carried, when ``used`` lists their
    generation times in selection order, and ``used_cameras`` their cameras — a recording
    from before Render.frame_camera_ids has generation times only, which every camera shares
    at k·C); None when one has no pixels in the recording (``has_pixels``: whether the
    recording holds a frame's pixels, by default whether it carries them)."""
    out, k = [], 0
    cams = list(used_cameras) if used is not None and len(used_cameras) == len(used) else None
    for cam, g in selected:
        if used is not None:
            if (k < len(used) and abs(used[k] - g) <= TOL_MS
                    and (cams is None or cams[k] == cam)):
                k += 1
            else:
                continue  # the live dispatcher did not hold it
        a = arr.frame(cam, g)
        if a is None or a.frame is None or not has_pixels(a.frame):
            return None
        out.append(a.frame)
    return out
