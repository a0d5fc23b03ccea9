"""Preprocessing: each step switchable; equalisation removes ring artefacts."""

from __future__ import annotations

import math

import numpy as np
import pytest

from mapping.polar import FanGeometry
from mapping.preprocess import Preprocessor, PreprocessParams, equalize_rows


def ringed_ping(rng: np.random.Generator) -> np.ndarray:
    """Speckled seabed with a strong per-row gain ripple (rings in Cartesian)."""
    texture = rng.gamma(2.0, 30.0, (400, 128))
    ripple = 1.0 + 0.4 * np.sin(np.arange(400) / 3.0)[:, None]
    return np.clip(texture * ripple, 0, 255).astype(np.uint8)


def fan() -> FanGeometry:
    return FanGeometry.of(np.radians(np.linspace(-60, 60, 128)), 400, 0.0125, 1.0, math.radians(15))


def test_row_equalisation_flattens_the_ring_artefacts() -> None:
    image = ringed_ping(np.random.default_rng(1)).astype(np.float32)
    before = image.mean(axis=1).std()
    after = equalize_rows(image).mean(axis=1).std()
    assert after < before / 100


@pytest.mark.parametrize(
    "params",
    [
        PreprocessParams(),
        PreprocessParams(equalize_rows=False, clahe=False, histogram_match=False),
        PreprocessParams(denoise="median"),
        PreprocessParams(denoise="nlm"),
        PreprocessParams(blur=True),
    ],
)
def test_every_configuration_gives_a_valid_cartesian_frame(params: PreprocessParams) -> None:
    pre = Preprocessor(fan(), 15.0, params)
    frame = pre(ringed_ping(np.random.default_rng(2)))
    assert frame.image.dtype == np.float32
    assert frame.image.min() >= 0.0 and frame.image.max() <= 1.0
    assert frame.mask.any()
    assert np.all(frame.image[~frame.mask] == 0.0)
    assert np.all(frame.weight[~frame.mask] == 0.0)
    assert frame.image[frame.mask].std() > 0.01


def test_the_first_frame_fixes_the_histogram_reference() -> None:
    pre = Preprocessor(fan(), 15.0)
    rng = np.random.default_rng(3)
    first = pre(ringed_ping(rng))
    reference = pre.reference_cdf
    assert reference is not None
    pre(ringed_ping(rng) // 2)  # a darker ping is matched to the first one's histogram
    assert pre.reference_cdf is reference
    assert first.image[first.mask].mean() > 0.2


def test_an_unknown_denoiser_is_an_error() -> None:
    with pytest.raises(ValueError, match="unknown denoise method"):
        Preprocessor(fan(), 15.0, PreprocessParams(denoise="wiener"))(
            ringed_ping(np.random.default_rng(4))
        )
