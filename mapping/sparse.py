"""Sparse symmetric positive definite solves for the pose problems.

The normal matrices of ``mapping.fusion`` and ``mapping.posegraph`` are symmetric and
positive definite (a whisker of damping keeps a pose without factors from making them
singular), with the structure of the survey: a chain in time, tied across lanes by loop
closures and at every knot by the GNSS bias, plus a few dense columns (the compass
coefficients, the GNSS time offset). SuperLU's default for such a matrix (a COLAMD
ordering, which orders for A^T A, with partial pivoting) fills it badly: on a synthetic
two-hour hectare survey (34 lanes at 10 Hz, 232,637 unknowns, 2.8 million non-zeros) one
Gauss-Newton step took 454 s and 7.0 GB. Ordered by minimum degree on the symmetric
structure and factored without pivoting (SuperLU's symmetric mode), the same step takes
7 s and 0.6 GB (factor fill 5.2x).

Nine tenths of that step were the ordering itself: on the hectare's first 24,000 frames
(74,652 unknowns) SuperLU took 3.3-4.2 s to order and factor, 0.4 s to factor the same
matrix already in that order. A survey's solves factor matrices of one structure over and
over (each Gauss-Newton step, each re-weighing of the variance components, the closures'
covariances), so the ordering is kept by structure (``ORDERINGS`` of them) and each
factorisation is of the matrix permuted into it. A structure met for the first time is
ordered (SuperLU's minimum degree, its own postorder included) and then factored like the
others, so the factor of a matrix never depends on which structures came before it.
"""

from __future__ import annotations

import hashlib
import threading
from collections import OrderedDict
from dataclasses import dataclass

import numpy as np
import numpy.typing as npt
import scipy.sparse as sp
import scipy.sparse.linalg as spla

Array = npt.NDArray[np.float64]
IntArray = npt.NDArray[np.int64]

DAMPING = 1e-9
"""Added to the diagonal: far below any real weight."""
ORDERINGS = 8
"""Structures whose ordering is kept (the newest): a survey's solve meets a few at a time
(with and without its closures, a windowed covariance's sub-problems)."""

_orderings: OrderedDict[bytes, IntArray] = OrderedDict()
_orderings_lock = threading.Lock()


@dataclass(frozen=True)
class SpdFactor:
    """The factor of a symmetric positive definite matrix A, ordered: with Q the
    permutation ``order`` (A[order][:, order] is what was factored) and SuperLU's own
    (identity but for its postorder), P A P^T = L U, U = D L^T."""

    lu: spla.SuperLU
    order: IntArray

    @property
    def shape(self) -> tuple[int, int]:
        return self.lu.shape

    @property
    def L(self) -> sp.csc_matrix:
        return self.lu.L

    @property
    def U(self) -> sp.csc_matrix:
        return self.lu.U

    @property
    def symmetric(self) -> bool:
        """One permutation for rows and columns (then U = D L^T)."""
        return bool(np.array_equal(self.lu.perm_r, self.lu.perm_c))

    @property
    def perm(self) -> IntArray:
        """For each of A's unknowns, its row in L (``symmetric`` factors)."""
        inverse = np.empty_like(self.order)
        inverse[self.order] = np.arange(self.order.size)
        return np.asarray(self.lu.perm_r, np.int64)[inverse]

    def solve(self, rhs: Array) -> Array:
        """A^-1 rhs (one right-hand side or a column of them)."""
        rhs = np.asarray(rhs, float)
        out = np.empty_like(rhs)
        out[self.order] = self.lu.solve(np.ascontiguousarray(rhs[self.order]))
        return out


def _structure(a: sp.csc_matrix) -> bytes:
    digest = hashlib.blake2b(digest_size=20)
    digest.update(np.asarray(a.shape, np.int64).tobytes())
    digest.update(np.asarray(a.indptr, np.int64).tobytes())
    digest.update(np.asarray(a.indices, np.int64).tobytes())
    return digest.digest()


def _ordering(a: sp.csc_matrix) -> IntArray:
    """The ordering of ``a``'s structure: minimum degree on A + A^T (SuperLU's, with its
    postorder), kept for the next matrix of that structure."""
    key = _structure(a)
    with _orderings_lock:
        order = _orderings.get(key)
        if order is not None:
            _orderings.move_to_end(key)
            return order
    lu = spla.splu(
        a, permc_spec="MMD_AT_PLUS_A", diag_pivot_thresh=0.0, options={"SymmetricMode": True}
    )
    order = np.argsort(np.asarray(lu.perm_c, np.int64)).astype(np.int64)
    with _orderings_lock:
        _orderings[key] = order
        while len(_orderings) > ORDERINGS:
            _orderings.popitem(last=False)
    return order


def factor_spd(normal: sp.spmatrix) -> SpdFactor:
    """The factorisation of a symmetric positive definite ``normal`` (damped here)."""
    a = sp.csc_matrix(normal) + sp.identity(normal.shape[0], format="csc") * DAMPING
    a = sp.csc_matrix(a)
    a.sum_duplicates()
    a.sort_indices()
    order = _ordering(a)
    permuted = sp.csc_matrix(a[order][:, order])
    lu = spla.splu(
        permuted, permc_spec="NATURAL", diag_pivot_thresh=0.0, options={"SymmetricMode": True}
    )
    return SpdFactor(lu, order)


def solve_spd(normal: sp.spmatrix, rhs: Array) -> Array:
    """``normal^-1 rhs`` for a symmetric positive definite ``normal`` (damped here)."""
    return factor_spd(normal).solve(rhs)
