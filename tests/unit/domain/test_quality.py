"""PSNR/SSIM against scikit-image, the identical-image cap, input checks, reward arithmetic;
the dynamic-region mask and scores on a moving square, where the answer is known."""

from __future__ import annotations

import math

import numpy as np
import pytest
from skimage.metrics import peak_signal_noise_ratio, structural_similarity

from aoi3d.quality import (
    DYNAMIC_REWARD,
    DYNAMIC_TAU,
    PSNR_CAP_DB,
    DynamicScore,
    QualityScore,
    RewardWeights,
    dynamic_mask,
    dynamic_score,
    psnr,
    score,
    ssim,
)


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


# --- the dynamic region ----------------------------------------------------------------------
_H, _W, _SIDE = 40, 52, 6
_BACKGROUND = (0.2, 0.5, 0.3)
_SQUARE = (0.9, 0.8, 0.1)


def _square_at(row: int, col: int) -> np.ndarray:
    """A static, uniform background with a uniform _SIDE×_SIDE square at (row, col)."""
    image = np.empty((_H, _W, 3), np.float64)
    image[:] = _BACKGROUND
    image[row:row + _SIDE, col:col + _SIDE] = _SQUARE
    return image


def _grown(row: int, col: int) -> np.ndarray:
    """The square at (row, col) grown by one pixel on every side (its 3×3 dilation)."""
    mask = np.zeros((_H, _W), bool)
    mask[max(0, row - 1):row + _SIDE + 1, max(0, col - 1):col + _SIDE + 1] = True
    return mask


def test_mask_is_the_old_and_new_squares_dilated_by_one_pixel() -> None:
    # t − 2C, t − C, t: the square moves right by 10 px a frame (no overlap).
    before2, before1, now = _square_at(15, 3), _square_at(15, 13), _square_at(15, 23)
    mask = dynamic_mask(now, [before1, before2])
    expected = _grown(15, 3) | _grown(15, 13) | _grown(15, 23)
    np.testing.assert_array_equal(mask, expected)
    assert mask.sum() == 3 * (_SIDE + 2) ** 2
    # K = 1: only t − C counts.
    np.testing.assert_array_equal(dynamic_mask(now, [before1]),
                                  _grown(15, 13) | _grown(15, 23))
    # No dilation: exactly the pixels that changed.
    raw = dynamic_mask(now, [before1], dilation_px=0)
    expected_raw = np.zeros((_H, _W), bool)
    expected_raw[15:21, 13:19] = expected_raw[15:21, 23:29] = True
    np.testing.assert_array_equal(raw, expected_raw)


def test_mask_of_an_overlapping_move_is_what_changed() -> None:
    # A uniform square moved by 2 px: its overlap does not change, so only the two 2-px
    # strips are "changed" before the dilation.
    raw = dynamic_mask(_square_at(10, 12), [_square_at(10, 10)], dilation_px=0)
    expected = np.zeros((_H, _W), bool)
    expected[10:16, 10:12] = expected[10:16, 16:18] = True
    np.testing.assert_array_equal(raw, expected)


def test_mask_threshold_is_strict_and_per_channel_max() -> None:
    level = round(DYNAMIC_TAU * 255)
    assert level == 8
    now = np.full((20, 20, 3), 100, np.uint8)
    before = now.copy()
    before[5, 5, 1] = 100 + level  # exactly τ: not a change
    before[12, 12, 2] = 100 - (level + 1)  # one level more, in one channel only: a change
    mask = dynamic_mask(now, [before], dilation_px=0)
    assert mask.sum() == 1 and mask[12, 12]


def test_no_motion_gives_an_empty_mask_and_no_scores_not_zero() -> None:
    still = _square_at(15, 20)
    pred = np.clip(still + 0.1, 0, 1)
    mask = dynamic_mask(still, [still, still])
    assert not mask.any()
    dyn = dynamic_score(pred, still, mask)
    assert dyn == DynamicScore(psnr_db=None, ssim=None, fraction=0.0, pixels=0)
    s = score(pred, still, previous=[still, still])
    assert s.dynamic is not None and s.dynamic.psnr_db is None and s.dynamic.ssim is None


def test_dynamic_psnr_is_the_psnr_of_the_masked_pixels_only() -> None:
    before2, before1, now = _square_at(15, 3), _square_at(15, 13), _square_at(15, 23)
    mask = _grown(15, 3) | _grown(15, 13) | _grown(15, 23)
    pred = now.copy()
    pred[mask] += 0.1  # every masked value is off by 0.1: MSE 0.01, 20 dB
    pred[~mask] -= 0.15  # the static part is worse, and must not count
    s = score(pred, now, previous=[before1, before2])
    assert s.dynamic is not None
    assert s.dynamic.psnr_db == pytest.approx(20.0, abs=1e-9)
    assert s.dynamic.pixels == 3 * 64
    assert s.dynamic.fraction == pytest.approx(3 * 64 / (_H * _W))
    # The full-image PSNR is the whole image's (hand-computed: pooled MSE).
    full_mse = (mask.sum() * 0.1**2 + (~mask).sum() * 0.15**2) / mask.size
    assert s.psnr_db == pytest.approx(10 * math.log10(1 / full_mse), abs=1e-9)
    # Random errors: 10·log10(1 / mean of the squared masked errors, channels pooled).
    rng = np.random.default_rng(1)
    noisy = np.clip(now + rng.normal(0, 0.07, now.shape), 0, 1)
    expected = 10 * math.log10(1 / np.mean((noisy - now)[mask] ** 2))
    assert dynamic_score(noisy, now, mask).psnr_db == pytest.approx(expected, abs=1e-9)


def test_dynamic_ssim_is_the_ssim_map_mean_over_the_mask() -> None:
    pred, truth = _pair(seed=5, noise=0.08)
    mask = np.zeros(truth.shape[:2], bool)
    mask[8:20, 10:30] = True
    mask[0:3, :] = True  # in the border: outside the valid SSIM region
    _, smap = structural_similarity(
        pred.astype(np.float64), truth.astype(np.float64), gaussian_weights=True, sigma=1.5,
        use_sample_covariance=False, data_range=1.0, channel_axis=-1, full=True)
    inner = np.zeros_like(mask)
    inner[5:-5, 5:-5] = mask[5:-5, 5:-5]
    expected = float(smap[inner].mean())
    dyn = dynamic_score(pred, truth, mask)
    assert dyn.ssim == pytest.approx(expected, abs=1e-6)
    assert dyn.ssim != pytest.approx(ssim(pred, truth), abs=1e-3)  # not the full-image mean
    # A mask in the border only: PSNR is defined, SSIM is not.
    border = np.zeros_like(mask)
    border[0:3, :] = True
    only_border = dynamic_score(pred, truth, border)
    assert only_border.psnr_db is not None and only_border.ssim is None


def test_identical_masked_pixels_are_capped() -> None:
    now, before = _square_at(15, 23), _square_at(15, 3)
    pred = now.copy()
    mask = dynamic_mask(now, [before])
    pred[~mask] = 0.0  # wrong everywhere else
    assert dynamic_score(pred, now, mask).psnr_db == PSNR_CAP_DB


def test_dynamic_score_leaves_the_reward_and_full_scores_alone() -> None:
    pred, truth = _pair(seed=2)
    before = np.roll(truth, 3, axis=1)
    plain = score(pred, truth)
    with_dynamic = score(pred, truth, previous=[before, before])
    assert plain.dynamic is None
    assert with_dynamic.dynamic is not None and with_dynamic.dynamic.psnr_db is not None
    assert (with_dynamic.psnr_db, with_dynamic.ssim, with_dynamic.reward) == (
        plain.psnr_db, plain.ssim, plain.reward)
    assert with_dynamic.reward_terms == ("psnr", "ssim")


@pytest.mark.parametrize(
    ("previous", "kwargs", "match"),
    [
        ([], {}, "at least one earlier truth frame"),
        (np.zeros((20, 30, 3), np.float32), {}, "sequence of earlier truth images"),
        ([np.zeros((20, 31, 3), np.float32)], {}, r"\(20, 30, 3\).*\(20, 31, 3\)"),
        ([np.zeros((20, 30, 3), np.int32)], {}, "dtype"),
        ([np.zeros((20, 30, 3), np.float32)], {"tau": 1.0}, "tau"),
        ([np.zeros((20, 30, 3), np.float32)], {"tau": float("nan")}, "tau"),
        ([np.zeros((20, 30, 3), np.float32)], {"dilation_px": -1}, "dilation_px"),
    ],
)
def test_dynamic_mask_rejects_bad_input(previous, kwargs, match) -> None:
    with pytest.raises(ValueError, match=match):
        dynamic_mask(np.zeros((20, 30, 3), np.float32), previous, **kwargs)


def test_dynamic_score_rejects_a_mask_of_the_wrong_shape_or_type() -> None:
    image = np.zeros((20, 30, 3), np.float32)
    with pytest.raises(ValueError, match="mask shape"):
        dynamic_score(image, image, np.zeros((20, 31), bool))
    with pytest.raises(ValueError, match="bool"):
        dynamic_score(image, image, np.zeros((20, 30), np.uint8))


def test_the_dynamic_reward_weighs_the_dynamic_region_instead_of_the_whole_image() -> None:
    before2, before1, now = _square_at(15, 3), _square_at(15, 13), _square_at(15, 23)
    pred = now.copy()
    pred[15:23, 23:31] += 0.1  # the moving square is off
    s = score(pred, now, DYNAMIC_REWARD, previous=[before1, before2])
    assert s.dynamic is not None and s.dynamic.psnr_db is not None
    assert s.reward == pytest.approx(0.02 * s.dynamic.psnr_db + 0.5 * s.dynamic.ssim)
    assert s.reward_terms == ("psnr_dynamic", "ssim_dynamic")  # no LPIPS fn, weight-0 terms out
    # The same error on a static part costs the dynamic reward nothing, the paper's a lot.
    still_err = now.copy()
    still_err[0:8, 0:8] += 0.1
    prev = [before1, before2]
    a, perfect = score(still_err, now, DYNAMIC_REWARD, previous=prev), score(
        now, now, DYNAMIC_REWARD, previous=prev)
    assert a.reward == pytest.approx(perfect.reward) and a.reward > s.reward
    paper, paper_perfect = score(still_err, now, previous=prev), score(now, now, previous=prev)
    assert paper.reward < paper_perfect.reward - 0.1
    # With LPIPS the full-image LPIPS term stays.
    lp = score(pred, now, DYNAMIC_REWARD, lambda p, t: 0.25, previous=[before1, before2])
    assert lp.reward == pytest.approx(s.reward - 0.25)
    assert lp.reward_terms == ("lpips", "psnr_dynamic", "ssim_dynamic")


def test_the_dynamic_reward_falls_back_to_the_full_image_when_nothing_moved() -> None:
    still = _square_at(15, 20)
    pred = np.clip(still + 0.1, 0, 1)
    s = score(pred, still, DYNAMIC_REWARD, previous=[still, still])
    assert s.dynamic.psnr_db is None
    assert s.reward == pytest.approx(0.02 * s.psnr_db + 0.5 * s.ssim)
    assert s.reward_terms == ("psnr_dynamic=full", "ssim_dynamic=full")


def test_the_dynamic_reward_needs_earlier_truth_frames_and_finite_weights() -> None:
    pred, truth = _pair()
    with pytest.raises(ValueError, match="no earlier truth frames"):
        score(pred, truth, DYNAMIC_REWARD)
    with pytest.raises(ValueError, match="psnr_dynamic"):
        RewardWeights(psnr_dynamic=math.inf)
    assert not RewardWeights().dynamic and DYNAMIC_REWARD.dynamic
