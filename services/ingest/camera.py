"""One camera of the ingest: its live state (intrinsics and poses received, clock offsets
measured, publishers' sequence numbers, images held) and counts, and what is read off it — the
pose and intrinsics in force for an image, a sequence number checked, its row of the status.

Pure, as the core that drives it (:mod:`services.ingest.core`)."""

from __future__ import annotations

import math
from collections import Counter, OrderedDict, deque
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from aoi3d.rigfile import TRUTH_ID, CameraSpec
from services import ros
from services.kit.rejected import Rejected, RejectReason

__all__ = ["OFFSET_WINDOW", "POSES_KEPT", "STREAMS_KEPT", "CameraState", "Wait"]

OFFSET_WINDOW = 64
"""Samples per camera over which the clock offset is estimated."""
POSES_KEPT = 256
"""Poses per camera kept for matching (8 s of a 30 Hz odometry)."""
STREAMS_KEPT = 16
"""Publishers per camera whose sequence numbers are followed."""


class Wait(Exception):
    """An image whose pose or intrinsics may still come: held, not refused (yet)."""


@dataclass
class CameraState:
    """One camera's live state and counts (read by the status and the metrics collector)."""

    spec: CameraSpec
    camera_id: int
    intrinsics: ros.Intrinsics | None = None
    poses: deque[tuple[float, np.ndarray]] = field(default_factory=lambda: deque(maxlen=POSES_KEPT))
    offsets: deque[float] = field(default_factory=lambda: deque(maxlen=OFFSET_WINDOW))
    last_seq: OrderedDict[tuple[str, bytes], int] = field(default_factory=OrderedDict)
    """The last sequence number of each publisher (topic, id): at most :data:`STREAMS_KEPT`,
    the least recently heard forgotten (a sender inventing ids cannot grow it)."""
    own_seq: int = 0
    received: Counter[str] = field(default_factory=Counter)
    """Samples received by kind."""
    rejected: Counter[str] = field(default_factory=Counter)
    """Samples rejected by reason."""
    published: int = 0
    lost: int = 0
    """Samples never received: gaps in the rmw_zenoh sequence numbers."""
    clamped: int = 0
    """Frames stamped ahead of their receipt (within the tolerance): generation = receipt."""
    last_stamp_s: float = math.nan
    last_receipt_s: float = math.nan
    last_age_s: float = math.nan
    publish_delay_s: float = math.nan
    """Source time (the rmw_zenoh attachment) − stamp of the last image: the robot's own
    delay between capture and publish."""
    ages: deque[float] = field(default_factory=lambda: deque(maxlen=OFFSET_WINDOW))
    held: list[tuple[float, np.ndarray, float, ros.Attachment | None, float]] = field(
        default_factory=list)
    """Images waiting for their pose or intrinsics: (deadline wall s, RGB, stamp, attachment,
    receipt wall s)."""

    @property
    def offset_estimate_s(self) -> float:
        """Robot clock − edge clock, estimated: the 90th percentile of (robot time − receipt)
        over the last samples — the offset if the fastest tenth of them took no time (NaN
        before any). Not the largest: a few samples stamped wrong cannot move it."""
        if not self.offsets:
            return math.nan
        ordered = sorted(self.offsets)
        return ordered[min(len(ordered) - 1, int(0.9 * len(ordered)))]

    @property
    def role(self) -> str:
        return "truth" if self.camera_id == TRUTH_ID else "train"

    def sequence(self, topic: str, att: ros.Attachment) -> None:
        """A sample of ``topic`` with rmw_zenoh's attachment: a gap counts as lost, an old
        sequence number is refused (``sequence_replayed``)."""
        stream = (topic, att.gid)
        last = self.last_seq.get(stream)
        if last is not None and att.sequence <= last:
            raise Rejected(RejectReason.SEQUENCE_REPLAYED, f"sequence {att.sequence} after {last} "
                                                           f"on {topic} (duplicate or reordered)")
        if last is not None and att.sequence > last + 1:
            self.lost += att.sequence - last - 1
        self.last_seq[stream] = att.sequence
        self.last_seq.move_to_end(stream)
        while len(self.last_seq) > STREAMS_KEPT:
            self.last_seq.popitem(last=False)

    def pose_at(self, stamp: float, final: bool, tolerance_s: float) -> np.ndarray:
        """The pose in force at ``stamp`` (the file's, or the topic's nearest within the
        tolerance: the spec's, else ``tolerance_s``); :class:`Wait` when one may still come
        (unless ``final``)."""
        spec = self.spec.pose
        if spec.static:
            return spec.static_c2w()
        tol = spec.tolerance_s or tolerance_s
        best, best_dt, newest = None, math.inf, -math.inf
        for t, c2w in self.poses:
            dt = abs(t - stamp)
            newest = max(newest, t)
            if dt < best_dt:
                best, best_dt = c2w, dt
        if (best is None or best_dt > tol) and not final and newest < stamp + tol:
            raise Wait  # a pose within the tolerance may still come
        if best is None or best_dt > tol:
            what = (f"no pose received yet on {spec.topic}" if best is None else
                    f"the nearest pose on {spec.topic} is {best_dt:.3f} s away")
            raise Rejected(RejectReason.NO_POSE, f"{what} (tolerance {tol:g} s)")
        return best

    def intrinsics_in_force(self, final: bool) -> ros.Intrinsics:
        """The file's intrinsics, or the newest CameraInfo's; :class:`Wait` before the first
        (unless ``final``)."""
        spec = self.spec.intrinsics
        if spec.static:
            assert (spec.fx is not None and spec.fy is not None and spec.cx is not None
                    and spec.cy is not None and spec.width is not None
                    and spec.height is not None), "static: all six values (validated)"
            return ros.Intrinsics(spec.fx, spec.fy, spec.cx, spec.cy, spec.width, spec.height)
        if self.intrinsics is None and not final:
            raise Wait
        if self.intrinsics is None:
            raise Rejected(RejectReason.NO_INTRINSICS,
                           f"no CameraInfo received yet on {spec.camera_info}")
        return self.intrinsics

    def status(self, now_s: float, offset_in_force: float) -> dict[str, Any]:
        """Its row of the status route (plain JSON values)."""
        spec = self.spec
        ages = sorted(self.ages)
        return {
            "name": spec.name, "id": self.camera_id, "role": self.role,
            "image": spec.image or spec.url,
            "image_type": spec.kind,
            "intrinsics": "static" if spec.intrinsics.static else spec.intrinsics.camera_info,
            "pose": "static" if spec.pose.static else spec.pose.topic,
            "received": dict(self.received), "published": self.published,
            "rejected": dict(self.rejected), "lost": self.lost, "clamped": self.clamped,
            "last_stamp_s": _num(self.last_stamp_s, nd=6),
            "since_last_s": _num(now_s - self.last_receipt_s),
            "age_ms_last": _num(self.last_age_s, 1000.0, 1),
            "age_ms_median": _num(ages[len(ages) // 2], 1000.0, 1) if ages else None,
            "clock_offset_s": _num(self.offset_estimate_s, nd=4),
            "clock_offset_in_force_s": _num(offset_in_force, nd=4),
            "publish_delay_ms": _num(self.publish_delay_s, 1000.0, 1),
        }


def _num(x: float | None, scale: float = 1.0, nd: int = 3) -> float | None:
    return None if x is None or not math.isfinite(x) else round(x * scale, nd)
