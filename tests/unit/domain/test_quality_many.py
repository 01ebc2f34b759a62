"""``score_many``: one render against several truths gives what one ``score`` call each gives,
bit for bit (the metrics service scores each render at its decision and its display time in
one call; the virtual clock calls ``score``). Random images and smooth ones, every reward
weighting, with and without LPIPS (a random-weight network: the batch paths, not the
pretrained values, are under test), a kept dynamic mask in place of the earlier frames."""

from __future__ import annotations

import kornia
import numpy as np
import pytest
import torch
from hypothesis import given, settings
from hypothesis import strategies as st

from aoi3d.lpips import LPIPS, LpipsDistance
from aoi3d.quality import (
    DYNAMIC_REWARD,
    RewardWeights,
    Truth,
    _chw,
    _ssim_maps,
    dynamic_mask,
    score,
    score_many,
)


def _lpips() -> LpipsDistance:
    torch.manual_seed(0)
    model = LPIPS("alex").eval().requires_grad_(False)
    for lin in model.lins:
        lin.weight.abs_()
    return LpipsDistance(model)


LPIPS_FN = _lpips()


def _images(seed: int, n: int, h: int = 40, w: int = 52) -> list[np.ndarray]:
    rng = np.random.default_rng(seed)
    base = rng.integers(0, 256, (h, w, 3)).astype(np.int16)
    out = []
    for _ in range(n):  # related images: a moving patch over a shared background
        img = base.copy()
        y, x = rng.integers(0, h - 12), rng.integers(0, w - 12)
        img[y:y + 12, x:x + 12] = rng.integers(0, 256, 3)
        out.append(np.clip(img + rng.integers(-8, 9, img.shape), 0, 255).astype(np.uint8))
    return out


@pytest.mark.parametrize("weights", [RewardWeights(), DYNAMIC_REWARD],
                         ids=["paper", "dynamic"])
@pytest.mark.parametrize("lpips", [True, False], ids=["lpips", "no-lpips"])
@pytest.mark.parametrize("k", [1, 2, 3])
def test_many_equals_one_score_each(weights: RewardWeights, lpips: bool, k: int) -> None:
    ims = _images(k, 3 * k + 1)
    pred, truths = ims[0], [(ims[1 + 3 * i], ims[2 + 3 * i:4 + 3 * i]) for i in range(k)]
    fn = LPIPS_FN if lpips else None
    many = score_many(pred, [Truth(t, prev) for t, prev in truths], weights, fn)
    each = [score(pred, t, weights, fn, previous=prev) for t, prev in truths]
    assert many == each  # dataclass equality: every float exactly equal


def test_a_kept_mask_scores_as_the_earlier_frames_do() -> None:
    pred, truth, a, b = _images(7, 4)
    mask = dynamic_mask(truth, [a, b])
    assert score_many(pred, [Truth(truth, mask=mask)], lpips_fn=LPIPS_FN) == \
        [score(pred, truth, lpips_fn=LPIPS_FN, previous=[a, b])]


def test_without_a_many_hook_each_pair_is_asked() -> None:
    pred, t1, t2 = _images(3, 3)
    pairs: list[tuple[float, float]] = []

    def plain(p: np.ndarray, t: np.ndarray) -> float:
        pairs.append((float(p.mean()), float(t.mean())))
        return LPIPS_FN(p, t)

    got = score_many(pred, [Truth(t1), Truth(t2)], lpips_fn=plain)
    assert len(pairs) == 2
    unit = [(im.astype(np.float64) / 255.0).astype(np.float32) for im in (pred, t1, t2)]
    assert [q.lpips for q in got] == [LPIPS_FN(unit[0], t) for t in unit[1:]]


def test_shapes_must_agree_and_nothing_to_score_is_nothing() -> None:
    pred, truth = _images(1, 2)
    with pytest.raises(ValueError, match="shapes differ"):
        score_many(pred, [Truth(truth[:-1])])
    assert score_many(pred, []) == []
    with pytest.raises(ValueError, match="dynamic region"):
        score_many(pred, [Truth(truth)], DYNAMIC_REWARD)


@settings(max_examples=25, deadline=None)
@given(seed=st.integers(0, 2**31 - 1), k=st.integers(1, 3),
       h=st.integers(11, 30), w=st.integers(11, 30))
def test_ssim_maps_are_kornias_bit_for_bit(seed: int, k: int, h: int, w: int) -> None:
    rng = np.random.default_rng(seed)
    p = _chw(rng.random((h, w, 3)))
    ts = [_chw(rng.random((h, w, 3))) for _ in range(k)]
    for got, t in zip(_ssim_maps(p, ts), ts, strict=True):
        want = kornia.metrics.ssim(p, t, 11, max_val=1.0, eps=0.0, padding="valid")
        assert torch.equal(got, want)


def test_lpips_many_equals_the_pairs_bit_for_bit() -> None:
    rng = np.random.default_rng(5)
    pred = rng.random((72, 96, 3)).astype(np.float32)
    truths = [rng.random((72, 96, 3)).astype(np.float32) for _ in range(3)]
    assert LPIPS_FN.many(pred, truths) == [LPIPS_FN(pred, t) for t in truths]
    assert LPIPS_FN.many(pred, []) == []
