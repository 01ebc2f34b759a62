"""The whole rig file (:class:`Rig`): its cameras, truth camera or view, scene box, sizes,
clock and limits, checked together; and what the pipeline derives from it (camera ids on the
wire, the working size, the rendered camera)."""

from __future__ import annotations

import math
from typing import Annotated

import numpy as np
from pydantic import Field, field_validator, model_validator

from aoi3d.rigfile.spec import (
    CameraSpec,
    ClockSpec,
    IntrinsicsSpec,
    PoseSpec,
    SourceSpec,
    Strict,
    ViewSpec,
)
from aoi3d.scene.camera import Camera

__all__ = ["TRUTH_ID", "Rig", "scaled_camera"]

TRUTH_ID = 0
"""The held-out camera's id on the wire (the truth key); training cameras are 1..N in the order
of the file."""


class Rig(Strict):
    """A rig file. See docs/real-cameras.md."""

    source: SourceSpec = Field(default_factory=SourceSpec)
    cameras: list[CameraSpec] = Field(min_length=1, max_length=257)
    truth: str | None = Field(
        None, description="The camera held out as the ground truth (not trained on; the render "
                          "shows its view and is scored against it). None: renders are made "
                          "but cannot be scored.")
    view: ViewSpec | None = Field(None, description="The rendered view when there is no truth "
                                                    "camera (default: the first camera's).")
    aabb: list[float] = Field(min_length=6, max_length=6,
                              description="The scene box: min x, y, z, then max x, y, z (world "
                                          "units of the poses).")
    size: list[int] | None = Field(
        None, min_length=2, max_length=2,
        description="Working size [width, height]: every frame is resized to it (intrinsics "
                    "scaled). Default: the rendered view's own size.")
    time_scale: float = Field(1.0, gt=0, le=10,
                              description="Sim seconds per wall second of the run: 1 for a real "
                                          "robot; a played dataset's --time-scale.")
    truth_period_ms: float = Field(100.0, gt=0, le=60_000,
                                   description="Sim ms between two truth frames at most (the "
                                               "metrics service pairs a render with the truth "
                                               "frame of its time, or the newest this much "
                                               "older).")
    clock: ClockSpec = Field(default_factory=ClockSpec)
    pose_tolerance_s: float = Field(0.05, gt=0, le=10,
                                    description="A pose topic's message is matched to an image "
                                                "when their stamps differ by at most this.")
    max_image_bytes: int = Field(32 * 1024 * 1024, ge=1024, le=256 * 1024 * 1024,
                                 description="Larger samples are refused before decoding.")
    max_image_pixels: int = Field(2048 * 2048, ge=1, le=8192 * 8192,
                                  description="Larger images (width × height, as declared) are "
                                              "refused before decoding.")
    url_protocols: list[Annotated[str, Field(pattern=r"^[a-z][a-z0-9+.-]{0,31}$")]] = Field(
        default_factory=list, max_length=16,
        description="FFmpeg protocols a camera's url may use besides rtsp and rtsps (e.g. "
                    "[http, https, srt]); a url of any other protocol (concat:, file:, …) is "
                    "refused.")

    @field_validator("aabb")
    @classmethod
    def _box(cls, v: list[float]) -> list[float]:
        if not all(math.isfinite(x) for x in v) or any(v[i + 3] <= v[i] for i in range(3)):
            raise ValueError("6 finite numbers, min x y z then max x y z, each min < max")
        return v

    @field_validator("size")
    @classmethod
    def _size(cls, v: list[int] | None) -> list[int] | None:
        if v is not None and not all(8 <= x <= 4096 for x in v):
            raise ValueError("[width, height], each 8..4096 pixels")
        return v

    @model_validator(mode="after")
    def _consistent(self) -> Rig:
        names = [c.name for c in self.cameras]
        dupes = sorted({n for n in names if names.count(n) > 1})
        if dupes:
            raise ValueError(f"cameras: names must differ ({', '.join(dupes)} repeated)")
        accepted = {"rtsp", "rtsps", *self.url_protocols}
        for i, c in enumerate(self.cameras):
            if c.protocol is not None and c.protocol not in accepted:
                raise ValueError(
                    f"cameras[{i}].url: the {c.protocol}: protocol is not accepted (rtsp://, "
                    f"rtsps:// or a video file; name it in url_protocols to allow it)")
        topics = [c.image or c.url for c in self.cameras]
        if len(set(topics)) != len(topics):
            raise ValueError("cameras: two cameras share an image topic or url")
        if self.truth is not None:
            if self.truth not in names:
                raise ValueError(f"truth: no camera is named {self.truth!r} (cameras: "
                                 f"{', '.join(names)})")
            cam = self.cameras[names.index(self.truth)]
            if not (cam.pose.static and cam.intrinsics.static):
                raise ValueError(f"truth: the truth camera {self.truth!r} needs a static pose "
                                 "and intrinsics in the file (the render is made from its view "
                                 "before any frame arrives)")
            if self.view is not None:
                raise ValueError("view: the truth camera is the rendered view; give view only "
                                 "without truth")
        elif self.view is None:
            first = self.cameras[0]
            if not (first.pose.static and first.intrinsics.static):
                raise ValueError("view: without a truth camera, give view (a static pose and "
                                 "intrinsics), or give the first camera a static pose and "
                                 "intrinsics")
        if self.view is not None and not (self.view.pose.static and self.view.intrinsics.static):
            raise ValueError("view: needs a static pose and intrinsics, not topics")
        if len(self.train) < 1:
            raise ValueError("cameras: at least one camera besides the truth camera")
        if len(self.train) > 256:
            raise ValueError("cameras: at most 256 training cameras")
        return self

    # ---------------------------------------------------------------- derived
    @property
    def train(self) -> list[CameraSpec]:
        """The training cameras, ids 1..N in file order."""
        return [c for c in self.cameras if c.name != self.truth]

    def ids(self) -> dict[str, int]:
        """Camera name → id on the wire: the truth camera 0, the others 1..N in file order."""
        out = {c.name: i for i, c in enumerate(self.train, start=1)}
        if self.truth is not None:
            out[self.truth] = TRUTH_ID
        return out

    def camera(self, name: str) -> CameraSpec:
        return next(c for c in self.cameras if c.name == name)

    def _view_spec(self) -> tuple[IntrinsicsSpec, PoseSpec]:
        if self.truth is not None:
            cam = self.camera(self.truth)
            return cam.intrinsics, cam.pose
        if self.view is not None:
            return self.view.intrinsics, self.view.pose
        return self.cameras[0].intrinsics, self.cameras[0].pose

    @property
    def working_size(self) -> tuple[int, int]:
        """(width, height) of every frame on the pipeline's wire."""
        if self.size is not None:
            return int(self.size[0]), int(self.size[1])
        intr, _ = self._view_spec()
        assert intr.width is not None and intr.height is not None, "the view is static"
        return int(intr.width), int(intr.height)

    def view_camera(self) -> Camera:
        """The rendered (held-out) camera at the working size."""
        intr, pose = self._view_spec()
        assert (intr.fx is not None and intr.fy is not None and intr.cx is not None
                and intr.cy is not None and intr.width is not None
                and intr.height is not None), "the view is static (validated)"
        return scaled_camera(pose.static_c2w(), intr.fx, intr.fy, intr.cx, intr.cy,
                             (intr.width, intr.height), self.working_size)

    @property
    def scene_box(self) -> np.ndarray:
        return np.asarray(self.aabb, dtype=np.float64)


def scaled_camera(c2w: np.ndarray, fx: float, fy: float, cx: float, cy: float,
                  native: tuple[int, int], size: tuple[int, int]) -> Camera:
    """A camera whose intrinsics (for an image of ``native`` size) are scaled to ``size``."""
    sx, sy = size[0] / native[0], size[1] / native[1]
    return Camera(c2w=c2w, fx=fx * sx, fy=fy * sy, cx=cx * sx, cy=cy * sy,
                  width=size[0], height=size[1])
