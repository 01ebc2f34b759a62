"""Every non-Python file the packages ship is named in pyproject's package-data.

An installed aoi3d (the image, `pip install .`) holds only what package-data names: a kernel
source or a page left out is found only when the image's build step fails (CI stop 45 lost
`_native_flow.c` that way).
"""

from __future__ import annotations

import fnmatch
import subprocess
import tomllib
from pathlib import Path

ROOT = Path(__file__).resolve().parents[3]
# Typing stubs for protobuf's generated module: read by mypy in the checkout, never at run time.
NOT_SHIPPED = {"services/kit/pb/aoi3d_pb2.pyi"}


def _shipped_patterns() -> dict[str, list[str]]:
    data = tomllib.loads((ROOT / "pyproject.toml").read_text())
    return data["tool"]["setuptools"]["package-data"]


def _covered(path: str, patterns: dict[str, list[str]]) -> bool:
    for package, globs in patterns.items():
        folder = package.replace(".", "/") + "/"
        if path.startswith(folder):
            rest = path[len(folder):]
            if any(fnmatch.fnmatch(rest, g) for g in globs):
                return True
    return False


def test_every_tracked_data_file_is_package_data() -> None:
    tracked = subprocess.run(
        ["git", "ls-files", "aoi3d", "aoi3d_cli", "services"],
        cwd=ROOT, capture_output=True, text=True, check=True,
    ).stdout.split()
    data_files = [p for p in tracked if not p.endswith(".py") and p not in NOT_SHIPPED]
    assert data_files, "git ls-files found no data files: the test would check nothing"
    patterns = _shipped_patterns()
    missing = [p for p in data_files if not _covered(p, patterns)]
    assert not missing, f"not in [tool.setuptools.package-data], so not installed: {missing}"


def test_the_check_fails_on_a_missing_kernel() -> None:
    patterns = {"aoi3d.field": ["_native.c"]}
    assert _covered("aoi3d/field/_native.c", patterns)
    assert not _covered("aoi3d/field/_native_flow.c", patterns)
