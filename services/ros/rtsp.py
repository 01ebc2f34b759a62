"""An IP camera for the tests and ``aoi3d ros2 rtsp``: a dataset's camera as H.264 pushed over
RTSP (RECORD) to an ingest listening there, and the rig file's entry that reads it."""

from __future__ import annotations

import threading
import time
from collections.abc import Callable

import numpy as np

from services.ros.robot import camera_name

__all__ = ["RtspPusher", "push_rtsp", "rtsp_camera_entry"]


class RtspPusher:
    """A camera that pushes H.264 over RTSP (RECORD) to ``url`` — to an ingest listening
    there (``listen: true``). Frames go out at their due wall time, their pts the wall time
    since the first frame, so the receiver's RTCP-mapped generation time is when each was
    due."""

    def __init__(self, url: str, width: int, height: int, *, crf: int = 12) -> None:
        import av

        self._out = av.open(url, mode="w", format="rtsp", options={"rtsp_transport": "tcp"})
        self._stream = self._out.add_stream("libx264", rate=30)
        self._stream.width, self._stream.height = width, height
        self._stream.pix_fmt = "yuv420p"
        self._stream.options = {"tune": "zerolatency", "preset": "ultrafast", "crf": str(crf)}
        from fractions import Fraction

        self._stream.codec_context.time_base = Fraction(1, 1000)
        self._t0: float | None = None
        try:
            self._out.start_encoding()  # connects (OSError when nobody listens)
        except BaseException:
            self._out.close()
            raise

    def send(self, rgb: np.ndarray, due_s: float) -> None:
        import av

        if self._t0 is None:
            self._t0 = due_s
        frame = av.VideoFrame.from_ndarray(np.ascontiguousarray(rgb, dtype=np.uint8),
                                           format="rgb24")
        frame.pts = round((due_s - self._t0) * 1000)
        from fractions import Fraction

        frame.time_base = Fraction(1, 1000)
        for packet in self._stream.encode(frame):
            self._out.mux(packet)

    def close(self) -> None:
        try:
            for packet in self._stream.encode():
                self._out.mux(packet)
        finally:
            self._out.close()


def rtsp_camera_entry(ds, camera_id: int, url: str, *, listen: bool = True) -> dict:
    """A rig file's entry for the dataset's camera ``camera_id`` streamed as H.264 to ``url``
    (static pose and intrinsics: an IP camera has no topics)."""
    c = ds.cameras[camera_id]
    return {"name": camera_name(camera_id), "url": url, "listen": listen,
            "intrinsics": {"fx": c.fx, "fy": c.fy, "cx": c.cx, "cy": c.cy, "width": c.width,
                           "height": c.height},
            "pose": {"c2w": [float(x) for x in np.asarray(c.c2w).ravel()],
                     "convention": "opengl"}}


def push_rtsp(ds, camera_id: int, url: str, *, period_ms: float = 30.0,
              time_scale: float = 1.0, stop: threading.Event | None = None,
              frames: int | None = None, duration_s: float | None = None,
              clock: Callable[[], float] = time.time) -> int:
    """An IP camera: the dataset's camera ``camera_id`` as H.264 pushed over RTSP to ``url``
    (an ingest listening there), frame k showing scene time k·period at wall start + k·period /
    time scale; returns the frames sent."""
    stop = stop or threading.Event()
    c = ds.cameras[camera_id]
    for attempt in range(20):  # a listener re-opens every few seconds: knock again
        try:
            pusher = RtspPusher(url, c.width, c.height)
            break
        except OSError:
            if attempt == 19 or stop.wait(0.5):
                raise
    period_wall_s = period_ms / 1000.0 / time_scale
    start, k, sent = clock(), 0, 0
    try:
        while not stop.is_set() and (frames is None or sent < frames):
            due = start + k * period_wall_s
            if duration_s is not None and due - start >= duration_s:
                break
            wait = due - clock()
            if wait > 0 and stop.wait(wait):
                break
            pusher.send(ds.frame(camera_id, ds.frame_index(k * period_ms)), due)
            sent += 1
            k += 1
    finally:
        pusher.close()
    return sent
