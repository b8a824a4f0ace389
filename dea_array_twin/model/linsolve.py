"""Sparse ``LDL^T`` factorisations of the free-free tangent ``K_ff``, with symbolic reuse.

Every tangent of one model has the same sparsity pattern, so the fill-reducing
ordering, the elimination tree and the map from the tangent's nonzeros to the
factor's input are computed once per set of free dofs (:class:`Factoriser`), and each
new tangent costs only the numeric factorisation.

The factorisation is ``P K_ff P^T = L D L^T`` with unit lower-triangular ``L`` and
block-diagonal ``D`` (no pivoting beyond the symmetric ordering).  By Sylvester's law
of inertia ``D`` has as many negative eigenvalues as ``K_ff``, so the stability check
(``K_ff`` positive definite: a stable minimum) is a count of negative pivots.

Back ends:

* ``"block"`` (the default): :mod:`.multifrontal`, compiled, on the 3x3 node blocks
  of ``K_ff`` in a minimum-degree node ordering (SuperLU's MMD on the node graph, once,
  then an elimination-tree postorder) with relaxed supernodes; dense fronts, the inertia
  from the 3x3 pivots as it runs.  Where it pays, the subtrees below the top of the
  elimination tree are dealt to two threads, then the top is factored on their update
  matrices (:meth:`Factoriser.factor`, ``NewtonSettings.factor_threads``): the same
  arithmetic in the same order, so the same factors to the bit.
* ``"block-uplooking"``: the same factorisation one 3x3 block at a time (:mod:`.ldl`,
  the up-looking algorithm of QDLDL): the reference the tests compare ``"block"``
  with.  On the default 1-by-3 mesh it factors in about 0.4x and solves in about 0.4x
  the time of QDLDL's scalar LDL^T; ``"block"`` takes about the same on the 1-by-3 and
  less on larger arrays (``benchmarks/bench_core.py --arrays``).
* ``"superlu"`` (scipy): SuperLU with a symmetric minimum-degree ordering and
  diagonal pivots (``diag_pivot_thresh = 0``), an ``LDL^T`` in disguise whose ``U``
  diagonal is ``D``; if it had to pivot off the diagonal the inertia is unknown (-1).
  No symbolic reuse.  Also the fallback of the block back ends when an exactly zero pivot
  stops it, or when the free dofs are not whole nodes.
"""

from __future__ import annotations

import threading
import weakref
from concurrent.futures import ThreadPoolExecutor

import numpy as np
import scipy.sparse as sp
import scipy.sparse.linalg as spla

from . import ldl, multifrontal
from .assembly import SparsePattern

BACKENDS = ("block", "block-uplooking", "superlu")

#: Factorisers per pattern (shared by the twins of one geometry, see
#: ``membrane._PATTERNS``) and set of free dofs: the symbolic analysis is pure data.
_FACTORISERS: "weakref.WeakKeyDictionary[SparsePattern, dict]" = weakref.WeakKeyDictionary()
_FACTORISERS_LOCK = threading.Lock()
#: A factorisation runs on two threads when that is predicted to take at most this share of the
#: time on one (:meth:`Factoriser._subtrees`).
PARALLEL_SHARE = 0.85
#: Supernodes below which a factorisation stays on one thread (a thread hand-over costs ~0.1 ms).
PARALLEL_MIN_SUPERNODES = 200
#: Supernodes moved to the top of the tree at most while looking for the best split (on the 1-by-3,
#: 4-by-4 and 8-by-8 the best came within 16; each costs a sort, ~0.1 ms on the 1-by-3).
MAX_TOP_SUPERNODES = 32
_SUBTREE_POOL: ThreadPoolExecutor | None = None
_SUBTREE_POOL_LOCK = threading.Lock()


def _subtree_pool() -> ThreadPoolExecutor:
    """The worker thread that factors the second thread's subtrees (made on first use, shared by all
    factorisers)."""
    global _SUBTREE_POOL
    with _SUBTREE_POOL_LOCK:
        if _SUBTREE_POOL is None:
            _SUBTREE_POOL = ThreadPoolExecutor(1, thread_name_prefix="ldl-subtree")
        return _SUBTREE_POOL


def factoriser(pattern: SparsePattern, free: np.ndarray, backend: str = "block") -> "Factoriser":
    """The :class:`Factoriser` of ``free`` on ``pattern``, made once (a few of the newest kept).

    Thread-safe: a twin's background tangents (:class:`.twin.ArrayTwin`) ask for it from a
    worker thread while the solver's thread may be adding or evicting an entry."""
    key = (free.tobytes(), backend)
    with _FACTORISERS_LOCK:
        cache = _FACTORISERS.setdefault(pattern, {})
        if key not in cache:
            if len(cache) >= 8:  # unit modes rarely change
                cache.pop(next(iter(cache)))
            cache[key] = Factoriser(pattern, free, backend)
        return cache[key]


class LDLFactor:
    """The numeric factor of one ``K_ff``: ``solve`` and the inertia."""

    def __init__(self, solve, negative: int):
        self._solve = solve
        self._negative = negative

    def solve(self, b: np.ndarray) -> np.ndarray:
        """``K_ff^-1 b``."""
        return self._solve(b)

    def negative_pivots(self) -> int:
        """Number of negative eigenvalues of ``K_ff``, -1 if unknown."""
        return self._negative() if callable(self._negative) else self._negative


class Factoriser:
    """Factorisations of ``K_ff`` for one set of free dofs on a fixed pattern.

    Parameters
    ----------
    pattern : SparsePattern
        The global tangent's pattern.
    free : ndarray
        Sorted free dof numbers.
    backend : str
        ``"block"``, ``"block-uplooking"`` or ``"superlu"`` (see the module docstring).
    """

    def __init__(self, pattern: SparsePattern, free: np.ndarray, backend: str = "block"):
        if backend not in BACKENDS:
            raise ValueError(f"linear solver must be one of {BACKENDS}, got {backend!r}")
        self.pattern, self.free = pattern, free
        nodes = free[::3] // 3
        whole_nodes = free.size % 3 == 0 and np.array_equal(free, (3 * nodes[:, None] + np.arange(3)).ravel())
        self.backend = backend if whole_nodes else "superlu"
        if self.backend != "superlu":
            self._symbolic(nodes)

    def _symbolic(self, nodes: np.ndarray) -> None:
        """Node ordering, elimination tree, supernodes, fronts and value maps (once per free set)."""
        pattern, n = self.pattern, nodes.size
        index = np.full(pattern.n_dofs // 3, -1)
        index[nodes] = np.arange(n)
        rows, cols = index[pattern.rows // 3], index[pattern.cols // 3]
        inside = (rows >= 0) & (cols >= 0)
        graph = sp.csc_matrix((np.ones(np.count_nonzero(inside)), (rows[inside], cols[inside])), shape=(n, n))
        graph.sum_duplicates()
        graph.data[:] = 1.0
        # Minimum-degree ordering of the node graph (diagonally dominant, so SuperLU keeps
        # its symmetric ordering), then a postorder of its elimination tree (the same fill;
        # the multifrontal stack needs it): block row i of the factor is node order[i].
        lu = spla.splu((graph + 10.0 * sp.eye(n)).tocsc(), permc_spec="MMD_AT_PLUS_A", diag_pivot_thresh=0.0,
                       options={"SymmetricMode": True})
        order = np.argsort(lu.perm_c)
        ap, ai = self._upper(graph, order)
        order = order[multifrontal.postorder(ldl.elimination_tree(n, ap, ai)[0])]
        ap, ai = self._upper(graph, order)
        parent, counts = ldl.elimination_tree(n, ap, ai)
        # The up-looking back end reads the upper triangle, the multifrontal one the lower (the
        # pattern is symmetric: either has all nine entries of its blocks when the other has).
        if self.backend == "block-uplooking":
            bp, bi = ap, ai
        else:
            lower = sp.tril(graph[order][:, order], format="csc")
            lower.sort_indices()
            bp, bi = lower.indptr.astype(np.int64), lower.indices.astype(np.int64)
        positions = self._positions(nodes[order], bp, bi)
        if positions is None:
            self.backend = "superlu"  # a node pair coupled in some components only: not 3x3 blocks
            return
        lp = np.concatenate([[0], np.cumsum(counts)]).astype(np.int64)
        self._n, self._order, self._lp = n, order.astype(np.int64), lp
        if self.backend == "block-uplooking":
            self._ap, self._ai, self._parent, self._position = ap, ai, parent, positions
            return
        # Supernodes: column j joins j - 1 when j is j - 1's parent and only child and
        # its pattern is j - 1's without row j.
        children = np.bincount(parent[parent >= 0], minlength=n)
        j = np.arange(1, n)
        joins = (parent[j - 1] == j) & (counts[j] == counts[j - 1] - 1) & (children[j] == 1)
        start = multifrontal.amalgamate(np.concatenate([[0], j[~joins], [n]]).astype(np.int64), counts, parent)
        li = multifrontal.row_pattern(n, ap, ai, parent, lp)
        fp, fn, front_children, stack_size, largest, self._lp, self._li = multifrontal.fronts(start, lp, li, parent)
        self._frontal = (bp, bi, positions, start, fp, fn, front_children, self._lp)
        self._sizes = (int(stack_size), int(largest))
        self._split = self._subtrees(start, fp, fn)

    @staticmethod
    def _subtrees(start: np.ndarray, fp: np.ndarray, fn: np.ndarray) -> tuple | None:
        """Ranges of supernodes ``(begins, ends)`` for each of two threads, then those of the top of the
        tree for one thread after both, and the stack room a thread's subtrees' update matrices
        need besides the sequential factorisation's (they all wait for the top); None if that
        gains too little.

        Subtrees of the elimination tree are ranges of the postorder.  Starting from the whole
        tree, the heaviest subtree's root is moved to the top, one at a time (its children's
        subtrees join the others), and the subtrees are dealt to the two threads heaviest
        first to the less loaded; a supernode's work is taken as ``ncol m^2`` (``m`` its
        front's nodes).  Of these partitions, the one with the least ``max(W_1, W_2) +
        W_top`` is kept if that is at most :data:`PARALLEL_SHARE` of the whole.
        """
        n_super = start.size - 1
        if n_super < PARALLEL_MIN_SUPERNODES:
            return None
        ncol, m = np.diff(start), np.diff(fp)
        work = ncol * m.astype(float) ** 2
        supernode = np.repeat(np.arange(n_super), ncol)
        has_parent = m > ncol
        parent = np.full(n_super, -1)
        parent[has_parent] = supernode[fn[fp[:-1][has_parent] + ncol[has_parent]]]
        subtree, count = work.copy(), np.ones(n_super, np.int64)
        kids: list[list[int]] = [[] for _ in range(n_super)]
        for s in range(n_super):  # children come before their parent
            if parent[s] >= 0:
                subtree[parent[s]] += subtree[s]
                count[parent[s]] += count[s]
                kids[parent[s]].append(s)
        total = work.sum()
        roots, top_work, best = [int(s) for s in np.flatnonzero(parent < 0)], 0.0, None
        for _ in range(MAX_TOP_SUPERNODES):
            roots.sort(key=lambda s: -subtree[s])
            loads, dealt = [0.0, 0.0], ([], [])
            for s in roots:  # heaviest first to the less loaded thread
                k = int(loads[1] < loads[0])
                loads[k] += subtree[s]
                dealt[k].append(s)
            time = max(loads) + top_work
            if best is None or time < best[0]:
                best = (time, [sorted(d) for d in dealt])
            heaviest = roots.pop(0)
            top_work += work[heaviest]
            roots.extend(kids[heaviest])
            if not roots:
                break
        time, dealt = best
        if time > PARALLEL_SHARE * total or not all(dealt):
            return None
        below = np.zeros(n_super, bool)
        threads = []
        for d in dealt:
            begins = np.array([s - count[s] + 1 for s in d], np.int64)
            ends = np.array(d, np.int64) + 1
            for b, e in zip(begins, ends):
                below[b:e] = True
            threads.append((begins, ends))
        top = np.flatnonzero(~below)  # runs of consecutive supernodes of the top
        cuts = np.flatnonzero(np.diff(top) > 1) + 1
        runs = (top[np.concatenate([[0], cuts])].astype(np.int64),
                top[np.concatenate([cuts - 1, [top.size - 1]])].astype(np.int64) + 1)
        roots = np.concatenate(dealt)
        return threads[0], threads[1], runs, int(((3 * (m[roots] - ncol[roots])) ** 2).sum())

    @staticmethod
    def _upper(graph: sp.csc_matrix, order: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Upper triangle's block pattern (CSC) of ``graph`` in ``order``."""
        upper = sp.triu(graph[order][:, order], format="csc")
        upper.sort_indices()
        return upper.indptr.astype(np.int64), upper.indices.astype(np.int64)

    def _positions(self, nodes: np.ndarray, bp: np.ndarray, bi: np.ndarray) -> np.ndarray | None:
        """Position in the pattern's nonzeros of entry (a, c) of block (bi[p], column of p), shape (nnz, 3, 3).

        None when a node pair is coupled in some components only (not 3x3 blocks).

        The nonzeros are sorted by row, then column, so only each block's first entry is
        searched for: with whole 3x3 blocks, rows ``3 i + a`` of one node hold the same
        columns, and entry ``(a, c)`` is ``a`` row lengths and ``c`` places after it.  That
        every entry is where this says is then checked (on the 8-by-8, searching for all
        nine took 0.4 s of each call).
        """
        pattern = self.pattern
        n_dofs = pattern.n_dofs
        col = np.repeat(np.arange(bp.size - 1), np.diff(bp))
        keys = pattern.rows * n_dofs + pattern.cols
        row_start = np.searchsorted(pattern.rows, np.arange(n_dofs + 1))
        r0, c0 = 3 * nodes[bi], 3 * nodes[col]
        first = np.searchsorted(keys, r0 * n_dofs + c0)
        stride = row_start[r0 + 1] - row_start[r0]
        position = (first[:, None, None] + stride[:, None, None] * np.arange(3)[None, :, None]
                    + np.arange(3)[None, None, :])
        wanted = ((r0[:, None, None] + np.arange(3)[None, :, None]) * n_dofs
                  + c0[:, None, None] + np.arange(3)[None, None, :])
        if np.any(position >= keys.size) or np.any(keys[np.minimum(position, keys.size - 1)] != wanted):
            return None
        return position

    def factor(self, values: np.ndarray, threads: int = 2) -> LDLFactor:
        """Factor ``K_ff`` of the pattern's nonzeros ``values`` (``"block"``: on two threads where it pays
        and ``threads`` is 2, with the same arithmetic, so the same factors to the last bit)."""
        if self.backend == "superlu":
            return self._superlu(values)
        n, lp = self._n, self._lp
        lx, dinv = np.empty((lp[-1], 3, 3)), np.empty((n, 3, 3))
        if self.backend == "block":
            li = self._li
            negative = self._multifrontal(values, lx, dinv, threads)
        else:
            li = np.empty(lp[-1], np.int64)
            negative = ldl.factor(n, self._ap, self._ai, values[self._position], lp, self._parent, li, lx, dinv)
        if negative < 0:
            return self._superlu(values)  # a zero pivot stopped the block factorisation
        order = self._order

        def solve(b: np.ndarray) -> np.ndarray:
            x = np.empty(b.size)
            ldl.solve(n, lp, li, lx, dinv, order, np.ascontiguousarray(b, dtype=float), x)
            return x

        return LDLFactor(solve, negative)

    def _multifrontal(self, values: np.ndarray, lx: np.ndarray, dinv: np.ndarray, threads: int) -> int:
        """:func:`.multifrontal.factor_ranges` over all supernodes; with a split and two threads, the
        subtrees of one thread on the worker thread beside those of the other here, then the top of
        the tree here (:func:`.multifrontal.factor_top`)."""
        start = self._frontal[3]
        n_super = start.size - 1
        args = (values, *self._frontal, lx, dinv)
        if self._split is None or threads < 2:
            whole = np.array([0], np.int64), np.array([n_super], np.int64)
            return multifrontal.factor_ranges(*args, *whole, *multifrontal.workspace(self._n, n_super, *self._sizes))
        a, b, top, extra = self._split
        stack_size, largest = self._sizes
        mine, other = (multifrontal.workspace(self._n, n_super, stack_size + extra, largest) for _ in range(2))
        subtrees = _subtree_pool().submit(multifrontal.factor_ranges, *args, *b, *other)
        negative = [multifrontal.factor_ranges(*args, *a, *mine), subtrees.result()]
        negative.append(multifrontal.factor_top(*args, *top, *mine[:4], *other[:4],
                                                *multifrontal.workspace(self._n, n_super, stack_size, largest)))
        return -1 if min(negative) < 0 else sum(negative)

    def _superlu(self, values: np.ndarray) -> LDLFactor:
        k_ff = self.pattern.block(values, self.free, self.free).tocsc()  # symmetric: CSR data is CSC
        lu = spla.splu(k_ff, permc_spec="MMD_AT_PLUS_A", diag_pivot_thresh=0.0, options={"SymmetricMode": True})

        def negative() -> int:
            if not np.array_equal(lu.perm_r, lu.perm_c):
                return -1
            return int(np.count_nonzero(lu.U.diagonal() < 0))

        return LDLFactor(lu.solve, negative)
