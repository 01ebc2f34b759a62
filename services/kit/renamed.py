"""Settings renamed for one release: which old environment variables a process was started
with, and the one deprecation line that names them (the dispatcher's ``AOI3D_TRAINER_*``, the
viewer's ``AOI3D_VIEWER_TRAINER_URL``). The settings classes read the old names themselves
(a second env source, or an alias); this module only tells the operator."""

from __future__ import annotations

import logging
import os
from collections.abc import Mapping

__all__ = ["renamed_variables", "warn_renamed"]


def renamed_variables(old: str, new: str,
                      environ: Mapping[str, str] = os.environ) -> dict[str, str]:
    """Each variable of ``environ`` set under an old name, mapped to its new name, in name
    order. ``old`` ending in ``_`` is a prefix (``AOI3D_TRAINER_`` → ``AOI3D_DISPATCHER_``),
    else one whole name."""
    out: dict[str, str] = {}
    for key in environ:
        name = key.upper()
        if old.endswith("_") and name.startswith(old):
            out[name] = new + name[len(old):]
        elif name == old:
            out[name] = new
    return dict(sorted(out.items()))


def warn_renamed(logger: str, renamed: Mapping[str, str]) -> None:
    """One warning naming every old variable read and its new name (none: nothing)."""
    if renamed:
        logging.getLogger(logger).warning(
            "deprecated: %s read as %s; the old names go in the next release",
            ", ".join(renamed), ", ".join(renamed.values()))
