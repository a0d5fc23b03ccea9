"""The paper's blending baselines (Table V): Hurtós et al.'s distance-based weighted mean
over every frame, and Su et al.'s variance score over fixed windows with a plain mean."""

from __future__ import annotations

import itertools
import math

import cv2
import numpy as np
import pytest

from mapping.blend import (
    BlendParams,
    FanWeigher,
    FeatureScorer,
    WindowScorer,
    hurtos_weight,
    local_variance,
    make_scorer,
    robust_blend,
    su_blend,
    weighted_mean_blend,
)
from mapping.fmt import hamming_taper
from mapping.grid import SonarGrid
from mapping.mosaic import SonarPose, TileGrid, assemble
from mapping.polar import FanGeometry, polar_to_ground
from mapping.preprocess import Preprocessor
from mapping.tiles import MemorySpill, TileStore
from tests.mapping import synth
from tools.evaluation.metrics import image_metrics

# The Oculus-like fan of the preprocessing tests: 128 beams over 120 degrees, 5 m.
FAN = FanGeometry.of(np.radians(np.linspace(-60, 60, 128)), 400, 0.0125, 1.0, math.radians(15))
TILES = TileGrid(res_m=0.02, tile_px=64)
SMALL = SonarGrid(shape=(32, 32), res_m=0.02, forward_max_m=0.64, starboard_min_m=0.0)


def grey(value: float) -> int:
    """The tiles' grey level of an intensity in [0, 1]."""
    return int(np.clip(np.rint(np.float32(value) * 254.0) + 1.0, 1, 255))


def level(grey_value: int) -> float:
    return (grey_value - 1) / 254.0


def world_pixel(store: TileStore, east: float, north: float) -> int:
    """The rendered grey value of the tile pixel holding UTM (east, north)."""
    t = store.grid.tile_m
    key = (math.floor(east / t), math.floor(north / t))
    west, top = store.grid.tile_west_north(key)
    image = store.render(key).values
    return int(image[int((top - north) / store.grid.res_m), int((east - west) / store.grid.res_m)])


# -- Hurtós ---------------------------------------------------------------------------------


def test_the_hurtos_weight_is_one_at_the_fans_centre_and_nothing_at_its_edges() -> None:
    pre = Preprocessor(FAN, 15.0)
    grid, weight, mask = pre.grid, pre.fan_weight, pre.tables.mask
    assert grid is not None
    near, far = pre.min_range_m, (FAN.n_ranges - 0.5) * FAN.range_resolution_m
    # Largest on the middle beam (the grid's middle column) half way across the band.
    row, col = np.unravel_index(int(np.argmax(weight)), weight.shape)
    assert weight.max() > 0.98
    assert abs(col + 0.5 - grid.shape[1] / 2) <= 1.0
    forward = grid.forward_max_m - (row + 0.5) * grid.res_m
    starboard = grid.starboard_min_m + (col + 0.5) * grid.res_m
    slant = math.sqrt(forward**2 + starboard**2 + FAN.altitude_m**2)
    assert abs(slant - (near + far) / 2) < 0.03
    # Half way to a lateral edge (30 of 60 degrees) at mid-range: half the weight.
    f30, s30 = polar_to_ground(
        np.array((near + far) / 2), np.array(math.radians(30.0)), FAN.altitude_m, FAN.tilt_rad
    )
    r30 = round((grid.forward_max_m - float(f30)) / grid.res_m - 0.5)
    c30 = round((float(s30) - grid.starboard_min_m) / grid.res_m - 0.5)
    assert weight[r30, c30] == pytest.approx(0.5, abs=0.03)
    # Nothing outside the fan, next to nothing on its rim (lateral edges, near and far
    # range), yet something everywhere inside it.
    rim = mask & ~cv2.erode(mask.astype(np.uint8), np.ones((3, 3), np.uint8)).astype(bool)
    assert np.all(weight[~mask] == 0.0)
    assert weight[rim].max() < 0.03
    assert weight[mask].min() > 0.0
    # Port and starboard mirror each other.
    np.testing.assert_array_equal(mask, mask[:, ::-1])
    np.testing.assert_allclose(weight, weight[:, ::-1], atol=1e-5)
    # The frame's weights are its fan weights: no variance, no taper.
    image = np.random.default_rng(1).random(mask.shape).astype(np.float32)
    frame_weight = FanWeigher()(image, mask, pre.weight, weight)
    np.testing.assert_array_equal(frame_weight, np.where(mask, weight, 0.0))


def test_a_pixel_seen_by_a_fans_centre_and_by_another_fans_edge_takes_the_centres_value() -> None:
    pre = Preprocessor(FAN, 15.0)
    grid, weight, mask = pre.grid, pre.fan_weight, pre.tables.mask
    assert grid is not None
    row, centre_col = np.unravel_index(int(np.argmax(weight)), weight.shape)
    edge_col = int(np.flatnonzero(mask[row])[0]) + 4  # four pixels in from the port edge
    w_centre, w_edge = float(weight[row, centre_col]), float(weight[row, edge_col])
    assert w_centre > 0.98 and w_edge < 0.05
    params = BlendParams(method="hurtos")
    store = TileStore(TileGrid(0.02, 256), params)
    scorer = make_scorer(params)
    # Boresight north, pixel-aligned eastwards: frame B's edge pixel on frame A's centre.
    east_a, north = 10.0 - grid.starboard_min_m, 10.0
    east_b = east_a + (centre_col - edge_col) * grid.res_m
    for index, (east, value) in enumerate(((east_a, 0.8), (east_b, 0.2))):
        image = np.where(mask, np.float32(value), np.float32(0.0))
        score = scorer(image, mask, pre.weight, pre.fan_weight)
        store.insert(index, image, score, mask, grid, SonarPose(east, north, 0.0), 0.0, False)
    there_e = east_a + grid.starboard_min_m + (centre_col + 0.5) * grid.res_m
    there_n = north + grid.forward_max_m - (row + 0.5) * grid.res_m
    blended = level(world_pixel(store, there_e, there_n))
    expected = (w_centre * 0.8 + w_edge * 0.2) / (w_centre + w_edge)
    assert blended == pytest.approx(expected, abs=0.01)
    assert blended > 0.77  # the plain mean would be 0.5


def small_frame(value: float, weight: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    return (
        np.full(SMALL.shape, value, np.float32),
        np.full(SMALL.shape, weight, np.float32),
        np.ones(SMALL.shape, bool),
    )


def test_hurtos_counts_every_frame_not_only_the_stacks_best() -> None:
    # Five settled frames over one pixel, a stack of two: the weighted mean of all five.
    weights = [0.9, 0.3, 0.6, 0.2, 0.5]
    values = [0.1, 0.9, 0.5, 0.7, 0.3]
    spill = MemorySpill()
    store = TileStore(TILES, BlendParams(method="hurtos", top_n=2), spill, evict_after_s=1.0)
    for k, (w, v) in enumerate(zip(weights, values, strict=True)):
        image, score, mask = small_frame(v, w)
        store.insert(k, image, score, mask, SMALL, SonarPose(0.2, 0.1, 0.0), float(k), False)
        if k == 2:
            # The sums outside the stack leave memory with the tile and come back.
            store.render_dirty()
            store.evict_idle(now=10.0)
            assert not store.active
    assert store.reloaded == 1
    ws, vs = np.array(weights, np.float32), np.array(values, np.float32)
    everyone = float((ws * vs).sum() / ws.sum())  # 0.38
    two_best = float((ws[[0, 2]] * vs[[0, 2]]).sum() / ws[[0, 2]].sum())  # 0.26
    got = store.render((0, 0)).values[40, 25]
    assert abs(int(got) - grey(everyone)) <= 1
    assert abs(int(got) - grey(two_best)) > 20
    # The reference blend says the same of the same candidates.
    value, covered = weighted_mean_blend(vs[None, :], ws[None, :])
    assert covered[0] and value[0] == pytest.approx(everyone, rel=1e-6)


def test_a_movable_frame_taken_out_leaves_the_others_weighted_mean() -> None:
    store = TileStore(TILES, BlendParams(method="hurtos", top_n=4))
    for k, (v, w) in enumerate(((0.2, 0.9), (0.8, 0.3), (0.5, 0.6))):
        image, score, mask = small_frame(v, w)
        store.insert(k, image, score, mask, SMALL, SonarPose(0.2, 0.1, 0.0), float(k))
    all_three = (0.2 * 0.9 + 0.8 * 0.3 + 0.5 * 0.6) / 1.8
    assert abs(int(store.render((0, 0)).values[40, 25]) - grey(all_three)) <= 1
    store.remove(0, [(0, 0)])
    others = (0.8 * 0.3 + 0.5 * 0.6) / 0.9
    assert abs(int(store.render((0, 0)).values[40, 25]) - grey(others)) <= 1


# -- Su -------------------------------------------------------------------------------------


def textured(rng: np.random.Generator, k: int) -> np.ndarray:
    """A frame whose texture strength changes from frame to frame (and within it)."""
    ramp = np.linspace(0.2, 1.0, 50, dtype=np.float32)[None, :]
    strength = np.float32(0.1 + 0.9 * ((k * 7) % 11) / 10)
    return (rng.random((40, 50)).astype(np.float32) * ramp * strength).astype(np.float32)


def test_su_statistics_are_plain_moving_averages_over_fixed_windows() -> None:
    rng = np.random.default_rng(5)
    params = BlendParams(method="su", su_short_frames=3, su_long_frames=5)
    su, ema = WindowScorer(params), FeatureScorer(params)
    mask = np.ones((40, 50), bool)
    instants = []
    largest_gap = 0.0
    for k in range(12):
        image = textured(rng, k)
        instants.append(local_variance(image, params.variance_window))
        score = su(image, mask)
        ema(image, mask)
        assert su.short is not None and su.long is not None and ema.short is not None
        short = np.mean(instants[max(0, k - 2) : k + 1], axis=0)
        long = np.mean(instants[max(0, k - 4) : k + 1], axis=0)
        np.testing.assert_allclose(su.short, short, rtol=1e-5, atol=1e-9)
        np.testing.assert_allclose(su.long, long, rtol=1e-5, atol=1e-9)
        # Eq. 10 on them, normalised within the fan.
        norm_s = (short - short.min()) / (short.max() - short.min())
        norm_l = (long - long.min()) / (long.max() - long.min())
        np.testing.assert_allclose(score, norm_s * np.exp(-norm_l), rtol=1e-4, atol=1e-6)
        largest_gap = max(largest_gap, float(np.abs(su.short - ema.short).max() / short.mean()))
    # The EMA's statistics are another thing.
    assert largest_gap > 0.2
    assert make_scorer(params).__class__ is WindowScorer


def test_a_frame_older_than_the_long_window_no_longer_counts() -> None:
    params = BlendParams(method="su", su_short_frames=2, su_long_frames=6)
    mask = np.ones((40, 50), bool)
    rng = np.random.default_rng(6)
    frames = [textured(rng, k) for k in range(8)]
    odd_first = [frames[0] * np.float32(8.0), *frames[1:]]
    runs = []
    for sequence in (frames, odd_first):
        su, ema = WindowScorer(params), FeatureScorer(params)
        longs = []
        for image in sequence:
            su(image, mask)
            ema(image, mask)
            assert su.long is not None and ema.long is not None
            longs.append((su.long.copy(), ema.long.copy()))
        runs.append(longs)
    (plain, plain_ema), (odd, odd_ema) = runs[0][5], runs[1][5]
    assert np.abs(odd - plain).max() > 0.1 * plain.mean()  # frame 0 is one of the last 6
    (plain, plain_ema), (odd, odd_ema) = runs[0][6], runs[1][6]
    np.testing.assert_allclose(odd, plain, rtol=1e-6)  # ... and here it has left
    assert np.abs(odd_ema - plain_ema).max() > 0.05 * plain_ema.mean()  # the EMA remembers


def test_su_windows_default_to_the_box_equivalents_of_the_papers_emas() -> None:
    p = BlendParams()
    # An EMA with decay beta averages noise as a box of (1 + beta) / (1 - beta) frames.
    assert p.su_short_frames == round((1 + p.beta_s) / (1 - p.beta_s)) == 4
    assert p.su_long_frames == round((1 + p.beta_l) / (1 - p.beta_l)) == 66


def test_su_keeps_by_rho_and_averages_the_kept_plainly() -> None:
    params = BlendParams(rho=0.68)
    # Two kept candidates of different scores (0.3 < 0.68: dropped): their plain mean,
    # where the robust blend weighs them by s^gamma.
    intensity = np.array([[0.2, 0.8, 0.5]], np.float32)
    score = np.array([[1.0, 0.7, 0.3]], np.float32)
    value, covered = su_blend(intensity, score, params)
    robust, _ = robust_blend(intensity, score, params)
    assert covered[0] and value[0] == pytest.approx(0.5, abs=1e-6)
    assert robust[0] == pytest.approx((0.2 + 0.8 * 0.7**1.4) / (1 + 0.7**1.4), abs=1e-5)
    # No trimming either: an outlier among the kept stays in the mean.
    intensity = np.array([[0.50, 0.52, 0.95, 0.48]], np.float32)
    score = np.array([[1.0, 0.9, 0.85, 0.8]], np.float32)
    value, _ = su_blend(intensity, score, params)
    robust, _ = robust_blend(intensity, score, params)
    assert value[0] == pytest.approx((0.50 + 0.52 + 0.95 + 0.48) / 4, abs=1e-6)
    assert robust[0] < 0.53  # MAD-trimmed
    # The tiles render it the same way.
    store = TileStore(TILES, BlendParams(method="su"))
    for k, (v, s) in enumerate(((0.2, 1.0), (0.8, 0.7), (0.5, 0.3))):
        image, weight, mask = small_frame(v, s)
        store.insert(k, image, weight, mask, SMALL, SonarPose(0.2, 0.1, 0.0), float(k))
    assert abs(int(store.render((0, 0)).values[40, 25]) - grey(0.5)) <= 1


# -- end to end ------------------------------------------------------------------------------

METHODS = ("robust", "average", "hurtos", "su")


def synthetic_survey(method: str) -> tuple[np.ndarray, tuple[float, float]]:
    """Two lanes north, 3 m apart, a frame every 25 cm over a textured, speckled seabed,
    blended with ``method``: the mosaic (0 = no data) and its top-left UTM corner."""
    rng = np.random.default_rng(11)
    world = synth.seabed(np.random.default_rng(2))
    grid, mask = synth.fan()
    forward, starboard = synth.grid_coordinates(grid)
    fan_weight = hurtos_weight(
        np.arctan2(starboard, forward),
        np.hypot(forward, starboard),
        mask,
        (-math.radians(64), math.radians(64)),
        (2.2, 4.9),
    )
    taper = hamming_taper(mask, 10)
    params = BlendParams(method=method)
    scorer = make_scorer(params)
    store = TileStore(TileGrid(0.02, 256), params)
    for k, (east, north) in enumerate(survey_poses()):
        image = synth.view(world, grid, mask, east, north, 0.0, rng)
        image = np.clip(image, 0.0, 1.0)
        score = scorer(image, mask, taper, fan_weight)
        store.insert(k, image, score, mask, grid, SonarPose(east, north, 0.0), 0.1 * k, False)
    return assemble(store.grid, {t.key: t.values for t in store.rendered_tiles()})


def survey_poses() -> list[tuple[float, float]]:
    return [(east, 2.0 + 0.25 * i) for east in (5.0, 8.0) for i in range(25)]


def surely_covered(shape: tuple[int, int], corner: tuple[float, float]) -> np.ndarray:
    """Mosaic pixels at least 4 cm (two pixels) inside some frame's fan (which the
    synthetic frame's grid cuts 1.5 m forward of the sonar)."""
    rows, cols = np.indices(shape)
    east = corner[0] + (cols + 0.5) * 0.02
    north = corner[1] - (rows + 0.5) * 0.02
    inside = np.zeros(shape, bool)
    margin = 0.04
    for e, n in survey_poses():
        forward, starboard = north - n, east - e
        r = np.hypot(forward, starboard)
        lateral = r * (math.radians(64) - np.abs(np.arctan2(starboard, forward)))
        ahead = forward > 5.0 - 175 * 0.02 + margin
        inside |= (r > 2.2 + margin) & (r < 4.9 - margin) & (lateral > margin) & ahead
    return inside


@pytest.fixture(scope="module")
def mosaics() -> dict[str, tuple[np.ndarray, tuple[float, float]]]:
    return {method: synthetic_survey(method) for method in METHODS}


def test_every_method_maps_the_whole_survey_and_each_its_own_way(
    mosaics: dict[str, tuple[np.ndarray, tuple[float, float]]],
) -> None:
    corners = {corner for _, corner in mosaics.values()}
    shapes = {image.shape for image, _ in mosaics.values()}
    assert len(corners) == 1 and len(shapes) == 1
    (image, corner) = mosaics["robust"]
    footprint = surely_covered(image.shape, corner)
    assert footprint.sum() > 100_000
    for method, (values, _) in mosaics.items():
        holes = footprint & (values == 0)
        assert holes.sum() == 0, (method, int(holes.sum()))
    common = np.logical_and.reduce([v > 0 for v, _ in mosaics.values()])
    for a, b in itertools.combinations(METHODS, 2):
        va = mosaics[a][0][common].astype(float)
        vb = mosaics[b][0][common].astype(float)
        assert np.abs(va - vb).mean() > 2.0, (a, b)
    # Sharpness ranks them as the paper's Table V does: averaging, Hurtos, Su, robust
    # (0.35, 0.40, 0.47, 0.59 Ten. here).
    sharpness = {
        method: image_metrics((values.astype(float) - 1.0) / 254.0, common)
        for method, (values, _) in mosaics.items()
    }
    for key in ("tenengrad", "variance_of_laplacian"):
        ranked = [sharpness[m][key] for m in ("average", "hurtos", "su", "robust")]
        assert all(a < b for a, b in itertools.pairwise(ranked)), (key, ranked)


def test_an_unknown_method_is_refused_naming_the_methods() -> None:
    with pytest.raises(ValueError, match=r"'median' \(robust, average, hurtos, su\)"):
        BlendParams(method="median")
