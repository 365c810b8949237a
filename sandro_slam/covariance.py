"""The covariances of a factor graph's variables at a solution, every block its factors touch at once.

The information matrix J^T J of the linearised, whitened graph is factorised as L D L^T (scipy's SuperLU with a
symmetric fill-reducing ordering and no pivoting) and inverted on the pattern of L only (Takahashi's recurrence,
"selected inversion", in dense blocks over L's supernodes): every variable's marginal covariance and the
cross-covariance of the variables of every factor, for about the cost of the factorisation, instead of one
back-substitution per variable. What a factor outside the graph (a loop candidate) would see of the variables it
joins comes from forward substitutions with the same factor, along the elimination tree's paths from its variables
to the root only. Blocks are in gtsam's tangent convention of each variable (the factors' own linearisation: Pose3
[rotation, translation] on the right).
"""

from __future__ import annotations

import gtsam
import numba
import numpy as np
import scipy.sparse as sp
import scipy.sparse.linalg as spl

PATTERN_VALUE = 1e-30  # x the median diagonal: stored on every block a factor touches, so that the pattern is
# the blocks' (a factor's Jacobian can hold exact zeros); far below any eigenvalue that matters


class FactorCovariances:
    """Covariances of `graph`'s variables at `values` (from the factors' whitened Jacobians). `floor` adds that
    many times the information matrix's median diagonal to its diagonal: a weak prior on every variable, for
    graphs whose covariances leave directions numerically free.

    Raises:
        ValueError: the information matrix is singular (a variable no factor determines) or, numerically, not
            positive definite.
    """

    def __init__(self, graph: gtsam.NonlinearFactorGraph, values: gtsam.Values, floor: float = 0.0):
        zeros = values.zeroVectors()
        self._offset: dict[int, int] = {}
        self._dim: dict[int, int] = {}
        size = 0
        for key in sorted(values.keys()):
            self._offset[key], self._dim[key] = size, len(zeros.at(key))
            size += self._dim[key]
        groups: dict[tuple[int, int], tuple[list[np.ndarray], list[list[int]]]] = {}  # by Jacobian shape
        for index in range(graph.size()):
            factor = graph.at(index)
            A, _ = factor.linearize(values).jacobian()
            jacobians, columns = groups.setdefault(A.shape, ([], []))
            jacobians.append(A)
            columns.append(
                [c for key in factor.keys() for c in range(self._offset[key], self._offset[key] + self._dim[key])]
            )
        rows, cols, data, block_rows, block_cols = [], [], [], [], []
        row = 0
        for (m, k), (jacobians, columns) in groups.items():
            A, C = np.stack(jacobians), np.array(columns)  # (factors, m, k), (factors, k)
            first = row + m * np.arange(len(C))
            rows.append(np.broadcast_to((first[:, None] + np.arange(m))[:, :, None], A.shape).ravel())
            cols.append(np.broadcast_to(C[:, None, :], A.shape).ravel())
            data.append(A.ravel())
            block_rows.append(np.broadcast_to(C[:, :, None], (len(C), k, k)).ravel())
            block_cols.append(np.broadcast_to(C[:, None, :], (len(C), k, k)).ravel())
            row += m * len(C)
        J = sp.csc_matrix((np.concatenate(data), (np.concatenate(rows), np.concatenate(cols))), shape=(row, size))
        information = (J.T @ J).tocsc()
        touched = np.concatenate(block_rows), np.concatenate(block_cols)
        median = float(np.median(information.diagonal()))
        value = PATTERN_VALUE * median
        information = (information + sp.csc_matrix((np.full(len(touched[0]), value), touched), (size, size))).tocsc()
        if floor > 0.0:  # on the diagonal, and every variable's own block on the pattern
            own = [np.arange(self._offset[key], self._offset[key] + self._dim[key]) for key in self._offset]
            r = np.concatenate([np.repeat(c, len(c)) for c in own])
            q = np.concatenate([np.tile(c, len(c)) for c in own])
            entries = np.where(r == q, floor * median, value)
            information = (information + sp.csc_matrix((entries, (r, q)), (size, size))).tocsc()
        try:
            lu = spl.splu(information, permc_spec="MMD_AT_PLUS_A", diag_pivot_thresh=0.0,
                          options={"SymmetricMode": True})  # fmt: skip
        except RuntimeError as error:
            raise ValueError(f"singular information matrix: {error}") from None
        if not np.array_equal(lu.perm_r, lu.perm_c):
            raise ValueError("the factorisation pivoted: the information matrix is not positive definite")
        self._position = lu.perm_c  # variable column c sits at row/column perm_c[c] of L
        # SuperLU leaves out the entries of L that come out exactly zero; the recurrence needs them all: the
        # symbolic pattern of the permuted matrix, with SuperLU's values where it has them
        coo = information.tocoo()
        rows, cols = self._position[coo.row], self._position[coo.col]
        upper = rows < cols
        permuted = sp.csc_matrix((np.ones(int(upper.sum())), (rows[upper], cols[upper])), (size, size))
        permuted.sort_indices()
        self._indptr, self._indices = _filled_pattern(
            permuted.indptr.astype(np.int64), permuted.indices.astype(np.int64)
        )
        L = lu.L.tocsc()
        L.sort_indices()
        l_values, held = _scattered(
            self._indptr, self._indices, L.indptr.astype(np.int64), L.indices.astype(np.int64), L.data
        )
        if not held:  # cannot happen in exact arithmetic: the symbolic pattern holds every entry of L
            raise ValueError("the factor has entries off its symbolic pattern")
        self._l_values, self._d = l_values, lu.U.diagonal()
        self._z = _selected_inverse(self._indptr, self._indices, l_values, self._d)

    def block(self, a: int, b: int) -> np.ndarray:
        """Cov(x_a, x_b), (dim a, dim b); a == b gives a's marginal covariance.

        Raises:
            KeyError: the pair is not on the pattern (no factor joins a and b, and elimination did not join them).
        """
        return self._gathered(self._columns(a), self._columns(b), f"Cov(x_{a}, x_{b})")

    def joint(self, keys: list[int]) -> np.ndarray:
        """The joint covariance of the variables `keys` (stacked in that order), e.g. those of one factor.

        Raises:
            KeyError: a pair of them is not on the pattern.
        """
        columns = np.concatenate([self._columns(key) for key in keys])
        return self._gathered(columns, columns, f"the joint covariance of {list(keys)}")

    def projected(self, factor: gtsam.NonlinearFactor, values: gtsam.Values) -> tuple[np.ndarray, np.ndarray]:
        """(b, M) of `factor` linearised at `values`: its whitened error vector b and M = A Sigma A^T, the
        covariance that its variables' joint covariance Sigma puts on its whitened measurement (A its whitened
        Jacobian)."""
        A, b = factor.linearize(values).jacobian()
        return b, A @ self.joint(list(factor.keys())) @ A.T

    def mahalanobis(
        self,
        factors: list[gtsam.NonlinearFactor],
        values: gtsam.Values,
        measurement_scale: float = 1.0,
        variable_scale: float = 1.0,
        correlated: bool = True,
    ) -> np.ndarray:
        """(len(factors),) b^T S^-1 b per factor linearised at `values`: b its whitened error vector, A its
        whitened Jacobian and S = `measurement_scale` I + `variable_scale` A Sigma A^T, Sigma its variables' joint
        covariance (`correlated`) or their marginal blocks alone (cross-covariances taken as zero). Batched over
        the factors of one shape: the same as `projected` factor by factor. Factors whose variables the graph
        does not join (loop candidates) need not be in it: where Sigma is off the pattern, their A Sigma A^T comes
        from forward substitutions with the factor (`_forward_projections`)."""
        out = np.empty(len(factors))
        groups: dict[tuple, tuple[list[int], list[np.ndarray], list[np.ndarray], list[np.ndarray]]] = {}
        for n, factor in enumerate(factors):
            A, b = factor.linearize(values).jacobian()
            keys = factor.keys()
            shape = (A.shape, tuple(self._dim[key] for key in keys))
            positions, jacobians, errors, columns = groups.setdefault(shape, ([], [], [], []))
            positions.append(n)
            jacobians.append(A)
            errors.append(b)
            columns.append(np.concatenate([self._columns(key) for key in keys]))
        for ((m, _), dims), (positions, jacobians, errors, columns) in groups.items():
            stacked = np.array(columns)  # (factors, k)
            sigma = self._entries_at(stacked, stacked)
            if not correlated:
                own = np.repeat(np.arange(len(dims)), dims)
                sigma = np.where(own[:, None] == own[None, :], sigma, 0.0)
            A = np.stack(jacobians)
            b = np.stack(errors)
            off = np.isnan(sigma).any(axis=(1, 2))
            projected = np.empty((len(A), m, m))
            projected[~off] = A[~off] @ sigma[~off] @ np.swapaxes(A[~off], 1, 2)
            if off.any():
                projected[off] = _forward_projections(
                    self._indptr, self._indices, self._l_values, self._d, self._position[stacked[off]], A[off]
                )
            S = measurement_scale * np.eye(m) + variable_scale * projected
            out[positions] = np.einsum("nm,nm->n", b, np.linalg.solve(S, b[:, :, None])[:, :, 0])
        return out

    def _gathered(self, rows: np.ndarray, cols: np.ndarray, what: str) -> np.ndarray:
        """The covariance entries at variable columns `rows` x `cols`; KeyError naming `what` off the pattern."""
        out = self._entries_at(rows, cols)
        if np.isnan(out).any():
            raise KeyError(f"{what} is not on the factor's pattern")
        return out

    def _entries_at(self, rows: np.ndarray, cols: np.ndarray) -> np.ndarray:
        """The covariance entries at variable columns `rows` (..., m) x `cols` (..., n), as (..., m, n): stacks of
        blocks alike; NaN off the pattern."""
        rows, cols = self._position[rows][..., :, None], self._position[cols][..., None, :]
        # Z is stored on and below its diagonal: each entry at (the larger, the smaller) of its two positions
        z_rows, z_cols = np.maximum(rows, cols), np.minimum(rows, cols)
        out = _entries(self._indptr, self._indices, self._z, z_rows.ravel(), z_cols.ravel())
        return out.reshape(z_rows.shape)

    def _columns(self, key: int) -> np.ndarray:
        return np.arange(self._offset[key], self._offset[key] + self._dim[key])


@numba.njit(cache=True)
def _entries(indptr: np.ndarray, indices: np.ndarray, z: np.ndarray, rows: np.ndarray, cols: np.ndarray) -> np.ndarray:
    """z at (rows[i] >= cols[i]) of the CSC pattern (sorted rows); NaN where the pattern has no such entry."""
    out = np.full(len(rows), np.nan)
    for n in range(len(rows)):
        lo, hi = indptr[cols[n]], indptr[cols[n] + 1]
        while lo < hi:
            mid = (lo + hi) // 2
            if indices[mid] < rows[n]:
                lo = mid + 1
            else:
                hi = mid
        if lo < indptr[cols[n] + 1] and indices[lo] == rows[n]:
            out[n] = z[lo]
    return out


@numba.njit(cache=True)
def _forward_projections(
    indptr: np.ndarray, indices: np.ndarray, l_values: np.ndarray, d: np.ndarray, rows: np.ndarray, A: np.ndarray
) -> np.ndarray:
    """(F, m, m) Y^T D^-1 Y per factor, Y = L^-1 G (L unit lower triangular, CSC with sorted rows and the diagonal
    first; D its diagonal), G (n, m) holding the factor's A (F, m, k) transposed at its `rows` (F, k) of L. The
    entries of L^-1 g lie on the paths up the elimination tree (each column's parent: its first row below the
    diagonal) from g's rows: the substitution visits those columns alone, in increasing order. With the information
    matrix H = P^T L D L^T P and `rows` the factor's variable columns permuted by P, this is A H^-1 A^T."""
    n = len(d)
    count, m, k = A.shape
    out = np.empty((count, m, m))
    y = np.zeros((n, m))
    visited = np.full(n, -1)
    path = np.empty(n, np.int64)
    for f in range(count):
        length = 0
        for j in range(k):
            node = rows[f, j]
            y[node, :] += A[f, :, j]
            while node != -1 and visited[node] != f:
                visited[node] = f
                path[length] = node
                length += 1
                node = indices[indptr[node] + 1] if indptr[node + 1] - indptr[node] > 1 else -1
        columns = np.sort(path[:length])
        M = np.zeros((m, m))
        yc = np.empty(m)
        for c in columns:  # element by element: no temporary arrays in the innermost loops
            for i in range(m):
                yc[i] = y[c, i]
                y[c, i] = 0.0
            for p in range(indptr[c] + 1, indptr[c + 1]):
                row = indices[p]
                for i in range(m):
                    y[row, i] -= l_values[p] * yc[i]
            for i in range(m):
                for j in range(m):
                    M[i, j] += yc[i] * yc[j] / d[c]
        out[f] = M
    return out


@numba.njit(cache=True)
def _filled_pattern(indptr: np.ndarray, indices: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The pattern of the Cholesky factor L (CSC, rows sorted, the diagonal first) of a symmetric matrix given by
    its strictly upper pattern (CSC, `indptr`, `indices`): the elimination tree, then each row of L as the paths
    up that tree from the row's entries in the matrix (Davis, "Direct Methods for Sparse Linear Systems", ch. 4)."""
    n = len(indptr) - 1
    parent = np.full(n, -1)
    ancestor = np.full(n, -1)
    for k in range(n):
        for p in range(indptr[k], indptr[k + 1]):
            i = indices[p]
            while i != -1 and i < k:
                following = ancestor[i]
                ancestor[i] = k
                if following == -1:
                    parent[i] = k
                i = following
    counts = np.ones(n, dtype=np.int64)  # the diagonal
    mark = np.full(n, -1)
    for k in range(n):
        mark[k] = k
        for p in range(indptr[k], indptr[k + 1]):
            i = indices[p]
            while mark[i] != k:
                counts[i] += 1
                mark[i] = k
                i = parent[i]
    l_indptr = np.zeros(n + 1, dtype=np.int64)
    l_indptr[1:] = np.cumsum(counts)
    l_indices = np.empty(l_indptr[n], dtype=np.int64)
    fill = l_indptr[:-1].copy()
    for j in range(n):
        l_indices[fill[j]] = j
        fill[j] += 1
    mark[:] = -1
    for k in range(n):  # rows in increasing order: every column's rows come out sorted
        mark[k] = k
        for p in range(indptr[k], indptr[k + 1]):
            i = indices[p]
            while mark[i] != k:
                l_indices[fill[i]] = k
                fill[i] += 1
                mark[i] = k
                i = parent[i]
    return l_indptr, l_indices


@numba.njit(cache=True)
def _scattered(
    indptr: np.ndarray, indices: np.ndarray, s_indptr: np.ndarray, s_indices: np.ndarray, s_values: np.ndarray
) -> tuple[np.ndarray, bool]:
    """The values of a sparse matrix (CSC, sorted rows) laid out on a pattern (zero where it has none); False when
    the pattern does not hold one of its entries."""
    values = np.zeros(len(indices))
    for j in range(len(indptr) - 1):
        at = indptr[j]
        for p in range(s_indptr[j], s_indptr[j + 1]):
            while at < indptr[j + 1] and indices[at] != s_indices[p]:
                at += 1
            if at == indptr[j + 1]:
                return values, False
            values[at] = s_values[p]
    return values, True


@numba.njit(cache=True)
def _supernodes(indptr: np.ndarray, indices: np.ndarray) -> np.ndarray:
    """The first column of each supernode of L (CSC, sorted rows, the diagonal first), then n: columns j and j+1
    share one when the rows of column j below its diagonal are j+1 and exactly the rows of column j+1 (a pose's
    columns, and chains of the elimination tree's separators)."""
    n = len(indptr) - 1
    starts = [0]
    for j in range(n - 1):
        below = indptr[j + 1] - indptr[j] - 1
        if not (below > 0 and below == indptr[j + 2] - indptr[j + 1] and indices[indptr[j] + 1] == j + 1):
            starts.append(j + 1)
    starts.append(n)
    return np.array(starts)


@numba.njit(cache=True)
def _selected_inverse(indptr: np.ndarray, indices: np.ndarray, l_values: np.ndarray, d: np.ndarray) -> np.ndarray:
    """Z = (L D L^T)^-1 on the pattern of L (CSC, sorted rows, unit diagonal stored first in each column, closed
    under elimination), in the same layout. Supernode by supernode from the last (Takahashi's recurrence in
    blocks): with J a supernode's columns, R the rows below them, Lh = L_RJ L_JJ^-1,
    Z_RJ = -Z_RR Lh and Z_JJ = (L_JJ D_J L_JJ^T)^-1 - Lh^T Z_RJ, where Z_RR lies in the columns done already
    (the pattern is closed: every row of R after a row k is on column k's pattern). Dense products instead of one
    merge of two sparse columns per entry: the same flops, at the speed of BLAS."""
    starts = _supernodes(indptr, indices)
    owner = np.empty(len(d), np.int64)
    for J in range(len(starts) - 1):
        owner[starts[J] : starts[J + 1]] = J
    z = np.zeros(len(l_values))
    for J in range(len(starts) - 2, -1, -1):
        first, width = starts[J], starts[J + 1] - starts[J]
        rows = indices[indptr[first] : indptr[first + 1]]  # its own columns, then R
        L = np.zeros((len(rows), width))
        for k in range(width):
            L[k:, k] = l_values[indptr[first + k] : indptr[first + k + 1]]
        inverse = _unit_lower_inverse(L[:width, :])
        Z = np.zeros((len(rows), width))
        Z[:width, :] = inverse.T @ np.diag(1.0 / d[first : first + width]) @ inverse
        R = rows[width:]
        if len(R):
            Lh = np.ascontiguousarray(L[width:, :]) @ inverse
            Zrr = np.zeros((len(R), len(R)))
            q = 0
            while q < len(R):  # the rows of R in one supernode K at a time
                k_first = starts[owner[R[q]]]
                k_rows = indices[indptr[k_first] : indptr[k_first + 1]]
                at, positions = 0, np.empty(len(R) - q, np.int64)  # of R[q:] among K's rows
                for p in range(q, len(R)):
                    while at < len(k_rows) - 1 and k_rows[at] != R[p]:
                        at += 1
                    positions[p - q] = at
                end = q
                while end < len(R) and owner[R[end]] == owner[R[q]]:
                    end += 1
                for p in range(q, end):  # column R[p] stores K's rows from its own on
                    base = indptr[R[p]] - (R[p] - k_first)
                    for i in range(p, len(R)):
                        Zrr[i, p] = Zrr[p, i] = z[base + positions[i - q]]
                q = end
            Zrj = -(Zrr @ Lh)
            Z[width:, :] = Zrj
            Z[:width, :] -= Lh.T @ Zrj
        for k in range(width):
            z[indptr[first + k] : indptr[first + k + 1]] = Z[k:, k]
    return z


@numba.njit(cache=True)
def _unit_lower_inverse(L: np.ndarray) -> np.ndarray:
    """The inverse of a unit lower triangular matrix (forward substitution, column by column)."""
    n = len(L)
    inverse = np.eye(n)
    for j in range(n):
        for i in range(j + 1, n):
            total = 0.0
            for k in range(j, i):
                total += L[i, k] * inverse[k, j]
            inverse[i, j] = -total
    return inverse
