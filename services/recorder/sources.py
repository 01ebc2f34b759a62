"""The frames an import or a live replay takes from an MCAP file, per camera and without their
pixels (issue 44: read incrementally, memory bounded whatever the file's length): an aoi3d
recording's (:func:`recorded_streams`, pixels read back from the file when a frame is
written or played) or a rosbag2's through the ingest's own core (:func:`rosbag_streams`,
pixels spooled to a temporary file). :func:`kind_of` tells the two apart."""

from __future__ import annotations

import functools
import math
import tempfile
from collections import Counter
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from services.kit.pb import aoi3d_pb2 as pb
from services.kit.rejected import Rejected
from services.recorder.mcapfile import McapFileError, Reading

__all__ = ["NotImportable", "Spool", "Stream", "kind_of", "recorded_streams", "rosbag_streams"]


_KIND_MESSAGES = 10_000
"""Messages read at most to find the file's kind from its schemas."""


class NotImportable(ValueError):
    """The file cannot become a dataset; the message says why."""


@dataclass
class Stream:
    """One camera's recorded frames, by generation time, without their pixels: ``pixels``
    gives a frame with them (read from the recording, or from the import's spool)."""

    name: str
    frames: list[pb.Frame] = field(default_factory=list)
    pixels: Callable[[pb.Frame], pb.Frame] = lambda fr: fr


class Spool:
    """The PNG bytes of the frames a rosbag import made, in a temporary file: memory holds
    where each is, not the pixels."""

    def __init__(self) -> None:
        self._file = tempfile.TemporaryFile()  # noqa: SIM115 - closed by close()
        self._where: dict[tuple[int, float], tuple[int, int]] = {}

    def keep(self, fr: pb.Frame) -> pb.Frame:
        self._file.seek(0, 2)
        self._where[(fr.camera_id, fr.generation_ms)] = (self._file.tell(), len(fr.image.data))
        self._file.write(fr.image.data)
        fr.image.data = b""
        return fr

    def pixels(self, fr: pb.Frame) -> pb.Frame:
        offset, size = self._where[(fr.camera_id, fr.generation_ms)]
        self._file.seek(offset)
        out = pb.Frame()
        out.CopyFrom(fr)
        out.image.data = self._file.read(size)
        return out

    def close(self) -> None:
        self._file.close()


def kind_of(path: Path) -> str:
    """``recording`` (aoi3d's protobuf schemas) or ``rosbag2`` (``ros2msg`` schemas), from
    the schemas before the first message (the summary is not needed: a cut file works)."""
    reading = Reading([path])
    schemas = reading.schemas_seen

    def kind() -> str | None:
        if any(name.startswith("aoi3d.") for name in schemas):
            return "recording"
        if any(enc == "ros2msg" for enc in schemas.values()):
            return "rosbag2"
        return None

    try:
        for k, _ in enumerate(reading.messages()):
            if kind() is not None or k >= _KIND_MESSAGES:
                break
    except McapFileError as err:
        raise NotImportable(str(err)) from None
    if kind() is not None:
        return kind()  # type: ignore[return-value]
    names = ", ".join(sorted(schemas)) or "none"
    raise NotImportable(f"{path}: neither an aoi3d recording (aoi3d.* schemas) nor a rosbag2 "
                        f"of ROS 2 messages (ros2msg schemas); its schemas: {names}")


def recorded_streams(path: Path, site: str | None = None, *, notes: list[str] | None = None
                     ) -> tuple[str, dict[int, Stream], np.ndarray | None]:
    """One site's frames with pixels on record (truth and delivered), by camera id, and the
    scene box its renders carry (None without a render); ``site`` may be left out when there
    is one. ``notes`` gets a line for each file read up to a cut."""
    from services.recorder.recording import load

    try:
        rec = load(path)
    except McapFileError as err:
        raise NotImportable(str(err)) from None
    if notes is not None:
        notes.extend(rec.cut_short)
    sites = sorted(rec.sites)
    if site is None:
        if len(sites) != 1:
            raise NotImportable(f"{path} holds sites {', '.join(sites) or 'none'}: name one "
                                "with --site")
        site = sites[0]
    if site not in rec.sites:
        raise NotImportable(f"no site {site} in {path}; it holds {', '.join(sites) or 'none'}")
    sr = rec.sites[site]
    streams: dict[int, Stream] = {}
    for fr in [*sr.truth, *sr.deliveries]:
        if rec.has_pixels(site, fr):  # (frames known from before the recording: none)
            streams.setdefault(fr.camera_id, Stream(
                f"cam{fr.camera_id}", pixels=functools.partial(rec.with_pixels, site))
            ).frames.append(fr)
    for s in streams.values():
        s.frames.sort(key=lambda f: f.generation_ms)
    aabb = next((np.asarray(r.aabb).reshape(2, 3) for r in sr.renders.values()
                 if len(r.aabb) == 6), None)
    return site, streams, aabb


def _type(name: str) -> str:
    """``sensor_msgs/msg/Image`` and ``sensor_msgs/Image`` alike."""
    return name.replace("/msg/", "/")


def rosbag_streams(files: list[Path], rig_path: Path, spool: Spool
                   ) -> tuple[dict[int, Stream], np.ndarray, Counter]:
    """A rosbag2's frames through the ingest's core (the rig file says which topic is which
    camera), pixels kept in ``spool``; what the core refuses counted by reason."""
    from aoi3d.rigfile import RigError, load_rig
    from services import ros
    from services.ingest.core import IngestCore
    from services.kit.keys import Keys

    try:
        rig = load_rig(rig_path)
    except RigError as err:
        raise NotImportable(str(err)) from None
    if rig.truth is None:
        raise NotImportable(f"{rig_path}: the rig names no truth camera; a dataset needs the "
                            "held-out view (truth: <camera>)")
    streams: dict[int, Stream] = {}
    rejected: Counter = Counter()
    core: IngestCore | None = None
    routes: dict = {}

    def take(published) -> None:
        for p in published:
            fr = spool.keep(pb.Frame.FromString(p.payload))
            streams.setdefault(fr.camera_id, Stream(p.camera, pixels=spool.pixels)
                               ).frames.append(fr)

    def expire(now_s: float) -> None:
        assert core is not None
        frames, refused = core.expire(now_s)
        take(frames)
        rejected.update(err.reason for _name, err in refused)

    reading = Reading(files)  # a split bag's files one after another, each in file order
    try:
        for m in reading.messages():
            receipt_s = m.message.log_time / 1e9
            if core is None:
                # the run's clock starts as early as a stamp the ingest accepts (max_age_s)
                # a bag has topics, not Zenoh keys or attachments: the bridge's key format
                core = IngestCore(rig, Keys("import"), epoch_s=receipt_s - rig.clock.max_age_s,
                                  time_scale=1.0, key_format=ros.KeyFormat("bridge"))
                routes = {r.topic: r for r in core.routes}
            route = routes.get("/" + m.channel.topic.strip("/"))
            if route is None:
                continue
            if m.schema is None or _type(m.schema.name) != _type(route.ros_type):
                rejected["wrong_type"] += 1
                continue
            try:
                take(core.on_sample(route, m.channel.topic, m.message.data, None, receipt_s))
            except Rejected as err:
                rejected[err.reason] += 1
            expire(receipt_s)
    except McapFileError as err:
        raise NotImportable(str(err)) from None
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
    if reading.cut_short:
        rejected["cut_short"] += 1
    return streams, rig.scene_box.reshape(2, 3), rejected
