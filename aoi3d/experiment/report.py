"""What an experiment writes next to its numbers: the code version, the machine, the config,
and the CSV/JSON files themselves (strict JSON: NaN is written as null)."""

from __future__ import annotations

import csv
import json
import math
import os
import platform
import subprocess
import time
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import torch

import aoi3d

__all__ = ["code_version", "machine", "to_jsonable", "write_csv", "write_json"]


def code_version() -> str:
    """``git describe --always --dirty --tags`` of the checkout aoi3d runs from, else the
    package version."""
    root = Path(aoi3d.__file__).resolve().parent.parent
    try:
        out = subprocess.run(
            ["git", "describe", "--always", "--dirty", "--tags"], cwd=root, capture_output=True,
            text=True, timeout=10, check=True,
        )
        described = out.stdout.strip()
    except (OSError, subprocess.SubprocessError):
        described = ""
    version = getattr(aoi3d, "__version__", "unknown")
    return f"{described} (aoi3d {version})" if described else f"aoi3d {version}"


def _cpu_model() -> str:
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                return line.split(":", 1)[1].strip()
    except OSError:
        pass
    return platform.processor() or "unknown"


def machine() -> dict[str, Any]:
    """The machine the numbers were computed on (the local one; Ray nodes are not listed)."""
    info: dict[str, Any] = {
        "hostname": platform.node(),
        "platform": platform.platform(),
        "python": platform.python_version(),
        "torch": torch.__version__,
        "cpu": _cpu_model(),
        "cpu_count": os.cpu_count(),
        "cuda": torch.cuda.get_device_name(0) if torch.cuda.is_available() else None,
        "time": time.strftime("%Y-%m-%dT%H:%M:%S%z"),
    }
    if hasattr(os, "getloadavg"):
        info["loadavg"] = [round(x, 2) for x in os.getloadavg()]
    return info


def to_jsonable(value: Any) -> Any:
    """``value`` with NaN/inf floats as None, tuples as lists, numpy scalars as Python."""
    if isinstance(value, dict):
        return {str(k): to_jsonable(v) for k, v in value.items()}
    if isinstance(value, list | tuple):
        return [to_jsonable(v) for v in value]
    if hasattr(value, "item") and not isinstance(value, str | bytes):
        value = value.item()
    if isinstance(value, float) and not math.isfinite(value):
        return None
    return value


def write_json(path: Path, doc: Any) -> Path:
    """Strict JSON, indented."""
    path.write_text(json.dumps(to_jsonable(doc), indent=1, allow_nan=False) + "\n")
    return path


def write_csv(path: Path, rows: Sequence[dict[str, Any]]) -> Path:
    """One line per row; columns in first-seen order; NaN/None as empty cells."""
    columns: list[str] = []
    for row in rows:
        columns.extend(k for k in row if k not in columns)
    with path.open("w", newline="") as fh:
        writer = csv.DictWriter(fh, fieldnames=columns)
        writer.writeheader()
        for row in rows:
            writer.writerow({k: ("" if v is None else v) for k, v in to_jsonable(row).items()})
    return path
