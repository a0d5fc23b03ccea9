"""The survey-wide fusion on a synthetic lawnmower with field-like sensor errors: the
GNSS wanders (Gauss-Markov, tens of seconds) and lags, the compass is biased, the gyro
has a bias; registrations are good to millimetres. The map must keep its shape, find the
compass bias, and not depend on the ping rate."""

from __future__ import annotations

import math

import numpy as np
import pytest

from mapping.fusion import (
    Fusion,
    FusionData,
    FusionParams,
    RelativeConstraint,
    diagonal_sqrt_info,
)
from mapping.se2 import relative_pose
from mapping.sparse import SpdFactor

SPEED = 0.4
LANE_M = 20.0
SPACING_M = 4.0
N_LANES = 3


def _path(t: np.ndarray) -> np.ndarray:
    """True (east, north, heading) of lanes north/south joined by half circles."""
    lane_s = LANE_M / SPEED
    turn_s = math.pi * (SPACING_M / 2) / SPEED
    period = lane_s + turn_s
    out = np.zeros((t.size, 3))
    for k, tk in enumerate(t):
        lane = int(tk // period)
        u = tk - lane * period
        x0 = lane * SPACING_M
        up = lane % 2 == 0
        if u < lane_s:
            d = u * SPEED
            out[k] = (x0, d if up else LANE_M - d, 0.0 if up else math.pi)
        else:
            a = (u - lane_s) / turn_s * math.pi  # 0..pi around the turn centre
            r = SPACING_M / 2
            if up:
                out[k] = (x0 + r - r * math.cos(a), LANE_M + r * math.sin(a), a)
            else:
                out[k] = (x0 + r - r * math.cos(a), -r * math.sin(a), math.pi + a)
    out[:, 2] %= 2 * math.pi
    return out


def _gauss_markov(rng, n, dt, sigma, tau):
    phi = math.exp(-dt / tau)
    x = np.zeros((n, 2))
    x[0] = rng.normal(0, sigma, 2)
    for k in range(1, n):
        x[k] = phi * x[k - 1] + rng.normal(0, sigma * math.sqrt(1 - phi * phi), 2)
    return x


def _survey(
    rate_hz: float,
    seed: int = 3,
    compass_bias_deg: float = 4.0,
    lanes: int = N_LANES,
    reg_sigma: tuple[float, float] = (0.003, math.radians(0.03)),
):
    rng = np.random.default_rng(seed)
    duration = lanes * LANE_M / SPEED + (lanes - 1) * math.pi * (SPACING_M / 2) / SPEED
    nav = np.random.default_rng(100 + seed)  # the same navigation at every ping rate
    gnss_t = np.arange(0.0, duration, 0.2)
    lag = 0.15
    bias = _gauss_markov(nav, gnss_t.size, 0.2, 1.2, 40.0)
    gnss_xy = _path(gnss_t - lag)[:, :2] + bias + nav.normal(0, 0.6, (gnss_t.size, 2))
    head_t = np.arange(0.0, duration, 0.5)
    head = (
        _path(head_t)[:, 2]
        + math.radians(compass_bias_deg)
        + nav.normal(0, math.radians(1.0), head_t.size)
    ) % (2 * math.pi)
    times = np.arange(0.5, duration - 0.5, 1.0 / rate_hz)
    truth = _path(times)
    gyro_bias = math.radians(0.1)
    # Angle random walk of 0.02 degrees/sqrt(s), on the navigation's own clock.
    walk = np.cumsum(rng.normal(0, math.radians(0.02) * math.sqrt(1.0 / rate_hz), times.size))
    yaw = np.unwrap(truth[:, 2]) + gyro_bias * times + walk
    data = FusionData(gnss_t, gnss_xy, head_t, head, yaw, np.zeros(times.size, bool))
    constraints = []
    for k in range(1, times.size):
        rel = relative_pose(truth[k - 1], truth[k])
        constraints.append(
            RelativeConstraint(
                k - 1,
                k,
                rel.forward_m + rng.normal(0, reg_sigma[0]),
                rel.starboard_m + rng.normal(0, reg_sigma[0]),
                rel.yaw_rad + rng.normal(0, reg_sigma[1]),
                diagonal_sqrt_info((0.003, 0.003, math.radians(0.03))),
            )
        )
    initial = truth.copy()
    initial[:, :2] += bias[np.searchsorted(gnss_t, times).clip(0, gnss_t.size - 1)]
    initial[:, 2] += math.radians(compass_bias_deg)
    return times, truth, data, constraints, initial


def _shape_error(est: np.ndarray, truth: np.ndarray) -> float:
    """RMS position error (m) after the best rigid 2-D fit: the map's shape."""
    a, b = est[:, :2] - est[:, :2].mean(0), truth[:, :2] - truth[:, :2].mean(0)
    u, _, vt = np.linalg.svd(a.T @ b)
    r = (u @ vt).T
    return float(np.sqrt(np.mean(np.sum((a @ r.T - b) ** 2, axis=1))))


@pytest.fixture(scope="module")
def five_hz():
    times, truth, data, constraints, initial = _survey(5.0)
    solution, _ = Fusion(times, data).solve(initial, constraints)
    return times, truth, solution


def test_exact_registrations_are_not_bent_by_the_gnss_wander() -> None:
    """A chain of exact registrations weighted as real ones: the map keeps its true shape
    to millimetres although the GNSS wanders by a metre between lanes (a per-frame prior
    model bends the lanes to follow it)."""
    times, truth, data, constraints, initial = _survey(5.0, reg_sigma=(0.0, 0.0))
    solution, _ = Fusion(times, data).solve(initial, constraints)
    assert _shape_error(solution.poses, truth) < 0.01


def test_map_keeps_its_shape_on_a_wandering_gnss(five_hz) -> None:
    """Registrations with millimetre noise: what is left is the chain's own random walk."""
    times, truth, solution = five_hz
    assert _shape_error(solution.poses, truth) < 0.06
    # The lanes are not bent to the GNSS wander: 10 s relative motion stays exact.
    step = 50
    rel_err = [
        math.hypot(
            relative_pose(solution.poses[k], solution.poses[k + step]).forward_m
            - relative_pose(truth[k], truth[k + step]).forward_m,
            relative_pose(solution.poses[k], solution.poses[k + step]).starboard_m
            - relative_pose(truth[k], truth[k + step]).starboard_m,
        )
        for k in range(0, times.size - step, 10)
    ]
    assert float(np.sqrt(np.mean(np.square(rel_err)))) < 0.04


def test_constant_compass_bias_and_gyro_bias_are_recovered() -> None:
    """Eight lanes (9 minutes): the GNSS over the survey fixes the map's rotation, the
    compass's 4 degree misalignment is found to about a degree, the gyro bias too."""
    times, truth, data, constraints, initial = _survey(2.0, lanes=8)
    solution, _ = Fusion(times, data).solve(initial, constraints)
    assert math.degrees(solution.compass_coefficients[0]) == pytest.approx(4.0, abs=1.2)
    heading_error = (solution.poses[:, 2] - truth[:, 2] + math.pi) % (2 * math.pi) - math.pi
    assert abs(math.degrees(float(np.mean(heading_error)))) < 1.2
    assert math.degrees(solution.gyro_bias_rps) == pytest.approx(0.1, abs=0.01)


def test_gnss_lag_is_estimated(five_hz) -> None:
    _, _, solution = five_hz
    assert solution.time_offset_s == pytest.approx(0.15, abs=0.08)


def test_result_does_not_depend_on_the_ping_rate() -> None:
    placed = {}
    for rate in (2.0, 10.0):
        # Exact registrations, weighted as real ones: what is left is how the weights
        # depend on the rate (they must not).
        times, _truth, data, constraints, initial = _survey(rate, reg_sigma=(0.0, 0.0))
        solution, _ = Fusion(times, data, FusionParams()).solve(initial, constraints)
        placed[rate] = (times, solution.poses)
    t2, p2 = placed[2.0]
    t10, p10 = placed[10.0]
    common = np.intersect1d(np.round(t2, 6), np.round(t10, 6))
    a = p2[np.isin(np.round(t2, 6), common)]
    b = p10[np.isin(np.round(t10, 6), common)]
    assert a.shape[0] > 50
    # The same shape to millimetres; where the whole map sits rests on the GNSS average
    # (tens of centimetres of uncertainty) and may differ by a few centimetres.
    assert _shape_error(a, b) < 0.005
    assert float(np.max(np.hypot(*(a[:, :2] - b[:, :2]).T))) < 0.1


def test_a_gap_bridged_by_odometry_keeps_one_graph() -> None:
    """Frames 100-110 lost (rejected, 2 s): an odometry edge with its covariance spans
    the gap, and both sides stay one rigid map (not two segments floating on the GNSS)."""
    times, truth, data, constraints, initial = _survey(5.0)
    keep = np.ones(times.size, bool)
    keep[100:110] = False
    index = np.flatnonzero(keep)
    position = {int(k): i for i, k in enumerate(index)}
    kept = [
        RelativeConstraint(
            position[c.i], position[c.j], c.forward_m, c.starboard_m, c.yaw_rad, c.sqrt_info
        )
        for c in constraints
        if c.i in position and c.j in position
    ]
    rel = relative_pose(truth[99], truth[110])
    dt = times[110] - times[99]
    kept.append(
        RelativeConstraint(
            position[99],
            position[110],
            rel.forward_m + 0.05,
            rel.starboard_m - 0.04,
            rel.yaw_rad,
            diagonal_sqrt_info((0.02 + 0.05 * dt, 0.02 + 0.05 * dt, math.radians(0.5 + 0.5 * dt))),
            kind="odometry",
        )
    )
    sub = FusionData(
        data.gnss_times,
        data.gnss_xy,
        data.heading_times,
        data.headings,
        data.yaw_integral[keep],
        np.zeros(index.size, bool),
    )
    solution, _ = Fusion(times[keep], sub).solve(initial[keep], kept)
    across = relative_pose(solution.poses[position[99]], solution.poses[position[110]])
    error = math.hypot(across.forward_m - rel.forward_m, across.starboard_m - rel.starboard_m)
    # The bridge was 6 cm off; a graph in two pieces would put them a GNSS bias apart.
    assert error < 0.15  # the bridge's own sigma here is 0.13 m
    before, after = index < 100, index >= 110
    assert _shape_error(solution.poses[before], truth[keep][before]) < 0.06
    assert _shape_error(solution.poses[after], truth[keep][after]) < 0.06


def _with_closures(rate_hz: float, lanes: int, seed: int = 5):
    """The lawnmower with closures from each frame of a lane, once a second, to the
    nearest frame of the lane before (2 cm, 0.3 degrees), as the survey-end pass adds."""
    times, truth, data, chain, initial = _survey(rate_hz, seed=seed, lanes=lanes)
    rng = np.random.default_rng(seed)
    lane = np.floor(times / (LANE_M / SPEED + math.pi * (SPACING_M / 2) / SPEED)).astype(int)
    closures = []
    for k in range(0, times.size, int(rate_hz)):
        before = np.flatnonzero(lane == lane[k] - 1)
        if before.size == 0:
            continue
        i = int(before[np.argmin(np.hypot(*(truth[before, :2] - truth[k, :2]).T))])
        if np.hypot(*(truth[i, :2] - truth[k, :2])) > 1.2 * SPACING_M:
            continue
        rel = relative_pose(truth[i], truth[k])
        closures.append(
            RelativeConstraint(
                i,
                k,
                rel.forward_m + rng.normal(0, 0.02),
                rel.starboard_m + rng.normal(0, 0.02),
                rel.yaw_rad + rng.normal(0, math.radians(0.3)),
                diagonal_sqrt_info((0.02, 0.02, math.radians(0.3))),
                robust=True,
                kind="closure",
            )
        )
    return times, truth, data, chain + closures, initial, closures


def _dense_relative_covariances(fusion: Fusion, pairs, poses) -> np.ndarray:
    """The relative covariances from the dense inverse of the information matrix."""
    _, _, _, jac = fusion._last
    sigma = np.linalg.inv((jac.T @ jac).toarray() + 1e-9 * np.eye(jac.shape[1]))
    out = []
    for i, j in pairs:
        idx = np.r_[3 * i : 3 * i + 3, 3 * j : 3 * j + 3]
        dx, dy = poses[j, :2] - poses[i, :2]
        s, c = math.sin(poses[i, 2]), math.cos(poses[i, 2])
        fwd, stb = s * dx + c * dy, c * dx - s * dy
        jr = np.array([[-s, -c, stb, s, c, 0], [-c, s, -fwd, c, -s, 0], [0, 0, -1, 0, 0, 1]], float)
        out.append(jr @ sigma[np.ix_(idx, idx)] @ jr.T)
    return np.array(out)


@pytest.mark.parametrize("by", ["reach", "columns"])
def test_relative_covariances_are_the_dense_inverse_in_bounded_batches(monkeypatch, by) -> None:
    """The closures' predicted covariances come from the sparse factor a few poses at a
    time (here one: the poses' cache, or the columns' batch bound, forced down) and equal
    the dense inverse's, over each pose's reach in the symmetric factor
    (``mapping.marginals``) or, were the factor not symmetric, by whole columns."""
    import mapping.fusion as fusion_module
    import mapping.marginals as marginals

    times, _, data, constraints, initial, closures = _with_closures(2.0, 3)
    fusion = Fusion(times, data)
    solution, _ = fusion.solve(initial, constraints)
    pairs = [(c.i, c.j) for c in closures]
    assert len(pairs) >= 30
    monkeypatch.setattr(marginals, "CACHE_BYTES", 1)
    monkeypatch.setattr(fusion_module, "_RHS_BYTES", 1)
    if by == "columns":
        monkeypatch.setattr(SpdFactor, "symmetric", property(lambda self: False))
    got = fusion.relative_covariances(pairs)
    want = _dense_relative_covariances(fusion, pairs, solution.poses)
    np.testing.assert_allclose(got, want, rtol=1e-7, atol=1e-12)


def test_windowed_relative_covariances_err_wide_and_close() -> None:
    """Past the exact solve's budget (forced here), each batch of pairs gets the marginal
    of the sub-problem around it: never tighter than the exact covariance (it leaves
    factors out) and close to it (within 25 % in every direction on this survey, with
    windows much shorter than the survey)."""
    times, _, data, constraints, initial, closures = _with_closures(2.0, 8)
    fusion = Fusion(times, data)
    fusion.solve(initial, constraints)
    pairs = [(c.i, c.j) for c in closures]
    exact = fusion.relative_covariances(pairs)
    windowed = fusion.relative_covariances(pairs, max_exact_work=0.0, margin_s=30.0, window_s=90.0)
    assert times[-1] - times[0] > 5 * 90.0
    ratios = np.array(
        [
            np.linalg.eigvals(np.linalg.solve(e, w)).real
            for e, w in zip(exact, windowed, strict=True)
        ]
    )
    assert ratios.min() > 1.0 - 1e-6
    assert ratios.max() < 1.25
    # The windows left something out somewhere: the windowed path was taken.
    assert ratios.max() > 1.0 + 1e-6


def test_the_normal_matrix_of_a_lawnmower_factors_with_little_fill() -> None:
    """Ordered for the symmetric structure, the factor of a survey's information matrix
    stays a few times its size (SuperLU's default ordering filled this one 20 times over,
    and a two-hour survey's to 7 GB a step)."""
    from mapping.sparse import factor_spd

    times, _, data, constraints, initial, _ = _with_closures(5.0, 6)
    fusion = Fusion(times, data)
    fusion.solve(initial, constraints)
    _, _, _, jac = fusion._last
    normal = (jac.T @ jac).tocsc()
    lu = factor_spd(normal)
    fill = (lu.L.nnz + lu.U.nnz) / normal.nnz
    assert fill < 8.0, fill
    rhs = np.arange(normal.shape[0], dtype=float)
    x = lu.solve(rhs)
    assert np.linalg.norm(normal @ x + 1e-9 * x - rhs) < 1e-8 * np.linalg.norm(rhs)


def test_loop_candidates_are_found_the_same_a_chunk_at_a_time(monkeypatch) -> None:
    """Candidate pairs are found a bounded chunk of frames at a time (a two-hour survey
    has tens of millions of pairs in reach): any chunk size gives the same pairs, one per
    block of stride on each side, each the best of its block."""
    import mapping.loops as loops
    from mapping.frames import SonarMount

    times, truth, *_ = _survey(5.0, lanes=4)
    mapped = np.ones(times.size, bool)
    lit, half = (1.0, 5.0), math.radians(65.0)
    params = loops.LoopParams()
    whole = loops.find_candidates(times, truth, mapped, SonarMount(), lit, half, params)
    assert len(whole) > 50
    for chunk in (7, 64, 333):
        monkeypatch.setattr(loops, "_CHUNK_FRAMES", chunk)
        assert loops.find_candidates(times, truth, mapped, SonarMount(), lit, half, params) == whole
    stride = round(params.stride_s * 5.0)
    blocks = {(i // stride, j // stride) for i, j in whole}
    assert len(blocks) == len(whole)
    assert all(times[j] - times[i] >= params.min_gap_s for i, j in whole)
