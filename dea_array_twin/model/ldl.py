"""Sparse ``LDL^T`` of a symmetric matrix of 3x3 node blocks, compiled with numba.

The free-free tangent ``K_ff`` couples the three dofs of every node with the three
of each neighbour, so it is a sparse matrix of dense 3x3 blocks.  It is factored as

    P K_ff P^T = L D L^T,

``L`` unit lower-triangular in blocks, ``D`` block-diagonal (3x3 symmetric blocks),
``P`` a fill-reducing node ordering.  The algorithm is the up-looking one of QDLDL
(and T. Davis' LDL) with every scalar replaced by a 3x3 block: for block row ``k``,
``w`` solves ``L w = K(:, k)`` over the elimination-tree reach of column ``k``, then

    L(k, i) = w_i^T D_i^-1,        D_k = K(k, k) - sum_i L(k, i) w_i.

Working on blocks makes one index load serve 27 multiply-adds.  The default back end
computes the same factors multifrontally (:mod:`.multifrontal`, dense fronts); this
one-block-at-a-time form is its reference (``linear_solver="block-uplooking"``), and
:func:`solve` serves both.  By Sylvester's law of
inertia the negative eigenvalues of ``K_ff`` are those of the blocks ``D_k``, counted
from the pivots of each block's own 3x3 ``LDL^T``.  No pivoting beyond the ordering:
an exactly zero pivot stops the factorisation (reported, the caller falls back).
"""

from __future__ import annotations

import numba
import numpy as np

from .kernels import JIT


@numba.njit(**JIT)
def elimination_tree(n, ap, ai):
    """Parent of each block column and the number of blocks below the diagonal in each column of ``L``.

    ``ap``, ``ai``: the upper triangle's block pattern in CSC.
    """
    work = np.zeros(n, np.int64)
    counts = np.zeros(n, np.int64)
    parent = np.full(n, -1, np.int64)
    for j in range(n):
        work[j] = j
        for p in range(ap[j], ap[j + 1]):
            i = ai[p]
            while work[i] != j:
                if parent[i] == -1:
                    parent[i] = j
                counts[i] += 1
                work[i] = j
                i = parent[i]
    return parent, counts


@numba.njit(inline="always", **JIT)
def invert_pivot(d, dk):
    """Write ``D_k^-1`` of the symmetric 3x3 pivot ``d`` into ``dk``; return its negative eigenvalues.

    The inertia comes from the pivots of ``d``'s own ``LDL^T``; -1 if one is zero (or not finite).
    """
    p0 = d[0, 0]
    if p0 == 0.0:
        return -1
    l10, l20 = d[1, 0] / p0, d[2, 0] / p0
    p1 = d[1, 1] - l10 * d[1, 0]
    if p1 == 0.0:
        return -1
    l21 = (d[2, 1] - l20 * d[1, 0]) / p1
    p2 = d[2, 2] - l20 * d[2, 0] - l21 * l21 * p1
    if p2 == 0.0 or not (np.isfinite(p0) and np.isfinite(p1) and np.isfinite(p2)):
        return -1
    c00 = d[1, 1] * d[2, 2] - d[1, 2] * d[2, 1]
    c01 = d[0, 2] * d[2, 1] - d[0, 1] * d[2, 2]
    c02 = d[0, 1] * d[1, 2] - d[0, 2] * d[1, 1]
    c11 = d[0, 0] * d[2, 2] - d[0, 2] * d[2, 0]
    c12 = d[0, 2] * d[1, 0] - d[0, 0] * d[1, 2]
    c22 = d[0, 0] * d[1, 1] - d[0, 1] * d[1, 0]
    inv = 1.0 / (p0 * p1 * p2)  # det D_k
    dk[0, 0], dk[0, 1], dk[0, 2] = c00 * inv, c01 * inv, c02 * inv
    dk[1, 0], dk[1, 1], dk[1, 2] = c01 * inv, c11 * inv, c12 * inv
    dk[2, 0], dk[2, 1], dk[2, 2] = c02 * inv, c12 * inv, c22 * inv
    return (p0 < 0.0) + (p1 < 0.0) + (p2 < 0.0)


@numba.njit(**JIT)
def factor(n, ap, ai, ax, lp, parent, li, lx, dinv):
    """Fill ``li``, ``lx`` (``L`` by block columns) and ``dinv`` (``D_k^-1``).

    ``ax[p]`` is the block ``K(ai[p], k)`` for ``ap[k] <= p < ap[k + 1]`` (upper triangle
    with the diagonal).  Returns the number of negative eigenvalues of ``D`` (that is,
    of ``K``), or -1 if a zero pivot stopped the factorisation.
    """
    y = np.zeros((n, 3, 3))
    marked = np.zeros(n, np.bool_)
    reach = np.empty(n, np.int64)
    stack = np.empty(n, np.int64)
    next_free = lp[:-1].copy()
    d = np.empty((3, 3))
    w = np.empty((3, 3))
    negative = 0
    for k in range(n):
        count = 0
        d[:, :] = 0.0
        for p in range(ap[k], ap[k + 1]):  # scatter column k; collect the reach of its rows
            b = ai[p]
            if b == k:
                d[:, :] = ax[p]
                continue
            y[b] = ax[p]
            if not marked[b]:
                marked[b] = True
                stack[0] = b
                depth = 1
                i = parent[b]
                while i != -1 and i < k and not marked[i]:
                    marked[i] = True
                    stack[depth] = i
                    depth += 1
                    i = parent[i]
                while depth > 0:
                    depth -= 1
                    reach[count] = stack[depth]
                    count += 1
        for t in range(count - 1, -1, -1):  # topological order: w_c final, push it down column c
            c = reach[t]
            w[:, :] = y[c]
            y[c] = 0.0
            w00, w01, w02 = w[0, 0], w[0, 1], w[0, 2]
            w10, w11, w12 = w[1, 0], w[1, 1], w[1, 2]
            w20, w21, w22 = w[2, 0], w[2, 1], w[2, 2]
            end = next_free[c]
            for q in range(lp[c], end):
                lq = lx[q]
                yr = y[li[q]]
                for a in range(3):
                    l0, l1, l2 = lq[a, 0], lq[a, 1], lq[a, 2]
                    yr[a, 0] -= l0 * w00 + l1 * w10 + l2 * w20
                    yr[a, 1] -= l0 * w01 + l1 * w11 + l2 * w21
                    yr[a, 2] -= l0 * w02 + l1 * w12 + l2 * w22
            dc = dinv[c]
            lk = lx[end]
            for a in range(3):  # L(k, c) = w^T D_c^-1
                for b in range(3):
                    lk[a, b] = w[0, a] * dc[0, b] + w[1, a] * dc[1, b] + w[2, a] * dc[2, b]
            for a in range(3):  # D_k -= L(k, c) w
                for b in range(3):
                    d[a, b] -= lk[a, 0] * w[0, b] + lk[a, 1] * w[1, b] + lk[a, 2] * w[2, b]
            li[end] = k
            next_free[c] = end + 1
            marked[c] = False
        count = invert_pivot(d, dinv[k])
        if count < 0:
            return -1
        negative += count
    return negative


@numba.njit(**JIT)
def solve(n, lp, li, lx, dinv, order, b, x):
    """``x = K^-1 b`` from the factors; ``order[i]`` is the node of block row ``i``."""
    y = np.empty((n, 3))
    for i in range(n):
        for a in range(3):
            y[i, a] = b[3 * order[i] + a]
    for i in range(n):  # L y = b
        y0, y1, y2 = y[i, 0], y[i, 1], y[i, 2]
        for q in range(lp[i], lp[i + 1]):
            lq = lx[q]
            yr = y[li[q]]
            for a in range(3):
                yr[a] -= lq[a, 0] * y0 + lq[a, 1] * y1 + lq[a, 2] * y2
    for i in range(n):  # D z = y
        di = dinv[i]
        y0, y1, y2 = y[i, 0], y[i, 1], y[i, 2]
        for a in range(3):
            y[i, a] = di[a, 0] * y0 + di[a, 1] * y1 + di[a, 2] * y2
    # L^T x = z, the columns last to first and each column's blocks last to first: L is read
    # as one descending stream, which the hardware prefetcher follows (reading each column
    # upwards while stepping down the columns defeated it: on the 4-by-4, 16 MB of L, this
    # half of the solve took ~3 ms instead of ~0.8 ms).
    for i in range(n - 1, -1, -1):
        s0, s1, s2 = y[i, 0], y[i, 1], y[i, 2]
        for q in range(lp[i + 1] - 1, lp[i] - 1, -1):
            lq = lx[q]
            yr = y[li[q]]
            s0 -= lq[0, 0] * yr[0] + lq[1, 0] * yr[1] + lq[2, 0] * yr[2]
            s1 -= lq[0, 1] * yr[0] + lq[1, 1] * yr[1] + lq[2, 1] * yr[2]
            s2 -= lq[0, 2] * yr[0] + lq[1, 2] * yr[1] + lq[2, 2] * yr[2]
        y[i, 0], y[i, 1], y[i, 2] = s0, s1, s2
    for i in range(n):
        for a in range(3):
            x[3 * order[i] + a] = y[i, a]
