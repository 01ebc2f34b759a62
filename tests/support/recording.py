"""Messages for the recorder's, player's and importer's tests: incompressible images (so sizes
are predictable), frames, and one message of every kind the recorder keeps."""

from __future__ import annotations

import contextlib
import math
import subprocess
from collections.abc import Iterator
from pathlib import Path

import numpy as np
import pytest

from aoi3d.scene.camera import Camera, look_at
from services.kit.codec import camera_to_pb, encode_frame, encode_png
from services.kit.keys import Keys
from services.kit.pb import aoi3d_pb2 as pb
from services.recorder.core import Recording

W, H = 24, 18
RUN = "rec"
K = Keys(RUN)


def camera() -> Camera:
    return Camera(c2w=look_at((0.0, -4.0, 1.0), (0.0, 0.0, 0.5)), fx=20.0, fy=20.0,
                  cx=W / 2, cy=H / 2, width=W, height=H)


def noise_image(seed: int) -> np.ndarray:
    """Incompressible pixels (a PNG about as big as raw), so sizes are predictable."""
    return np.random.default_rng(seed).integers(0, 256, (H, W, 3), dtype=np.uint8)


def frame(cam: int, gen_ms: float, *, delivery_ms: float = 0.0, seed: int = 0) -> bytes:
    return encode_frame(camera_id=cam, sequence=int(gen_ms // 30), generation_ms=gen_ms,
                        scene_time_ms=gen_ms, camera=camera(),
                        image=encode_png(noise_image(seed)), send_ms=gen_ms,
                        delivery_ms=delivery_ms)


def one_of_each(t_ms: float = 300.0) -> list[tuple[str, bytes]]:
    """A delivery, a truth frame, a decision, a render, a Quality and an Outcome."""
    cam = camera()
    from services.kit.codec import camera_to_pb

    pose, intr = camera_to_pb(cam)
    decision = pb.Decision(decision_id=7, time_ms=t_ms, camera_ids=[1, 2],
                           aoi_ms=[40.0, math.nan], policy="mat:70", incarnation=5,
                           selected=[pb.FrameRef(camera_id=1, sequence=8,
                                                 generation_ms=t_ms - 40, aoi_ms=40.0)])
    render = pb.Render(decision_id=7, time_ms=t_ms, pose=pose, intrinsics=intr,
                       image=encode_png(noise_image(9)), backend="grid", carry="fresh",
                       render_steps=30, decision_incarnation=5, seed=3,
                       aabb=[-1, -1, -1, 1, 1, 1], site="site1")
    quality = pb.Quality(decision_id=7, time_ms=t_ms, psnr_db=21.5, ssim=0.6, reward=0.7,
                         decision_incarnation=5, site="site1")
    outcome = pb.Outcome(decision_id=6, incarnation=5, site="site1", state="skipped",
                         reason=pb.END_REASON_SUPERSEDED)
    return [(K.edge_frame(1), frame(1, t_ms - 40, delivery_ms=t_ms - 5)),
            (K.truth, encode_frame(camera_id=0, sequence=10, generation_ms=t_ms,
                                   scene_time_ms=t_ms, camera=cam,
                                   image=encode_png(noise_image(1)))),
            (K.decision, decision.SerializeToString()), (K.render, render.SerializeToString()),
            (K.quality, quality.SerializeToString()), (K.outcome, outcome.SerializeToString())]

AABB = [-1.0, -1.0, -1.0, 1.0, 1.0, 1.0]


def recording_camera(x: float) -> Camera:
    return Camera(c2w=look_at((x, -4.0, 1.0), (0.0, 0.0, 0.5)), fx=20.0, fy=20.0,
                  cx=W / 2, cy=H / 2, width=W, height=H)


def frame_seed(cam: int, k: int) -> int:
    return 100 * cam + k


def write_recording(path: Path, *, lost=((2, 7),), moving: int | None = None, truth: bool = True,
            frames: int = 20) -> None:
    """Truth camera 0 and cameras 1, 2 generating every 30 ms (``lost``: (camera, k) never
    delivered), one render carrying the scene box."""
    rec = Recording(path)
    for k in range(frames):
        gen = 30.0 * k
        for cam in ((0, 1, 2) if truth else (1, 2)):
            if (cam, k) in lost:
                continue
            camera = recording_camera(float(cam) + (0.01 * k if cam == moving else 0.0))
            payload = encode_frame(camera_id=cam, sequence=k, generation_ms=gen,
                                   scene_time_ms=gen, camera=camera,
                                   image=encode_png(noise_image(frame_seed(cam, k))), send_ms=gen,
                                   delivery_ms=gen + 5.0 if cam else 0.0)
            rec.write(K.truth if cam == 0 else K.edge_frame(cam), payload, log_ns=k)
    pose, intr = camera_to_pb(recording_camera(0.0))
    render = pb.Render(decision_id=1, time_ms=300.0, pose=pose, intrinsics=intr,
                       image=encode_png(noise_image(9)), backend="grid", carry="fresh",
                       aabb=AABB, site="site1")
    rec.write(K.render, render.SerializeToString(), log_ns=frames)
    rec.close()


def write_long_recording(path: Path, *, steps: int, size: tuple[int, int] = (24, 18),
                         compression: str = "zstd", chunk_bytes: int = 1 << 20) -> int:
    """A recording of ``steps`` decision epochs 30 ms apart: truth camera 0 and cameras 1, 2
    delivering a ``size`` frame of noise each (incompressible: the file is about
    3 × steps × w × h × 3 bytes), and a ``mat:70`` decision after them. Its size in bytes."""
    w, h = size
    rng = np.random.default_rng(7)
    cams = {c: Camera(c2w=look_at((float(c), -4.0, 1.0), (0.0, 0.0, 0.5)), fx=20.0 * w / W,
                      fy=20.0 * w / W, cx=w / 2, cy=h / 2, width=w, height=h)
            for c in (0, 1, 2)}
    rec = Recording(path, compression=compression, chunk_bytes=chunk_bytes)
    for k in range(1, steps + 1):
        s = 30.0 * k
        for c in (0, 1, 2):
            pixels = rng.integers(0, 256, (h, w, 3), dtype=np.uint8)
            payload = encode_frame(camera_id=c, sequence=k, generation_ms=s - 2.0,
                                   scene_time_ms=s - 2.0, camera=cams[c],
                                   image=encode_png(pixels), send_ms=s - 2.0,
                                   delivery_ms=s - 1.0 if c else 0.0)
            rec.write(K.truth if c == 0 else K.edge_frame(c), payload, log_ns=3 * k + c)
        d = pb.Decision(decision_id=k, time_ms=s, camera_ids=[1, 2], aoi_ms=[2.0, 2.0],
                        policy="mat:70",
                        selected=[pb.FrameRef(camera_id=c, sequence=k, generation_ms=s - 2.0,
                                              aoi_ms=2.0) for c in (1, 2)])
        rec.write(K.decision, d.SerializeToString(), log_ns=3 * k + 3)
    pose, intr = camera_to_pb(cams[0])
    render = pb.Render(decision_id=1, time_ms=30.0, pose=pose, intrinsics=intr,
                       image=encode_png(rng.integers(0, 256, (h, w, 3), dtype=np.uint8)),
                       backend="grid", carry="fresh", aabb=AABB, site="site1")
    rec.write(K.render, render.SerializeToString(), log_ns=3 * steps + 4)
    return rec.close().bytes_written


@contextlib.contextmanager
def small_disk(tmp_path: Path, size_kib: int) -> Iterator[Path]:
    """A real filesystem of ``size_kib`` KiB (tmpfs; the tests run as root)."""
    mnt = tmp_path / "disk"
    mnt.mkdir()
    r = subprocess.run(["mount", "-t", "tmpfs", "-o", f"size={size_kib}k", "tmpfs", str(mnt)],
                       capture_output=True, text=True)
    if r.returncode != 0:
        pytest.skip(f"cannot mount a tmpfs here (not root?): {r.stderr.strip()}")
    try:
        yield mnt
    finally:
        subprocess.run(["umount", "-l", str(mnt)], check=False)
