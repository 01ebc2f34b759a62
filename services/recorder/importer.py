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
from services.kit.codec import camera_from_pb, png_bytes
from services.kit.pb import aoi3d_pb2 as pb
from services.kit.rejected import Rejected

__all__ = [
    "POSE_TOL",
    "ImportReport",
    "NotImportable",
    "import_mcap",
    "kind_of",
    "recorded_streams",
]

POSE_TOL = 1e-4
"""Largest change of any camera-to-world entry (metres or cosines) a fixed camera may show."""
_TOL_MS = 1e-6


class NotImportable(ValueError):
    """The file cannot become a dataset; the message says why."""


@dataclass
class _Stream:
    """One camera's recorded frames, by generation time."""

    name: str
    frames: list[pb.Frame] = field(default_factory=list)


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


def kind_of(path: Path) -> str:
    """``recording`` (aoi3d's protobuf schemas) or ``rosbag2`` (``ros2msg`` schemas)."""
    from mcap.exceptions import McapError
    from mcap.reader import make_reader

    try:
        with open(path, "rb") as stream:
            reader = make_reader(stream)
            summary = reader.get_summary()
            schemas = list(summary.schemas.values()) if summary is not None else []
            if not schemas:  # no summary (a recording cut short): read schemas on the way
                from mcap.records import Schema
                from mcap.stream_reader import StreamReader

                stream.seek(0)
                schemas = [r for r in StreamReader(stream).records if isinstance(r, Schema)]
    except McapError as err:
        raise NotImportable(f"{path} cannot be read as MCAP: {err}") from None
    if any(s.name.startswith("aoi3d.") for s in schemas):
        return "recording"
    if any(s.encoding == "ros2msg" for s in schemas):
        return "rosbag2"
    names = ", ".join(sorted({s.name for s in schemas})) or "none"
    raise NotImportable(f"{path}: neither an aoi3d recording (aoi3d.* schemas) nor a rosbag2 "
                        f"of ROS 2 messages (ros2msg schemas); its schemas: {names}")


def recorded_streams(path: Path, site: str | None = None) -> tuple[str, dict[int, _Stream],
                                                                  np.ndarray | None]:
    """One site's frames with pixels (truth and delivered), by camera id, and the scene box
    its renders carry (None without a render); ``site`` may be left out when there is one."""
    from services.recorder.recording import load

    rec = load(path)
    sites = sorted(rec.sites)
    if site is None:
        if len(sites) != 1:
            raise NotImportable(f"{path} holds sites {', '.join(sites) or 'none'}: name one "
                                "with --site")
        site = sites[0]
    if site not in rec.sites:
        raise NotImportable(f"no site {site} in {path}; it holds {', '.join(sites) or 'none'}")
    sr = rec.sites[site]
    streams: dict[int, _Stream] = {}
    for fr in [*sr.truth, *sr.deliveries]:
        if fr.image.data:  # (frames known from before the recording began have no pixels)
            streams.setdefault(fr.camera_id, _Stream(f"cam{fr.camera_id}")).frames.append(fr)
    for s in streams.values():
        s.frames.sort(key=lambda f: f.generation_ms)
    aabb = next((np.asarray(r.aabb).reshape(2, 3) for r in sr.renders.values()
                 if len(r.aabb) == 6), None)
    return site, streams, aabb


def _from_rosbag(files: list[Path], rig_path: Path) -> tuple[dict[int, _Stream], np.ndarray,
                                                      Counter]:
    from mcap.reader import make_reader

    from aoi3d.rigfile import load_rig
    from services import ros
    from services.ingest.core import IngestCore
    from services.kit.keys import Keys

    rig = load_rig(rig_path)
    if rig.truth is None:
        raise NotImportable(f"{rig_path}: the rig names no truth camera; a dataset needs the "
                            "held-out view (truth: <camera>)")
    streams: dict[int, _Stream] = {}
    rejected: Counter = Counter()
    core: IngestCore | None = None

    def take(published) -> None:
        for p in published:
            fr = pb.Frame.FromString(p.payload)
            streams.setdefault(fr.camera_id, _Stream(p.camera)).frames.append(fr)

    def expire(now_s: float) -> None:
        assert core is not None, "after the first message"
        frames, refused = core.expire(now_s)
        take(frames)
        rejected.update(err.reason for _name, err in refused)

    def messages():
        for f in files:  # a split bag's files one after another
            with open(f, "rb") as stream:
                yield from make_reader(stream).iter_messages(log_time_order=True)

    for schema, channel, message in messages():
        receipt_s = message.log_time / 1e9
        if core is None:
            # the run's clock starts as early as a stamp the ingest accepts (max_age_s)
            # a bag has topics, not Zenoh keys or attachments: the bridge's key format
            core = IngestCore(rig, Keys("import"), epoch_s=receipt_s - rig.clock.max_age_s,
                              time_scale=1.0, key_format=ros.KeyFormat("bridge"))
            routes = {r.topic: r for r in core.routes}
        route = routes.get("/" + channel.topic.strip("/"))
        if route is None:
            continue
        if schema is None or _type(schema.name) != _type(route.ros_type):
            rejected["wrong_type"] += 1
            continue
        try:
            take(core.on_sample(route, channel.topic, message.data, None, receipt_s))
        except Rejected as err:
            rejected[err.reason] += 1
        expire(receipt_s)
    path = files[0].parent if len(files) > 1 else files[0]
    if core is None:
        raise NotImportable(f"{path} holds no message")
    expire(math.inf)
    ids = rig.ids()
    missing = [c.name for c in rig.cameras if ids[c.name] not in streams]
    if missing:
        why = ", ".join(f"{k} {v}" for k, v in sorted(rejected.items())) or "none refused"
        raise NotImportable(f"camera(s) {', '.join(missing)} of {rig_path}: no frame in {path} "
                            f"(the ingest refused: {why})")
    return streams, rig.scene_box.reshape(2, 3), rejected


def _type(name: str) -> str:
    """``sensor_msgs/msg/Image`` and ``sensor_msgs/Image`` alike."""
    return name.replace("/msg/", "/")


def _fixed_camera(stream: _Stream) -> Camera:
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


def _mcap_files(path: Path) -> list[Path]:
    """The file ``path``, or a rosbag2 folder's .mcap files (split or not) in order."""
    files = [path]
    if path.is_dir():
        files = sorted(path.glob("*.mcap"), key=lambda f: [int(t) if t.isdigit() else t for t
                                                           in re.split(r"(\d+)", f.name)])
        if not files:
            raise NotImportable(f"{path} is a folder without an .mcap file")
    elif not path.is_file():
        raise NotImportable(f"no file at {path}")
    return files


def _on_the_grid(streams: dict[int, _Stream], order: list[int], t0: float, t1: float,
                 step: float, n_frames: int
                 ) -> tuple[list[Camera], list[list[int]], list[dict]]:
    """Per camera: its camera, its frame at each t0 + k·step (the newest), its report row."""
    cameras: list[Camera] = []
    picks: list[list[int]] = []
    rows: list[dict] = []
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
    return cameras, picks, rows


def import_mcap(path: str | Path, out: str | Path, *, site: str | None = None,
                rig: str | Path | None = None, fps: int | None = None,
                aabb: list[float] | None = None) -> tuple[SceneDataset, ImportReport]:
    """Write the dataset ``out`` from the MCAP file ``path`` (see the module docstring)."""
    path = Path(path)
    files = _mcap_files(path)
    kind = kind_of(files[0])
    if kind == "recording" and path.is_dir():
        raise NotImportable(f"{path}: give an aoi3d recording's .mcap file (its .partN "
                            "segments are found beside it)")
    rejected: Counter = Counter()
    box = None
    if kind == "recording":
        if rig is not None:
            raise NotImportable("--rig is for a rosbag2; an aoi3d recording carries its "
                                "cameras itself")
        site, streams, box = recorded_streams(path, site)
    else:
        if rig is None:
            raise NotImportable(f"{path} is a rosbag2: give the rig file that says which topic "
                                "is which camera (--rig)")
        if site is not None:
            raise NotImportable("--site is for an aoi3d recording (a rosbag2 has no sites)")
        streams, box, rejected = _from_rosbag(files, Path(rig))
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
    truth_gens = np.array([f.generation_ms for f in streams[HELDOUT_ID].frames])
    if fps is None:
        gaps = np.diff(np.unique(truth_gens))
        if gaps.size == 0:
            raise NotImportable(f"{path} holds one truth frame: give --fps")
        fps = max(1, round(1000.0 / float(np.median(gaps))))
    step = 1000.0 / fps
    t0 = max(s.frames[0].generation_ms for s in streams.values())
    t1 = min(s.frames[-1].generation_ms for s in streams.values())
    if t1 < t0:
        raise NotImportable(f"the cameras' frames do not overlap in time (the latest first frame "
                            f"at {t0:.0f} ms, the earliest last one at {t1:.0f} ms)")
    n_frames = math.floor((t1 - t0) / step + 1e-9) + 1
    cameras, picks, rows = _on_the_grid(streams, order, t0, t1, step, n_frames)
    sizes = {(c.width, c.height) for c in cameras}
    if len(sizes) != 1:
        raise NotImportable(f"the cameras' images differ in size ({sorted(sizes)}): the layout "
                            "holds one size")

    def frame_png(camera_id: int, k: int) -> bytes:
        return png_bytes(streams[order[camera_id]].frames[picks[camera_id][k]].image)

    report = ImportReport(source=str(path), kind=kind, site=site, out=str(out), fps=fps,
                          n_frames=n_frames, t0_ms=t0, cameras=rows, rejected=dict(rejected))
    ds = write_dataset(out, cameras, frame_png, fps=fps, n_frames=n_frames, aabb=box,
                       extra={"imported": {k: v for k, v in report.to_dict().items()
                                           if k != "out"}})
    return ds, report
