"""Process-wide settings for training a radiance field on the CPU, made by entry points.

A constructor changes nothing outside its object: :class:`aoi3d.field.FieldTrainer` does not
touch torch's thread count or the C allocator. The programs that train — the trainer
service's ``__main__``, ``aoi3d field train``, the experiments' and the PPO training's worker
processes (through :func:`aoi3d.experiment.episode.set_torch_threads`), the field benchmarks
— call :func:`configure_process` once, before they train.
"""

from __future__ import annotations

import ctypes
import ctypes.util
import sys

__all__ = ["configure_process", "tune_malloc"]

_MALLOC_TUNED = False


def tune_malloc() -> None:
    """Keep freed blocks in glibc's heap (no mmap/munmap and page faults on every step);
    once per process, a no-op elsewhere than glibc."""
    global _MALLOC_TUNED
    if _MALLOC_TUNED or not sys.platform.startswith("linux"):
        return
    _MALLOC_TUNED = True
    name = ctypes.util.find_library("c")
    if name is None:
        return
    try:
        libc = ctypes.CDLL(name)
        m_trim_threshold, m_mmap_threshold = -1, -3
        libc.mallopt(m_mmap_threshold, 1 << 30)
        libc.mallopt(m_trim_threshold, 1 << 30)
    except (OSError, AttributeError):  # not glibc
        return


def configure_process(num_threads: int | None = None, *, malloc: bool = True) -> None:
    """Torch's intra-op threads (None keeps torch's default) and, with ``malloc``, glibc's
    allocator tuned for training (:func:`tune_malloc`)."""
    if num_threads is not None:
        if num_threads < 1:
            raise ValueError(f"num_threads must be >= 1 or None, got {num_threads}")
        import torch

        torch.set_num_threads(num_threads)
    if malloc:
        tune_malloc()
