"""Writing a file or a folder atomically: readers see the old one or the new one, never a part.

Every writer of a file that another process may read while it is written (checkpoints, the
episode cache, cached weights, the supervisor's state) goes through :func:`atomic_path`: it
hands out a temporary path in the same folder (so the final rename stays on one file system)
and, when the block ends without an exception, renames it over the target in one step. On an
exception the temporary file is removed and the target is left as it was.

A folder (a scene dataset, generated or converted) goes through :func:`atomic_dir`, the one
"write a folder, then swap it into place": a hidden sibling ``.<name>.tmp-<pid>-<token>`` to
write into, then :func:`swap_dir` — the folder there is renamed aside
(``.<name>.old-<pid>-<token>``), the new one renamed in, the old one removed; should the
second rename fail, the old folder is put back. Leftovers of a killed writer carry its pid
(``aoi3d.scene.dataset`` removes those of dead writers).
"""

from __future__ import annotations

import os
import shutil
import uuid
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path

__all__ = ["atomic_dir", "atomic_path", "swap_dir", "write_atomic"]


@contextmanager
def atomic_path(path: str | Path) -> Iterator[Path]:
    """A temporary path beside ``path`` to write to (its folder created if missing); it
    replaces ``path`` when the block ends cleanly and is removed otherwise."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(f".{path.name}.{os.getpid()}-{uuid.uuid4().hex[:8]}.tmp")
    try:
        yield tmp
        os.replace(tmp, path)
    finally:
        tmp.unlink(missing_ok=True)


def write_atomic(path: str | Path, data: bytes | str) -> None:
    """Write ``data`` (text as UTF-8) to ``path`` atomically (:func:`atomic_path`)."""
    with atomic_path(path) as tmp:
        tmp.write_bytes(data.encode() if isinstance(data, str) else data)


def swap_dir(tmp: str | Path, path: str | Path) -> None:
    """Move the finished folder ``tmp`` to ``path``, replacing a folder there: the old one is
    renamed aside first and put back if the final rename fails, then removed."""
    tmp, path = Path(tmp), Path(path)
    old = path.parent / f".{path.name}.old-{os.getpid()}-{uuid.uuid4().hex[:8]}"
    had_old = path.exists()
    if had_old:
        os.rename(path, old)
    try:
        os.rename(tmp, path)
    except OSError:
        if had_old and not path.exists():
            os.rename(old, path)
        raise
    if had_old:
        shutil.rmtree(old, ignore_errors=True)


@contextmanager
def atomic_dir(path: str | Path) -> Iterator[Path]:
    """A new hidden folder beside ``path`` to write into (its parent created if missing); it
    replaces ``path`` (:func:`swap_dir`) when the block ends cleanly and is removed
    otherwise."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.parent / f".{path.name}.tmp-{os.getpid()}-{uuid.uuid4().hex[:8]}"
    tmp.mkdir()
    try:
        yield tmp
        swap_dir(tmp, path)
    finally:
        if tmp.exists():
            shutil.rmtree(tmp, ignore_errors=True)
