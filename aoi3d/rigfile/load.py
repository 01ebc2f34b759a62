"""Reading a rig file (``.json``, any case, else YAML) and validating it: :class:`RigError`
names the file and each bad field. Bounded work whatever the file holds: at most
:data:`MAX_RIG_BYTES`, text in UTF-8 (or UTF-16/32 with a byte-order mark), at most
:data:`MAX_RIG_VALUES` values once parsed (YAML aliases counted each time they are used) and
at most :data:`MAX_RIG_CAMERAS` cameras, each refused before anything is validated."""

from __future__ import annotations

import codecs
import json
from pathlib import Path

from pydantic import ValidationError

from aoi3d.rigfile.model import Rig

__all__ = ["MAX_RIG_BYTES", "MAX_RIG_CAMERAS", "MAX_RIG_VALUES", "RigError", "load_rig",
           "missing_videos", "rig_from_dict"]

MAX_RIG_BYTES = 1024 * 1024
"""A rig file's size at most (257 cameras take about 150 kB)."""
MAX_RIG_VALUES = 100_000
"""Values (mappings, lists, scalars) a parsed rig document may hold."""
MAX_RIG_CAMERAS = 257
"""Cameras a rig may list: 256 training cameras and the truth camera."""
_BOMS = ((codecs.BOM_UTF32_LE, "utf-32"), (codecs.BOM_UTF32_BE, "utf-32"),
         (codecs.BOM_UTF8, "utf-8-sig"), (codecs.BOM_UTF16_LE, "utf-16"),
         (codecs.BOM_UTF16_BE, "utf-16"))


class RigError(ValueError):
    """A rig file that cannot be used: one line per problem, each naming its field."""


def _where(loc: tuple[int | str, ...]) -> str:
    out = ""
    for part in loc:
        if isinstance(part, int):
            out += f"[{part}]"
        elif part in ("function-after", "function-before") or "[" in str(part):
            continue
        else:
            out += ("." if out else "") + str(part)
    return out or "(top level)"


def _bounded(doc: object, source: str) -> None:
    """Refuse a document of over :data:`MAX_RIG_VALUES` values or :data:`MAX_RIG_CAMERAS`
    cameras, counting at most that many (an alias bomb costs nothing)."""
    if isinstance(doc, dict) and isinstance(doc.get("cameras"), list) \
            and len(doc["cameras"]) > MAX_RIG_CAMERAS:
        raise RigError(f"{source}: cameras: at most {MAX_RIG_CAMERAS} cameras (256 training "
                       f"cameras and the truth camera), got {len(doc['cameras'])}")
    stack, seen = [doc], 0
    while stack:
        node = stack.pop()
        seen += 1
        if seen > MAX_RIG_VALUES:
            raise RigError(f"{source}: over {MAX_RIG_VALUES} values (YAML aliases count each "
                           f"time they are used); a rig file is a short list of cameras")
        if isinstance(node, dict):
            stack.extend(node.keys())
            stack.extend(node.values())
        elif isinstance(node, list | tuple):
            stack.extend(node)


def rig_from_dict(doc: object, source: str = "rig") -> Rig:
    """Validate a parsed rig document; :class:`RigError` names each bad field."""
    if not isinstance(doc, dict):
        raise RigError(f"{source}: a rig file is a mapping (cameras:, aabb:, …), got "
                       f"{type(doc).__name__}")
    _bounded(doc, source)
    try:
        return Rig.model_validate(doc)
    except ValidationError as err:
        lines = []
        for e in err.errors():
            msg = e["msg"].removeprefix("Value error, ")
            lines.append(f"{source}: {_where(e['loc'])}: {msg}")
        raise RigError("\n".join(lines)) from None


def _text(path: Path) -> str:
    """The file's text: refused when too large, unreadable or not Unicode text."""
    try:
        size = path.stat().st_size
        if size > MAX_RIG_BYTES:
            raise RigError(f"{path}: {size} bytes; a rig file may have at most {MAX_RIG_BYTES}")
        with path.open("rb") as f:
            data = f.read(MAX_RIG_BYTES + 1)
    except OSError as err:
        raise RigError(f"{path}: cannot read the rig file ({err.strerror or err})") from None
    if len(data) > MAX_RIG_BYTES:  # grew since stat, or not a regular file
        raise RigError(f"{path}: over {MAX_RIG_BYTES} bytes; a rig file may have at most that")
    encoding = next((name for bom, name in _BOMS if data.startswith(bom)), "utf-8")
    try:
        text = data.decode(encoding)
    except UnicodeDecodeError as err:
        raise RigError(f"{path}: not {encoding.upper()} text (byte {err.start}); save the rig "
                       f"file as UTF-8") from None
    if "\x00" in text:
        raise RigError(f"{path}: holds NUL characters (UTF-16 without a byte-order mark?); "
                       f"save the rig file as UTF-8")
    return text


def load_rig(path: str | Path, *, videos: bool = False) -> Rig:
    """Read and validate a rig file (``.json``, any case, else YAML). ``videos``: also
    refuse a camera whose url names a video file that does not exist here (what
    ``aoi3d ros2 check`` and ``aoi3d up --rig`` ask; a process that does not play the
    videos leaves it)."""
    path = Path(path)
    text = _text(path)
    is_json = path.suffix.lower() == ".json"
    try:
        if is_json:
            doc = json.loads(text)
        else:
            import yaml

            doc = yaml.load(text, Loader=getattr(yaml, "CSafeLoader", yaml.SafeLoader))
    except Exception as err:  # YAMLError, JSONDecodeError, RecursionError: one line of them
        raise RigError(f"{path}: not valid {'JSON' if is_json else 'YAML'} "
                       f"({(str(err).splitlines() or [type(err).__name__])[0]})") from None
    rig = rig_from_dict(doc, str(path))
    if videos:
        missing = missing_videos(rig)
        if missing:
            raise RigError("\n".join(f"{path}: {m}" for m in missing))
    return rig


def missing_videos(rig: Rig) -> list[str]:
    """One line per camera whose url is a video file that is not there (relative paths are
    from the working directory, where the ingest opens them)."""
    out = []
    for i, c in enumerate(rig.cameras):
        if c.url is not None and c.protocol is None and not Path(c.url).is_file():
            out.append(f"cameras[{i}].url: no video file {c.url!r} (relative paths are from "
                       f"the working directory, {Path.cwd()})")
    return out
