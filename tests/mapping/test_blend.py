"""Robust blending keeps detail that plain averaging smears."""

from __future__ import annotations

import numpy as np

from mapping.blend import BlendParams, FeatureScorer, robust_blend
from tools.evaluation.metrics import tenengrad


def test_a_sharp_edge_stays_sharper_than_with_averaging() -> None:
    rng = np.random.default_rng(4)
    size = 64
    truth = np.zeros((size, size), np.float32)
    truth[:, size // 2 :] = 1.0
    mask = np.ones((size, size), bool)
    scorer = FeatureScorer()
    stacks = []
    for k in range(12):
        # Frames misregistered by a few pixels, as real ones are, and noisy.
        shift = int(rng.integers(-3, 4))
        frame = np.roll(truth, shift, axis=1) + rng.normal(0, 0.05, truth.shape).astype(np.float32)
        if k % 3 == 0:
            frame = np.roll(frame, 5, axis=1)  # an outlier frame, badly registered
        stacks.append((np.clip(frame, 0, 1), scorer(frame, mask)))
    intensity = np.stack([f for f, _ in stacks], axis=-1)
    score = np.stack([s for _, s in stacks], axis=-1)
    sharp, covered = robust_blend(intensity, score, BlendParams())
    smooth = intensity.mean(axis=-1)
    assert covered.all()
    assert tenengrad(sharp.astype(float), mask) > 1.3 * tenengrad(smooth.astype(float), mask)


def test_rho_topn_mad_and_gamma_follow_the_paper() -> None:
    # One pixel, five candidates; scores decide who is kept, MAD trims the outlier.
    intensity = np.array([[[0.50, 0.52, 0.48, 0.95, 0.10]]], np.float32)
    score = np.array([[[1.00, 0.90, 0.80, 0.85, 0.30]]], np.float32)
    params = BlendParams(rho=0.68, top_n=16, eta=2.7, gamma=1.4)
    value, covered = robust_blend(intensity, score, params)
    # 0.10 (score 0.30 < 0.68) is dropped by rho; 0.95 is trimmed by MAD.
    kept_i = np.array([0.50, 0.52, 0.48])
    kept_w = np.array([1.00, 0.90, 0.80]) ** 1.4
    assert covered[0, 0]
    np.testing.assert_allclose(value[0, 0], (kept_i * kept_w).sum() / kept_w.sum(), rtol=1e-5)


def test_masked_median_matches_numpy() -> None:
    rng = np.random.default_rng(8)
    values = rng.random((50, 40, 16)).astype(np.float32)
    keep = rng.random((50, 40, 16)) < 0.6
    keep[0, 0] = False
    expected = np.nanmedian(np.where(keep[1:], values[1:], np.nan), axis=-1)
    from mapping.blend import masked_median

    got = masked_median(values, keep)
    np.testing.assert_allclose(got[1:], expected, rtol=1e-6)
    assert got[0, 0] == 0.0
