"""Video I/O with ffmpeg (from imageio-ffmpeg): probe, decode to RGB arrays, encode H.264.

The DyNeRF layout (:mod:`aoi3d.scene.dynerf`) reads and writes its ``camNN.mp4`` with these.
"""

from __future__ import annotations

import re
import subprocess
from collections.abc import Iterable
from dataclasses import dataclass
from pathlib import Path

import numpy as np

__all__ = ["DEFAULT_CRF", "VideoInfo", "decode_video", "encode_video", "probe_video"]

DEFAULT_CRF = 15
"""x264 constant rate factor of :func:`export_dynerf` (0 lossless … 51 worst; 15 ≈ visually
lossless)."""


def _ffmpeg_exe() -> str:
    try:
        import imageio_ffmpeg
    except ImportError as exc:  # pragma: no cover - depends on the environment
        raise ImportError(
            "reading or writing DyNeRF videos needs imageio-ffmpeg: pip install imageio-ffmpeg"
        ) from exc
    return imageio_ffmpeg.get_ffmpeg_exe()


@dataclass(frozen=True)
class VideoInfo:
    """What :func:`probe_video` learns without decoding: size, frame count, frame rate."""

    width: int
    height: int
    n_frames: int
    fps: float


_STREAM_RE = re.compile(r"Stream #\d+:\d+.*?: Video: (?P<rest>.*)")
_SIZE_RE = re.compile(r" (\d+)x(\d+)[, \[]")
_FPS_RE = re.compile(r" (\d+(?:\.\d+)?) fps")
_COUNT_RE = re.compile(r"frame=\s*(\d+)")


def _ffmpeg_error(stderr: bytes) -> str:
    lines = [ln.strip() for ln in stderr.decode(errors="replace").splitlines() if ln.strip()]
    return lines[-1] if lines else "no message"


def probe_video(path: str | Path) -> VideoInfo:
    """Size, exact frame count and frame rate of a video (packets copied, not decoded: fast)."""
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"video {path} is missing")
    proc = subprocess.run(
        [_ffmpeg_exe(), "-hide_banner", "-nostdin", "-i", str(path), "-map", "0:v:0",
         "-c", "copy", "-f", "null", "-"],
        capture_output=True, check=False,
    )
    text = proc.stderr.decode(errors="replace")
    stream = _STREAM_RE.search(text)
    if proc.returncode != 0 or stream is None:
        raise ValueError(f"{path.name} is not a readable video ({_ffmpeg_error(proc.stderr)})")
    size, fps = _SIZE_RE.search(stream["rest"]), _FPS_RE.search(stream["rest"])
    counts = _COUNT_RE.findall(text)
    if size is None or not counts:
        raise ValueError(f"{path.name}: ffmpeg reported no frame size or frame count")
    return VideoInfo(width=int(size[1]), height=int(size[2]), n_frames=int(counts[-1]),
                     fps=float(fps[1]) if fps else 0.0)


def decode_video(path: str | Path, size: tuple[int, int] | None = None,
                 n_frames: int | None = None) -> np.ndarray:
    """Decode a video to uint8 RGB (T, H, W, 3), scaled by ffmpeg's area filter to
    ``size = (W, H)`` (None: as stored), at most ``n_frames`` frames. The array is read-only.

    One ffmpeg process writes raw RGB to a pipe that is read whole (the approach of
    ``imageio_ffmpeg.read_frames``, minus its per-frame copies and its resize warning).
    """
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"video {path} is missing")
    if size is None:
        info = probe_video(path)
        size = (info.width, info.height)
    width, height = size
    cmd = [_ffmpeg_exe(), "-v", "error", "-nostdin", "-i", str(path), "-map", "0:v:0",
           "-vf", f"scale={width}:{height}:flags=area", "-pix_fmt", "rgb24", "-f", "rawvideo"]
    if n_frames is not None:
        cmd += ["-frames:v", str(n_frames)]
    proc = subprocess.run([*cmd, "-"], capture_output=True, check=False)
    if proc.returncode != 0:
        raise ValueError(f"{path.name} could not be decoded ({_ffmpeg_error(proc.stderr)})")
    frame_bytes = width * height * 3
    if len(proc.stdout) % frame_bytes:
        raise ValueError(f"{path.name}: ffmpeg returned a partial frame")
    return np.frombuffer(proc.stdout, dtype=np.uint8).reshape(-1, height, width, 3)


def encode_video(path: str | Path, frames: Iterable[np.ndarray], size: tuple[int, int],
                 fps: float, crf: int = DEFAULT_CRF) -> int:
    """Encode uint8 RGB frames of ``size = (W, H)`` as H.264 (yuv420p, like DyNeRF's videos)
    with imageio-ffmpeg; returns the number of frames written. W and H must be even."""
    width, height = size
    if width % 2 or height % 2:
        raise ValueError(f"H.264 yuv420p needs an even width and height, got {width}×{height}")
    if not 0 <= crf <= 51:
        raise ValueError(f"crf must be in [0, 51], got {crf}")
    _ffmpeg_exe()
    import imageio_ffmpeg

    writer = imageio_ffmpeg.write_frames(
        str(path), (width, height), fps=fps, codec="libx264", quality=None, macro_block_size=1,
        pix_fmt_out="yuv420p", output_params=["-crf", str(crf), "-preset", "medium"],
        ffmpeg_log_level="error",
    )
    writer.send(None)
    count = 0
    try:
        for frame in frames:
            if frame.shape != (height, width, 3) or frame.dtype != np.uint8:
                raise ValueError(f"frame {count}: expected uint8 {(height, width, 3)}, got "
                                 f"{frame.dtype} {frame.shape}")
            writer.send(np.ascontiguousarray(frame))
            count += 1
    finally:
        writer.close()
    return count
