"""The pose optimiser solves the paper's objective exactly where the answer is known."""

from __future__ import annotations

import math

import numpy as np

from mapping.posegraph import Edge, OptimiserParams, optimise
from mapping.se2 import compose, relative_pose


def chain(rng: np.random.Generator, n: int) -> np.ndarray:
    poses = np.zeros((n, 3))
    poses[0] = (10.0, -5.0, 0.4)
    for k in range(1, n):
        heading = (poses[k - 1, 2] + rng.normal(0, 0.02)) % (2 * math.pi)
        poses[k] = (
            poses[k - 1, 0] + 0.1 * math.sin(heading),
            poses[k - 1, 1] + 0.1 * math.cos(heading),
            heading,
        )
    return poses


def exact_edges(poses: np.ndarray) -> list[Edge]:
    edges = []
    for k in range(len(poses) - 1):
        r = relative_pose(poses[k], poses[k + 1])
        edges.append(Edge(k, k + 1, r.forward_m, r.starboard_m, r.yaw_rad))
    return edges


def test_consistent_edges_and_priors_are_reproduced_exactly() -> None:
    truth = chain(np.random.default_rng(1), 300)
    start = truth + np.array([0.5, -0.3, 0.05])  # a wrong start, right priors and edges
    solution = optimise(start, truth, exact_edges(truth))
    np.testing.assert_allclose(solution.poses[:, :2], truth[:, :2], atol=1e-6)
    np.testing.assert_allclose(
        np.angle(np.exp(1j * (solution.poses[:, 2] - truth[:, 2]))), 0.0, atol=1e-8
    )


def test_two_poses_match_the_closed_form_weighted_least_squares() -> None:
    # Pose 0 and 1 on the x axis facing east (heading pi/2: forward = +x). The edge says
    # 1 is 1 m ahead of 0; the priors say 0 at x=0 and 1 at x=1.2. Headings agree, so the
    # problem is linear in x: minimise lam (x1 - x0 - 1)^2 + x0^2 + (x1 - 1.2)^2.
    lam = 4.0
    priors = np.array([[0.0, 0.0, math.pi / 2], [1.2, 0.0, math.pi / 2]])
    edges = [Edge(0, 1, 1.0, 0.0, 0.0)]
    solution = optimise(priors, priors, edges, OptimiserParams(lam=lam))
    a = np.array([[1 + lam, -lam], [-lam, 1 + lam]])
    b = np.array([-lam * 1.0, lam * 1.0 + 1.2])
    x0, x1 = np.linalg.solve(a, b)
    np.testing.assert_allclose(solution.poses[:, 0], [x0, x1], atol=1e-9)
    np.testing.assert_allclose(solution.poses[:, 1], 0.0, atol=1e-9)


def test_noisy_priors_are_corrected_by_precise_edges() -> None:
    rng = np.random.default_rng(2)
    truth = chain(rng, 1500)
    edges = []
    for e in exact_edges(truth):
        edges.append(
            Edge(
                e.i,
                e.j,
                e.forward_m + rng.normal(0, 0.003),
                e.starboard_m + rng.normal(0, 0.003),
                e.yaw_rad + rng.normal(0, 0.001),
            )
        )
    priors = truth + np.column_stack(
        [
            rng.normal(0, 1, len(truth)),
            rng.normal(0, 1, len(truth)),
            rng.normal(0, 0.03, len(truth)),
        ]
    )
    solution = optimise(priors, priors, edges)
    prior_error = np.linalg.norm(priors[:, :2] - truth[:, :2], axis=1).mean()
    error = np.linalg.norm(solution.poses[:, :2] - truth[:, :2], axis=1).mean()
    assert error < prior_error / 5
    step_error = np.linalg.norm(
        np.diff(solution.poses[:, :2], axis=0) - np.diff(truth[:, :2], axis=0), axis=1
    ).mean()
    assert step_error < 0.01


def test_fixed_poses_do_not_move() -> None:
    truth = chain(np.random.default_rng(3), 50)
    priors = truth + 0.3
    fixed = np.zeros(50, bool)
    fixed[:10] = True
    start = priors.copy()
    start[:10] = truth[:10]
    weights = np.zeros((50, 2))  # no priors: only the held poses and the edges place them
    solution = optimise(start, priors, exact_edges(truth), prior_weights=weights, fixed=fixed)
    np.testing.assert_array_equal(solution.poses[:10], truth[:10])
    # With the first poses held at the truth, exact edges carry the truth on.
    np.testing.assert_allclose(solution.poses[:, :2], truth[:, :2], atol=1e-6)


def test_compose_inverts_relative_pose() -> None:
    a = np.array([3.0, 4.0, 5.5])
    b = np.array([3.7, 3.1, 0.2])
    np.testing.assert_allclose(compose(a, relative_pose(a, b)), b, atol=1e-12)


def test_sonar_mount_lever_arm_and_yaw() -> None:
    from mapping.frames import SonarMount
    from mapping.se2 import RelativePose

    mount = SonarMount(forward_m=-0.45, starboard_m=0.2, yaw_rad=math.radians(30))
    vehicle = np.array([100.0, 200.0, math.radians(90)])  # facing east
    sonar = mount.sonar_pose(vehicle)
    # 0.45 m behind (west) and 0.2 m to starboard (south) of the antenna, boresight 120 deg.
    np.testing.assert_allclose(sonar[:2], [100.0 - 0.45, 200.0 - 0.2], atol=1e-12)
    assert math.isclose(sonar[2], math.radians(120))
    # A vehicle motion seen by the sonar and converted back is the same motion.
    motion = RelativePose(0.3, -0.05, math.radians(2))
    back = mount.vehicle_relative(mount.sonar_relative(motion))
    np.testing.assert_allclose(
        [back.forward_m, back.starboard_m, back.yaw_rad],
        [motion.forward_m, motion.starboard_m, motion.yaw_rad],
        atol=1e-12,
    )
    # And it agrees with the sonar poses before and after the motion.
    after = compose(vehicle, motion)
    seen = relative_pose(mount.sonar_pose(vehicle), mount.sonar_pose(after))
    expected = mount.sonar_relative(motion)
    np.testing.assert_allclose(
        [seen.forward_m, seen.starboard_m, seen.yaw_rad],
        [expected.forward_m, expected.starboard_m, expected.yaw_rad],
        atol=1e-12,
    )
