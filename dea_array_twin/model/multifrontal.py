"""Multifrontal ``LDL^T`` of a symmetric matrix of 3x3 node blocks, compiled with numba.

The same factorisation as :mod:`.ldl` (``P K P^T = L D L^T``, unit lower-triangular
``L`` in 3x3 blocks, block-diagonal ``D``, the same node ordering and the same pivots),
computed so that almost all the arithmetic runs in dense loops over contiguous memory
instead of one 3x3 block at a time through index arrays.

Columns of ``L`` whose patterns nest (column ``j + 1`` is column ``j`` without its first
row, and ``j`` is ``j + 1``'s only child in the elimination tree) form a *supernode*.
The nodes are put in a postorder of the elimination tree (the same fill), so that each
supernode ``s`` with columns ``J`` and rows below them ``R`` is processed after its
children.  Its dense *front* over ``J + R``

    F_s = K(J + R, J) + sum_{children c} U_c   (extend-add),

is partially factored over ``J`` with 3x3 block pivots (Schur complement, with
``W = L D``):

    D_k = F(k, k),   L(i, k) = F(i, k) D_k^-1,   F(i, j) -= L(i, k) W(j, k)^T  (i, j > k),

and what is left on ``R`` is its update matrix ``U_s = F(R, R)``, passed to its
parent.  In the postorder a parent comes right after its last child, so the fronts of
consecutive supernodes alternate between two buffers and the last child's ``U_s`` is
read from its own front; only the other children's are copied to a stack (the
children of the next supernode are always on top).  Only the lower block triangle of
a front is stored or updated.  ``L`` comes out in the
block-column layout of :mod:`.ldl` (the same ``lp``/``li``, so :func:`.ldl.solve`
solves with it), and the negative eigenvalues are counted from the pivots of each
``D_k`` as there (Sylvester's law of inertia).
"""

from __future__ import annotations

import numba
import numpy as np

from .kernels import JIT
from .ldl import invert_pivot


@numba.njit(**JIT)
def postorder(parent):
    """A postorder of the forest ``parent`` (children in increasing order, then the node)."""
    n = parent.size
    head = np.full(n, -1, np.int64)
    sibling = np.full(n, -1, np.int64)
    for j in range(n - 1, -1, -1):
        if parent[j] != -1:
            sibling[j] = head[parent[j]]
            head[parent[j]] = j
    order = np.empty(n, np.int64)
    stack = np.empty(n, np.int64)
    k = 0
    for root in range(n):
        if parent[root] != -1:
            continue
        top = 0
        stack[0] = root
        while top >= 0:
            j = stack[top]
            child = head[j]
            if child == -1:
                top -= 1
                order[k] = j
                k += 1
            else:
                head[j] = sibling[child]
                top += 1
                stack[top] = child
    return order


@numba.njit(**JIT)
def row_pattern(n, ap, ai, parent, lp):
    """Row indices of each block column of ``L`` (ascending; ``lp`` from the column counts).

    Row ``k`` of ``L`` is the elimination-tree reach of the upper pattern of column ``k``.
    """
    li = np.empty(lp[-1], np.int64)
    next_free = lp[:-1].copy()
    mark = np.full(n, -1, np.int64)
    for k in range(n):
        mark[k] = k
        for p in range(ap[k], ap[k + 1]):
            i = ai[p]
            while mark[i] != k:
                li[next_free[i]] = k
                next_free[i] += 1
                mark[i] = k
                i = parent[i]
    return li


@numba.njit(**JIT)
def amalgamate(start, counts, parent):
    """Merge supernodes with their last child while few explicit zeros are stored (relaxed supernodes).

    ``start``: the fundamental supernodes (first columns, and ``n``) in a postorder.  A
    child ending just before a supernode and whose parent column is in it has rows
    inside the parent's front, so the merged front is the child's columns plus the
    parent's: its columns store zeros where their own pattern is thinner.  The merge
    stays while under 5 % of the stored entries are zeros: fewer, bigger fronts at no cost
    to the triangular solves, which read the zeros too (measured on the 1-by-3 and the
    4-by-4: merging up to 8 columns with < 30 % zeros stored 9 % more of ``L`` and made
    the solves ~10 % slower, without a faster factorisation; CHOLMOD's looser rule made
    the 1-by-3's factorisation slower as well).
    """
    n_super = start.size - 1
    first = np.empty(n_super, np.int64)
    zeros = np.empty(n_super, np.int64)
    count = 0
    for s in range(n_super):
        f, last = start[s], start[s + 1] - 1
        rows = counts[last]
        z = 0
        while count > 0 and parent[f - 1] != -1 and f <= parent[f - 1] <= last:
            g = first[count - 1]  # the previous supernode, a child: merge it if the zeros allow
            ncol = last - g + 1
            stored = ncol * (ncol - 1) // 2 + ncol * rows
            extra = z + zeros[count - 1]
            for j in range(g, f):
                extra += (last - j + rows) - counts[j]
            share = extra / stored
            if share >= 0.05:
                break
            count -= 1
            f, z = g, extra
        first[count], zeros[count] = f, z
        count += 1
    out = np.empty(count + 1, np.int64)
    out[:count] = first[:count]
    out[count] = start[-1]
    return out


@numba.njit(**JIT)
def fronts(start, lp, li, parent):
    """Front node lists (``fp`` offsets into ``fn``), children counts, stack size and ``L``'s layout.

    The front of supernode ``s`` (columns ``start[s] .. start[s + 1] - 1``) is its
    columns followed by the rows of its last column.  Returns ``fp, fn, children,
    stack_size, largest, sp, si``: ``stack_size`` the largest total size of the update
    matrices waiting on the stack, ``largest`` the largest front's dimension, ``sp`` and
    ``si`` the block columns of ``L`` as stored (a column of a relaxed supernode also
    has the rows of its front that are zero in ``L``).
    """
    n_super = start.size - 1
    n = start[-1]
    supernode = np.empty(n, np.int64)
    fp = np.zeros(n_super + 1, np.int64)
    sp = np.zeros(n + 1, np.int64)
    for s in range(n_super):
        last = start[s + 1] - 1
        supernode[start[s]:start[s + 1]] = s
        fp[s + 1] = fp[s] + (start[s + 1] - start[s]) + (lp[last + 1] - lp[last])
        for j in range(start[s], last + 1):
            sp[j + 1] = sp[j] + (fp[s + 1] - fp[s]) - (j - start[s]) - 1
    fn = np.empty(fp[-1], np.int64)
    si = np.empty(sp[-1], np.int64)
    children = np.zeros(n_super, np.int64)
    sizes = np.empty(n_super, np.int64)
    waiting = np.empty(n_super, np.int64)
    depth, used, stack_size, largest = 0, 0, 0, 0
    for s in range(n_super):
        first, last = start[s], start[s + 1] - 1
        ncol = last - first + 1
        fn[fp[s]:fp[s] + ncol] = np.arange(first, last + 1)
        fn[fp[s] + ncol:fp[s + 1]] = li[lp[last]:lp[last + 1]]
        for j in range(first, last + 1):
            si[sp[j]:sp[j + 1]] = fn[fp[s] + j - first + 1:fp[s + 1]]
        if parent[last] != -1:
            children[supernode[parent[last]]] += 1
        largest = max(largest, fp[s + 1] - fp[s])
    held = False  # whether the last supernode's update matrix stayed in its front (see factor)
    for s in range(n_super):  # the stack as the factorisation will use it
        for _ in range(children[s] - (1 if held else 0)):
            depth -= 1
            used -= sizes[waiting[depth]]
        ncol = start[s + 1] - start[s]
        rows = 3 * (fp[s + 1] - fp[s] - ncol)
        sizes[s] = rows * rows
        held = rows > 0 and fn[fp[s] + ncol] < start[s + 2]  # its parent is the next supernode
        if rows > 0 and not held:
            waiting[depth] = s
            depth += 1
            used += sizes[s]
            stack_size = max(stack_size, used)
    return fp, fn, children, stack_size, 3 * largest, sp, si


@numba.njit(inline="always", fastmath={"contract"}, **JIT)
def _update_block(f, r, t, wt, first, end):
    """``F(r:r+3, first:end) -= F(r:r+3, t:t+3) W(first:end, t:t+3)^T``: one node block row
    updated by one pivot block (``W^T`` stored in ``wt``).

    Three rows at a time over views indexed from 0, so that the loop compiles to vector
    instructions and each loaded ``W`` entry serves three rows.
    """
    a00, a01, a02 = f[r, t], f[r, t + 1], f[r, t + 2]
    a10, a11, a12 = f[r + 1, t], f[r + 1, t + 1], f[r + 1, t + 2]
    a20, a21, a22 = f[r + 2, t], f[r + 2, t + 1], f[r + 2, t + 2]
    r0, r1, r2 = f[r, first:end], f[r + 1, first:end], f[r + 2, first:end]
    w0, w1, w2 = wt[t, first:end], wt[t + 1, first:end], wt[t + 2, first:end]
    for j in range(r0.size):
        x0, x1, x2 = w0[j], w1[j], w2[j]
        r0[j] -= a00 * x0 + a01 * x1 + a02 * x2
        r1[j] -= a10 * x0 + a11 * x1 + a12 * x2
        r2[j] -= a20 * x0 + a21 * x1 + a22 * x2


@numba.njit(inline="always", **JIT)
def _extend_add(f, src, base, stride, rows, position):
    """Add the update matrix stored at ``src[base:]`` (row stride ``stride``, lower block triangle)
    of a child with update rows ``rows`` to the front ``f``, whose block row of node ``i`` is
    ``position[i]``."""
    for u in range(rows.size):
        ru = 3 * position[rows[u]]
        for v in range(u + 1):
            rv = 3 * position[rows[v]]
            at = base + 3 * u * stride + 3 * v
            for a in range(3):
                for b in range(3):
                    f[ru + a, rv + b] += src[at + a * stride + b]


def workspace(n: int, n_super: int, stack_size: int, largest: int) -> tuple:
    """Scratch arrays of one thread of :func:`factor_range`: ``(stack, offset, waiting, state,
    position, buffers, wt)`` (``state`` = stack depth and top, zero: an empty stack)."""
    return (np.empty(max(stack_size, 1)), np.empty(n_super, np.int64), np.empty(n_super, np.int64),
            np.zeros(2, np.int64), np.empty(n, np.int64), np.empty((2, largest * largest)),
            np.empty((largest, largest)))


@numba.njit(inline="always", **JIT)
def factor_range(values, bp, bi, bpos, start, fp, fn, children, lp, lx, dinv, s_begin, s_end,
                 stack, offset, waiting, state, position, buffers, wt):
    """Fill ``lx`` (``L`` in the block columns ``lp`` of :func:`row_pattern`) and ``dinv`` for the
    supernodes ``s_begin .. s_end - 1``, on the stack given (``stack``, ``offset``, ``waiting``
    and ``state`` = its depth and top, updated here); all of them: ``0 .. start.size - 1`` on
    an empty stack.

    ``values`` are the tangent's nonzeros; ``bpos[p, a, b]`` is the position in them of
    entry ``(a, b)`` of block ``(bi[p], j)`` of the lower triangle, ``bp[j] <= p <
    bp[j + 1]``.  A subtree of the elimination tree is a range of the postorder, so
    disjoint ones can be factored at once, each on its own stack
    (:class:`.linsolve.Factoriser`): the supernodes read only their own columns of
    ``values`` and the update matrices of their children, and write only their own
    columns of ``lx`` and ``dinv``.  The last supernode of a range
    always leaves its update matrix on the stack (never held in its front, as within a
    range when its parent is the next supernode), for the range that has its parent.
    ``position``, ``buffers`` and ``wt`` are scratch (:func:`workspace`).  Returns the
    number of negative eigenvalues of its pivots, or -1 if a zero pivot stopped it.
    """
    d = np.empty((3, 3))
    depth, top = state[0], state[1]
    negative, held = 0, -1
    for s in range(s_begin, s_end):
        first, m = start[s], fp[s + 1] - fp[s]
        ncol = start[s + 1] - first
        nodes = fn[fp[s]:fp[s + 1]]
        size, pivots = 3 * m, 3 * ncol
        f = buffers[s % 2, :size * size].reshape((size, size))
        for t in range(m):
            position[nodes[t]] = t
        for r in range(size):  # lower block triangle, diagonal blocks in full
            for j in range(3 * (r // 3) + 3):
                f[r, j] = 0.0
        for j in range(first, first + ncol):  # K's columns
            c = 3 * (j - first)
            for p in range(bp[j], bp[j + 1]):
                r = 3 * position[bi[p]]
                for a in range(3):
                    for b in range(3):
                        f[r + a, c + b] += values[bpos[p, a, b]]
        waiting_children = children[s]
        if held == s - 1 and s > s_begin:  # the last child, s - 1, left its update matrix in its front
            child_pivots = 3 * (start[s] - start[s - 1])
            child_size = 3 * (fp[s] - fp[s - 1])
            rows = fn[fp[s - 1] + child_pivots // 3:fp[s]]
            _extend_add(f, buffers[(s - 1) % 2], child_pivots * child_size + child_pivots, child_size, rows,
                        position)
            waiting_children -= 1
        for _ in range(waiting_children):  # extend-add the other children's update matrices
            depth -= 1
            child = waiting[depth]
            rows = fn[fp[child] + start[child + 1] - start[child]:fp[child + 1]]
            top = offset[child]
            _extend_add(f, stack, top, 3 * rows.size, rows, position)
        for k in range(ncol):  # partial factorisation over the supernode's columns
            c = 3 * k
            for a in range(3):
                for b in range(3):
                    d[a, b] = f[c + a, c + b]
            dk = dinv[first + k]
            count = invert_pivot(d, dk)
            if count < 0:
                return -1
            negative += count
            for r in range(c + 3, size):  # W = F(:, k), L = W D_k^-1
                w0, w1, w2 = f[r, c], f[r, c + 1], f[r, c + 2]
                wt[c, r], wt[c + 1, r], wt[c + 2, r] = w0, w1, w2
                for b in range(3):
                    f[r, c + b] = w0 * dk[0, b] + w1 * dk[1, b] + w2 * dk[2, b]
            for r in range(c + 3, size, 3):  # the rest of the pivot columns
                _update_block(f, r, c, wt, c + 3, min(pivots, r + 3))
        for r in range(pivots, size, 3):  # update matrix F(R, R) -= L(R, J) W(R, J)^T
            for t in range(0, pivots, 3):
                _update_block(f, r, t, wt, pivots, r + 3)
        for k in range(ncol):  # L's block columns
            q = lp[first + k]
            for t in range(k + 1, m):
                for a in range(3):
                    for b in range(3):
                        lx[q, a, b] = f[3 * t + a, 3 * k + b]
                q += 1
        held = -1
        if size > pivots and s + 1 < s_end and fn[fp[s] + ncol] < start[s + 2]:
            held = s  # the parent is the next supernode (s is its last child): U_s stays in this front
        elif size > pivots:  # push U_s
            dim = size - pivots
            offset[s] = top
            for r in range(dim):
                for j in range(3 * (r // 3) + 3):
                    stack[top + r * dim + j] = f[pivots + r, pivots + j]
            top += dim * dim
            waiting[depth] = s
            depth += 1
    state[0], state[1] = depth, top
    return negative


@numba.njit(**JIT)
def factor_ranges(values, bp, bi, bpos, start, fp, fn, children, lp, lx, dinv, begins, ends,
                  stack, offset, waiting, state, position, buffers, wt):
    """:func:`factor_range` over the ranges ``begins[i] .. ends[i] - 1`` in turn, on one stack:
    the negative eigenvalues of all their pivots, or -1 if a zero pivot stopped it."""
    negative = 0
    for i in range(begins.size):
        count = factor_range(values, bp, bi, bpos, start, fp, fn, children, lp, lx, dinv, begins[i], ends[i],
                             stack, offset, waiting, state, position, buffers, wt)
        if count < 0:
            return -1
        negative += count
    return negative


@numba.njit(**JIT)
def factor_top(values, bp, bi, bpos, start, fp, fn, children, lp, lx, dinv, begins, ends,
               a_stack, a_offset, a_waiting, a_state, b_stack, b_offset, b_waiting, b_state,
               stack, offset, waiting, state, position, buffers, wt):
    """:func:`factor_ranges` over the top of the tree (``begins``, ``ends``: runs of its
    supernodes), after two threads factored the subtrees below it on stacks ``a`` and ``b``.

    Before each run the update matrices of the subtrees' roots that come before it in the
    postorder are moved from the bottoms of the two stacks to the top of ``stack``, in the
    order of their supernodes: so ``stack`` holds, supernode by supernode, what the
    sequential factorisation's stack holds.  Returns the negative eigenvalues of the top's
    pivots, or -1.
    """
    ia, ib, negative = 0, 0, 0
    for i in range(begins.size):
        depth, top = state[0], state[1]
        while True:
            take_a = ia < a_state[0] and a_waiting[ia] < begins[i]
            take_b = ib < b_state[0] and b_waiting[ib] < begins[i]
            if not (take_a or take_b):
                break
            if take_a and (not take_b or a_waiting[ia] < b_waiting[ib]):
                s, src, at = a_waiting[ia], a_stack, a_offset[a_waiting[ia]]
                end = a_offset[a_waiting[ia + 1]] if ia + 1 < a_state[0] else a_state[1]
                ia += 1
            else:
                s, src, at = b_waiting[ib], b_stack, b_offset[b_waiting[ib]]
                end = b_offset[b_waiting[ib + 1]] if ib + 1 < b_state[0] else b_state[1]
                ib += 1
            stack[top:top + end - at] = src[at:end]
            offset[s] = top
            waiting[depth] = s
            depth += 1
            top += end - at
        state[0], state[1] = depth, top
        count = factor_ranges(values, bp, bi, bpos, start, fp, fn, children, lp, lx, dinv, begins[i:i + 1],
                              ends[i:i + 1], stack, offset, waiting, state, position, buffers, wt)
        if count < 0:
            return -1
        negative += count
    return negative
