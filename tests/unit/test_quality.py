"""PSNR/SSIM against scikit-image, the identical-image cap, input checks, reward arithmetic."""

from __future__ import annotations

import math

import numpy as np
import pytest
from skimage.metrics import peak_signal_noise_ratio, structural_similarity

from aoi3d.quality import PSNR_CAP_DB, QualityScore, RewardWeights, psnr, score, ssim


def _pair(seed: int = 0, shape: tuple[int, int, int] = (40, 52, 3), noise: float = 0.05):
    """A smooth image and a noisy copy of it, float32 in [0, 1]."""
    rng = np.random.default_rng(seed)
    h, w, _ = shape
    yy, xx = np.mgrid[0:h, 0:w]
    base = np.stack(
        [0.5 + 0.4 * np.sin(xx / 5.0), 0.5 + 0.4 * np.cos(yy / 7.0), (xx + yy) / (h + w)], axis=-1
    )
    noisy = np.clip(base + rng.normal(0, noise, base.shape), 0, 1)
    return noisy.astype(np.float32), base.astype(np.float32)


def _sk_ssim(a: np.ndarray, b: np.ndarray) -> float:
    return structural_similarity(
        a.astype(np.float64),
        b.astype(np.float64),
        gaussian_weights=True,
        sigma=1.5,
        use_sample_covariance=False,
        data_range=1.0,
        channel_axis=-1,
    )


@pytest.mark.parametrize("noise", [0.01, 0.05, 0.2])
def test_psnr_and_ssim_agree_with_scikit_image(noise: float) -> None:
    pred, truth = _pair(noise=noise)
    expected_psnr = peak_signal_noise_ratio(
        truth.astype(np.float64), pred.astype(np.float64), data_range=1.0
    )
    assert psnr(pred, truth) == pytest.approx(expected_psnr, abs=1e-6)
    assert ssim(pred, truth) == pytest.approx(_sk_ssim(pred, truth), abs=1e-6)


def test_uint8_input_is_scaled_to_unit_range() -> None:
    pred, truth = _pair(seed=3)
    p8 = np.round(pred * 255).astype(np.uint8)
    t8 = np.round(truth * 255).astype(np.uint8)
    expected = peak_signal_noise_ratio(t8, p8, data_range=255)
    assert psnr(p8, t8) == pytest.approx(expected, abs=1e-6)
    assert ssim(p8, t8) == pytest.approx(_sk_ssim(p8 / 255.0, t8 / 255.0), abs=1e-6)
    # Mixed dtypes: the uint8 image is scaled, the float one kept.
    assert psnr(p8, t8 / 255.0) == pytest.approx(expected, abs=1e-6)


def test_identical_images_are_capped_and_finite() -> None:
    _, truth = _pair()
    assert psnr(truth, truth) == PSNR_CAP_DB
    assert ssim(truth, truth) == pytest.approx(1.0, abs=1e-9)
    s = score(truth, truth)
    assert math.isfinite(s.reward)
    assert s.reward == pytest.approx(0.02 * PSNR_CAP_DB + 0.5 * 1.0)


def test_worse_image_scores_lower() -> None:
    pred_good, truth = _pair(noise=0.02)
    pred_bad, _ = _pair(noise=0.2)
    assert psnr(pred_good, truth) > psnr(pred_bad, truth)
    assert ssim(pred_good, truth) > ssim(pred_bad, truth)
    assert score(pred_good, truth).reward > score(pred_bad, truth).reward


def test_size_mismatch_names_both_shapes() -> None:
    a = np.zeros((20, 30, 3), np.float32)
    b = np.zeros((20, 31, 3), np.float32)
    with pytest.raises(ValueError, match=r"\(20, 30, 3\).*\(20, 31, 3\)"):
        psnr(a, b)
    with pytest.raises(ValueError, match=r"\(20, 30, 3\).*\(20, 31, 3\)"):
        ssim(a, b)


@pytest.mark.parametrize(
    ("image", "match"),
    [
        (np.zeros((20, 30), np.float32), "H×W×C"),
        (np.zeros((20, 30, 3), np.int32), "dtype"),
        (np.full((20, 30, 3), np.nan, np.float32), "non-finite"),
    ],
)
def test_bad_images_raise(image: np.ndarray, match: str) -> None:
    with pytest.raises(ValueError, match=match):
        psnr(image, image)


def test_ssim_rejects_images_smaller_than_the_window() -> None:
    a = np.zeros((8, 30, 3), np.float32)
    with pytest.raises(ValueError, match="11"):
        ssim(a, a)


def test_reward_without_lpips_uses_psnr_and_ssim_only() -> None:
    pred, truth = _pair()
    s = score(pred, truth)
    assert isinstance(s, QualityScore)
    assert s.lpips is None
    assert s.reward_terms == ("psnr", "ssim")
    assert s.psnr_db == pytest.approx(psnr(pred, truth))
    assert s.ssim == pytest.approx(ssim(pred, truth))
    assert s.reward == pytest.approx(0.02 * s.psnr_db + 0.5 * s.ssim)


def test_reward_with_custom_weights_and_lpips_fn() -> None:
    pred, truth = _pair()
    calls: list[tuple[np.dtype, tuple[int, ...]]] = []

    def fake_lpips(p: np.ndarray, t: np.ndarray) -> float:
        calls.append((p.dtype, p.shape))
        return float(np.abs(p - t).mean())

    w = RewardWeights(psnr=0.1, ssim=2.0, lpips=-3.0)
    s = score(pred, truth, weights=w, lpips_fn=fake_lpips)
    expected_lpips = float(np.abs(pred - truth).mean())
    assert calls == [(np.dtype(np.float32), pred.shape)]
    assert s.lpips == pytest.approx(expected_lpips, rel=1e-5)
    assert s.reward_terms == ("psnr", "ssim", "lpips")
    assert s.reward == pytest.approx(0.1 * s.psnr_db + 2.0 * s.ssim - 3.0 * s.lpips)


def test_default_weights_and_non_finite_weight() -> None:
    assert RewardWeights() == RewardWeights(psnr=0.02, ssim=0.5, lpips=-1.0)
    with pytest.raises(ValueError, match="ssim"):
        RewardWeights(ssim=float("nan"))
