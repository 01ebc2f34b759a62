"""Reading a rig file (``.json``, else YAML) and validating it: :class:`RigError` names each
bad field."""

from __future__ import annotations

import json
from pathlib import Path

from pydantic import ValidationError

from aoi3d.rigfile.model import Rig

__all__ = ["RigError", "load_rig", "rig_from_dict"]


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


def rig_from_dict(doc: object, source: str = "rig") -> Rig:
    """Validate a parsed rig document; :class:`RigError` names each bad field."""
    if not isinstance(doc, dict):
        raise RigError(f"{source}: a rig file is a mapping (cameras:, aabb:, …), got "
                       f"{type(doc).__name__}")
    try:
        return Rig.model_validate(doc)
    except ValidationError as err:
        lines = []
        for e in err.errors():
            msg = e["msg"].removeprefix("Value error, ")
            lines.append(f"{source}: {_where(e['loc'])}: {msg}")
        raise RigError("\n".join(lines)) from None


def load_rig(path: str | Path) -> Rig:
    """Read and validate a rig file (``.json``, else YAML)."""
    path = Path(path)
    try:
        text = path.read_text(encoding="utf-8")
    except OSError as err:
        raise RigError(f"{path}: cannot read the rig file ({err.strerror or err})") from None
    try:
        if path.suffix.lower() == ".json":
            doc = json.loads(text)
        else:
            import yaml

            doc = yaml.safe_load(text)
    except Exception as err:  # yaml.YAMLError, json.JSONDecodeError: the parser's own words
        raise RigError(f"{path}: not valid {'JSON' if path.suffix == '.json' else 'YAML'} "
                       f"({str(err).splitlines()[0]})") from None
    return rig_from_dict(doc, str(path))
