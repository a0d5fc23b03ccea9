"""The fusion weighs each GNSS fix by the accuracy its receiver reports: an RTK survey's
track follows its centimetre fixes, a few fixes that say they are worse do not pull it,
and a receiver that reports nothing (or an autonomous fix) keeps the model's sigmas."""

from __future__ import annotations

import dataclasses
import math

import numpy as np
import pytest

from mapping.fusion import (
    Fusion,
    FusionData,
    FusionParams,
    GnssErrorModel,
    RelativeConstraint,
    diagonal_sqrt_info,
)
from mapping.samples import GnssFixType
from mapping.se2 import relative_pose
from tests.mapping.test_fusion import _path

RATE_HZ = 5.0
DURATION_S = 180.0
LAG_S = 0.03
RTK_H_ACC_M = 0.015
BAD = (60.0, 64.0)
"""Seconds of survey whose fixes say 1 m and are 0.5 m east of the antenna."""


def _rtk_survey(seed: int = 7) -> tuple[np.ndarray, np.ndarray, FusionData, list, np.ndarray]:
    """A lawnmower at 0.4 m/s with an RTK receiver at 5 Hz (15 mm white, an 8 mm wander,
    fixes LAG_S old, reporting 15 mm, fix type 6), but for BAD, where the fixes report
    1 m in RTK float and sit 0.5 m east. Registrations good to 3 mm, a compass 3 degrees
    off, a gyro with a bias."""
    rng = np.random.default_rng(seed)
    gnss_t = np.arange(0.0, DURATION_S, 0.2)
    wander = np.cumsum(rng.normal(0, 0.0008, (gnss_t.size, 2)), axis=0).clip(-0.008, 0.008)
    gnss_xy = _path(gnss_t - LAG_S)[:, :2] + wander + rng.normal(0, 0.015, (gnss_t.size, 2))
    accuracy = np.full(gnss_t.size, RTK_H_ACC_M)
    fix_type = np.full(gnss_t.size, int(GnssFixType.RTK_FIXED), np.int64)
    bad = (gnss_t >= BAD[0]) & (gnss_t < BAD[1])
    gnss_xy[bad, 0] += 0.5
    accuracy[bad] = 1.0
    fix_type[bad] = int(GnssFixType.RTK_FLOAT)
    head_t = np.arange(0.0, DURATION_S, 0.5)
    head = (_path(head_t)[:, 2] + math.radians(3.0) + rng.normal(0, 0.02, head_t.size)) % (
        2 * math.pi
    )
    times = np.arange(0.5, DURATION_S - 0.5, 1.0 / RATE_HZ)
    truth = _path(times)
    yaw = np.unwrap(truth[:, 2]) + math.radians(0.1) * times
    data = FusionData(
        gnss_t, gnss_xy, head_t, head, yaw, np.zeros(times.size, bool), accuracy, fix_type
    )
    constraints = []
    for k in range(1, times.size):
        rel = relative_pose(truth[k - 1], truth[k])
        constraints.append(
            RelativeConstraint(
                k - 1,
                k,
                rel.forward_m + rng.normal(0, 0.003),
                rel.starboard_m + rng.normal(0, 0.003),
                rel.yaw_rad + rng.normal(0, math.radians(0.03)),
                diagonal_sqrt_info((0.003, 0.003, math.radians(0.03))),
            )
        )
    initial = truth.copy()
    initial[:, :2] += 0.3
    initial[:, 2] += math.radians(2.0)
    return times, truth, data, constraints, initial


@pytest.fixture(scope="module")
def rtk():
    return _rtk_survey()


def _position_errors(poses: np.ndarray, truth: np.ndarray) -> np.ndarray:
    return np.asarray(np.hypot(*(poses[:, :2] - truth[:, :2]).T), float)


def test_an_rtk_track_follows_the_fixes_that_report_centimetres(rtk) -> None:
    """The track lies within 2 cm RMS of the truth, and the fixes that say 1 m, 0.5 m
    off, move it by less than 3 cm: the solution follows the accurate ones."""
    times, truth, data, constraints, initial = rtk
    solution, _ = Fusion(times, data).solve(initial, constraints)
    error = _position_errors(solution.poses, truth)
    assert float(np.sqrt(np.mean(error**2))) < 0.02
    during = (times >= BAD[0] - 2.0) & (times < BAD[1] + 2.0)
    assert float(error[during].max()) < 0.03


def test_weighed_as_an_m8n_the_same_fixes_give_decimetres(rtk) -> None:
    """Without the reported accuracies the same fixes count as an M8N's (0.6 m white, a
    1.2 m wander): the property above is the weighting's, not the survey's."""
    times, truth, data, constraints, initial = rtk
    blind = dataclasses.replace(data, gnss_accuracy_m=None, gnss_fix_type=None)
    solution, _ = Fusion(times, blind).solve(initial, constraints)
    error = _position_errors(solution.poses, truth)
    assert float(np.sqrt(np.mean(error**2))) > 0.04


@pytest.mark.parametrize("prior_error_s", [-0.15, 0.1, 0.3])
def test_the_rtk_lag_is_found_from_a_prior_frames_off(rtk, prior_error_s: float) -> None:
    """The prior puts the fixes up to a frame and a half away from when they were taken
    (the fixes are bracketed again as the estimate moves): the lag is found within 25 ms
    (10 mm along the track at 0.4 m/s, the wander's size) and the track stays within 2
    cm RMS."""
    times, truth, data, constraints, initial = rtk
    params = FusionParams(gnss=GnssErrorModel(time_offset_s=LAG_S + prior_error_s))
    solution, _ = Fusion(times, data, params).solve(initial, constraints)
    assert abs(solution.time_offset_s - LAG_S) < 0.025
    error = _position_errors(solution.poses, truth)
    assert float(np.sqrt(np.mean(error**2))) < 0.02


def test_without_reported_accuracy_the_model_sigmas_hold_exactly() -> None:
    """No accuracy, accuracies that are NaN, and autonomous fixes (3-D) that report an
    M8N's 1.3 m give the model's sigmas and the same solution, to the last bit."""
    model = GnssErrorModel()
    white, wander = model.fix_sigmas(
        np.array([1.3, math.nan, 0.02]), np.array([3, 6, 3], np.int64), 3
    )
    assert white.tolist() == [model.white_sigma_m] * 3
    assert wander.tolist() == [model.bias_sigma_m] * 3

    times, _, data, constraints, initial = _rtk_survey(seed=11)
    none = dataclasses.replace(data, gnss_accuracy_m=None, gnss_fix_type=None)
    nan = dataclasses.replace(data, gnss_accuracy_m=np.full(data.gnss_times.size, math.nan))
    autonomous = dataclasses.replace(
        data,
        gnss_accuracy_m=np.full(data.gnss_times.size, 1.3),
        gnss_fix_type=np.full(data.gnss_times.size, int(GnssFixType.FIX_3D), np.int64),
    )
    reference, _ = Fusion(times, none).solve(initial, constraints)
    for variant in (nan, autonomous):
        solution, _ = Fusion(times, variant).solve(initial, constraints)
        assert np.array_equal(solution.poses, reference.poses)
        assert np.array_equal(solution.bias_xy, reference.bias_xy)


def test_a_corrected_fix_is_capped_at_what_it_reports() -> None:
    """A corrected fix's white noise and wander are each the model's, at most its
    reported accuracy (metres): RTK fixed 15 mm, float 0.2 m, SBAS 1.5 m (the model's);
    a reported accuracy below the floor is the floor."""
    model = GnssErrorModel()
    white, wander = model.fix_sigmas(
        np.array([0.015, 0.2, 1.5, 0.0001]),
        np.array([6, 5, 4, 6], np.int64),
        4,
    )
    floor = model.accuracy_floor_m
    assert white.tolist() == [0.015, 0.2, model.white_sigma_m, floor]
    assert wander.tolist() == [0.015, 0.2, model.bias_sigma_m, floor]
