"""A recording read back (:func:`load`): per site, the delivered frames, the truth frames, the
decisions with their AoI vectors, the renders, their Quality and the outcomes — what a replay
(:mod:`services.recorder.replay`), the importer and the player take.

**Streaming** (issue 44). :func:`load` reads the file once, in file order, one chunk in
memory at a time (:mod:`services.recorder.mcapfile`), and keeps every message *but the
pixels*: of each image it keeps where it is (:class:`Pixels`, 22 bytes an image), and a
frame's pixels are read again when one is needed (:meth:`Recorded.with_pixels`, a few chunks
cached). So memory grows with the recording's messages at about a hundredth of the file's
size (7.5 MiB a minute of the default run are pixels), not with the file.

What cannot be read is counted, never raised past the caller: a message whose bytes do not
decode with its schema, a schema that is not the recorder's on a recorded topic
(:attr:`Recorded.refused`); a file cut short is read up to its last whole record
(:attr:`Recorded.cut_short`); a file that is not MCAP, or a record over the caps, is one
line naming the file (:class:`services.recorder.mcapfile.McapFileError`).
"""

from __future__ import annotations

from collections import Counter, defaultdict
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
from foxglove_schemas_protobuf.CompressedImage_pb2 import CompressedImage
from foxglove_schemas_protobuf.RawImage_pb2 import RawImage

from services.kit.pb import aoi3d_pb2 as pb
from services.recorder.core import segments, sim_ms_of, sim_ns
from services.recorder.mcapfile import ChunkCache, McapFileError, Reading, Where

__all__ = ["McapFileError", "Pixels", "Recorded", "SiteRecord", "load"]

_CLASSES: dict[str, Any] = {cls.DESCRIPTOR.full_name: cls for cls in (
    pb.Frame, pb.Decision, pb.Render, pb.Quality, pb.Outcome)}
_IMAGES: dict[str, Any] = {"foxglove.CompressedImage": CompressedImage,
                           "foxglove.RawImage": RawImage}
_EXPECTED: dict[str, Any] = {"delivery": pb.Frame, "truth": pb.Frame, "decision": pb.Decision,
             "render": pb.Render, "quality": pb.Quality, "outcome": pb.Outcome}


@dataclass
class SiteRecord:
    deliveries: list[pb.Frame] = field(default_factory=list)
    truth: list[pb.Frame] = field(default_factory=list)
    decisions: list[pb.Decision] = field(default_factory=list)
    renders: dict[tuple[int, int], pb.Render] = field(default_factory=dict)
    qualities: dict[tuple[int, int], pb.Quality] = field(default_factory=dict)
    outcomes: list[pb.Outcome] = field(default_factory=list)
    frames_without_pixels: int = 0


class Pixels:
    """Where each recorded image is, by frame id (``<site>/cam<n>``, ``<site>/truth``) and
    generation time (ns): numpy arrays, read again through a :class:`ChunkCache`."""

    def __init__(self, files: list[Path]) -> None:
        self._cache = ChunkCache(files)
        self._lists: dict[str, list[tuple[int, int, int, int]]] = defaultdict(list)
        self._index: dict[str, tuple[np.ndarray, np.ndarray]] = {}

    def add(self, frame_id: str, gen_ns: int, where: Where) -> None:
        self._lists[frame_id].append((gen_ns, where.file, where.offset, where.index))

    def freeze(self) -> None:
        """The lists as sorted arrays (the last of equal times wins, as a re-recorded one)."""
        for frame_id, items in self._lists.items():
            arr = np.asarray(items, dtype=np.int64).reshape(-1, 4)
            order = np.argsort(arr[:, 0], kind="stable")
            self._index[frame_id] = (arr[order, 0].copy(), arr[order, 1:].copy())
        self._lists.clear()

    def where(self, frame_id: str, gen_ms: float) -> Where | None:
        got = self._index.get(frame_id)
        if got is None:
            return None
        gens, wheres = got
        ns = sim_ns(gen_ms)
        k = int(np.searchsorted(gens, ns, side="right")) - 1
        if k < 0 or gens[k] != ns:
            return None
        f, o, i = (int(x) for x in wheres[k])
        return Where(f, o, i)

    def data(self, where: Where, schema: str) -> bytes:
        data: bytes = _IMAGES[schema].FromString(self._cache.message(where).data).data
        return data

    @property
    def images(self) -> int:
        return sum(len(g) for g, _ in self._index.values())


@dataclass
class Recorded:
    path: Path
    files: list[Path]
    metadata: dict[str, str]
    sites: dict[str, SiteRecord]
    pixels: Pixels | None = None
    """Where the images are; None: the frames carry their pixels (built in memory)."""
    cut_short: list[str] = field(default_factory=list)
    refused: Counter[str] = field(default_factory=Counter)
    """Messages that could not be taken, by reason (``bad_message``, ``wrong_schema``,
    ``unknown_schema``)."""
    _schemas: dict[str, str] = field(default_factory=dict)

    @staticmethod
    def frame_id(site: str, fr: pb.Frame) -> str:
        return f"{site}/{'truth' if fr.camera_id == 0 else f'cam{fr.camera_id}'}"

    def has_pixels(self, site: str, fr: pb.Frame) -> bool:
        if fr.image.data or self.pixels is None:
            return bool(fr.image.data)
        return self.pixels.where(self.frame_id(site, fr), fr.generation_ms) is not None

    def with_pixels(self, site: str, fr: pb.Frame) -> pb.Frame:
        """``fr`` with its pixels (a copy, read from the file; ``fr`` itself when it has them
        or none were recorded)."""
        if fr.image.data or self.pixels is None:
            return fr
        frame_id = self.frame_id(site, fr)
        where = self.pixels.where(frame_id, fr.generation_ms)
        if where is None:
            return fr
        out = pb.Frame()
        out.CopyFrom(fr)
        out.image.data = self.pixels.data(where, self._schemas[frame_id])
        return out


def _valid(msg: Any) -> bool:
    """What the recorder checked when it wrote a message (times finite, an AoI per camera),
    checked again: a damaged file's message that decodes but cannot be used is refused."""
    times = {pb.Frame: ("generation_ms", "delivery_ms", "send_ms"),
             pb.Decision: ("time_ms",), pb.Render: ("time_ms",), pb.Quality: ("time_ms",)}
    if not all(np.isfinite(getattr(msg, t)) for t in times.get(type(msg), ())):
        return False
    if isinstance(msg, pb.Decision):
        return len(msg.aoi_ms) == len(msg.camera_ids) and all(
            np.isfinite(r.generation_ms) for r in msg.selected)
    if isinstance(msg, pb.Render):
        return all(np.isfinite(g) for g in msg.frame_generation_ms)
    return True


def load(path: Path) -> Recorded:
    """Every message of ``path`` and its segments but the pixels (see the module
    docstring); :class:`FileNotFoundError` without a file, :class:`McapFileError` for one
    that is not MCAP."""
    files = segments(Path(path))
    if not files:
        raise FileNotFoundError(f"no recording at {path}")
    sites: dict[str, SiteRecord] = defaultdict(SiteRecord)
    pixels = Pixels(files)
    metadata: dict[str, str] = {}
    reading = Reading(files)
    refused: Counter[str] = Counter()
    image_schema: dict[str, str] = {}
    for m in reading.messages():
        topic = m.channel.topic
        parts = topic.strip("/").split("/")
        if topic == "/tf" or parts[-1] == "calibration" or len(parts) < 2:
            continue
        site, what = parts[0], "/".join(parts[1:])
        name = m.schema.name if m.schema is not None else ""
        if what.endswith("image"):
            if what == "render/image":
                continue
            cls = _IMAGES.get(name)
            if cls is None:
                refused["wrong_schema"] += 1
                continue
            try:
                img = cls.FromString(m.message.data)
            except Exception:  # DecodeError: bytes that are not this message
                refused["bad_message"] += 1
                continue
            frame_id = f"{site}/{parts[1]}"
            image_schema[frame_id] = name
            pixels.add(frame_id, sim_ns(sim_ms_of(img.timestamp)), m.where)
            continue
        want = _EXPECTED.get(what)
        if want is None:
            continue  # a topic the recorder does not write: not ours to judge
        if _CLASSES.get(name) is not want:
            refused["unknown_schema" if name not in _CLASSES else "wrong_schema"] += 1
            continue
        assert want is not None
        try:
            msg = want.FromString(m.message.data)
        except Exception:
            refused["bad_message"] += 1
            continue
        if not _valid(msg):
            refused["bad_message"] += 1
            continue
        rec = sites[site]
        if what == "delivery":
            rec.deliveries.append(msg)
        elif what == "truth":
            rec.truth.append(msg)
        elif what == "decision":
            rec.decisions.append(msg)
        elif what == "render":
            rec.renders[(msg.decision_incarnation, msg.decision_id)] = msg
        elif what == "quality":
            rec.qualities[(msg.decision_incarnation, msg.decision_id)] = msg
        else:
            rec.outcomes.append(msg)
    for record in reading.metadata:
        if record.name == "aoi3d":
            metadata = dict(record.metadata)
            break
    pixels.freeze()
    out = Recorded(Path(path), files, metadata, dict(sites), pixels, reading.cut_short,
                   refused, image_schema)
    for site, rec in out.sites.items():
        for fr in [*rec.deliveries, *rec.truth]:
            if not out.has_pixels(site, fr):
                rec.frames_without_pixels += 1
        rec.deliveries.sort(key=lambda fr: (fr.delivery_ms, fr.camera_id))
        rec.truth.sort(key=lambda fr: fr.generation_ms)
        rec.decisions.sort(key=lambda d: (d.time_ms, d.decision_id))
    return out
