"""Preprocessing: each step switchable; equalisation removes ring artefacts."""

from __future__ import annotations

import math

import cv2
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


# The flat field (step 0): the sonar's uneven insonification, fixed to the sonar, taken out.


def _lit(fan: FanGeometry, altitude_m: float) -> np.ndarray:
    """A fixed insonification on (range, beam): the vertical lobe over r / h, each beam's
    own gain, and a lit band's near edge curved across the fan."""
    r = (np.arange(fan.n_ranges) + 0.5) * fan.range_resolution_m
    bearing = np.asarray(fan.bearings_rad)
    depression = np.degrees(np.arcsin(np.clip(altitude_m / r, 0.0, 1.0)))[:, None]
    lobe = np.exp(-0.5 * ((depression - 25.0 + 6.0 * bearing[None, :] ** 2) / 8.0) ** 2)
    beam_gain = 1.0 + 0.15 * np.sin(np.arange(bearing.size) * 1.7)[None, :]
    return 0.05 + lobe * beam_gain


def _moving_seabed(rng: np.random.Generator, n: int, shape: tuple[int, int]) -> list[np.ndarray]:
    """A textured seabed (30 %, a few range lines across) sliding through the fan by 3
    range lines a ping."""
    long = rng.normal(0.0, 1.0, (shape[0] + 3 * n, shape[1])).astype(np.float32)
    long = cv2.GaussianBlur(long, (0, 0), 2.0)
    long = 1.0 + 0.3 * long / long.std()
    return [long[3 * k : 3 * k + shape[0]] for k in range(n)]


def _fixed_share(frames: list[np.ndarray], first_row: int) -> float:
    """The share of a frame's variance that is the same in every frame (its mean)."""
    stack = np.stack([f[first_row:].astype(np.float64) for f in frames])
    return float(stack.mean(axis=0).var() / stack.var(axis=(1, 2)).mean())


def _correlation(a: np.ndarray, b: np.ndarray) -> float:
    return float(np.corrcoef(a.astype(np.float64).ravel(), b.astype(np.float64).ravel())[0, 1])


@pytest.mark.parametrize("altitudes", [(1.0, 1.0), (0.9, 1.3)])
def test_the_flat_field_takes_out_the_insonification_fixed_to_the_sonar(
    altitudes: tuple[float, float],
) -> None:
    geometry = fan()
    rng = np.random.default_rng(4)
    n = 120
    seabed = _moving_seabed(rng, n, (geometry.n_ranges, len(geometry.bearings_rad)))
    heights = np.linspace(*altitudes, n)  # over a slope: the lit band moves in range
    pings = [
        np.clip(70.0 * _lit(geometry, h) * bed * rng.gamma(1.5, 1 / 1.5, bed.shape), 0, 255)
        for h, bed in zip(heights, seabed, strict=True)
    ]
    plain = Preprocessor(geometry, 15.0, PreprocessParams(flat_field_s=0.0))
    flat = Preprocessor(geometry, 15.0, PreprocessParams(flat_field_s=10.0))
    before = [plain.polar(p.astype(np.uint8)) for p in pings]
    after = [
        flat.polar(p.astype(np.uint8), float(h), k / 5.0)
        for k, (p, h) in enumerate(zip(pings, heights, strict=True))
    ]
    first = plain.first_lit_row
    # Row equalisation alone leaves the beams' gains and the curved edge in every frame
    # (4 % of its variance here); flattened, a quarter of that.
    share = _fixed_share(before[20:], first)
    assert share > 0.03
    assert _fixed_share(after[20:], first) < 0.4 * share

    # Two consecutive frames correlate on the seabed where it moved to (3 range lines
    # on) more than on what stayed in place, more clearly than without the flat field.
    def contrast(frames: list[np.ndarray]) -> float:
        moved = _correlation(frames[60][first + 3 :], frames[61][first:-3])
        still = _correlation(frames[60][first:], frames[61][first:])
        return moved / still

    assert _correlation(after[60][first + 3 :], after[61][first:-3]) > 0.05
    assert contrast(after) > 1.1 * contrast(before)


def test_a_bright_object_leaves_no_ghost_in_the_frames_after_it() -> None:
    geometry = fan()
    rng = np.random.default_rng(5)
    flat = Preprocessor(
        geometry, 15.0, PreprocessParams(flat_field_s=10.0, equalize_rows=False, clahe=False)
    )
    level = 60.0 * _lit(geometry, 1.0)
    for k in range(60):
        ping = level * rng.gamma(1.5, 1 / 1.5, level.shape)
        if k == 50:
            ping[250:270, 60:70] = 255.0  # a tyre, for one ping
        flat.flatten(ping.astype(np.float32), 1.0, k / 5.0)
    after = flat.flatten(level.astype(np.float32), 1.0, 60 / 5.0)
    # Where it was, the next frame is as bright as around it (within a few per cent).
    inside = after[250:270, 60:70].mean()
    around = after[230:290, 40:90].mean()
    assert abs(inside / around - 1.0) < 0.05
