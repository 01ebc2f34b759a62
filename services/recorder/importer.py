"""A recording as a scene dataset for the experiments (``aoi3d scene import``).

Two kinds of MCAP file are read:

- **an aoi3d recording** (``aoi3d up --record``): one site's delivered frames — the frames of
  the cameras that reached the edge (a frame the link lost is not in it) — and its truth
  frames (the held-out view), pixels, poses and intrinsics as recorded;
- **a rosbag2 in MCAP** of real cameras (``ros2 bag record -s mcap``: CDR messages with their
  ``ros2msg`` schemas): the rig file that runs them live says which topic is which camera, and
  every message goes through the ingest's own core (:class:`services.ingest.core.IngestCore`:
  the same decoding, resizing, pose matching by stamp and refusals as live), its log time
  standing for its receipt. What the core refuses is counted by reason in the report.

**The dataset** is the project's own layout: a fixed rig on a frame grid of ``fps``. Camera 0
is the truth camera; 1..N the others, in the order of their recorded ids. The layout holds one
pose per camera, so a camera whose pose moves by more than ``POSE_TOL`` (in any entry of its
camera-to-world matrix) is refused, naming it. The grid starts at the latest first frame of
any camera and ends at the earliest last one (every camera has a frame at every grid point);
frame k of a camera is the newest of its frames generated at or before t0 + k/fps: what that
camera showed then. ``fps`` defaults to the rate of the truth camera's frames, rounded (the
layout's fps is a whole number: the emulator's 30-ms period is 33.3/s and becomes 33, so 1
frame in 100 falls between grid points). The report counts, per camera, the recorded frames
used, those that fell between grid points (``dropped``) and the grid points that repeat a frame
older than one grid step (``held``: a gap in the recording — a frame the link lost).
"""

from __future__ import annotations

import bisect
import math
import re
from collections import Counter
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from aoi3d.scene import HELDOUT_ID, Camera, SceneDataset, write_dataset
from aoi3d.scene.dataset import png_problem
from services.kit.codec import camera_from_pb, decode_image, png_bytes
from services.kit.pb import aoi3d_pb2 as pb
from services.kit.rejected import Rejected
from services.recorder.sources import (
    NotImportable,
    Spool,
    Stream,
    kind_of,
    recorded_streams,
    rosbag_streams,
)

__all__ = [
    "MAX_FPS",
    "MAX_GRID_FRAMES",
    "POSE_TOL",
    "ImportReport",
    "NotImportable",
    "import_mcap",
    "kind_of",
    "recorded_streams",
]

MAX_FPS = 1000
"""The grid's rate at most: one frame a millisecond (a slot)."""
MAX_GRID_FRAMES = 2_000_000
"""Grid points (frames × cameras) a dataset may have: 30 GB of 96×72 PNGs, 29 hours of 19
cameras at 33 fps; refused before anything is written."""
POSE_TOL = 1e-4
"""Largest change of any camera-to-world entry (metres or cosines) a fixed camera may show."""
_TOL_MS = 1e-6


@dataclass
class ImportReport:
    """What an import made of a recording (``aoi3d scene import --json`` prints it)."""

    source: str
    kind: str
    site: str | None
    out: str
    fps: int
    n_frames: int
    t0_ms: float
    cameras: list[dict]
    rejected: dict[str, int] = field(default_factory=dict)

    def to_dict(self) -> dict:
        return {"source": self.source, "kind": self.kind, "site": self.site, "out": self.out,
                "fps": self.fps, "n_frames": self.n_frames, "t0_ms": self.t0_ms,
                "cameras": self.cameras, "rejected": self.rejected}


def _fixed_camera(stream: Stream) -> Camera:
    c2w = np.stack([np.asarray(f.pose.c2w, dtype=np.float64) for f in stream.frames])
    moved = float(np.max(np.ptp(c2w, axis=0)))
    if moved > POSE_TOL:
        raise NotImportable(f"camera {stream.name} moves (its pose changes by up to {moved:.3g} "
                            "in a camera-to-world entry): the dataset layout holds one pose "
                            "per camera")
    first = stream.frames[0]
    try:
        return camera_from_pb(first.pose, first.intrinsics)
    except Rejected as err:
        raise NotImportable(f"camera {stream.name}: {err.detail}") from None


def import_mcap(path: str | Path, out: str | Path, *, site: str | None = None,
                rig: str | Path | None = None, fps: int | None = None,
                aabb: list[float] | None = None) -> tuple[SceneDataset, ImportReport]:
    """Write the dataset ``out`` from the MCAP file ``path`` (see the module docstring)."""
    path = Path(path)
    files = [path]
    if path.is_dir():  # a rosbag2 folder (metadata.yaml and its .mcap files, split or not)
        files = sorted(path.glob("*.mcap"), key=lambda f: [int(t) if t.isdigit() else t for t
                                                           in re.split(r"(\d+)", f.name)])
        if not files:
            raise NotImportable(f"{path} is a folder without an .mcap file")
    elif not path.is_file():
        raise NotImportable(f"no file at {path}")
    kind = kind_of(files[0])
    if kind == "recording" and path.is_dir():
        raise NotImportable(f"{path}: give an aoi3d recording's .mcap file (its .partN "
                            "segments are found beside it)")
    spool = Spool()
    try:
        return _import(path, files, kind, out, site=site, rig=rig, fps=fps, aabb=aabb,
                       spool=spool)
    finally:
        spool.close()


def _grid_fps(path: Path, truth_gens: list[float], fps: int | None) -> int:
    """The dataset's frame rate: ``fps`` checked, else the truth camera's (its median gap)."""
    if fps is None:
        gaps = np.diff(np.unique(np.array(truth_gens)))
        if gaps.size == 0:
            raise NotImportable(f"{path} holds one truth frame: give --fps")
        gap = float(np.median(gaps))
        if gap < 1000.0 / MAX_FPS:
            raise NotImportable(f"{path}: the truth frames are {gap:.3g} ms apart (median), "
                                f"a grid over {MAX_FPS} fps: give --fps")
        fps = max(1, round(1000.0 / gap))
    if not 1 <= fps <= MAX_FPS:
        raise NotImportable(f"--fps must be 1..{MAX_FPS} (a frame a millisecond at most), "
                            f"got {fps}")
    return fps


def _import(path: Path, files: list[Path], kind: str, out: str | Path, *, site: str | None,
            rig: str | Path | None, fps: int | None, aabb: list[float] | None,
            spool: Spool) -> tuple[SceneDataset, ImportReport]:
    rejected: Counter = Counter()
    box = None
    if kind == "recording":
        if rig is not None:
            raise NotImportable("--rig is for a rosbag2; an aoi3d recording carries its "
                                "cameras itself")
        notes: list[str] = []
        site, streams, box = recorded_streams(path, site, notes=notes)
        if notes:
            rejected["cut_short"] += len(notes)
    else:
        if rig is None:
            raise NotImportable(f"{path} is a rosbag2: give the rig file that says which topic "
                                "is which camera (--rig)")
        if site is not None:
            raise NotImportable("--site is for an aoi3d recording (a rosbag2 has no sites)")
        streams, box, rejected = rosbag_streams(files, Path(rig), spool)
    if aabb is not None:
        box = np.asarray(aabb, dtype=np.float64).reshape(2, 3)
    if box is None:
        raise NotImportable(f"{path} records no scene box (no render carries one): give "
                            "--aabb xmin ymin zmin xmax ymax zmax")
    if HELDOUT_ID not in streams:
        raise NotImportable(f"{path} holds no frame of the truth camera (the held-out view): "
                            "a dataset needs it")
    train = sorted(c for c in streams if c != HELDOUT_ID)
    if not train:
        raise NotImportable(f"{path} holds frames of the truth camera only")
    order = [HELDOUT_ID, *train]
    for s in streams.values():
        s.frames.sort(key=lambda f: f.generation_ms)
    fps = _grid_fps(path, [f.generation_ms for f in streams[HELDOUT_ID].frames], fps)
    step = 1000.0 / fps
    t0 = max(s.frames[0].generation_ms for s in streams.values())
    t1 = min(s.frames[-1].generation_ms for s in streams.values())
    if t1 < t0:
        raise NotImportable(f"the cameras' frames do not overlap in time (the latest first frame "
                            f"at {t0:.0f} ms, the earliest last one at {t1:.0f} ms)")
    n_frames = math.floor((t1 - t0) / step + 1e-9) + 1
    if n_frames * len(order) > MAX_GRID_FRAMES:
        raise NotImportable(f"{path}: {n_frames} frames × {len(order)} cameras at {fps} fps "
                            f"over {(t1 - t0) / 1000:.1f} s, over the {MAX_GRID_FRAMES} frames "
                            f"a dataset may have: give a lower --fps")
    cameras: list[Camera] = []
    picks: list[list[int]] = []
    rows: list[dict[str, object]] = []
    for cam in order:
        s = streams[cam]
        cameras.append(_fixed_camera(s))
        gens = [f.generation_ms for f in s.frames]
        pick = [bisect.bisect_right(gens, t0 + k * step + _TOL_MS) - 1 for k in range(n_frames)]
        used = set(pick)
        in_span = [i for i, g in enumerate(gens) if t0 - _TOL_MS <= g <= t1 + _TOL_MS]
        held = sum(1 for k, i in enumerate(pick) if t0 + k * step - gens[i] >= step - _TOL_MS)
        rows.append({"id": len(rows), "name": s.name, "recorded_id": cam,
                     "frames": len(s.frames), "used": len(used),
                     "dropped": len([i for i in in_span if i not in used]), "held": held})
        picks.append(pick)
    sizes = {(c.width, c.height) for c in cameras}
    if len(sizes) != 1:
        raise NotImportable(f"the cameras' images differ in size ({sorted(sizes)}): the layout "
                            "holds one size")

    def frame_png(camera_id: int, k: int) -> bytes:
        s = streams[order[camera_id]]
        return _checked_png(path, s, s.frames[picks[camera_id][k]])

    report = ImportReport(source=str(path), kind=kind, site=site, out=str(out), fps=fps,
                          n_frames=n_frames, t0_ms=t0, cameras=rows, rejected=dict(rejected))
    ds = write_dataset(out, cameras, frame_png, fps=fps, n_frames=n_frames, aabb=box,
                       extra={"imported": {k: v for k, v in report.to_dict().items()
                                           if k != "out"}})
    return ds, report


def _checked_png(path: Path, s: Stream, fr: pb.Frame) -> bytes:
    """The PNG bytes of recorded frame ``fr`` of stream ``s``, once its whole image decodes; a
    damaged image is :class:`NotImportable`, in one line naming the file, camera and frame
    (nothing is written: the dataset's folder is atomic)."""
    try:
        image = s.pixels(fr).image
        decode_image(image)  # the whole image decodes, not just its first and last bytes
        data = png_bytes(image)
    except (Rejected, ValueError, OSError) as err:
        why = err.detail if isinstance(err, Rejected) else type(err).__name__
        why = " ".join(why.split())  # one line
        raise NotImportable(f"{path}: camera {s.name}, frame at {fr.generation_ms:g} ms: "
                            f"its image cannot be read ({why})") from None
    if problem := png_problem(data[:8], data[-12:], len(data)):
        raise NotImportable(f"{path}: camera {s.name}, frame at {fr.generation_ms:g} ms: "
                            f"{problem.replace('frame file', 'its image')}")
    return data
