"""Image helpers shared by the dataset readers and writers: sizes, resizing, PNG, caching.

Also :func:`replace_dir`, the atomic "write a folder, then swap it into place" used by the
exporters so an interrupted export never leaves something that looks like a dataset.
"""

from __future__ import annotations

import contextlib
import threading
from collections.abc import Callable, Iterator
from io import BytesIO
from pathlib import Path

import numpy as np
from PIL import Image

from aoi3d.atomic import atomic_dir

__all__ = [
    "DEFAULT_PNG_CACHE_BYTES",
    "PngCache",
    "encode_png",
    "replace_dir",
    "resize_area",
    "target_size",
]

DEFAULT_PNG_CACHE_BYTES = 512 * 1024**2
"""Default budget of a :class:`PngCache` (all 19 × 300 frames of the default scene ≈ 60 MB)."""


def target_size(
    width: int, height: int, *, downscale: float | None = None, target_width: int | None = None
) -> tuple[int, int]:
    """The size ``(W, H)`` an image of ``width × height`` is read at.

    ``downscale`` divides both sides; ``target_width`` sets ``W`` and keeps the aspect ratio.
    Sides are rounded to the nearest pixel (at least 1). Neither given: the size as stored.
    """
    if downscale is not None and target_width is not None:
        raise ValueError("give downscale or width, not both")
    if downscale is not None:
        if not (np.isfinite(downscale) and downscale > 0):
            raise ValueError(f"downscale must be a finite number > 0, got {downscale}")
        factor = float(downscale)
    elif target_width is not None:
        if int(target_width) != target_width or target_width < 1:
            raise ValueError(f"width must be a positive integer, got {target_width}")
        factor = width / int(target_width)
    else:
        return int(width), int(height)
    return max(1, round(width / factor)), max(1, round(height / factor))


def resize_area(image: np.ndarray, size: tuple[int, int]) -> np.ndarray:
    """Resize a uint8 H×W×C image to ``size = (W, H)`` by area averaging (box filter)."""
    if (image.shape[1], image.shape[0]) == tuple(size):
        return image
    resized = Image.fromarray(image).resize(size, Image.Resampling.BOX)
    return np.asarray(resized, dtype=np.uint8)


def encode_png(image: np.ndarray, compress_level: int = 1) -> bytes:
    """A uint8 H×W×3 image as PNG bytes (level 1: fast; PNG is lossless at every level)."""
    buf = BytesIO()
    Image.fromarray(np.ascontiguousarray(image)).save(
        buf, format="PNG", compress_level=compress_level
    )
    return buf.getvalue()


class PngCache:
    """Thread-safe PNG bytes per ``(camera_id, frame_index)``, filled until a byte budget.

    Once the budget is spent new entries are not kept (rather than evicting old ones: the
    camera service reads frames cyclically, the worst case for LRU eviction).
    """

    def __init__(self, max_bytes: int = DEFAULT_PNG_CACHE_BYTES) -> None:
        if max_bytes < 0:
            raise ValueError(f"max_bytes must be ≥ 0, got {max_bytes}")
        self.max_bytes = int(max_bytes)
        self._entries: dict[tuple[int, int], bytes] = {}
        self._bytes = 0
        self._lock = threading.Lock()

    @property
    def nbytes(self) -> int:
        """Bytes held."""
        return self._bytes

    def __len__(self) -> int:
        return len(self._entries)

    def get(self, key: tuple[int, int], make: Callable[[], bytes]) -> bytes:
        """The cached bytes for ``key``, or ``make()`` (stored while the budget lasts)."""
        with self._lock:
            hit = self._entries.get(key)
        if hit is not None:
            return hit
        data = make()
        with self._lock:
            if key not in self._entries and self._bytes + len(data) <= self.max_bytes:
                self._entries[key] = data
                self._bytes += len(data)
        return data


def _looks_like_dataset(path: Path) -> bool:
    names = {p.name for p in path.iterdir()}
    return bool(
        names & {"transforms_train.json", "transforms.json", "poses_bounds.npy"}
        or any(n.startswith("cam") and n.endswith(".mp4") for n in names)
    )


@contextlib.contextmanager
def replace_dir(out: str | Path, *, overwrite: bool = False) -> Iterator[Path]:
    """Yield a hidden temporary sibling of ``out`` to write into; on success it becomes
    ``out`` (atomically replacing a dataset there when ``overwrite``), on error it is removed.

    Raises ``FileExistsError`` if ``out`` is a non-empty folder (without ``overwrite``) or
    holds something that is not a dataset (never deleted).
    """
    out = Path(out).absolute()
    if out.exists():
        if not out.is_dir():
            raise FileExistsError(f"{out} exists and is not a directory")
        if any(out.iterdir()):
            if not overwrite:
                raise FileExistsError(f"{out} exists and is not empty (overwrite replaces it)")
            if not _looks_like_dataset(out):
                raise FileExistsError(f"{out} exists and is not a dataset; refusing to replace it")
    with atomic_dir(out) as tmp:  # the one folder swap (aoi3d.atomic)
        yield tmp
