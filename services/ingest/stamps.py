"""The ingest's time (docs/real-cameras.md): from a camera's stamp to the pipeline's sim clock.

A frame's generation time is its ``header.stamp`` − the camera's clock offset (robot − edge)
in force, its arrival the receipt at the edge; both go on the pipeline's sim clock,
``sim_ms = (wall_s − epoch_s) × time_scale × 1000``. The offset is measured per camera from
every sample (the 90th percentile of stamp − receipt over the last ones: the publisher's source
time from the rmw_zenoh attachment when there is one), shown, and used when the rig says
``offset_s: auto``.
"""

from __future__ import annotations

import math

from aoi3d.rigfile import ClockSpec
from services.ingest.camera import CameraState
from services.kit.rejected import Rejected, RejectReason

__all__ = ["Stamps"]


class Stamps:
    """The run's sim clock (``epoch_s``, ``time_scale``) and the rig's ``clock`` settings."""

    def __init__(self, epoch_s: float, time_scale: float, clock: ClockSpec) -> None:
        self.epoch_s = epoch_s
        self.time_scale = time_scale
        self.clock = clock

    def sim_ms(self, wall_s: float) -> float:
        return (wall_s - self.epoch_s) * self.time_scale * 1000.0

    def offset_in_force(self, state: CameraState) -> float:
        """Robot clock − edge clock in force for the camera: the rig's, or the estimate
        (``auto``; 0 before any sample)."""
        off = self.clock.offset_s
        if off == "auto":
            est = state.offset_estimate_s
            return 0.0 if math.isnan(est) else est
        return float(off)

    def stamp_ms(self, s: CameraState, stamp: float, receipt_s: float) -> tuple[float, float]:
        """(generation sim ms, age in wall s) of an image stamped ``stamp``."""
        clock = self.clock
        edge_stamp = stamp - self.offset_in_force(s)
        age = receipt_s - edge_stamp
        if age < -clock.future_tolerance_s:
            raise Rejected(RejectReason.STAMP_FUTURE,
                           f"stamped {-age:.3f} s after its receipt (tolerance "
                           f"{clock.future_tolerance_s:g} s; robot clock − edge clock "
                           f"measured {s.offset_estimate_s:+.3f} s, in force "
                           f"{self.offset_in_force(s):+.3f} s)")
        if age > clock.max_age_s:
            raise Rejected(RejectReason.STAMP_STALE,
                           f"stamped {age:.1f} s before its receipt (limit "
                           f"{clock.max_age_s:g} s)")
        if age < 0:
            edge_stamp, age = receipt_s, 0.0
        # The model's time is slotted (1 ms): a stamp maps to its nearest slot. Unrounded, a
        # phase-locked robot's frame of t = k·C lands at k·C + 3e-5 ms (float seconds since the
        # epoch), "after" a decision at k·C, and the metrics service paired that decision with
        # the truth frame one period older.
        gen = float(round(self.sim_ms(edge_stamp)))
        if gen < 0:
            raise Rejected(RejectReason.STAMP_BEFORE_RUN,
                           f"stamped {-gen / 1000 / self.time_scale:.1f} s "
                           "before the run's clock started")
        return gen, age
