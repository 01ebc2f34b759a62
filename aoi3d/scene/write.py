"""Writing scene datasets in the project's layout (see :mod:`aoi3d.scene.dataset`).

:func:`generate_dataset` renders the turbine scene of a :class:`SceneConfig` to disk,
:func:`ensure_dataset` reuses what is there when it is whole and of that config, and
:func:`write_dataset` writes frames that already exist (a recording's, ``aoi3d scene
import``). Each writes into a hidden sibling directory and renames it into place when
complete, so an interrupted run never leaves something that looks like a dataset.
"""

from __future__ import annotations

import contextlib
import json
import logging
import multiprocessing
import os
import re
import shutil
from collections.abc import Callable, Iterable
from concurrent.futures import ProcessPoolExecutor, as_completed
from pathlib import Path
from typing import Any

import numpy as np
from PIL import Image

from aoi3d.atomic import atomic_dir
from aoi3d.scene.camera import Camera
from aoi3d.scene.dataset import (
    FORMAT_VERSION,
    TEST_JSON,
    TRAIN_JSON,
    Progress,
    SceneDataset,
    frame_file_relpath,
    load_dataset,
    png_problem,
)
from aoi3d.scene.placement import HELDOUT_ID, place_cameras
from aoi3d.scene.turbine import AABB, ROTOR_AABB, SCENE_VERSION, SceneConfig, TurbineScene

__all__ = ["CHUNK_FRAMES", "ensure_dataset", "generate_dataset", "write_dataset"]

CHUNK_FRAMES = 30
"""Frames of one camera rendered per batch (the unit of progress)."""

log = logging.getLogger("aoi3d.scene.dataset")  # the logger's name from before the split


def _transforms(
    camera_ids: Iterable[int], cameras: list[Camera], cfg: SceneConfig, aabb: np.ndarray
) -> dict[str, Any]:
    return _transforms_doc(camera_ids, cameras, cfg.n_frames, {
        "format_version": FORMAT_VERSION,
        "scene_version": SCENE_VERSION,
        "fps": cfg.fps,
        "n_frames": cfg.n_frames,
        "duration_s": cfg.duration_s,
        "aabb": np.asarray(aabb).tolist(),
        "heldout_id": HELDOUT_ID,
        "n_cameras": len(cameras),
        "config": cfg.to_dict(),
        "config_hash": cfg.config_hash,
    })


def _transforms_doc(
    camera_ids: Iterable[int], cameras: list[Camera], n_frames: int, block: dict[str, Any]
) -> dict[str, Any]:
    """A transforms file of ``camera_ids`` with ``n_frames`` each and the ``aoi3d`` block."""
    ids = list(camera_ids)
    ref = cameras[ids[0]]
    frames = []
    for cam_id in ids:
        cam = cameras[cam_id]
        own_intrinsics = (cam.fx, cam.fy, cam.cx, cam.cy, cam.width, cam.height) != (
            ref.fx,
            ref.fy,
            ref.cx,
            ref.cy,
            ref.width,
            ref.height,
        )
        for k in range(n_frames):
            entry: dict[str, Any] = {
                "file_path": frame_file_relpath(cam_id, k),
                "time": k / n_frames,
                "transform_matrix": cam.c2w.tolist(),
                "camera_id": cam_id,
                "frame_index": k,
            }
            if own_intrinsics:
                entry.update(
                    fl_x=cam.fx, fl_y=cam.fy, cx=cam.cx, cy=cam.cy, w=cam.width, h=cam.height
                )
            frames.append(entry)
    return {
        "camera_angle_x": ref.camera_angle_x,
        "fl_x": ref.fx,
        "fl_y": ref.fy,
        "cx": ref.cx,
        "cy": ref.cy,
        "w": ref.width,
        "h": ref.height,
        "frames": frames,
        "aoi3d": block,
    }


def _save_png(path: Path, image: np.ndarray) -> None:
    Image.fromarray(image).save(path, format="PNG", compress_level=3)


_TMP_RE = re.compile(r"^\.(?P<name>.+)\.(?:tmp|old)-(?P<pid>\d+)-[0-9a-f]{8}$")


def _remove_stale_temps(path: Path) -> None:
    """Delete hidden leftovers of interrupted generations of ``path`` (dead writers only)."""
    if not path.parent.is_dir():
        return
    for entry in path.parent.iterdir():
        match = _TMP_RE.match(entry.name)
        if not match or match["name"] != path.name or not entry.is_dir():
            continue
        pid = int(match["pid"])
        alive = True
        try:
            os.kill(pid, 0)
        except ProcessLookupError:
            alive = False
        except PermissionError:
            alive = True
        if not alive:
            shutil.rmtree(entry, ignore_errors=True)


def _check_replaceable(path: Path) -> None:
    if not path.exists():
        return
    if not path.is_dir():
        raise FileExistsError(f"{path} exists and is not a directory")
    names = {p.name for p in path.iterdir()}
    if names and not names & {TRAIN_JSON, TEST_JSON}:
        raise FileExistsError(
            f"{path} exists and is not an aoi3d scene dataset; refusing to replace it"
        )


def _write_camera(
    scene: TurbineScene,
    camera: Camera,
    camera_id: int,
    root: Path,
    on_frames: Callable[[int], None] | None = None,
) -> int:
    """Render and save every frame of one camera under ``root``; returns the frame count."""
    n_frames = scene.cfg.n_frames
    for start in range(0, n_frames, CHUNK_FRAMES):
        indices = range(start, min(start + CHUNK_FRAMES, n_frames))
        for k, image in zip(indices, scene.render_frames(camera, indices), strict=True):
            _save_png(root / frame_file_relpath(camera_id, k), image)
        if on_frames:
            on_frames(len(indices))
    return n_frames


def _render_camera_job(
    cfg: dict[str, Any], camera: dict[str, Any], camera_id: int, root: str
) -> int:
    """Process-pool entry point: one camera's frames (plain data in, frame count out)."""
    scene = TurbineScene(SceneConfig.from_dict(cfg), cache_size=1)
    return _write_camera(scene, Camera.from_dict(camera), camera_id, Path(root))


def generate_dataset(
    path: str | Path,
    cfg: SceneConfig | None = None,
    progress: Progress | None = None,
    *,
    processes: int = 1,
) -> SceneDataset:
    """Render every frame of every camera of ``cfg`` to ``path`` (replacing a dataset there).

    ``progress(done, total)`` is called in this process as frames complete (``total`` =
    cameras × frames). ``processes > 1`` renders cameras in that many processes (``spawn``
    start method: a calling script needs the ``if __name__ == "__main__":`` guard); the
    output is byte-identical either way. Raises ``FileExistsError`` if ``path`` holds
    something other than a scene dataset.
    """
    cfg = cfg if cfg is not None else SceneConfig()
    if processes < 1:
        raise ValueError(f"processes must be ≥ 1, got {processes}")
    path = Path(path).absolute()
    _check_replaceable(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    _remove_stale_temps(path)
    if not cfg.seamless:
        lo, hi = cfg.seamless_rpm()
        log.warning(
            "scene loop not seamless: %.4g blade passes per %g s (rotor_rpm %g; try %g or %g)",
            cfg.blade_passes,
            cfg.duration_s,
            cfg.rotor_rpm,
            lo,
            hi,
        )

    cameras = place_cameras(cfg)
    total, done = len(cameras) * cfg.n_frames, 0

    def advance(n: int) -> None:
        nonlocal done
        done += n
        if progress:
            progress(done, total)

    with atomic_dir(path) as tmp:  # written beside, swapped into place when whole
        if progress:
            progress(0, total)
        for cam_id in range(len(cameras)):
            (tmp / f"frames/cam{cam_id:02d}").mkdir(parents=True)
        if processes == 1:
            scene = TurbineScene(cfg, cache_size=1)
            for cam_id, camera in enumerate(cameras):
                _write_camera(scene, camera, cam_id, tmp, advance)
        else:
            ctx = multiprocessing.get_context("spawn")
            with ProcessPoolExecutor(max_workers=processes, mp_context=ctx) as pool:
                jobs = [
                    pool.submit(_render_camera_job, cfg.to_dict(), cam.to_dict(), i, str(tmp))
                    for i, cam in enumerate(cameras)
                ]
                for job in as_completed(jobs):
                    advance(job.result())
        train_ids = list(range(1, len(cameras)))
        for name, ids in ((TRAIN_JSON, train_ids), (TEST_JSON, [HELDOUT_ID])):
            doc = _transforms(ids, cameras, cfg, ROTOR_AABB if cfg.framing == "rotor" else AABB)
            (tmp / name).write_text(json.dumps(doc, indent=1))
    return load_dataset(path)


def ensure_dataset(
    path: str | Path,
    cfg: SceneConfig | None = None,
    progress: Progress | None = None,
    *,
    processes: int = 1,
) -> SceneDataset:
    """The dataset at ``path``; generated first if missing, incomplete, or of another config."""
    cfg = cfg if cfg is not None else SceneConfig()
    with contextlib.suppress(FileNotFoundError, ValueError):
        ds = load_dataset(path)
        if ds.config_hash == cfg.config_hash and not ds.check_frames(decode=0):
            return ds
    return generate_dataset(path, cfg, progress, processes=processes)


def write_dataset(
    path: str | Path,
    cameras: list[Camera],
    frame_png: Callable[[int, int], bytes],
    *,
    fps: int,
    n_frames: int,
    aabb: np.ndarray,
    extra: dict[str, Any] | None = None,
) -> SceneDataset:
    """Write a dataset in the project's layout from frames that already exist (camera
    ``HELDOUT_ID`` is the held-out view; ``frame_png(camera_id, k)`` the PNG bytes of a frame,
    written as given), atomically, replacing a dataset at ``path``. It records no scene config
    (it was not generated); ``config_hash`` is the SHA-256 of its frames, cameras and grid, so the
    episode cache tells two contents apart. ``extra`` goes into the ``aoi3d`` block (where the
    frames came from)."""
    import hashlib

    path = Path(path).absolute()
    if fps < 1 or n_frames < 1:
        raise ValueError(f"fps and n_frames must be ≥ 1, got {fps}, {n_frames}")
    if len(cameras) < 2:
        raise ValueError(f"a dataset needs the held-out camera and one to train on, got "
                         f"{len(cameras)} camera(s)")
    _check_replaceable(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    _remove_stale_temps(path)
    digest = hashlib.sha256(f"{fps} {n_frames} {np.asarray(aabb).tolist()}".encode())
    with atomic_dir(path) as tmp:
        for cam_id, cam in enumerate(cameras):
            cam.validate()
            (tmp / f"frames/cam{cam_id:02d}").mkdir(parents=True)
            digest.update(np.asarray(cam.c2w, dtype=np.float64).tobytes())
            digest.update(f"{cam.fx} {cam.fy} {cam.cx} {cam.cy} {cam.width} {cam.height}"
                          .encode())
            for k in range(n_frames):
                data = frame_png(cam_id, k)
                problem = png_problem(data[:8], data[-12:], len(data))
                if problem:
                    raise ValueError(f"camera {cam_id} frame {k}: {problem}")
                digest.update(data)
                (tmp / frame_file_relpath(cam_id, k)).write_bytes(data)
        block = {"format_version": FORMAT_VERSION, "fps": int(fps), "n_frames": int(n_frames),
                 "duration_s": n_frames / fps, "aabb": np.asarray(aabb).tolist(),
                 "heldout_id": HELDOUT_ID, "n_cameras": len(cameras), "config": {},
                 "config_hash": digest.hexdigest()[:16], **(extra or {})}
        train_ids = [i for i in range(len(cameras)) if i != HELDOUT_ID]
        for name, ids in ((TRAIN_JSON, train_ids), (TEST_JSON, [HELDOUT_ID])):
            doc = _transforms_doc(ids, cameras, n_frames, block)
            (tmp / name).write_text(json.dumps(doc, indent=1))
    return load_dataset(path)
