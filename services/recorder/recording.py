"""A recording read back (:func:`load`): per site, the delivered frames (pixels joined back
from their Foxglove images), the truth frames, the decisions with their AoI vectors, the
renders, their Quality and the outcomes — what a replay (:mod:`services.recorder.replay`) and
the importer take."""

from __future__ import annotations

from collections import defaultdict
from dataclasses import dataclass, field
from pathlib import Path

from mcap.reader import make_reader
from mcap_protobuf.decoder import DecoderFactory

from services.kit.pb import aoi3d_pb2 as pb
from services.recorder.core import segments, sim_ms_of, sim_ns

__all__ = ["Recorded", "SiteRecord", "load"]

_CLASSES = {cls.DESCRIPTOR.full_name: cls for cls in (pb.Frame, pb.Decision, pb.Render,
                                                      pb.Quality, pb.Outcome)}


@dataclass
class SiteRecord:
    deliveries: list[pb.Frame] = field(default_factory=list)
    truth: list[pb.Frame] = field(default_factory=list)
    decisions: list[pb.Decision] = field(default_factory=list)
    renders: dict[tuple[int, int], pb.Render] = field(default_factory=dict)
    qualities: dict[tuple[int, int], pb.Quality] = field(default_factory=dict)
    outcomes: list[pb.Outcome] = field(default_factory=list)
    frames_without_pixels: int = 0


@dataclass
class Recorded:
    path: Path
    files: list[Path]
    metadata: dict[str, str]
    sites: dict[str, SiteRecord]


def load(path: Path) -> Recorded:
    """Every message of ``path`` and its segments, decoded with the schemas in the file."""
    files = segments(Path(path))
    if not files:
        raise FileNotFoundError(f"no recording at {path}")
    sites: dict[str, SiteRecord] = defaultdict(SiteRecord)
    images: dict[tuple[str, int], bytes] = {}
    metadata: dict[str, str] = {}
    for f in files:
        with open(f, "rb") as stream:
            reader = make_reader(stream, decoder_factories=[DecoderFactory()])
            for record in reader.iter_metadata():
                if record.name == "aoi3d" and not metadata:
                    metadata = dict(record.metadata)
            for schema, channel, _message, msg in reader.iter_decoded_messages(
                    log_time_order=False):
                topic = channel.topic
                parts = topic.strip("/").split("/")
                if topic == "/tf" or parts[-1] == "calibration":
                    continue
                site, what = parts[0], "/".join(parts[1:])
                assert schema is not None, "mcap decodes no message without its schema"
                if schema.name.startswith("aoi3d."):  # decoded with the file's schema; as
                    msg = _CLASSES[schema.name].FromString(msg.SerializeToString())  # ours
                if what.endswith("image"):
                    if what != "render/image":
                        images[(msg.frame_id, sim_ns(sim_ms_of(msg.timestamp)))] = msg.data
                elif what == "delivery":
                    sites[site].deliveries.append(msg)
                elif what == "truth":
                    sites[site].truth.append(msg)
                elif what == "decision":
                    sites[site].decisions.append(msg)
                elif what == "render":
                    sites[site].renders[(msg.decision_incarnation, msg.decision_id)] = msg
                elif what == "quality":
                    sites[site].qualities[(msg.decision_incarnation, msg.decision_id)] = msg
                elif what == "outcome":
                    sites[site].outcomes.append(msg)
    for site, rec in sites.items():
        for frames, name in ((rec.deliveries, None), (rec.truth, "truth")):
            for fr in frames:
                data = images.get((f"{site}/{name or f'cam{fr.camera_id}'}",
                                   sim_ns(fr.generation_ms)))
                if data is None:
                    rec.frames_without_pixels += 1
                else:
                    fr.image.data = data
        rec.deliveries.sort(key=lambda fr: (fr.delivery_ms, fr.camera_id))
        rec.truth.sort(key=lambda fr: fr.generation_ms)
        rec.decisions.sort(key=lambda d: (d.time_ms, d.decision_id))
    return Recorded(Path(path), files, metadata, dict(sites))
