"""Covariances from a factor's reach (``mapping.marginals``) against dense algebra."""

from __future__ import annotations

import numpy as np
import pytest
import scipy.sparse as sp

import mapping.marginals as marginals
from mapping.marginals import lower_solve, pose_covariance_blocks
from mapping.sparse import DAMPING, factor_spd


def _unit_lower(n: int, density: float, rng: np.random.Generator) -> sp.csc_matrix:
    strict = sp.random(n, n, density=density, random_state=rng, format="csc")
    return sp.csc_matrix(sp.tril(strict, -1) + sp.identity(n))


@pytest.mark.parametrize("nonzeros", [1, 3])
def test_the_reach_solve_is_the_triangular_solve(nonzeros: int) -> None:
    rng = np.random.default_rng(nonzeros)
    n = 300
    lower = _unit_lower(n, 0.01, rng)
    x = np.zeros(n)
    mark = np.zeros(n, np.int64)
    work = [np.zeros(n, np.int64) for _ in range(3)]
    for stamp in range(1, 40):
        index = rng.choice(n, nonzeros, replace=False).astype(np.int64)
        value = rng.normal(size=nonzeros)
        count = lower_solve(
            lower.indptr.astype(np.int64), lower.indices.astype(np.int64), lower.data,
            index, value, x, mark, stamp, *work,
        )  # fmt: skip
        reach = work[2][:count]
        b = np.zeros(n)
        b[index] = value
        want = np.linalg.solve(lower.toarray(), b)
        got = np.zeros(n)
        got[reach] = x[reach]
        np.testing.assert_allclose(got, want, atol=1e-10)
        # Only the reach is touched (the rest of ``want`` is exactly zero), each once.
        assert np.count_nonzero(want) <= count == np.unique(reach).size
        x[reach] = 0.0
        assert not x.any()


def test_pose_blocks_are_the_dense_inverse_whatever_the_order_and_cache(monkeypatch) -> None:
    """A chain of poses with a few ties across it and a dense column (the structure of
    the survey's normal matrix), the poses' unknowns as combinations of the factored ones
    (as two-stage's rigid submaps make them), pairs out of order, the cache at its least
    (the pair's own two poses)."""
    rng = np.random.default_rng(7)
    poses = 60
    n = 3 * poses + 4
    rows = []
    for k in range(poses - 1):
        rows.append(
            [(3 * k + a, 1.0) for a in range(3)] + [(3 * k + 3 + a, -1.0) for a in range(3)]
        )
    for _ in range(20):
        i, j = sorted(int(v) for v in rng.choice(poses, 2, replace=False))
        rows.append([(3 * i, 1.0), (3 * j + 1, -0.5), (n - 1 - int(rng.integers(4)), 0.3)])
    for k in range(poses):
        rows.append([(3 * k + a, 0.1) for a in range(3)] + [(n - 1, 0.2)])
    jac = sp.lil_matrix((len(rows), n))
    for r, entries in enumerate(rows):
        for c, v in entries:
            jac[r, c] += v * (1.0 + 0.1 * rng.normal())
    normal = sp.csc_matrix(jac.T @ jac) + sp.identity(n, format="csc")
    lu = factor_spd(normal)
    assert lu.symmetric
    t = sp.csr_matrix(
        sp.random(3 * poses, n, density=0.02, random_state=rng) + sp.eye(3 * poses, n)
    )
    pairs = np.array([(5, 40), (0, 1), (40, 5), (12, 59), (5, 41), (33, 2)], np.int64)
    monkeypatch.setattr(marginals, "CACHE_BYTES", 1)
    got = pose_covariance_blocks(lu, t, pairs)
    sigma = t @ np.linalg.inv(normal.toarray() + DAMPING * np.eye(n)) @ t.T
    for m, (i, j) in enumerate(pairs):
        idx = np.r_[3 * i : 3 * i + 3, 3 * j : 3 * j + 3]
        np.testing.assert_allclose(got[m], sigma[np.ix_(idx, idx)], rtol=1e-9, atol=1e-12)
