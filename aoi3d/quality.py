"""Quality of a rendered novel view against its ground truth: PSNR, SSIM, LPIPS and the reward.

Images are ``np.ndarray`` H×W×C (C = 3 for RGB): uint8 in [0, 255] (divided by 255) or float
in [0, 1]. Both metrics are computed with kornia in float64 with data range (``max_val``) 1.0:

- PSNR: ``kornia.metrics.psnr`` = 10·log10(1 / MSE), one MSE pooled over all pixels and
  channels. Identical images (MSE = 0) would give +inf; :func:`psnr` caps the value at
  :data:`PSNR_CAP_DB` = 100 dB so that every figure stays finite (JSON, Prometheus, reward).
  The cap is far above anything an 8-bit image can reach short of identity
  (one LSB of error on a 96×72 image is already ≈ 91 dB).
- SSIM: ``kornia.metrics.ssim`` with an 11×11 Gaussian window, σ = 1.5, c1 = 0.01², c2 = 0.03²,
  ``padding="valid"`` (the 5-pixel border where the window leaves the image is dropped, as in
  Wang et al. 2004 and scikit-image), then the mean over the map and the channels. This equals
  ``skimage.metrics.structural_similarity(gaussian_weights=True, sigma=1.5,
  use_sample_covariance=False, data_range=1, channel_axis=-1)``. Images must be at least 11×11.

LPIPS comes from :mod:`aoi3d.lpips` (``load_lpips_fn()``, AlexNet v0.1, weights cached by
``python -m aoi3d.lpips fetch``) and is passed in as ``lpips_fn``. Without it,
``QualityScore.lpips`` is ``None`` (never 0) and the reward uses only the terms listed in
``QualityScore.reward_terms``.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass

import kornia
import numpy as np
import torch

__all__ = [
    "PSNR_CAP_DB",
    "SSIM_SIGMA",
    "SSIM_WINDOW",
    "LpipsFn",
    "QualityScore",
    "RewardWeights",
    "psnr",
    "score",
    "ssim",
]

PSNR_CAP_DB = 100.0
"""PSNR reported for identical images (and the ceiling of every PSNR value)."""
SSIM_WINDOW = 11
"""Side of the SSIM Gaussian window, in pixels."""
SSIM_SIGMA = 1.5
"""Standard deviation of the SSIM Gaussian window, in pixels (fixed by kornia)."""

LpipsFn = Callable[[np.ndarray, np.ndarray], float]
"""``lpips_fn(pred, truth) -> distance``; both images float32 H×W×3 in [0, 1]."""


def _as_unit_float(image: np.ndarray, name: str) -> np.ndarray:
    """``image`` as float64 H×W×C in [0, 1] (uint8 is divided by 255); float kept as it is."""
    arr = np.asarray(image)
    if arr.ndim != 3 or arr.shape[2] < 1:
        raise ValueError(f"{name} must be an H×W×C image, got shape {arr.shape}")
    if arr.dtype == np.uint8:
        return arr.astype(np.float64) / 255.0
    if not np.issubdtype(arr.dtype, np.floating):
        raise ValueError(f"{name} must be uint8 or float in [0, 1], got dtype {arr.dtype}")
    arr = arr.astype(np.float64)
    if not np.isfinite(arr).all():
        raise ValueError(f"{name} contains non-finite values")
    return arr


def _pair(pred: np.ndarray, truth: np.ndarray) -> tuple[torch.Tensor, torch.Tensor]:
    """Both images as float64 tensors 1×C×H×W, after checking that their shapes agree."""
    p = _as_unit_float(pred, "pred")
    t = _as_unit_float(truth, "truth")
    if p.shape != t.shape:
        raise ValueError(f"image shapes differ: pred {p.shape} vs truth {t.shape}")
    return _chw(p), _chw(t)


def _chw(image: np.ndarray) -> torch.Tensor:
    """H×W×C array → 1×C×H×W tensor."""
    return torch.from_numpy(np.ascontiguousarray(image.transpose(2, 0, 1)))[None]


def psnr(pred: np.ndarray, truth: np.ndarray) -> float:
    """PSNR in dB (data range 1.0), capped at :data:`PSNR_CAP_DB` for identical images."""
    p, t = _pair(pred, truth)
    if torch.equal(p, t):
        return PSNR_CAP_DB
    value = float(kornia.metrics.psnr(p, t, max_val=1.0))
    return min(value, PSNR_CAP_DB)


def ssim(pred: np.ndarray, truth: np.ndarray) -> float:
    """Mean SSIM (11×11 Gaussian window, σ = 1.5, data range 1.0, valid region), in [-1, 1]."""
    p, t = _pair(pred, truth)
    h, w = p.shape[-2:]
    if min(h, w) < SSIM_WINDOW:
        raise ValueError(f"SSIM needs images of at least {SSIM_WINDOW}×{SSIM_WINDOW}, got {h}×{w}")
    ssim_map = kornia.metrics.ssim(p, t, SSIM_WINDOW, max_val=1.0, eps=0.0, padding="valid")
    return float(ssim_map.mean())


@dataclass(frozen=True)
class RewardWeights:
    """Weights of the reward ``psnr·PSNR_dB + ssim·SSIM + lpips·LPIPS`` (LPIPS: lower is better)."""

    psnr: float = 0.02
    ssim: float = 0.5
    lpips: float = -1.0

    def __post_init__(self) -> None:
        for name in ("psnr", "ssim", "lpips"):
            if not math.isfinite(getattr(self, name)):
                raise ValueError(f"reward weight {name} must be finite, got {getattr(self, name)}")


@dataclass(frozen=True)
class QualityScore:
    """Quality of one render; ``reward_terms`` names the metrics the reward was built from."""

    psnr_db: float
    ssim: float
    lpips: float | None
    reward: float
    reward_terms: tuple[str, ...]


def score(
    pred: np.ndarray,
    truth: np.ndarray,
    weights: RewardWeights = RewardWeights(),
    lpips_fn: LpipsFn | None = None,
) -> QualityScore:
    """PSNR, SSIM, LPIPS (when ``lpips_fn`` is given) and their weighted sum, the reward.

    Without ``lpips_fn`` the LPIPS term is unavailable: ``lpips`` is None and the reward is
    ``weights.psnr·psnr_db + weights.ssim·ssim`` with ``reward_terms == ("psnr", "ssim")``.
    """
    w = weights
    psnr_db = psnr(pred, truth)
    ssim_value = ssim(pred, truth)
    reward = w.psnr * psnr_db + w.ssim * ssim_value
    terms: tuple[str, ...] = ("psnr", "ssim")
    lpips_value: float | None = None
    if lpips_fn is not None:
        p = _as_unit_float(pred, "pred").astype(np.float32)
        t = _as_unit_float(truth, "truth").astype(np.float32)
        lpips_value = float(lpips_fn(p, t))
        if not math.isfinite(lpips_value):
            raise ValueError(f"lpips_fn returned a non-finite value: {lpips_value}")
        reward += w.lpips * lpips_value
        terms = (*terms, "lpips")
    return QualityScore(
        psnr_db=psnr_db, ssim=ssim_value, lpips=lpips_value, reward=reward, reward_terms=terms
    )
