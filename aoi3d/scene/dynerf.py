"""The DyNeRF / Neural 3D Video layout: one ``camNN.mp4`` per camera and ``poses_bounds.npy``.

On disk::

    cam00.mp4 cam01.mp4 cam03.mp4 …   one synchronised video per camera (ids may have gaps)
    poses_bounds.npy                  float N×17, one row per video in sorted camera order

A row is the LLFF 3×5 matrix (row-major: 15 numbers) followed by ``near, far``, the depth
bounds of the scene content seen by that camera. The matrix is ``[R | t | hwf]``: ``R``'s
columns are the camera's axes [down, right, back] in world coordinates, ``t`` its centre,
``hwf = (H, W, focal)`` the image height, width and focal length in pixels (principal point
at the image centre). The project's convention is OpenGL/NeRF [right, up, back], so

    R_opengl = R_llff · P,   P = [[0, -1, 0],      right = +right_llff   (column 1)
                                  [1,  0, 0],      up    = −down_llff    (column 0)
                                  [0,  0, 1]]      back  = +back_llff    (column 2)

and ``R_llff = R_opengl · Pᵀ`` on writing (:data:`LLFF_TO_OPENGL` is ``P``). Translations are
unchanged; no recentring or rescaling is applied (world units are the source's). Rotations
are projected onto the nearest rotation (SVD) to absorb float32 storage; a matrix further
than 1e-3 from a rotation is rejected.

Reading (:func:`load_dynerf`): camera ``cam00`` (``heldout``) is the held-out novel view and
becomes id 0; the other videos become ids 1..N in sorted order (:attr:`camera_names` keeps
``camNN``). Frames are decoded with ffmpeg (from imageio-ffmpeg) straight to the target size
by ffmpeg's area scaler, lazily, one whole video per camera on first access, and kept in
memory as uint8 (``cameras × frames × H × W × 3`` bytes when all are touched). Intrinsics
come from ``hwf`` scaled to the decoded size: ``fx = focal·W_out/W``, ``fy = focal·H_out/H``,
``cx = W_out/2``, ``cy = H_out/2``. The radiance field's box (:func:`frusta_aabb`) is the
smallest axis-aligned box holding every camera's view frustum between its near and far
bounds, unless ``aabb`` overrides it.
"""

from __future__ import annotations

import logging
import math
import re
import threading
from collections.abc import Callable, Iterable, Sequence
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from aoi3d.scene.camera import Camera
from aoi3d.scene.dataset import DatasetError, DatasetNotFound, SceneDataset
from aoi3d.scene.llff import (
    LLFF_TO_OPENGL,
    aabb_depth_bounds,
    frusta_aabb,
    llff_to_opengl,
    opengl_to_llff,
)
from aoi3d.scene.media import PngCache, encode_png, replace_dir, target_size
from aoi3d.scene.video import DEFAULT_CRF, VideoInfo, decode_video, encode_video, probe_video

__all__ = [
    "DEFAULT_CRF",
    "DEFAULT_FPS",
    "DEFAULT_MAX_WIDTH",
    "LAYOUT",
    "LLFF_TO_OPENGL",
    "POSES_BOUNDS",
    "DyNeRFDataset",
    "VideoInfo",
    "aabb_depth_bounds",
    "decode_video",
    "encode_video",
    "export_dynerf",
    "frusta_aabb",
    "llff_to_opengl",
    "load_dynerf",
    "opengl_to_llff",
    "probe_video",
]

log = logging.getLogger(__name__)

LAYOUT = "dynerf"
POSES_BOUNDS = "poses_bounds.npy"
VIDEO_RE = re.compile(r"^cam(\d+)\.mp4$")
DEFAULT_MAX_WIDTH = 480
"""Width videos are decoded at when neither ``downscale`` nor ``width`` is given and they are
wider (a full-size DyNeRF video is 2704×2028: 4.9 GB per camera decoded at full size)."""
DEFAULT_FPS = 30
"""Frame rate assumed when a video reports none (DyNeRF's are 30 fps)."""

Progress = Callable[[int, int], None]


# =============================================================================================
# The dataset
# =============================================================================================
@dataclass(frozen=True, eq=False, kw_only=True)
class DyNeRFDataset(SceneDataset):
    """A DyNeRF folder: frames decoded from each camera's video on first use, then in memory.

    :meth:`frame` returns a read-only view of the decoded video; :meth:`frame_png` encodes it
    (cached in :attr:`png_cache`); :meth:`preload` decodes every camera up front.
    """

    video_relpaths: tuple[str, ...]
    """Per camera id: the video file, relative to :attr:`root`."""
    source_sizes: tuple[tuple[int, int], ...]
    """Per camera id: the video's stored size ``(W, H)``."""
    bounds: np.ndarray
    """Per camera id: the LLFF ``(near, far)`` depth bounds, (n_cameras, 2)."""
    png_cache: PngCache = field(default_factory=PngCache, repr=False)
    _videos: dict[int, np.ndarray] = field(default_factory=dict, init=False, repr=False)
    _locks: dict[int, threading.Lock] = field(default_factory=dict, init=False, repr=False)
    _locks_guard: threading.Lock = field(default_factory=threading.Lock, init=False,
                                         repr=False)

    def frame_relpath(self, camera_id: int, frame_index: int) -> str:
        """The video holding the frame (relative to :attr:`root`)."""
        self._check(camera_id, frame_index)
        return self.video_relpaths[camera_id]

    def video(self, camera_id: int) -> np.ndarray:
        """All frames of one camera, uint8 (n_frames, H, W, 3), decoded on first call."""
        self._check(camera_id, 0)
        frames = self._videos.get(camera_id)
        if frames is not None:
            return frames
        with self._locks_guard:
            lock = self._locks.setdefault(camera_id, threading.Lock())
        with lock:
            frames = self._videos.get(camera_id)
            if frames is None:
                cam = self.cameras[camera_id]
                path = self.root / self.video_relpaths[camera_id]
                try:
                    frames = decode_video(path, (cam.width, cam.height), self.n_frames)
                except FileNotFoundError:
                    raise DatasetNotFound(f"{path}: video is missing; {self.fix_hint()}",
                                          path=path) from None
                except ValueError as err:
                    raise DatasetError(f"{path}: {err}; {self.fix_hint()}", path=path) from None
                if len(frames) < self.n_frames:
                    raise DatasetError(f"{path}: decoded to {len(frames)} frames, the dataset "
                                       f"has {self.n_frames}; {self.fix_hint()}", path=path)
                self._videos[camera_id] = frames
        return frames

    def frame(self, camera_id: int, frame_index: int) -> np.ndarray:
        """The decoded frame: uint8 (H, W, 3), read-only."""
        self._check(camera_id, frame_index)
        return self.video(camera_id)[frame_index]

    def frame_png(self, camera_id: int, frame_index: int) -> bytes:
        """The frame encoded as PNG (cached)."""
        self._check(camera_id, frame_index)
        return self.png_cache.get(
            (camera_id, frame_index), lambda: encode_png(self.frame(camera_id, frame_index))
        )

    def missing_frames(self) -> int:
        """Frames of cameras whose video is neither decoded nor on disk."""
        return self.n_frames * sum(
            i not in self._videos and not (self.root / rel).is_file()
            for i, rel in enumerate(self.video_relpaths)
        )

    def check_frames(self, *, decode: int = 1) -> list[tuple[Path, str]]:
        """Each camera's video that is neither decoded nor a non-empty file on disk, as
        ``(path, what)`` (``decode`` is ignored: the reader probed every video already, and
        decoding one means decoding the whole video)."""
        problems = []
        for i, rel in enumerate(self.video_relpaths):
            path = self.root / rel
            if i in self._videos:
                continue
            if not path.is_file():
                problems.append((path, "missing"))
            elif path.stat().st_size == 0:
                problems.append((path, "empty"))
        return problems

    def preload(self, processes: int = 1, *, png: bool = False) -> DyNeRFDataset:
        """Decode every camera now (``processes`` ffmpeg processes at once) and, with ``png``,
        encode every frame into :attr:`png_cache` (≈ 1 ms a frame at 96×72) so that a camera
        service's first loop costs no encoding; returns self."""
        if processes < 1:
            raise ValueError(f"processes must be ≥ 1, got {processes}")
        with ThreadPoolExecutor(max_workers=processes) as pool:
            list(pool.map(self.video, range(len(self.cameras))))
        if png:
            for camera_id in range(len(self.cameras)):
                for frame_index in range(self.n_frames):
                    self.frame_png(camera_id, frame_index)
        return self

    @property
    def decoded_bytes(self) -> int:
        """Memory held by decoded frames."""
        return sum(v.nbytes for v in self._videos.values())


def _video_files(root: Path) -> list[tuple[int, str]]:
    found: dict[int, str] = {}
    for entry in root.iterdir():
        match = VIDEO_RE.match(entry.name)
        if not match:
            continue
        number = int(match[1])
        if number in found:
            raise ValueError(f"{root}: {found[number]} and {entry.name} are the same camera")
        found[number] = entry.name
    return sorted(found.items())


def _read_poses_bounds(path: Path, n_videos: int, names: list[str]) -> np.ndarray:
    try:
        arr = np.load(path, allow_pickle=False)
    except (ValueError, OSError, EOFError) as exc:
        raise ValueError(f"{path} is not a readable .npy array ({exc})") from exc
    if arr.ndim != 2 or arr.shape[1] != 17:
        raise ValueError(
            f"{path.name} must be N×17 (per camera an LLFF 3×5 pose, then near and far), "
            f"got shape {arr.shape}"
        )
    if arr.shape[0] != n_videos:
        raise ValueError(
            f"{path.name} has {arr.shape[0]} rows but there are {n_videos} videos "
            f"({', '.join(names)}); rows follow the sorted camNN.mp4 files that exist"
        )
    if not np.all(np.isfinite(arr)):
        raise ValueError(f"{path.name} has non-finite entries")
    return arr.astype(np.float64)


def _frames_and_fps(root: Path, names: list[str], infos: list[VideoInfo],
                    n_frames: int | None) -> tuple[int, int]:
    """The frames used of each video (the shortest's count unless ``n_frames``) and the
    dataset's (integer) frame rate; the videos must agree on theirs."""
    counts = {name: info.n_frames for name, info in zip(names, infos, strict=True)}
    shortest = min(counts.values())
    if shortest < 1:
        raise ValueError(f"{root}: a video has no frames ({counts})")
    if len(set(counts.values())) > 1:
        log.warning("%s: videos differ in length %s; using the first %d frames of each",
                    root, counts, shortest)
    if n_frames is None:
        n_frames = shortest
    elif not 1 <= n_frames <= shortest:
        raise ValueError(f"n_frames must be in [1, {shortest}] (the shortest video), "
                         f"got {n_frames}")
    rates = {name: info.fps for name, info in zip(names, infos, strict=True)}
    if max(rates.values()) - min(rates.values()) > 1e-3:
        raise ValueError(f"{root}: videos differ in frame rate {rates}")
    fps = round(infos[0].fps) if infos[0].fps > 0 else DEFAULT_FPS
    if abs(fps - infos[0].fps) > 1e-3:
        log.warning("%s: %.3f fps rounded to %d (the dataset's fps is an integer)", root,
                    infos[0].fps, fps)
    return n_frames, fps


def _llff_camera(name: str, info: VideoInfo, row: np.ndarray, downscale: float | None,
                 width: int | None) -> Camera:
    """The camera of video ``name`` from its row of poses_bounds.npy, at the decoded size."""
    pose = row[:15].reshape(3, 5)
    h_pose, w_pose, focal = pose[:, 4]
    if not (h_pose > 0 and w_pose > 0 and focal > 0):
        raise ValueError(f"{POSES_BOUNDS} row of {name}: H, W, focal must be > 0, "
                         f"got {h_pose}, {w_pose}, {focal}")
    if abs(info.width / info.height - w_pose / h_pose) > 0.01 * w_pose / h_pose:
        raise ValueError(f"{name} is {info.width}×{info.height} but {POSES_BOUNDS} says "
                         f"{w_pose:g}×{h_pose:g} (W×H): the aspect ratios differ")
    if downscale is None and width is None and info.width > DEFAULT_MAX_WIDTH:
        w_out, h_out = target_size(info.width, info.height, target_width=DEFAULT_MAX_WIDTH)
    else:
        w_out, h_out = target_size(info.width, info.height, downscale=downscale,
                                   target_width=width)
    camera = Camera(c2w=llff_to_opengl(pose, f"{POSES_BOUNDS} row of {name}"),
                    fx=focal * w_out / w_pose, fy=focal * h_out / h_pose,
                    cx=w_out / 2.0, cy=h_out / 2.0, width=w_out, height=h_out)
    camera.validate()
    return camera


def load_dynerf(
    path: str | Path,
    *,
    downscale: float | None = None,
    width: int | None = None,
    heldout: int = 0,
    aabb: np.ndarray | Sequence[Sequence[float]] | None = None,
    n_frames: int | None = None,
    png_cache_bytes: int | None = None,
) -> DyNeRFDataset:
    """Read a DyNeRF folder (videos are probed, not decoded; see :class:`DyNeRFDataset`).

    ``downscale`` (factor) or ``width`` (pixels, aspect kept) sets the decoded size; neither:
    the stored size, capped at :data:`DEFAULT_MAX_WIDTH`. ``heldout`` is the number NN of
    the held-out ``camNN.mp4``. ``aabb`` overrides :func:`frusta_aabb`. ``n_frames`` uses
    only the first frames (default: the shortest video's count). Raises
    ``FileNotFoundError`` for missing files and ``ValueError`` for malformed ones.
    """
    root = Path(path).absolute()
    if not root.is_dir():
        raise FileNotFoundError(f"no DyNeRF dataset here: {root} is not a directory")
    videos = _video_files(root)
    names = [name for _, name in videos]
    if not (root / POSES_BOUNDS).is_file():
        raise FileNotFoundError(f"{root}: {POSES_BOUNDS} is missing (DyNeRF keeps the LLFF "
                                f"poses and bounds of the camNN.mp4 videos there)")
    if not videos:
        raise FileNotFoundError(f"{root}: no camNN.mp4 videos next to {POSES_BOUNDS}")
    rows = _read_poses_bounds(root / POSES_BOUNDS, len(videos), names)
    numbers = [number for number, _ in videos]
    if heldout not in numbers:
        raise ValueError(f"{root}: held-out camera cam{heldout:02d}.mp4 is missing (videos: "
                         f"{', '.join(names)}); choose another with heldout=NN")

    infos = [probe_video(root / name) for name in names]
    n_frames, fps = _frames_and_fps(root, names, infos, n_frames)
    cameras = [_llff_camera(name, info, row, downscale, width)
               for name, info, row in zip(names, infos, rows, strict=True)]
    near, far = rows[:, 15], rows[:, 16]
    if np.any(near <= 0) or np.any(far <= near):
        raise ValueError(f"{POSES_BOUNDS}: bounds need 0 < near < far, got near {near.tolist()}"
                         f", far {far.tolist()}")

    order = [numbers.index(heldout)] + [i for i, n in enumerate(numbers) if n != heldout]
    cameras = [cameras[i] for i in order]
    bounds = rows[order][:, 15:17]
    if aabb is None:
        box = frusta_aabb(cameras, bounds[:, 0], bounds[:, 1])
    else:
        box = np.asarray(aabb, dtype=np.float64)
        if box.shape != (2, 3) or not np.all(box[0] < box[1]):
            raise ValueError(f"aabb must be (2, 3) with min < max, got {box.tolist()}")
    return DyNeRFDataset(
        root=root, fps=fps, n_frames=n_frames, width=cameras[0].width,
        height=cameras[0].height, cameras=cameras, aabb=box,
        train_ids=list(range(1, len(cameras))), heldout_id=0, layout=LAYOUT,
        camera_names=tuple(Path(names[i]).stem for i in order),
        video_relpaths=tuple(names[i] for i in order),
        source_sizes=tuple((infos[i].width, infos[i].height) for i in order),
        bounds=bounds,
        png_cache=PngCache() if png_cache_bytes is None else PngCache(png_cache_bytes),
    )


# =============================================================================================
# Writing
# =============================================================================================
def _check_llff_camera(camera: Camera, camera_id: int) -> None:
    if not math.isclose(camera.fx, camera.fy, rel_tol=1e-9):
        raise ValueError(f"camera {camera_id}: LLFF stores one focal length, got "
                         f"fx={camera.fx}, fy={camera.fy}")
    if abs(camera.cx - camera.width / 2) > 1e-6 or abs(camera.cy - camera.height / 2) > 1e-6:
        raise ValueError(f"camera {camera_id}: LLFF assumes the principal point at the image "
                         f"centre, got cx={camera.cx}, cy={camera.cy} for "
                         f"{camera.width}×{camera.height}")


def export_dynerf(
    dataset: SceneDataset,
    out: str | Path,
    *,
    camera_ids: Iterable[int] | None = None,
    crf: int = DEFAULT_CRF,
    bounds: tuple[float, float] | None = None,
    overwrite: bool = False,
    progress: Progress | None = None,
) -> Path:
    """Write ``dataset`` as a DyNeRF folder: ``camNN.mp4`` (NN = camera id, so the held-out
    camera 0 is ``cam00``) and ``poses_bounds.npy``; returns the folder.

    ``camera_ids`` selects cameras (default all). ``bounds = (near, far)`` for every camera;
    default :func:`aabb_depth_bounds` of the dataset's box per camera. The folder is written
    beside ``out`` and renamed into place; ``overwrite`` replaces a dataset there.
    ``progress(done, total)`` counts frames.
    """
    ids = sorted(set(range(len(dataset.cameras)) if camera_ids is None else camera_ids))
    if not ids:
        raise ValueError("no cameras to export")
    for cam_id in ids:
        if not 0 <= cam_id < len(dataset.cameras):
            raise ValueError(f"camera id {cam_id} not in the dataset "
                             f"(0..{len(dataset.cameras) - 1})")
        _check_llff_camera(dataset.cameras[cam_id], cam_id)
    if bounds is not None and not 0 < bounds[0] < bounds[1]:
        raise ValueError(f"bounds must be 0 < near < far, got {bounds}")
    total, done = len(ids) * dataset.n_frames, 0
    rows = []
    with replace_dir(out, overwrite=overwrite) as tmp:
        for cam_id in ids:
            cam = dataset.cameras[cam_id]
            near, far = bounds if bounds is not None else aabb_depth_bounds(cam, dataset.aabb)
            hwf = np.array([[cam.height], [cam.width], [cam.fx]], dtype=np.float64)
            pose = np.concatenate([opengl_to_llff(cam.c2w), hwf], axis=1)
            rows.append(np.concatenate([pose.ravel(), [near, far]]))

            def frames(cam_id: int = cam_id) -> Iterable[np.ndarray]:
                nonlocal done
                for k in range(dataset.n_frames):
                    yield dataset.frame(cam_id, k)
                    done += 1
                    if progress:
                        progress(done, total)

            encode_video(tmp / f"cam{cam_id:02d}.mp4", frames(), (cam.width, cam.height),
                         dataset.fps, crf)
        np.save(tmp / POSES_BOUNDS, np.asarray(rows, dtype=np.float64))
    return Path(out).absolute()
