"""IP cameras and videos (issue 31, part 2): an ``rtsp://`` stream or a video file decoded with
PyAV (FFmpeg: H.264 and the rest), each frame with its generation time.

When was an RTSP frame generated? An RTP stream carries a media clock (the frame's timestamp,
90 kHz for video) that starts at a random value; the sender's RTCP *sender reports* pair one
media timestamp with the sender's wall clock (NTP time). FFmpeg maps the first sender report to
``start_time_realtime`` (µs since the Unix epoch) and the frames' times to seconds after it, so
with ``stamps: rtcp`` a frame's generation time is ``start_time_realtime + frame.time`` — the
sender's wall clock when it captured (or encoded) the frame, as good as the sender's clock and
its report (offset measured and shown, as for ROS stamps). A sender without sender reports
(``start_time_realtime`` unknown) falls back to the receipt. With ``stamps: receipt`` the
generation time is the receipt: the AoI then leaves out everything before the edge got the
frame (capture, encoding, the network), so it is a lower bound.

A video file plays in a loop at its own rate (scaled by the rig's time scale); a frame's
generation time is when it is due.
"""

from __future__ import annotations

import time
from collections.abc import Callable, Iterator
from dataclasses import dataclass

import numpy as np

__all__ = ["StreamEnded", "VideoFrame", "read_video"]

#: FFmpeg options of an RTSP reader: interleaved over TCP (no loss to a lossy network, no NAT
#: trouble). (Less probing — probesize, nobuffer — lost the decoder's parameters here.)
RTSP_OPTIONS = {"rtsp_transport": "tcp"}
LISTEN_TIMEOUT_S = 2
"""An RTSP listener gives up waiting for its camera after this long (and is opened again, so a
stop is seen)."""


class StreamEnded(Exception):
    """The stream closed or could not be opened (the reader opens it again)."""


@dataclass(frozen=True)
class VideoFrame:
    rgb: np.ndarray
    stamp_s: float
    """Generation time (wall s, the sender's clock)."""
    receipt_s: float
    width: int
    height: int


def _open(url: str, listen: bool, timeout_s: float):
    import av

    if url.lower().startswith(("rtsp://", "rtsps://")):
        options = dict(RTSP_OPTIONS)
        if listen:  # (PyAV's own timeout hangs a listener: FFmpeg's listen_timeout only)
            options |= {"rtsp_flags": "listen", "listen_timeout": str(LISTEN_TIMEOUT_S)}
            return av.open(url, options=options)
        options["timeout"] = str(int(timeout_s * 1e6))  # socket I/O, µs
        return av.open(url, options=options, timeout=timeout_s)
    return av.open(url)


def read_video(url: str, *, listen: bool = False, stamps: str = "rtcp",
               time_scale: float = 1.0, max_pixels: int = 2048 * 2048,
               stop: Callable[[], bool] = lambda: False, timeout_s: float = 5.0,
               clock: Callable[[], float] = time.time) -> Iterator[VideoFrame]:
    """The frames of one opening of ``url``, until it ends (:class:`StreamEnded`), ``stop()``
    says so, or a frame is larger than ``max_pixels`` (``ValueError``, before its pixels are
    converted; the stream's declared size is checked when it opens)."""
    import av

    rtsp = url.lower().startswith(("rtsp://", "rtsps://"))
    try:
        container = _open(url, listen, timeout_s)
    except (av.error.FFmpegError, OSError) as err:
        raise StreamEnded(f"{url}: {err}") from None
    try:
        video = container.streams.video[0] if container.streams.video else None
        if video is None:
            raise StreamEnded(f"{url}: no video stream")
        w, h = video.codec_context.width, video.codec_context.height
        if w * h > max_pixels:
            raise ValueError(f"a {w}x{h} stream exceeds {max_pixels} pixels")
        start_s = clock()
        first_time: float | None = None
        for packet in container.demux(video):
            if stop():
                return
            for frame in packet.decode():
                receipt = clock()
                if frame.width * frame.height > max_pixels:
                    raise ValueError(f"a {frame.width}x{frame.height} frame exceeds "
                                     f"{max_pixels} pixels")
                t = frame.time
                if rtsp:
                    realtime = container.start_time_realtime
                    known = stamps == "rtcp" and t is not None and realtime is not None \
                        and realtime > 0
                    stamp = realtime / 1e6 + t if known else receipt
                else:  # a file: due at its time since the loop began, scaled
                    if t is None:
                        continue
                    if first_time is None:
                        first_time = t
                    stamp = start_s + (t - first_time) / time_scale
                    wait = stamp - clock()
                    if wait > 0:
                        time.sleep(min(wait, 1.0))
                        if stop():
                            return
                    receipt = clock()
                yield VideoFrame(frame.to_ndarray(format="rgb24"), float(stamp), receipt,
                                 frame.width, frame.height)
        raise StreamEnded(f"{url}: the stream ended")
    except av.error.FFmpegError as err:
        raise StreamEnded(f"{url}: {err}") from None
    finally:
        container.close()
