"""The symmetric factorisations (``mapping.sparse``): the ordering kept by structure."""

from __future__ import annotations

import numpy as np
import scipy.sparse as sp

import mapping.sparse as sparse
from mapping.sparse import factor_spd, solve_spd


def _chain_normal(n: int, seed: int, ties: int = 10) -> sp.csc_matrix:
    """A chain of unknowns with a few ties across it and a dense last column."""
    rng = np.random.default_rng(seed)
    rows, cols, vals = [], [], []
    r = 0
    for k in range(n - 2):
        rows += [r, r]
        cols += [k, k + 1]
        vals += [1.0, -1.0 + 0.1 * rng.normal()]
        r += 1
    for _ in range(ties):
        i, j = rng.choice(n - 1, 2, replace=False)
        rows += [r, r, r]
        cols += [int(i), int(j), n - 1]
        vals += [1.0, -1.0, 0.2]
        r += 1
    for k in range(n):
        rows.append(r)
        cols.append(k)
        vals.append(0.3 + rng.random())
        r += 1
    jac = sp.csr_matrix((vals, (rows, cols)), shape=(r, n))
    return sp.csc_matrix(jac.T @ jac)


def test_a_structure_is_ordered_once_and_its_factor_does_not_depend_on_history(
    monkeypatch,
) -> None:
    orders = []
    real = sparse.spla.splu

    def counting(a, permc_spec=None, **kw):
        orders.append(permc_spec)
        return real(a, permc_spec=permc_spec, **kw)

    monkeypatch.setattr(sparse.spla, "splu", counting)
    monkeypatch.setattr(sparse, "_orderings", type(sparse._orderings)())
    normal = _chain_normal(400, 1)
    rhs = np.random.default_rng(2).normal(size=(400, 3))
    first = solve_spd(normal, rhs)
    # The same structure, other values (a Gauss-Newton step's next weights): not ordered again.
    again = solve_spd(normal * 1.5, rhs)
    assert orders.count("MMD_AT_PLUS_A") == 1
    np.testing.assert_allclose(again, first / 1.5, rtol=1e-6)  # the damping is not scaled
    # Another structure in between, then the first again: the same bits as when fresh.
    solve_spd(_chain_normal(300, 3), rhs[:300])
    assert np.array_equal(solve_spd(normal, rhs), first)
    monkeypatch.setattr(sparse, "_orderings", type(sparse._orderings)())
    assert np.array_equal(solve_spd(normal, rhs), first)
    want = np.linalg.solve(normal.toarray() + sparse.DAMPING * np.eye(400), rhs)
    np.testing.assert_allclose(first, want, rtol=1e-8, atol=1e-10)


def test_the_orderings_kept_are_bounded(monkeypatch) -> None:
    monkeypatch.setattr(sparse, "_orderings", type(sparse._orderings)())
    for seed in range(sparse.ORDERINGS + 3):
        factor = factor_spd(_chain_normal(100, seed))
        assert factor.symmetric
    assert len(sparse._orderings) == sparse.ORDERINGS
