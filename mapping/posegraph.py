"""Least-squares pose optimisation (Zhang et al., Sec. III.F, Eq. 6-7), as SE(2) nonlinear
least squares with sparse Gauss-Newton.

Poses are (x east, y north, heading) in the local frame: metres and radians clockwise
from grid north. Two kinds of residuals:

- local (an edge i -> j, from registration): the pose of j in the frame of i,
  r_pos = R(psi_i)^T (p_j - p_i) - d_ij (forward, starboard metres), and
  r_ang = wrap(psi_j - psi_i - dpsi_ij), weighted by lambda and lambda * alpha;
- global (a prior on i, from the EKF): r_pos = p_i - g_i, r_ang = wrap(psi_i - g_psi_i),
  weighted by 1 and alpha.

The paper's alpha = 1/225 balances squared angle residuals against squared metres; we
read the angles in degrees (1/225 puts 15 degrees on a par with 1 m, the ratio of a
compass's to a GPS's error), a choice ``angle_unit_deg`` records. The normal equations
are banded for a chain (plus a few loop-closure blocks), so each iteration costs time
linear in the number of poses.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
import numpy.typing as npt
import scipy.sparse as sp

from mapping.se2 import between, wrap_pi
from mapping.sparse import solve_spd

Array = npt.NDArray[np.float64]
IntArray = npt.NDArray[np.int64]


@dataclass(frozen=True, slots=True)
class Edge:
    """A relative-pose measurement: pose j in the frame of pose i.

    forward_m, starboard_m: translation (metres, frame of i); yaw_rad: psi_j - psi_i.
    weight: multiplies lambda for this edge (1 for the paper's consecutive pairs).
    """

    i: int
    j: int
    forward_m: float
    starboard_m: float
    yaw_rad: float
    weight: float = 1.0


@dataclass(frozen=True, slots=True)
class OptimiserParams:
    lam: float = 1e4
    """lambda: weight of the local (registration) residuals against the global priors."""
    alpha: float = 1.0 / 225.0
    """Weight of squared angle residuals against squared metres."""
    angle_unit_deg: bool = True
    """Angles enter the alpha-weighted terms in degrees (True) or radians."""
    max_iterations: int = 20
    tolerance: float = 1e-7
    """Stop when the largest update is below this (metres / radians)."""


@dataclass(frozen=True)
class Solution:
    poses: Array
    iterations: int
    cost: float
    initial_cost: float


def _residuals_and_jacobian(
    poses: Array,
    priors: Array,
    prior_weights: Array,
    edges: Sequence[Edge],
    params: OptimiserParams,
) -> tuple[Array, sp.csr_matrix]:
    n = poses.shape[0]
    ang = (180.0 / math.pi) if params.angle_unit_deg else 1.0
    sqrt_alpha = math.sqrt(params.alpha) * ang
    m = len(edges)
    # Local terms, vectorised over edges.
    ei = np.array([e.i for e in edges], np.int64)
    ej = np.array([e.j for e in edges], np.int64)
    meas = np.array([(e.forward_m, e.starboard_m, e.yaw_rad) for e in edges], float).reshape(m, 3)
    w = np.sqrt(params.lam * np.array([e.weight for e in edges], float))
    rel = between(poses, ei, ej)
    s, c, forward, starboard = rel.sin, rel.cos, rel.forward, rel.starboard
    r_local = np.column_stack(
        [
            w * (forward - meas[:, 0]),
            w * (starboard - meas[:, 1]),
            w * sqrt_alpha * wrap_pi(rel.turn - meas[:, 2]),
        ]
    )
    rows: list[IntArray] = []
    cols: list[IntArray] = []
    vals: list[Array] = []
    base = np.arange(m, dtype=np.int64) * 3

    def add(r: IntArray, col: IntArray, v: Array) -> None:
        rows.append(r)
        cols.append(col)
        vals.append(v)

    # d forward / d(x_i, y_i, psi_i, x_j, y_j)
    add(base, 3 * ei, -w * s)
    add(base, 3 * ei + 1, -w * c)
    add(base, 3 * ei + 2, w * starboard)
    add(base, 3 * ej, w * s)
    add(base, 3 * ej + 1, w * c)
    add(base + 1, 3 * ei, -w * c)
    add(base + 1, 3 * ei + 1, w * s)
    add(base + 1, 3 * ei + 2, -w * forward)
    add(base + 1, 3 * ej, w * c)
    add(base + 1, 3 * ej + 1, -w * s)
    add(base + 2, 3 * ei + 2, -w * sqrt_alpha)
    add(base + 2, 3 * ej + 2, w * sqrt_alpha)

    # Global priors.
    idx = np.arange(n, dtype=np.int64)
    wp = np.sqrt(prior_weights[:, 0])
    wa = np.sqrt(prior_weights[:, 1]) * sqrt_alpha
    r_prior = np.column_stack(
        [
            wp * (poses[:, 0] - priors[:, 0]),
            wp * (poses[:, 1] - priors[:, 1]),
            wa * wrap_pi(poses[:, 2] - priors[:, 2]),
        ]
    )
    pbase = 3 * m + idx * 3
    add(pbase, 3 * idx, wp)
    add(pbase + 1, 3 * idx + 1, wp)
    add(pbase + 2, 3 * idx + 2, wa)

    residual = np.concatenate([r_local.ravel(), r_prior.ravel()])
    jac = sp.csr_matrix(
        (np.concatenate(vals), (np.concatenate(rows), np.concatenate(cols))),
        shape=(3 * m + 3 * n, 3 * n),
    )
    return residual, jac


def optimise(
    initial: Array,
    priors: Array,
    edges: Sequence[Edge],
    params: OptimiserParams | None = None,
    prior_weights: Array | None = None,
    fixed: npt.NDArray[np.bool_] | None = None,
) -> Solution:
    """Minimise the paper's objective over all poses.

    initial, priors: (n, 3) poses; prior_weights: (n, 2) multipliers of the position and
    angle prior terms (default ones; 0 drops a prior); fixed: (n,) poses held where they
    are (the streaming engine holds the poses before its window this way).
    """
    params = params or OptimiserParams()
    poses = np.array(initial, float, copy=True)
    n = poses.shape[0]
    weights = np.ones((n, 2)) if prior_weights is None else np.asarray(prior_weights, float)
    free = np.ones(3 * n, bool)
    if fixed is not None:
        free[np.repeat(np.asarray(fixed, bool), 3)] = False
    residual, jac = _residuals_and_jacobian(poses, priors, weights, edges, params)
    initial_cost = float(residual @ residual)
    cost = initial_cost
    iterations = 0
    for iterations in range(1, params.max_iterations + 1):  # noqa: B007
        j_free = jac[:, free]
        normal = (j_free.T @ j_free).tocsc()
        gradient = j_free.T @ residual
        # A whisker of damping (in solve_spd) keeps a pose with no prior and no edge from
        # making the system singular; it is far below any real weight.
        step = solve_spd(normal, -gradient)
        poses_flat = poses.ravel()
        poses_flat[free] += step
        poses = poses_flat.reshape(n, 3)
        poses[:, 2] %= 2 * math.pi
        residual, jac = _residuals_and_jacobian(poses, priors, weights, edges, params)
        cost = float(residual @ residual)
        if float(np.max(np.abs(step), initial=0.0)) < params.tolerance:
            break
    return Solution(poses, iterations, cost, initial_cost)
