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

Dynamic region
--------------
Full-image scores are dominated by what every model learns (sky, ground, tower). The
*dynamic-region* scores look only at the pixels of the held-out view that move. The mask is
a function of the ground truth alone (:func:`dynamic_mask`): given the truth at t and at
t − C, …, t − K·C (C: the frame period, K = :data:`DYNAMIC_FRAMES` = 2),

    change(x) = max over k = 1..K and channels c of |truth_t(x, c) − truth_{t−kC}(x, c)|
    mask      = dilate(change > τ, 3×3 square, 1 iteration)

with τ = :data:`DYNAMIC_TAU` = 8/255 (on the [0, 1] scale; an 8-bit channel must change by
9 levels or more) and the dilation ``scipy.ndimage.binary_dilation`` with a 3×3 square
structuring element (8-connected: every pixel within one pixel, diagonals included, of a
changed pixel joins the mask), :data:`DYNAMIC_DILATION_PX` = 1 time. The mask therefore
holds a moving object where it is now and where it was at t − C, …, t − K·C, plus a one-pixel
rim. K = 2 because the scene's frames and the generation slots need not share a period
(30 fps scene, C = 30 ms): truth_{t−C} may show the same scene frame as truth_t,
truth_{t−2C} never does. τ: measured on data/turbine-rotor's held-out view over one loop
(``python bench/dynamic_mask.py``, results/dynamic_mask.json), 8/255 is the lowest
threshold that puts no mask pixel off the rotor (2/255 and 4/255 put 2.0 % and 1.5 % of the
mask more than a pixel away from it: faint shading changes) while it still covers 88 % of
the rotor's pixels (16/255: 77 %, 24/255: 63 %); the faint fringe of partly covered edge
pixels is taken back by the dilation. The mask is then the three blades: 14.8 % of the image
on average (12.3–15.6 %).

On the mask M (|M| pixels, c channels):

- ``psnr_db``: 10·log10(1 / MSE_M), MSE_M = the mean of (pred − truth)² over the |M|·c
  masked values (``kornia.metrics.psnr`` on them), capped at :data:`PSNR_CAP_DB` like
  :func:`psnr`;
- ``ssim``: the mean of the SSIM map (the same map :func:`ssim` averages, so each value
  already looks at the 11×11 window around its pixel) over the masked pixels of the valid
  region (the image less its 5-pixel border) and the channels;
- ``fraction``: |M| / (H·W).

An empty mask (nothing moved) gives ``psnr_db`` and ``ssim`` None — never 0 — and
``fraction`` 0; a mask that lies only in the 5-pixel border gives ``ssim`` None. The reward
stays the full-image reward: the dynamic scores are an extra lens, not a term of it.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Sequence
from dataclasses import dataclass

import kornia
import numpy as np
import torch
from scipy import ndimage

from aoi3d.metric import LPIPS, PSNR, PSNR_DYNAMIC, REWARD_TERMS, SSIM, SSIM_DYNAMIC

__all__ = [
    "DYNAMIC_DILATION_PX",
    "DYNAMIC_FRAMES",
    "DYNAMIC_REWARD",
    "DYNAMIC_TAU",
    "PSNR_CAP_DB",
    "SSIM_SIGMA",
    "SSIM_WINDOW",
    "DynamicScore",
    "LpipsFn",
    "QualityScore",
    "RewardWeights",
    "Truth",
    "dynamic_mask",
    "dynamic_score",
    "psnr",
    "score",
    "score_many",
    "ssim",
]

PSNR_CAP_DB = 100.0
"""PSNR reported for identical images (and the ceiling of every PSNR value)."""
SSIM_WINDOW = 11
"""Side of the SSIM Gaussian window, in pixels."""
SSIM_SIGMA = 1.5
"""Standard deviation of the SSIM Gaussian window, in pixels (fixed by kornia)."""
DYNAMIC_FRAMES = 2
"""K: earlier truth frames (t − C, …, t − K·C) the dynamic mask compares the truth at t with."""
DYNAMIC_TAU = 8.0 / 255.0
"""τ: a pixel moved when some channel changed by more than this (data range 1)."""
DYNAMIC_DILATION_PX = 1
"""Dilation of the changed pixels, in pixels (3×3 square structuring element per pixel)."""
_TAU_SLACK = 1e-9  # an 8-bit change of exactly τ·255 levels stays out despite float round-off

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


def _psnr(p: torch.Tensor, t: torch.Tensor) -> float:
    """PSNR of two tensors of the same shape (every value counts), capped."""
    if torch.equal(p, t):
        return PSNR_CAP_DB
    value = float(kornia.metrics.psnr(p, t, max_val=1.0))
    return min(value, PSNR_CAP_DB)


def _ssim_map(p: torch.Tensor, t: torch.Tensor) -> torch.Tensor:
    """The SSIM map 1×C×(H−10)×(W−10) of two 1×C×H×W tensors (valid region)."""
    h, w = p.shape[-2:]
    if min(h, w) < SSIM_WINDOW:
        raise ValueError(f"SSIM needs images of at least {SSIM_WINDOW}×{SSIM_WINDOW}, got {h}×{w}")
    return kornia.metrics.ssim(p, t, SSIM_WINDOW, max_val=1.0, eps=0.0, padding="valid")


def psnr(pred: np.ndarray, truth: np.ndarray) -> float:
    """PSNR in dB (data range 1.0), capped at :data:`PSNR_CAP_DB` for identical images."""
    return _psnr(*_pair(pred, truth))


def ssim(pred: np.ndarray, truth: np.ndarray) -> float:
    """Mean SSIM (11×11 Gaussian window, σ = 1.5, data range 1.0, valid region), in [-1, 1]."""
    return float(_ssim_map(*_pair(pred, truth)).mean())


def dynamic_mask(truth: np.ndarray, previous: Sequence[np.ndarray], *,
                 tau: float = DYNAMIC_TAU,
                 dilation_px: int = DYNAMIC_DILATION_PX) -> np.ndarray:
    """The pixels of ``truth`` that moved: H×W bool (see the module's "Dynamic region").

    ``previous``: the truth of the same view at t − C, t − 2C, … (K = ``len(previous)`` ≥ 1;
    :data:`DYNAMIC_FRAMES` in the experiments and the metrics service). A pixel is in the
    mask when some channel differs from some earlier frame by more than ``tau``, or when it
    is within ``dilation_px`` pixels (3×3 square, ``scipy.ndimage.binary_dilation``) of such
    a pixel.
    """
    if not (math.isfinite(tau) and 0.0 <= tau < 1.0):
        raise ValueError(f"tau must be in [0, 1), got {tau}")
    if isinstance(dilation_px, bool) or not isinstance(dilation_px, int) or dilation_px < 0:
        raise ValueError(f"dilation_px must be an int >= 0, got {dilation_px!r}")
    if isinstance(previous, np.ndarray) and previous.ndim == 3:
        raise ValueError("previous must be a sequence of earlier truth images, got one image")
    if len(previous) == 0:
        raise ValueError("the dynamic mask needs at least one earlier truth frame")
    now = _as_unit_float(truth, "truth")
    change = np.zeros(now.shape[:2])
    for k, image in enumerate(previous, start=1):
        before = _as_unit_float(image, f"truth at t - {k}C")
        if before.shape != now.shape:
            raise ValueError(f"image shapes differ: truth {now.shape} vs truth at t - {k}C "
                             f"{before.shape}")
        np.maximum(change, np.abs(now - before).max(axis=2), out=change)
    mask = change > tau + _TAU_SLACK
    if dilation_px and mask.any():
        mask = ndimage.binary_dilation(mask, structure=np.ones((3, 3), dtype=bool),
                                       iterations=dilation_px)
    return mask


@dataclass(frozen=True)
class DynamicScore:
    """Quality over the dynamic mask: ``psnr_db`` and ``ssim`` None when there is nothing to
    score (empty mask; for SSIM, no masked pixel in the valid region), never 0."""

    psnr_db: float | None
    ssim: float | None
    fraction: float
    """Pixels in the mask / pixels of the image."""
    pixels: int
    """Pixels in the mask."""


def _check_mask(mask: np.ndarray, shape: tuple[int, ...]) -> np.ndarray:
    m = np.asarray(mask)
    if m.dtype != np.bool_:
        raise ValueError(f"mask must be a bool array, got dtype {m.dtype}")
    if m.shape != shape[:2]:
        raise ValueError(f"mask shape {m.shape} does not match the image's {shape[:2]}")
    return m


def _dynamic(p: torch.Tensor, t: torch.Tensor, mask: np.ndarray,
             ssim_map: torch.Tensor | None) -> DynamicScore:
    h, w = mask.shape
    pixels = int(mask.sum())
    fraction = pixels / (h * w)
    if pixels == 0:
        return DynamicScore(psnr_db=None, ssim=None, fraction=0.0, pixels=0)
    m = torch.from_numpy(mask)
    psnr_db = _psnr(p[..., m], t[..., m])  # 1×C×|M|: every masked pixel and channel
    if ssim_map is None:
        ssim_map = _ssim_map(p, t)
    r = SSIM_WINDOW // 2
    inner = m[r:h - r, r:w - r]  # map[i, j] is the window centred on pixel (i + r, j + r)
    ssim_value = float(ssim_map[..., inner].mean()) if bool(inner.any()) else None
    return DynamicScore(psnr_db=psnr_db, ssim=ssim_value, fraction=fraction, pixels=pixels)


def dynamic_score(pred: np.ndarray, truth: np.ndarray, mask: np.ndarray) -> DynamicScore:
    """PSNR and SSIM of ``pred`` against ``truth`` over ``mask`` (H×W bool, e.g.
    :func:`dynamic_mask`), and the mask's pixel fraction."""
    p, t = _pair(pred, truth)
    return _dynamic(p, t, _check_mask(mask, tuple(p.shape[-2:])), None)


@dataclass(frozen=True)
class RewardWeights:
    """Weights of the reward ``psnr·PSNR_dB + ssim·SSIM + lpips·LPIPS + psnr_dynamic·
    PSNR_dyn_dB + ssim_dynamic·SSIM_dyn`` (LPIPS: lower is better).

    The default is the founding paper's reward (no dynamic terms).
    :data:`DYNAMIC_REWARD` weights what moves instead: the dynamic region's PSNR and SSIM in
    place of the full image's (see :func:`score` for a render with nothing moving)."""

    # The fields are :data:`aoi3d.metric.REWARD_TERMS`, in their order
    # (tests/unit/domain/test_metric.py).
    psnr: float = 0.02
    ssim: float = 0.5
    lpips: float = -1.0
    psnr_dynamic: float = 0.0
    ssim_dynamic: float = 0.0

    def __post_init__(self) -> None:
        for name in REWARD_TERMS:
            if not math.isfinite(getattr(self, name)):
                raise ValueError(f"reward weight {name} must be finite, got {getattr(self, name)}")

    @property
    def dynamic(self) -> bool:
        """Whether the reward has a dynamic-region term."""
        return self.psnr_dynamic != 0.0 or self.ssim_dynamic != 0.0

    def terms(self, lpips: bool) -> tuple[str, ...]:
        """The terms a reward with these weights is built from (those weighed, not 0), LPIPS
        only where it is available (``lpips``)."""
        return tuple(n for n in REWARD_TERMS
                     if getattr(self, n) != 0.0 and (lpips or n != LPIPS.short))


DYNAMIC_REWARD = RewardWeights(psnr=0.0, ssim=0.0, lpips=-1.0, psnr_dynamic=0.02,
                               ssim_dynamic=0.5)
"""The paper's weights on the dynamic region (the blades: what someone watching a turbine
looks at) instead of the whole image; LPIPS stays full-image."""


@dataclass(frozen=True)
class QualityScore:
    """Quality of one render; ``reward_terms`` names the metrics the reward was built from."""

    psnr_db: float
    ssim: float
    lpips: float | None
    reward: float
    reward_terms: tuple[str, ...]
    dynamic: DynamicScore | None = None
    """Scores over the dynamic mask; None when no earlier truth frames were given."""


@dataclass(frozen=True)
class Truth:
    """A ground-truth image to score a render against, with what its dynamic region needs:
    the truth at t − C, …, t − K·C (``previous``), or its :func:`dynamic_mask` already made
    (``mask``: a caller that scores many renders against one truth keeps it). Neither: no
    dynamic scores."""

    image: np.ndarray
    previous: Sequence[np.ndarray] | None = None
    mask: np.ndarray | None = None

    def dynamic_mask(self) -> np.ndarray | None:
        if self.mask is not None:
            return _check_mask(self.mask, np.asarray(self.image).shape)
        if self.previous is not None and len(self.previous) > 0:
            return dynamic_mask(self.image, self.previous)
        return None


def score(
    pred: np.ndarray,
    truth: np.ndarray,
    weights: RewardWeights = RewardWeights(),
    lpips_fn: LpipsFn | None = None,
    previous: Sequence[np.ndarray] | None = None,
) -> QualityScore:
    """PSNR, SSIM, LPIPS (when ``lpips_fn`` is given) and their weighted sum, the reward;
    with ``previous`` (the truth at t − C, …, t − K·C) also the dynamic-region scores.

    Without ``lpips_fn`` the LPIPS term is unavailable: ``lpips`` is None and the reward is
    ``weights.psnr·psnr_db + weights.ssim·ssim`` with ``reward_terms == ("psnr", "ssim")``.
    ``previous`` None (or empty): ``dynamic`` is None. The reward uses ``dynamic`` only
    through the weights ``psnr_dynamic`` and ``ssim_dynamic``; those need ``previous``
    (``ValueError`` without it), and where the dynamic region has nothing to score (an empty
    mask: nothing moved) the full image's PSNR or SSIM stands in, named ``psnr_dynamic=full``
    or ``ssim_dynamic=full`` in ``reward_terms``.
    """
    return score_many(pred, [Truth(truth, previous)], weights, lpips_fn)[0]


def score_many(
    pred: np.ndarray,
    truths: Sequence[Truth],
    weights: RewardWeights = RewardWeights(),
    lpips_fn: LpipsFn | None = None,
) -> list[QualityScore]:
    """:func:`score` of one render against each of ``truths`` (a render at its decision time
    and at its display time), the same numbers as one :func:`score` call each, bit for bit
    (tests/unit/domain/test_quality_many.py), for less work: the render is converted once, SSIM's
    local moments of every image are filtered in one batch (:func:`_ssim_maps`), and LPIPS
    (when ``lpips_fn`` has ``many``, as :func:`aoi3d.lpips.load_lpips_fn`'s has) runs the
    render and every truth through its network in one batch."""
    if not truths:
        return []
    w = weights
    p_np = _as_unit_float(pred, "pred")
    ts_np = [_as_unit_float(t.image, "truth") for t in truths]
    for t_np in ts_np:
        if t_np.shape != p_np.shape:
            raise ValueError(f"image shapes differ: pred {p_np.shape} vs truth {t_np.shape}")
    p, ts = _chw(p_np), [_chw(t_np) for t_np in ts_np]
    maps = _ssim_maps(p, ts)
    lpips_values: list[float | None] = [None] * len(truths)
    if lpips_fn is not None:
        p32 = p_np.astype(np.float32)
        t32 = [t_np.astype(np.float32) for t_np in ts_np]
        many = getattr(lpips_fn, "many", None)
        values = (list(many(p32, t32)) if callable(many)
                  else [lpips_fn(p32, one) for one in t32])
        for i, value in enumerate(values):
            lpips_values[i] = float(value)
            if not math.isfinite(lpips_values[i]):  # type: ignore[arg-type]
                raise ValueError(f"lpips_fn returned a non-finite value: {value}")
    out = []
    for truth, t, ssim_map, lpips_value in zip(truths, ts, maps, lpips_values, strict=True):
        mask = truth.dynamic_mask()
        dynamic = None if mask is None else _dynamic(p, t, mask, ssim_map)
        out.append(_assemble(w, _psnr(p, t), float(ssim_map.mean()), lpips_value, dynamic,
                             lpips_fn is not None))
    return out


def _ssim_maps(p: torch.Tensor, ts: Sequence[torch.Tensor]) -> list[torch.Tensor]:
    """The SSIM map of ``p`` against each of ``ts`` (1×C×H×W float64), as
    ``kornia.metrics.ssim(p, t, SSIM_WINDOW, max_val=1.0, eps=0.0, padding="valid")`` gives
    it, bit for bit: kornia's own Gaussian window and filter (``filter2d_separable``) and its
    arithmetic, in its order. Why not kornia's function: it filters the render's moments
    again for every truth, five filter calls a pair; here the moments of the render and of
    every truth are filtered in one call, side by side as channels (the filter is depthwise:
    each channel alone, the same numbers as one image at a time, and a third of the time of a
    batch of images on one core)."""
    h, w = p.shape[-2:]
    if min(h, w) < SSIM_WINDOW:
        raise ValueError(f"SSIM needs images of at least {SSIM_WINDOW}×{SSIM_WINDOW}, got {h}×{w}")
    k = len(ts)
    kernel = kornia.filters.get_gaussian_kernel1d(SSIM_WINDOW, SSIM_SIGMA, device=p.device,
                                                  dtype=p.dtype)
    c1, c2 = (0.01 * 1.0) ** 2, (0.03 * 1.0) ** 2
    images = [p, *ts, p**2, *(t**2 for t in ts), *(p * t for t in ts)]
    c = p.shape[1]  # each image's channels side by side: the filter is depthwise (per channel)
    stacked = torch.cat(images, dim=1)
    r = SSIM_WINDOW // 2
    filtered = kornia.filters.filter2d_separable(stacked, kernel, kernel)
    moments = torch.nn.functional.pad(filtered, (-r, -r, -r, -r)).reshape(len(images), c, h - 2 * r,
                                                                          w - 2 * r)
    mu1 = moments[0:1]
    mu1_sq = mu1**2
    maps = []
    for i in range(k):
        mu2 = moments[1 + i:2 + i]
        mu2_sq = mu2**2
        mu1_mu2 = mu1 * mu2
        sigma1_sq = moments[1 + k:2 + k] - mu1_sq
        sigma2_sq = moments[2 + k + i:3 + k + i] - mu2_sq
        sigma12 = moments[2 + 2 * k + i:3 + 2 * k + i] - mu1_mu2
        num = (2.0 * mu1_mu2 + c1) * (2.0 * sigma12 + c2)
        den = (mu1_sq + mu2_sq + c1) * (sigma1_sq + sigma2_sq + c2)
        maps.append(num / (den + 0.0))
    return maps


def _assemble(w: RewardWeights, psnr_db: float, ssim_value: float, lpips_value: float | None,
              dynamic: DynamicScore | None, has_lpips: bool) -> QualityScore:
    """The reward of one render's scores and the terms it was built from (see :func:`score`)."""
    reward = w.psnr * psnr_db + w.ssim * ssim_value
    terms: tuple[str, ...] = (PSNR.short, SSIM.short)
    if lpips_value is not None:
        reward += w.lpips * lpips_value
        terms = (*terms, LPIPS.short)
    if w.dynamic:
        if dynamic is None:
            raise ValueError("the reward weighs the dynamic region (psnr_dynamic, "
                             "ssim_dynamic) but no earlier truth frames were given")
        for name, weight, value, full in ((PSNR_DYNAMIC.short, w.psnr_dynamic, dynamic.psnr_db,
                                           psnr_db),
                                          (SSIM_DYNAMIC.short, w.ssim_dynamic, dynamic.ssim,
                                           ssim_value)):
            if weight == 0.0:
                continue
            reward += weight * (full if value is None else value)
            terms = (*terms, name if value is not None else f"{name}=full")
    weighed = w.terms(has_lpips)
    terms = tuple(t for t in terms if t.split("=")[0] in weighed)
    return QualityScore(
        psnr_db=psnr_db, ssim=ssim_value, lpips=lpips_value, reward=reward, reward_terms=terms,
        dynamic=dynamic,
    )
