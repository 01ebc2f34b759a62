"""The 3D viewer's core: what it draws, from the decisions and delivered frames (no bus, no
server, no threads; :mod:`services.viewer.runtime` feeds it and draws what it returns).

Per site it keeps the decision in force — each camera's AoI, the cameras it used, the policy
and its Γ — and the newest delivered frame of each camera (still encoded: decoded only when
drawn, as a small thumbnail). The geometry — a frustum per camera, the truth camera, the scene
box — comes from the dataset's cameras through :mod:`aoi3d.freeview` (the viewer's OpenCV
axes) and never changes during a run.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

from aoi3d.freeview import aoi_colour, frustum_fov_aspect, viser_pose
from aoi3d.scene.camera import Camera
from services.kit.codec import decode_decision, decode_frame
from services.kit.pb import aoi3d_pb2 as pb

__all__ = ["CameraState", "Frustum", "ViewerCore", "box_segments"]


@dataclass(frozen=True)
class Frustum:
    """Where a camera's frustum stands in the viewer (OpenCV axes) and its shape."""

    camera_id: int
    wxyz: tuple[float, float, float, float]
    position: tuple[float, float, float]
    fov: float
    aspect: float


@dataclass(frozen=True)
class CameraState:
    """A camera as the decision in force saw it."""

    camera_id: int
    aoi_ms: float
    colour: tuple[int, int, int]
    selected: bool


@dataclass
class _Site:
    decision: pb.Decision | None = None
    frames: dict[int, bytes] = field(default_factory=dict)
    """camera id → its newest delivered Frame (as received)."""
    frame_ms: dict[int, float] = field(default_factory=dict)
    version: int = 0
    """Moves on with every decision (the worker redraws when it changed)."""


def frustum_of(camera_id: int, camera: Camera) -> Frustum:
    wxyz, position = viser_pose(camera)
    fov, aspect = frustum_fov_aspect(camera)
    return Frustum(camera_id, tuple(float(v) for v in wxyz),  # type: ignore[arg-type]
                   tuple(float(v) for v in position), fov, aspect)  # type: ignore[arg-type]


def box_segments(aabb: np.ndarray) -> np.ndarray:
    """The 12 edges of the box ``aabb`` (2, 3) as (12, 2, 3) line segments."""
    lo, hi = np.asarray(aabb, dtype=np.float64).reshape(2, 3)
    corners = np.array([[(hi if i & 1 else lo)[0], (hi if i & 2 else lo)[1],
                         (hi if i & 4 else lo)[2]] for i in range(8)])
    edges = [(a, b) for a in range(8) for b in range(a + 1, 8)
             if bin(a ^ b).count("1") == 1]
    return np.stack([corners[[a, b]] for a, b in edges])


class ViewerCore:
    """See the module docstring. ``cameras``: the training cameras by id; ``truth``: the
    held-out (truth) camera; ``aabb``: the scene box (2, 3)."""

    def __init__(self, cameras: dict[int, Camera], truth: Camera, aabb: np.ndarray,
                 sites: list[str]) -> None:
        self.cameras = dict(cameras)
        self.truth = truth
        self.aabb = np.asarray(aabb, dtype=np.float64).reshape(2, 3)
        self.frustums = {c: frustum_of(c, cam) for c, cam in self.cameras.items()}
        self.truth_frustum = frustum_of(0, truth)
        self.sites = {s: _Site() for s in sites}
        diag = float(np.linalg.norm(self.aabb[1] - self.aabb[0]))
        self.frustum_scale = 0.06 * diag
        """World size of a frustum: small beside the box."""

    # ------------------------------------------------------------------ inputs
    def on_decision(self, site: str, payload: bytes) -> None:
        """Keep a decision as the one in force (the newest by time; Rejected when bad)."""
        msg = decode_decision(payload)
        s = self.sites[site]
        if s.decision is not None and msg.incarnation == s.decision.incarnation and \
                (msg.time_ms, msg.decision_id) <= (s.decision.time_ms, s.decision.decision_id):
            return
        s.decision = msg
        s.version += 1

    def on_frame(self, site: str, payload: bytes) -> int:
        """Keep a delivered frame as its camera's newest (validated, not decoded)."""
        frame = decode_frame(payload, frozenset(self.cameras))
        s = self.sites[site]
        if frame.generation_ms >= s.frame_ms.get(frame.camera_id, -math.inf):
            s.frames[frame.camera_id] = payload
            s.frame_ms[frame.camera_id] = frame.generation_ms
        return frame.camera_id

    # ------------------------------------------------------------------ outputs
    def version(self, site: str) -> int:
        return self.sites[site].version

    def states(self, site: str) -> dict[int, CameraState]:
        """Every camera's AoI, colour and whether the decision in force used it (grey and
        unused before the first decision)."""
        d = self.sites[site].decision
        gamma = d.gamma_ms if d is not None and d.HasField("gamma_ms") else None
        aoi = dict(zip(d.camera_ids, d.aoi_ms, strict=True)) if d is not None else {}
        used = {ref.camera_id for ref in d.selected} if d is not None else set()
        return {c: CameraState(c, float(aoi.get(c, math.nan)),
                               aoi_colour(float(aoi.get(c, math.nan)), gamma), c in used)
                for c in self.cameras}

    def thumbnail(self, site: str, camera_id: int, max_side: int = 96) -> np.ndarray | None:
        """The camera's newest delivered frame, shrunk to at most ``max_side`` pixels a side
        (uint8 H×W×3), None when none came."""
        payload = self.sites[site].frames.get(camera_id)
        if payload is None:
            return None
        rgb = decode_frame(payload).rgb()
        step = max(1, math.ceil(max(rgb.shape[:2]) / max_side))
        return np.ascontiguousarray(rgb[::step, ::step])

    def scene(self, site: str) -> dict:
        """What the viewer draws for ``site``, as JSON (GET /scene.json)."""
        d = self.sites[site].decision
        states = self.states(site)
        return {
            "site": site,
            "box": self.aabb.tolist(),
            "decision": None if d is None else {
                "decision_id": d.decision_id, "time_ms": d.time_ms, "policy": d.policy,
                "gamma_ms": d.gamma_ms if d.HasField("gamma_ms") else None,
                "selected": sorted(c for c, st in states.items() if st.selected)},
            "cameras": [{"camera_id": c, "aoi_ms": None if math.isnan(st.aoi_ms) else st.aoi_ms,
                         "colour": list(st.colour), "selected": st.selected,
                         "frame_ms": self.sites[site].frame_ms.get(c),
                         "position": list(self.frustums[c].position)}
                        for c, st in sorted(states.items())],
            "truth_camera": {"position": list(self.truth_frustum.position)},
        }
