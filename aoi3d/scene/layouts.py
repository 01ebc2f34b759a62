"""Open any supported dataset folder, or export one to another layout.

Layouts (:data:`LAYOUTS`), recognised by their files:

* ``aoi3d``  — the project's own (``transforms_train.json`` with an ``aoi3d`` block):
  :func:`aoi3d.scene.load_dataset`.
* ``dynerf`` — DyNeRF / Neural 3D Video (``poses_bounds.npy`` and ``camNN.mp4``):
  :func:`aoi3d.scene.dynerf.load_dynerf`.
* ``dnerf``  — D-NeRF / nerfstudio (``transforms_train.json`` or ``transforms.json`` with a
  per-frame ``time``): :func:`aoi3d.scene.dnerf.load_dnerf`.

Every reader returns a :class:`aoi3d.scene.SceneDataset`, the interface the services and
experiments use.
"""

from __future__ import annotations

import json
from collections.abc import Sequence
from dataclasses import replace
from pathlib import Path
from typing import Any

import numpy as np

from aoi3d.scene import dnerf, dynerf
from aoi3d.scene.dataset import LAYOUT as AOI3D_LAYOUT
from aoi3d.scene.dataset import (
    TRAIN_JSON,
    DatasetError,
    DatasetNotFound,
    SceneDataset,
    generate_command,
    load_dataset,
)
from aoi3d.scene.media import target_size

__all__ = ["EXPORT_FORMATS", "LAYOUTS", "detect_layout", "export_dataset", "open_dataset"]

LAYOUTS = (AOI3D_LAYOUT, dnerf.LAYOUT, dynerf.LAYOUT)
EXPORT_FORMATS = (dnerf.LAYOUT, dynerf.LAYOUT)


def _has_aoi3d_block(path: Path) -> bool:
    try:
        doc = json.loads(path.read_text())
    except (OSError, json.JSONDecodeError):
        return False
    return isinstance(doc, dict) and isinstance(doc.get("aoi3d"), dict)


def detect_layout(path: str | Path) -> str:
    """The layout of the dataset folder at ``path`` (one of :data:`LAYOUTS`).

    Raises :class:`~aoi3d.scene.DatasetNotFound` (a ``FileNotFoundError``; one line naming
    what was looked for and what to do) when none is recognised.
    """
    root = Path(path)
    if not root.is_dir():
        what = "is not a directory" if root.exists() else "does not exist"
        raise DatasetNotFound(f"no dataset here: {root} {what}; generate one with "
                              f"`{generate_command(root)}` or give a dataset folder", path=root)
    if (root / TRAIN_JSON).is_file() and _has_aoi3d_block(root / TRAIN_JSON):
        return AOI3D_LAYOUT
    if (root / dynerf.POSES_BOUNDS).is_file() or any(
        dynerf.VIDEO_RE.match(p.name) for p in root.iterdir()
    ):
        return dynerf.LAYOUT
    if any((root / name).is_file() for name in (*dnerf.SPLIT_JSONS.values(), dnerf.SINGLE_JSON)):
        return dnerf.LAYOUT
    raise DatasetNotFound(
        f"no dataset recognised in {root}: expected {TRAIN_JSON} (aoi3d or D-NeRF), "
        f"{dnerf.SINGLE_JSON} (nerfstudio), or {dynerf.POSES_BOUNDS} with camNN.mp4 (DyNeRF); "
        f"give the folder that holds them, or generate one with `{generate_command(root)}`",
        path=root)


def open_dataset(
    path: str | Path,
    *,
    layout: str | None = None,
    downscale: float | None = None,
    width: int | None = None,
    heldout: int | None = None,
    aabb: np.ndarray | Sequence[Sequence[float]] | None = None,
    verify: bool = False,
) -> SceneDataset:
    """Read the dataset at ``path`` in whatever layout it is (or ``layout``).

    A dataset that cannot be read raises :class:`~aoi3d.scene.DatasetError` (or
    :class:`~aoi3d.scene.DatasetNotFound`), one line naming the file and what to do.
    ``verify`` also checks every frame file (present, not empty, a whole PNG) and decodes one
    frame (:meth:`SceneDataset.require_frames`): what the commands and services that stream
    the frames do before they start.

    ``downscale`` (factor) / ``width`` (pixels) set the frame size of the DyNeRF and D-NeRF
    readers; ``heldout`` picks their held-out camera (DyNeRF: the NN of ``camNN.mp4``;
    D-NeRF: see :func:`aoi3d.scene.dnerf.load_dnerf`); ``aabb`` overrides the box of any
    layout. The aoi3d layout is read at its stored size with camera 0 held out: asking it
    for ``downscale``, ``width`` or ``heldout`` raises ``ValueError``.
    """
    layout = layout if layout is not None else detect_layout(path)
    ds = _read(path, layout, downscale=downscale, width=width, heldout=heldout, aabb=aabb)
    return ds.require_frames() if verify else ds


def _read(path: str | Path, layout: str, *, downscale: float | None, width: int | None,
          heldout: int | None, aabb: np.ndarray | Sequence[Sequence[float]] | None
          ) -> SceneDataset:
    if layout == AOI3D_LAYOUT:
        given = [n for n, v in (("downscale", downscale), ("width", width),
                                ("heldout", heldout)) if v is not None]
        if given:
            raise ValueError(f"{', '.join(given)}: not supported by the aoi3d layout (frames "
                             "are read as generated; regenerate with another --width)")
        ds = load_dataset(path)
        if aabb is not None:
            box = np.asarray(aabb, dtype=np.float64)
            if box.shape != (2, 3) or not np.all(box[0] < box[1]):
                raise ValueError(f"aabb must be (2, 3) with min < max, got {box.tolist()}")
            ds = replace(ds, aabb=box)
        return ds
    target_size(100, 100, downscale=downscale, target_width=width)  # bad options: ValueError
    root = Path(path).absolute()
    fix = (f"fix or restore the {layout} dataset's files (or give another folder); the layout "
           "is described in aoi3d/scene/" + layout + ".py")
    try:
        if layout == dynerf.LAYOUT:
            return dynerf.load_dynerf(path, downscale=downscale, width=width,
                                      heldout=0 if heldout is None else heldout, aabb=aabb)
        if layout == dnerf.LAYOUT:
            return dnerf.load_dnerf(path, downscale=downscale, width=width, heldout=heldout,
                                    aabb=aabb)
    except DatasetError:
        raise
    except FileNotFoundError as err:
        raise DatasetNotFound(f"{_named(err, root)}; {fix}", path=root) from err
    except ValueError as err:
        raise DatasetError(f"{_named(err, root)}; {fix}", path=root) from err
    raise ValueError(f"unknown layout {layout!r}; accepted: {', '.join(LAYOUTS)}")


def _named(err: Exception, root: Path) -> str:
    """The reader's message, led by the folder unless it names the folder already."""
    text = str(err)
    return text if str(root) in text else f"{root}: {text}"


def export_dataset(dataset: SceneDataset, out: str | Path, fmt: str, **options: Any) -> Path:
    """Write ``dataset`` to ``out`` in ``fmt`` (one of :data:`EXPORT_FORMATS`); ``options`` go
    to :func:`aoi3d.scene.dynerf.export_dynerf` or :func:`aoi3d.scene.dnerf.export_dnerf`."""
    if fmt == dynerf.LAYOUT:
        return dynerf.export_dynerf(dataset, out, **options)
    if fmt == dnerf.LAYOUT:
        return dnerf.export_dnerf(dataset, out, **options)
    raise ValueError(f"unknown export format {fmt!r}; accepted: {', '.join(EXPORT_FORMATS)}")
