"""A long range costs a frame about what a short one does (issue 34, lead 5).

The frames' cells grow with the sonar's range lines once those are coarser than 1 cm
(``preprocess.ground_cell_m``), so a 10 m fan is registered and blended on grids within
1.5 times a 5 m fan's, and a 5 m fan keeps today's grids exactly. The work is asserted by
the sizes it runs on (pixels, FFT sizes), never by time: ``seamap bench --range``
measures the time.
"""

from __future__ import annotations

import math

import numpy as np
import pytest

from mapping.fmt import FmtRegistrar
from mapping.polar import FanGeometry, fan_grid
from mapping.preprocess import Preprocessor, PreprocessParams, ground_cell_m
from mapping.se2 import RelativePose
from tests.mapping import test_fmt_bed as bed

TILT_DEG = 15.0


def _fan(range_m: float, altitude_m: float = 1.0) -> FanGeometry:
    """The M1200d's fan at ``range_m``: 512 beams over 130 degrees and range lines of
    max(1 cm, range / 600), as the simulator's sonar keeps them."""
    resolution = round(max(0.01, range_m / 600.0), 4)
    return FanGeometry.of(
        bed.bearing_table(512, 130.0),
        round(range_m / resolution),
        resolution,
        altitude_m,
        math.radians(TILT_DEG),
    )


def _work(pre: Preprocessor, params: PreprocessParams) -> dict[str, int]:
    """The sizes a frame's work runs on: the blending and registration grids' pixels, and
    the registrar's rotation (square) and translation FFTs."""
    assert pre.grid is not None
    registrar = FmtRegistrar(pre.registration_grid, pre.registration_tables.mask)
    return {
        "blending_px": pre.grid.shape[0] * pre.grid.shape[1],
        "registration_px": pre.registration_grid.shape[0] * pre.registration_grid.shape[1],
        "rotation_fft": registrar.n * registrar.n,
        "translation_fft": registrar.shape_t[0] * registrar.shape_t[1],
    }


@pytest.mark.parametrize(
    "params",
    [PreprocessParams(), PreprocessParams(registration_res_m=0.03)],
    ids=["pipeline", "live"],
)
@pytest.mark.parametrize(
    ("long_range_m", "bound"),
    # (600 / 500)^2 = 1.44 more range lines squared; the fans' shapes differ a little.
    [(10.0, 1.5), (17.5, 1.6)],
)
def test_a_long_range_frame_works_on_grids_about_those_of_a_5_m_one(
    params: PreprocessParams, long_range_m: float, bound: float
) -> None:
    short = _work(Preprocessor(_fan(5.0), TILT_DEG, params), params)
    long = _work(Preprocessor(_fan(long_range_m, altitude_m=2.0), TILT_DEG, params), params)
    for size, value in long.items():
        assert value <= bound * short[size], (size, value, short[size])


def test_a_5_m_fan_keeps_todays_grids() -> None:
    # Today's grids at the configured cells: the 22 surveys at 5 m map byte for byte.
    for params in (PreprocessParams(), PreprocessParams(registration_res_m=0.03)):
        fan = _fan(5.0)
        pre = Preprocessor(fan, TILT_DEG, params)
        assert pre.grid == fan_grid(fan, params.res_m, pre.min_range_m)
        assert pre.registration_grid == fan_grid(fan, params.registration_res_m, pre.min_range_m)
    # Range lines a hair coarser than 1 cm (a real log's rounding) keep them too.
    assert ground_cell_m(0.02, 0.01002, 0.01) == 0.02


def test_the_cell_grows_with_the_range_lines() -> None:
    assert ground_cell_m(0.02, 0.005, 0.01) == 0.02
    assert ground_cell_m(0.02, 0.0167, 0.01) == 0.033
    assert ground_cell_m(0.03, 0.0167, 0.01) == 0.05
    assert ground_cell_m(0.02, 0.0291, 0.01) == 0.058


@pytest.mark.parametrize(
    "step",
    [RelativePose(0.3, 0.05, 0.0), RelativePose(0.25, -0.1, math.radians(1.5))],
    ids=["straight", "turning"],
)
def test_a_pair_of_10_m_frames_registers_within_a_cell(step: RelativePose) -> None:
    sonar = bed.Sonar(range_m=10.0, range_resolution_m=0.0167, altitude_m=2.0, seed=1)
    cell = sonar.grid.res_m
    assert cell == pytest.approx(0.033)
    rng = np.random.default_rng(5)
    seabed = bed.make_seabed(rng, size_m=22.0)
    registrar = sonar.registrar()
    pose = (11.0, 1.0, 0.0)
    following = bed.moved(pose, step)
    earlier = registrar.prepare(sonar.frame(seabed, pose, rng))
    later = registrar.prepare(sonar.frame(seabed, following, rng))
    truth = bed.relative(pose, following)
    prior = RelativePose(truth.forward_m + 0.05, truth.starboard_m - 0.05, 0.0)
    result = registrar.register(earlier, later, prior, prior_sigma_m=0.15)
    error_m = math.hypot(
        result.relative.forward_m - truth.forward_m,
        result.relative.starboard_m - truth.starboard_m,
    )
    assert error_m < cell, (error_m, result.relative, truth)
    # A pixel's error at the end of 10 m lever arms: a cell over a few metres of fan.
    assert abs(math.degrees(result.relative.yaw_rad - truth.yaw_rad)) < 0.1
