"""Covariances of a few poses from a sparse factor, without solving for whole columns.

The loop closures' gate (``mapping.closures.select_closures``) needs, for every candidate
pair of frames, the 6 x 6 covariance of the two poses: a handful of entries of the
inverse of a normal matrix with hundreds of thousands of unknowns. Solving the factor
for each pose's unknowns (three columns of the inverse, each a pass over the whole
factor) made this the largest part of a long survey's optimisation: a pass over the
factor per column, one column per pose coordinate of every candidate.

With the normal matrix factored symmetrically (``mapping.sparse.factor_spd``: P A P^T =
L D L^T, SuperLU's U being D L^T), an entry of the inverse is

    Sigma_ab = y_a^T D^-1 y_b,   y_a = L^-1 P e_a,

and y_a is sparse: it is non-zero only on the unknowns that eliminating ``a`` reaches
(its ancestors in the factor's elimination tree). ``lower_solve`` computes it over that
reach alone (Gilbert and Peierls' sparse triangular solve: a depth-first search of the
factor's graph from the right-hand side's non-zeros, then the updates in topological
order), so a pose costs the length of its reach, not of the factor. The entries are the
same as the whole columns' to rounding (the tests compare them).
"""

from __future__ import annotations

from collections import OrderedDict

import numpy as np
import numpy.typing as npt
import scipy.sparse as sp

from mapping.kernels import compiled
from mapping.sparse import SpdFactor

Array = npt.NDArray[np.float64]
IntArray = npt.NDArray[np.int64]

CACHE_BYTES = 64 * 2**20
"""What the poses' solved vectors kept while the pairs are taken in order may hold
(candidate pairs of neighbouring frames share their poses): the newest poses, bounded
memory whatever the survey. A pose's three vectors on the hectare's first 24,000 frames
(74,652 unknowns): 15,000 entries at the median, 49,000 at most (16 bytes each)."""


@compiled
def lower_solve(
    indptr: IntArray,
    indices: IntArray,
    data: Array,
    rhs_index: IntArray,
    rhs_value: Array,
    x: Array,
    mark: IntArray,
    stamp: int,
    stack: IntArray,
    resume: IntArray,
    reach: IntArray,
) -> int:
    """x = L^-1 b for the unit lower triangular ``L`` (CSC: ``indptr``, ``indices``,
    ``data``; entries on or above the diagonal are ignored) and the sparse ``b``
    (``rhs_index``, ``rhs_value``). ``x`` must be zero on entry; on return it holds the
    solution on ``reach[:count]`` (the count returned) and zero elsewhere: the caller
    reads it there and sets it back to zero. ``mark`` (ints, never equal to ``stamp``
    where not visited in this call), ``stack``, ``resume`` and ``reach`` are work arrays
    of L's size."""
    count = 0
    for r in range(rhs_index.size):
        start = rhs_index[r]
        if mark[start] == stamp:
            continue
        # Depth-first from ``start`` along L's columns; each node is listed once its
        # descendants are (postorder): the reverse is a topological order.
        head = 0
        stack[0] = start
        mark[start] = stamp
        resume[0] = indptr[start]
        while head >= 0:
            j = stack[head]
            p = resume[head]
            end = indptr[j + 1]
            pushed = False
            while p < end:
                i = indices[p]
                p += 1
                if i <= j or mark[i] == stamp:
                    continue
                resume[head] = p
                head += 1
                stack[head] = i
                mark[i] = stamp
                resume[head] = indptr[i]
                pushed = True
                break
            if not pushed:
                head -= 1
                reach[count] = j
                count += 1
    for r in range(rhs_index.size):
        x[rhs_index[r]] += rhs_value[r]
    for k in range(count - 1, -1, -1):
        j = reach[k]
        xj = x[j]
        if xj == 0.0:
            continue
        for p in range(indptr[j], indptr[j + 1]):
            i = indices[p]
            if i > j:
                x[i] -= data[p] * xj
    return count


@compiled
def block_of(
    index: IntArray, value: Array, starts: IntArray, inverse_d: Array, work: Array
) -> Array:
    """The (m, m) matrix of y_a^T D^-1 y_b for the m sparse vectors y (vector a:
    ``index`` and ``value`` from ``starts[a]`` to ``starts[a + 1]``). ``work``: zeros of
    the factor's size (zeros again on return)."""
    m = starts.size - 1
    out = np.zeros((m, m))
    for b in range(m):
        for k in range(starts[b], starts[b + 1]):
            work[index[k]] = value[k] * inverse_d[index[k]]
        for a in range(b + 1):
            total = 0.0
            for k in range(starts[a], starts[a + 1]):
                total += value[k] * work[index[k]]
            out[a, b] = total
            out[b, a] = total
        for k in range(starts[b], starts[b + 1]):
            work[index[k]] = 0.0
    return out


class _Solver:
    """y = L^-1 P t_row^T for the rows of ``t`` (CSR: the unknowns asked about as linear
    in the factored problem's), with the work arrays for it."""

    def __init__(self, lu: SpdFactor, t: sp.csr_matrix) -> None:
        lower = sp.csc_matrix(lu.L)
        self.indptr = lower.indptr.astype(np.int64)
        self.indices = lower.indices.astype(np.int64)
        self.data = np.asarray(lower.data, np.float64)
        self.perm = lu.perm
        self.inverse_d = 1.0 / np.asarray(lu.U.diagonal(), np.float64)
        size = lower.shape[0]
        self.x = np.zeros(size)
        self.mark = np.zeros(size, np.int64)
        self.stamp = 0
        self.stack = np.zeros(size, np.int64)
        self.resume = np.zeros(size, np.int64)
        self.reach = np.zeros(size, np.int64)
        self.work = np.zeros(size)
        self.t = t

    def vectors(self, rows: IntArray) -> tuple[IntArray, Array, IntArray]:
        """The sparse y of each of ``rows`` of t, concatenated (index, value, starts)."""
        index: list[IntArray] = []
        value: list[Array] = []
        starts = np.zeros(rows.size + 1, np.int64)
        for k, row in enumerate(rows):
            a, b = self.t.indptr[row], self.t.indptr[row + 1]
            self.stamp += 1
            count = lower_solve(
                self.indptr, self.indices, self.data,
                self.perm[self.t.indices[a:b]], np.asarray(self.t.data[a:b], np.float64),
                self.x, self.mark, self.stamp, self.stack, self.resume, self.reach,
            )  # fmt: skip
            reach = self.reach[:count].copy()
            index.append(reach)
            value.append(self.x[reach].copy())
            self.x[reach] = 0.0
            starts[k + 1] = starts[k] + count
        return np.concatenate(index), np.concatenate(value), starts


def pose_covariance_blocks(lu: SpdFactor, t: sp.csr_matrix, pairs: IntArray) -> Array:
    """Per pair (i, j), the 6 x 6 covariance of poses i and j (x, y, psi each) from the
    symmetric factor ``lu`` of the information matrix (``SpdFactor.symmetric``), with ``t``
    the frames' unknowns (rows 3k, 3k + 1, 3k + 2 for frame k) as linear in the factored
    problem's (columns). The pairs are taken in order of their first pose, each pose's
    vectors solved once while it is among the newest used (``CACHE_BYTES``)."""
    solver = _Solver(lu, sp.csr_matrix(t))
    cache: OrderedDict[int, tuple[IntArray, Array, IntArray]] = OrderedDict()
    held = 0
    three = np.arange(3, dtype=np.int64)

    def pose(k: int) -> tuple[IntArray, Array, IntArray]:
        nonlocal held
        got = cache.get(k)
        if got is not None:
            cache.move_to_end(k)
            return got
        got = solver.vectors(3 * k + three)
        cache[k] = got
        held += got[0].nbytes + got[1].nbytes
        while held > CACHE_BYTES and len(cache) > 2:  # the pair being served stays
            _, (index, value, _) = cache.popitem(last=False)
            held -= index.nbytes + value.nbytes
        return got

    blocks = np.zeros((len(pairs), 6, 6))
    for m in np.lexsort((pairs[:, 1], pairs[:, 0])):
        (ia, va, sa), (ib, vb, sb) = pose(int(pairs[m, 0])), pose(int(pairs[m, 1]))
        index = np.concatenate([ia, ib])
        value = np.concatenate([va, vb])
        starts = np.concatenate([sa, sb[1:] + sa[-1]])
        blocks[m] = block_of(index, value, starts, solver.inverse_d, solver.work)
    return blocks
