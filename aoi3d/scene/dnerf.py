"""D-NeRF / nerfstudio transforms JSON with a per-frame ``time``: reader and writer.

Files: ``transforms_train.json``, ``transforms_test.json``, ``transforms_val.json`` (D-NeRF;
any of test/val may be absent) or a single ``transforms.json`` (nerfstudio). Each holds
intrinsics (``fl_x, fl_y, cx, cy, w, h`` as in nerfstudio, or D-NeRF's ``camera_angle_x``
with the size read from the images; a frame may carry its own) and ``frames: [{file_path,
time ∈ [0, 1], transform_matrix (OpenGL c2w)}]``. ``file_path`` is relative to the folder,
with an extension (nerfstudio) or without (D-NeRF: ``.png`` is appended).

Mapping to the project's fixed rig (:class:`aoi3d.scene.SceneDataset`):

* Frames are grouped into cameras by ``camera_id`` when every frame has one (multi-view
  exports, including :func:`export_dnerf` and the project's own layout); otherwise by pose
  (identical ``transform_matrix`` and intrinsics). A camera's frames are ordered by
  ``frame_index`` if present, else by ``time``. Every camera must have the same number of
  frames: that is ``n_frames``.
* D-NeRF's synthetic scenes are monocular — one pose per time — so each frame becomes a
  camera of its own with ``n_frames = 1``: a rig of many views, each seen at its own moment
  (:meth:`DNeRFDataset.frame_time` returns it). This keeps the contract (fixed pose per
  camera, every camera has every frame) without inventing images.
* The held-out camera (id 0) is the first camera of the test split (by ``camera_id``, else
  in file order), or ``heldout``; the training split's other cameras are ids 1..N; the
  remaining test/val cameras follow (not in ``train_ids``). A camera already seen in an
  earlier split (same ``camera_id``/pose) is not repeated — D-NeRF tools want a val split
  and :func:`export_dnerf` writes it as a copy of test.
* RGBA images are composited over ``background`` (white, like D-NeRF's ``white_bkgd``);
  ``downscale``/``width`` resize by area averaging and scale the intrinsics.
* The box: ``aabb`` argument, else the file's ``aabb`` (written by :func:`export_dnerf`),
  else :func:`focus_aabb` — a cube on the point nearest all optical axes with half side
  0.375 × the median camera distance (≈ the [-1.5, 1.5]³ box used for D-NeRF's scenes,
  whose cameras stand ≈ 4 from the origin).
"""

from __future__ import annotations

import json
from collections.abc import Callable, Iterator, Sequence
from contextlib import contextmanager
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, cast

import numpy as np
from PIL import Image

from aoi3d.scene.camera import Camera
from aoi3d.scene.dataset import PNG_END, DatasetError, DatasetNotFound, SceneDataset
from aoi3d.scene.media import PngCache, encode_png, replace_dir, resize_area, target_size
from aoi3d.scene.transforms import (
    Frame,
    Group,
    group_frames,
    group_intrinsics,
    ordered_frames,
    parse_frames,
    read_doc,
)

__all__ = [
    "DEFAULT_FPS",
    "LAYOUT",
    "SINGLE_JSON",
    "SPLIT_JSONS",
    "DNeRFDataset",
    "export_dnerf",
    "focus_aabb",
    "load_dnerf",
]

LAYOUT = "dnerf"
SPLIT_JSONS = {
    "train": "transforms_train.json",
    "test": "transforms_test.json",
    "val": "transforms_val.json",
}
SINGLE_JSON = "transforms.json"
DEFAULT_FPS = 30
"""Frame rate assumed when the files give none (D-NeRF's don't)."""
FOCUS_HALF_SIDE = 0.375
"""Half side of :func:`focus_aabb`'s cube, as a fraction of the median camera distance."""

Progress = Callable[[int, int], None]


@dataclass(frozen=True, eq=False, kw_only=True)
class DNeRFDataset(SceneDataset):
    """A D-NeRF / nerfstudio folder: one image file per camera and frame."""

    file_relpaths: tuple[tuple[str, ...], ...]
    """Per camera id, per frame index: the image file relative to :attr:`root`."""
    times: np.ndarray
    """Per camera id, per frame index: the capture ``time`` ∈ [0, 1], (n_cameras, n_frames)."""
    source_sizes: tuple[tuple[int, int], ...]
    """Per camera id: the stored image size ``(W, H)``."""
    splits: tuple[str, ...]
    """Per camera id: the split it was read from (``train``, ``test``, ``val`` or ``all``)."""
    background: tuple[int, int, int] = (255, 255, 255)
    png_cache: PngCache = field(default_factory=PngCache, repr=False)

    def frame_relpath(self, camera_id: int, frame_index: int) -> str:
        self._check(camera_id, frame_index)
        return self.file_relpaths[camera_id][frame_index]

    def frame_time(self, camera_id: int, frame_index: int) -> float:
        """The frame's ``time`` from the file, ∈ [0, 1]."""
        self._check(camera_id, frame_index)
        return float(self.times[camera_id, frame_index])

    def _needs_conversion(self, camera_id: int, img: Image.Image) -> bool:
        cam = self.cameras[camera_id]
        return img.format != "PNG" or img.mode != "RGB" or img.size != (cam.width, cam.height)

    def _convert(self, camera_id: int, img: Image.Image) -> np.ndarray:
        if img.mode in ("RGBA", "LA", "PA") or "transparency" in img.info:
            rgba = np.asarray(img.convert("RGBA"), dtype=np.float32) / 255.0
            alpha = rgba[..., 3:]
            bg = np.asarray(self.background, dtype=np.float32) / 255.0
            rgb = np.rint((rgba[..., :3] * alpha + bg * (1.0 - alpha)) * 255.0)
            image = rgb.astype(np.uint8)
        else:
            image = np.asarray(img.convert("RGB"), dtype=np.uint8)
        cam = self.cameras[camera_id]
        return resize_area(image, (cam.width, cam.height))

    def frame(self, camera_id: int, frame_index: int) -> np.ndarray:
        """The decoded frame: uint8 (H, W, 3), alpha composited, resized to the camera.
        Raises :class:`~aoi3d.scene.DatasetError` naming the file if it cannot be read."""
        path = self.frame_path(camera_id, frame_index)
        with self._reading(path), Image.open(path) as img:
            return self._convert(camera_id, img)

    def frame_png(self, camera_id: int, frame_index: int) -> bytes:
        """The file's bytes when it is an RGB PNG of the camera's size; else the converted
        frame encoded as PNG (cached)."""
        path = self.frame_path(camera_id, frame_index)
        with self._reading(path), Image.open(path) as img:
            if not self._needs_conversion(camera_id, img):
                data = path.read_bytes()
                if data[-12:] != PNG_END:
                    raise DatasetError(f"{path}: image file is cut short (a truncated PNG); "
                                       f"{self.fix_hint()}", path=path)
                return data
        return self.png_cache.get(
            (camera_id, frame_index), lambda: encode_png(self.frame(camera_id, frame_index))
        )

    @contextmanager
    def _reading(self, path: Path) -> Iterator[None]:
        """Errors of reading or decoding ``path``, as one-line :class:`DatasetError`."""
        try:
            yield
        except DatasetError:
            raise
        except FileNotFoundError:
            raise DatasetNotFound(f"{path}: image file is missing; {self.fix_hint()}",
                                  path=path) from None
        except (OSError, SyntaxError, ValueError) as err:  # PIL's errors for broken images
            raise DatasetError(f"{path}: image cannot be decoded ({err}); {self.fix_hint()}",
                               path=path) from None


# =============================================================================================
# Reading
# =============================================================================================

def focus_aabb(cameras: Sequence[Camera], half_side_ratio: float = FOCUS_HALF_SIDE) -> (
    np.ndarray
):
    """A cube (2, 3) centred on the point nearest (least squares) all cameras' optical axes,
    with half side ``half_side_ratio`` × the median camera distance from that point. Raises
    ``ValueError`` when the axes do not pin a point down (e.g. all parallel)."""
    a, b = np.zeros((3, 3)), np.zeros(3)
    for cam in cameras:
        d = -cam.c2w[:3, 2]
        proj = np.eye(3) - np.outer(d, d)
        a += proj
        b += proj @ cam.c2w[:3, 3]
    if len(cameras) < 2 or np.linalg.cond(a) > 1e8:
        raise ValueError("cannot derive a box: the cameras' optical axes do not meet near a "
                         "point (pass aabb)")
    focus = np.linalg.solve(a, b)
    half = half_side_ratio * float(np.median([np.linalg.norm(c.position - focus)
                                              for c in cameras]))
    return np.stack([focus - half, focus + half])


def _aabb_of(docs: list[dict[str, Any]], override: Any, cameras: list[Camera]) -> np.ndarray:
    value = override
    for doc in docs:
        if value is None:
            value = doc.get("aabb", (doc.get("aoi3d") or {}).get("aabb"))
    box = focus_aabb(cameras) if value is None else np.asarray(value, dtype=np.float64)
    if box.shape != (2, 3) or not np.all(box[0] < box[1]):
        raise ValueError(f"aabb must be (2, 3) with min < max, got {box.tolist()}")
    return box


def _transforms_files(root: Path) -> dict[str, Path]:
    """The split → transforms JSON of the folder ``root`` (``all``: a single transforms.json)."""
    if not root.is_dir():
        raise FileNotFoundError(f"no D-NeRF dataset here: {root} is not a directory")
    present = {s: root / name for s, name in SPLIT_JSONS.items() if (root / name).is_file()}
    if not present and (root / SINGLE_JSON).is_file():
        present = {"all": root / SINGLE_JSON}
    if not present:
        raise FileNotFoundError(f"{root}: no {', '.join(SPLIT_JSONS.values())} or "
                                f"{SINGLE_JSON} (D-NeRF / nerfstudio transforms)")
    if "train" not in present and "all" not in present:
        raise FileNotFoundError(f"{root}: {SPLIT_JSONS['train']} is missing")
    return present


def _rig_order(root: Path, groups: list[Group], by_camera_id: bool, heldout: int | None
               ) -> tuple[list[Group], list[Group]]:
    """The cameras in the dataset's order — the held-out one, the training ones, the rest —
    and the training ones."""
    holdout_pool = [g for g in groups if g.split == "test"] or groups
    if by_camera_id:
        holdout_pool = sorted(holdout_pool, key=lambda g: g.key)
        wanted = heldout if heldout is not None else holdout_pool[0].key
        chosen = next((g for g in groups if g.key == wanted), None)
        if chosen is None:
            raise ValueError(f"{root}: held-out camera_id {wanted} not found (have "
                             f"{sorted(g.key for g in groups)})")
    else:
        index = 0 if heldout is None else heldout
        if not 0 <= index < len(holdout_pool):
            raise ValueError(f"{root}: heldout={index} but the test split has "
                             f"{len(holdout_pool)} cameras")
        chosen = holdout_pool[index]
    train = [g for g in groups if g is not chosen and g.split in ("train", "all")]
    if by_camera_id:
        train.sort(key=lambda g: g.key)
    others = [g for g in groups if g is not chosen and g not in train]
    if not train:
        raise ValueError(f"{root}: no training cameras besides the held-out one")
    return [chosen, *train, *others], train


def _fixed_camera(root: Path, group: Group, downscale: float | None, width: int | None
                  ) -> tuple[Camera, list[Frame], tuple[int, int]]:
    """A camera's pose (the same in every frame) and intrinsics at the output size, its
    frames in time order, and its images' own size."""
    seq = ordered_frames(group)
    fx, fy, cx, cy, w, h = group_intrinsics(group, root)
    w_out, h_out = target_size(w, h, downscale=downscale, target_width=width)
    sx, sy = w_out / w, h_out / h
    for f in seq[1:]:
        if not np.allclose(f.c2w, seq[0].c2w, atol=1e-9):
            raise ValueError(f"camera {group.key!r}: frames have different poses "
                             f"({seq[0].file_relpath}, {f.file_relpath}); a camera_id "
                             "must name a fixed camera")
    camera = Camera(c2w=seq[0].c2w, fx=fx * sx, fy=fy * sy, cx=cx * sx, cy=cy * sy,
                    width=w_out, height=h_out)
    try:
        camera.validate()
    except ValueError as exc:
        raise ValueError(f"{root}: camera of {seq[0].file_relpath}: {exc}") from exc
    return camera, seq, (w, h)


def load_dnerf(
    path: str | Path,
    *,
    downscale: float | None = None,
    width: int | None = None,
    heldout: int | None = None,
    aabb: np.ndarray | Sequence[Sequence[float]] | None = None,
    fps: int | None = None,
    background: tuple[int, int, int] = (255, 255, 255),
    png_cache_bytes: int | None = None,
) -> DNeRFDataset:
    """Read a D-NeRF / nerfstudio folder (see the module docstring for the mapping).

    ``heldout``: the held-out camera's ``camera_id`` when frames carry one, else its position
    among the test split's cameras (default: the first). ``fps`` overrides the file's (default
    :data:`DEFAULT_FPS`). Raises ``FileNotFoundError`` for missing files, ``ValueError`` for
    malformed ones.
    """
    root = Path(path).absolute()
    present = _transforms_files(root)
    docs = {split: read_doc(p) for split, p in present.items()}
    frames = [f for split, doc in docs.items() for f in parse_frames(doc, split, present[split])]
    by_camera_id = all(f.camera_id is not None for f in frames)
    groups = group_frames(frames, by_camera_id)
    ordered, train = _rig_order(root, groups, by_camera_id, heldout)
    counts = {g.key if by_camera_id else i: len(g.frames) for i, g in enumerate(ordered)}
    if len(set(counts.values())) != 1:
        raise ValueError(
            f"{root}: cameras have different frame counts {counts}; every camera of the rig "
            "needs a frame at every time (monocular data: one pose per frame)")
    n_frames = len(ordered[0].frames)

    cameras, rels, times, sizes = [], [], [], []
    for group in ordered:
        camera, seq, (w, h) = _fixed_camera(root, group, downscale, width)
        cameras.append(camera)
        rels.append(tuple(f.file_relpath for f in seq))
        times.append([f.time if f.time is not None else k / n_frames for k, f in enumerate(seq)])
        sizes.append((w, h))

    missing = [rel for cam in rels for rel in cam if not (root / rel).is_file()]
    if missing:
        raise FileNotFoundError(f"{root}: {len(missing)} image file(s) missing, e.g. "
                                f"{', '.join(missing[:3])}")
    doc_list = list(docs.values())
    if fps is None:
        fps = next((int(d["fps"]) for d in doc_list if d.get("fps")), None) or next(
            (int(d["aoi3d"]["fps"]) for d in doc_list if (d.get("aoi3d") or {}).get("fps")),
            DEFAULT_FPS)
    if fps < 1:
        raise ValueError(f"fps must be ≥ 1, got {fps}")
    names = tuple(
        f"cam{g.key:02d}" if by_camera_id else Path(g.frames[0].file_relpath).with_suffix("")
        .as_posix() for g in ordered)
    return DNeRFDataset(
        root=root, fps=fps, n_frames=n_frames, width=cameras[0].width,
        height=cameras[0].height, cameras=cameras, aabb=_aabb_of(doc_list, aabb, cameras),
        train_ids=list(range(1, len(train) + 1)), heldout_id=0, layout=LAYOUT,
        camera_names=tuple(str(n) for n in names), file_relpaths=tuple(rels),
        times=np.asarray(times, dtype=np.float64), source_sizes=tuple(sizes),
        splits=tuple(g.split for g in ordered),
        background=cast(tuple[int, int, int], tuple(background)),
        png_cache=PngCache() if png_cache_bytes is None else PngCache(png_cache_bytes),
    )


# =============================================================================================
# Writing
# =============================================================================================
def _intrinsics_of(cam: Camera) -> dict[str, Any]:
    return {"fl_x": cam.fx, "fl_y": cam.fy, "cx": cam.cx, "cy": cam.cy, "w": cam.width,
            "h": cam.height}


def _split_doc(dataset: SceneDataset, ids: list[int], entries: list[dict[str, Any]]) -> (
    dict[str, Any]
):
    ref = dataset.cameras[ids[0]]
    for entry in entries:
        if entry.pop("_own_intrinsics"):
            entry.update(_intrinsics_of(dataset.cameras[entry["camera_id"]]))
    return {"camera_angle_x": ref.camera_angle_x, **_intrinsics_of(ref), "fps": dataset.fps,
            "aabb": np.asarray(dataset.aabb, dtype=np.float64).tolist(), "frames": entries}


def export_dnerf(
    dataset: SceneDataset,
    out: str | Path,
    *,
    rgba: bool = True,
    overwrite: bool = False,
    progress: Progress | None = None,
) -> Path:
    """Write ``dataset`` as a D-NeRF folder; returns it.

    ``train/cNN_fFFFF.png`` (training cameras), ``test/…`` (the held-out camera),
    ``val/…`` (the other cameras, if any); ``transforms_{train,val,test}.json`` with
    D-NeRF's keys (``camera_angle_x``, ``file_path`` without extension, ``time``,
    ``transform_matrix``), nerfstudio's intrinsics, and ``camera_id``, ``frame_index``,
    ``fps``, ``aabb`` so that :func:`load_dnerf` restores the rig exactly. Without other
    cameras val repeats test (D-NeRF's loader wants all three). ``rgba`` writes an opaque
    alpha channel, as D-NeRF's loader expects RGBA. ``progress(done, total)`` counts frames.
    """
    heldout = dataset.heldout_id
    train_ids = [i for i in dataset.train_ids if i != heldout]
    others = [i for i in range(len(dataset.cameras)) if i != heldout and i not in train_ids]
    if not train_ids:
        raise ValueError("the dataset has no training cameras")
    plan = [("train", train_ids), ("test", [heldout])] + ([("val", others)] if others else [])
    total = sum(len(ids) for _, ids in plan) * dataset.n_frames
    done = 0
    with replace_dir(out, overwrite=overwrite) as tmp:
        docs: dict[str, dict[str, Any]] = {}
        for split, ids in plan:
            (tmp / split).mkdir()
            ref = dataset.cameras[ids[0]]
            entries = []
            for cam_id in ids:
                cam = dataset.cameras[cam_id]
                own = _intrinsics_of(cam) != _intrinsics_of(ref)
                for k in range(dataset.n_frames):
                    name = f"{split}/c{cam_id:02d}_f{k:04d}"
                    if rgba:
                        image = dataset.frame(cam_id, k)
                        alpha = np.full((*image.shape[:2], 1), 255, dtype=np.uint8)
                        Image.fromarray(np.concatenate([image, alpha], axis=-1)).save(
                            tmp / f"{name}.png", format="PNG", compress_level=3)
                    else:
                        (tmp / f"{name}.png").write_bytes(dataset.frame_png(cam_id, k))
                    entries.append({
                        "file_path": f"./{name}", "time": dataset.frame_time(cam_id, k),
                        "transform_matrix": cam.c2w.tolist(), "camera_id": cam_id,
                        "frame_index": k, "_own_intrinsics": own,
                    })
                    done += 1
                    if progress:
                        progress(done, total)
            docs[split] = _split_doc(dataset, ids, entries)
        docs.setdefault("val", docs["test"])
        for split, doc in docs.items():
            (tmp / SPLIT_JSONS[split]).write_text(json.dumps(doc, indent=1))
    return Path(out).absolute()

