"""Compiled (numba) element loops for the residual and the tangent: the solver's hot path.

The same equations as the numpy reference in :mod:`.assembly` (which the tests compare
these against to 1e-12 relative), written as loops that keep every intermediate in
registers or small buffers instead of arrays of shape ``(ne, nq, ...)``, on blocks of
elements whose loops run over the block's elements so that the compiler vectorises
them (the gradients stored by blocks).  With ``F = [F1 F2]`` (3x2), ``g = dPsi/dc``, ``H = d2Psi/dc2``
(:mod:`.material`) and the reference gradients ``dN_a = (dN_a1, dN_a2)``:

    r_a  = t0 sum_q w_q  F S dN_a,            S = [[2 g0, g2], [g2, 2 g1]],
    K_ab = t0 sum_q w_q (F M_ab F^T + (dN_a . S dN_b) I_3),
    M_ab = T_a^T H T_b,                       T_a = [[2 dN_a1, 0], [0, 2 dN_a2], [dN_a2, dN_a1]],

which is ``B_a^T H B_b`` of :mod:`.assembly` with ``B_a = T_a F^T`` (each row of
``B_a`` is a combination of ``F1`` and ``F2``).  The tangent is summed straight into
the nonzeros of the global :class:`~.assembly.SparsePattern`, so no element matrices
are stored.

Compiled on first use and cached on disk (``cache=True``) next to this module, so a
new process loads them in well under a second; ``nogil=True`` lets other Python
threads (the ROS executor) run during a solve.
"""

from __future__ import annotations

import numba
import numpy as np

from .assembly import LANES, Discretisation, PointState, SparsePattern
from .material import Yeoh

#: Options of every compiled kernel of the model (cached on disk, the GIL released, numpy's error model).
JIT = {"cache": True, "nogil": True, "error_model": "numpy"}


@numba.njit(inline="always", **JIT)
def _gather(x, elements, e0, width, xb):
    """``xb[n, i, j]``: coordinate ``i`` of node ``n`` of element ``e0 + j`` (``j < width``, the block's elements)."""
    for n in range(elements.shape[1]):
        for j in range(width):
            base = 3 * elements[e0 + j, n]
            for i in range(3):
                xb[n, i, j] = x[base + i]


@numba.njit(inline="always", **JIT)
def _deformation(xb, gb, q, width, f):
    """``f[2 i + a, j] = F_ia`` at point ``q`` of lane ``j``: ``sum_n x_ni dN_n/dX_a`` (``gb``: the block)."""
    f[:, :width] = 0.0
    for n in range(gb.shape[0]):
        for j in range(width):
            d0, d1 = gb[n, 0, q, j], gb[n, 1, q, j]
            for i in range(3):
                f[2 * i, j] += xb[n, i, j] * d0
                f[2 * i + 1, j] += xb[n, i, j] * d1


@numba.njit(inline="always", **JIT)
def _stress(f, j, c10, c20, c30, k):
    """``(c0, c1, c2, det C, Y', Y'', g0, g1, g2)`` of lane ``j`` of ``f``.

    ``c = (F1.F1, F2.F2, F1.F2)`` and ``g = Y' dI - k dJ2`` (with ``I = tr C + 1/det C``,
    :func:`.material.energy_gradient`).
    """
    c0 = f[0, j] * f[0, j] + f[2, j] * f[2, j] + f[4, j] * f[4, j]
    c1 = f[1, j] * f[1, j] + f[3, j] * f[3, j] + f[5, j] * f[5, j]
    c2 = f[0, j] * f[1, j] + f[2, j] * f[3, j] + f[4, j] * f[5, j]
    det = c0 * c1 - c2 * c2
    xi = c0 + c1 + 1.0 / det - 3.0
    dy = c10 + xi * (2.0 * c20 + 3.0 * c30 * xi)
    ddy = 2.0 * c20 + 6.0 * c30 * xi
    a = dy / det**2 + k
    return c0, c1, c2, det, dy, ddy, dy - a * c1, dy - a * c0, 2.0 * a * c2


@numba.njit(inline="always", **JIT)
def _add_forces(gb, q, width, f, s, rb):
    """``rb[n, i, j] += (F S dN_n)_i`` at point ``q`` (``s``: ``w S11, w S22, w S12`` per lane)."""
    for n in range(gb.shape[0]):
        for j in range(width):
            d0, d1 = gb[n, 0, q, j], gb[n, 1, q, j]
            sd0 = s[0, j] * d0 + s[2, j] * d1
            sd1 = s[2, j] * d0 + s[1, j] * d1
            for i in range(3):
                rb[n, i, j] += f[2 * i, j] * sd0 + f[2 * i + 1, j] * sd1


@numba.njit(inline="always", **JIT)
def _scatter(elements, e0, width, rb, r):
    """``r`` += the block's element forces ``rb``."""
    for n in range(elements.shape[1]):
        for j in range(width):
            base = 3 * elements[e0 + j, n]
            for i in range(3):
                r[base + i] += rb[n, i, j]


@numba.njit(**JIT)
def _residual(x, elements, grad, wt, maxwell, c10, c20, c30, r, c, g):
    """Fill ``r`` (zeroed here), ``c`` and ``g`` (shape (ne, nq, 3)) of positions ``x``.

    ``grad`` (n_blocks, nen, 2, nq, LANES) and ``wt`` (n_blocks, nq, LANES) are stored by
    blocks of ``LANES`` elements (:attr:`.assembly.Discretisation.grad_blocks`): a block is
    worked on at once, its loops running over the block's elements (1.7x the
    element-at-a-time loop on this machine's AVX-512), with the operations of each element in
    the same order; each block's gradients are one contiguous read.
    """
    nen, nq, ne = grad.shape[1], grad.shape[3], elements.shape[0]
    r[:] = 0.0
    xb = np.empty((nen, 3, LANES))
    rb = np.empty((nen, 3, LANES))
    f = np.empty((6, LANES))  # F11 F12 F21 F22 F31 F32 of each element of the block
    s = np.empty((3, LANES))  # w S11, w S22, w S12
    for block in range(grad.shape[0]):
        e0, gb = block * LANES, grad[block]
        width = min(LANES, ne - e0)
        _gather(x, elements, e0, width, xb)
        rb[:, :, :width] = 0.0
        for q in range(nq):
            _deformation(xb, gb, q, width, f)
            for j in range(width):
                e = e0 + j
                c0, c1, c2, _, _, _, g0, g1, g2 = _stress(f, j, c10, c20, c30, maxwell[e])
                c[e, q, 0], c[e, q, 1], c[e, q, 2] = c0, c1, c2
                g[e, q, 0], g[e, q, 1], g[e, q, 2] = g0, g1, g2
                w = wt[block, q, j]
                s[0, j], s[1, j], s[2, j] = 2.0 * g0 * w, 2.0 * g1 * w, g2 * w
            _add_forces(gb, q, width, f, s, rb)
        _scatter(elements, e0, width, rb, r)


@numba.njit(inline="always", **JIT)
def _add_row(values, at, v0, v1, v2):
    """``values[at:at + 3] += (v0, v1, v2)``: one row of a 3x3 node block."""
    values[at] += v0
    values[at + 1] += v1
    values[at + 2] += v2


@numba.njit(**JIT)
def _tangent(x, elements, grad, wt, maxwell, c10, c20, c30, position, r, c, g, values):
    """Fill ``r``, ``c``, ``g`` and the global tangent nonzeros ``values`` (zeroed here).

    ``grad`` and ``wt`` as in :func:`_residual` (by blocks of ``LANES`` elements).
    ``position[e, p, b]`` is the index into ``values`` of local dofs ``(p, 3 b)`` of
    element ``e`` (:attr:`.SparsePattern.element_block_positions`); the three columns of
    node ``b`` follow it.  First, per quadrature point, ``F``, ``S`` and ``H T_b`` of every
    node of the block's elements; then each upper node block ``K_ab`` is summed over the
    points (nine sums and the geometric term per element of the block) and added to
    ``values``, with its mirror ``K_ba = K_ab^T``.
    """
    nen, nq, ne = grad.shape[1], grad.shape[3], elements.shape[0]
    r[:] = 0.0
    values[:] = 0.0
    xb = np.empty((nen, 3, LANES))
    rb = np.empty((nen, 3, LANES))
    fq = np.empty((nq, 6, LANES))  # F at each point
    sq = np.empty((nq, 3, LANES))  # w S: (s00, s11, s01)
    ht = np.empty((nq, nen, 6, LANES))  # w H T_b: (0, 0) (1, 0) (2, 0) (0, 1) (1, 1) (2, 1)
    kb = np.empty((10, LANES))  # K_ab's nine entries and its geometric term, per element
    for block in range(grad.shape[0]):
        e0, gb = block * LANES, grad[block]
        width = min(LANES, ne - e0)
        _gather(x, elements, e0, width, xb)
        rb[:, :, :width] = 0.0
        for q in range(nq):
            f, sw = fq[q], sq[q]
            _deformation(xb, gb, q, width, f)
            for j in range(width):
                e = e0 + j
                k = maxwell[e]
                c0, c1, c2, det, dy, ddy, g0, g1, g2 = _stress(f, j, c10, c20, c30, k)
                c[e, q, 0], c[e, q, 1], c[e, q, 2] = c0, c1, c2
                g[e, q, 0], g[e, q, 1], g[e, q, 2] = g0, g1, g2
                w = wt[block, q, j]
                # H = Y'' dI dI^T + Y' 2 det^-3 dJ dJ^T - (Y' det^-2 + k) d2J  (material.energy_derivatives)
                inv2 = 1.0 / det**2
                dj0, dj1, dj2 = c1, c0, -2.0 * c2
                di0, di1, di2 = 1.0 - inv2 * dj0, 1.0 - inv2 * dj1, -inv2 * dj2
                b = 2.0 * dy * inv2 / det
                m = dy * inv2 + k
                h00 = ddy * di0 * di0 + b * dj0 * dj0
                h11 = ddy * di1 * di1 + b * dj1 * dj1
                h22 = ddy * di2 * di2 + b * dj2 * dj2 + 2.0 * m
                h01 = ddy * di0 * di1 + b * dj0 * dj1 - m
                h02 = ddy * di0 * di2 + b * dj0 * dj2
                h12 = ddy * di1 * di2 + b * dj1 * dj2
                sw[0, j], sw[1, j], sw[2, j] = 2.0 * g0 * w, 2.0 * g1 * w, g2 * w
                for n in range(nen):
                    dn0, dn1 = gb[n, 0, q, j], gb[n, 1, q, j]
                    a1, a2 = 2.0 * w * dn0, w * dn1  # alpha_n = (2 dN1, 0, dN2), times w
                    b1, b2 = 2.0 * w * dn1, w * dn0  # beta_n  = (0, 2 dN2, dN1), times w
                    ht[q, n, 0, j] = h00 * a1 + h02 * a2
                    ht[q, n, 1, j] = h01 * a1 + h12 * a2
                    ht[q, n, 2, j] = h02 * a1 + h22 * a2
                    ht[q, n, 3, j] = h01 * b1 + h02 * b2
                    ht[q, n, 4, j] = h11 * b1 + h12 * b2
                    ht[q, n, 5, j] = h12 * b1 + h22 * b2
            _add_forces(gb, q, width, f, sw, rb)
        _scatter(elements, e0, width, rb, r)
        for na in range(nen):
            for nb in range(na, nen):
                kb[:, :width] = 0.0
                for q in range(nq):
                    f, sw, hb = fq[q], sq[q], ht[q, nb]
                    for j in range(width):
                        da0, da1 = gb[na, 0, q, j], gb[na, 1, q, j]
                        db0, db1 = gb[nb, 0, q, j], gb[nb, 1, q, j]
                        m00 = 2.0 * da0 * hb[0, j] + da1 * hb[2, j]
                        m01 = 2.0 * da0 * hb[3, j] + da1 * hb[5, j]
                        m10 = 2.0 * da1 * hb[1, j] + da0 * hb[2, j]
                        m11 = 2.0 * da1 * hb[4, j] + da0 * hb[5, j]
                        s00, s11, s01 = sw[0, j], sw[1, j], sw[2, j]
                        kb[9, j] += (s00 * da0 + s01 * da1) * db0 + (s01 * da0 + s11 * da1) * db1
                        f00, f01, f10, f11, f20, f21 = f[0, j], f[1, j], f[2, j], f[3, j], f[4, j], f[5, j]
                        u00, u10 = m00 * f00 + m01 * f01, m10 * f00 + m11 * f01  # M F^T, column j = 0
                        u01, u11 = m00 * f10 + m01 * f11, m10 * f10 + m11 * f11
                        u02, u12 = m00 * f20 + m01 * f21, m10 * f20 + m11 * f21
                        kb[0, j] += f00 * u00 + f01 * u10
                        kb[1, j] += f00 * u01 + f01 * u11
                        kb[2, j] += f00 * u02 + f01 * u12
                        kb[3, j] += f10 * u00 + f11 * u10
                        kb[4, j] += f10 * u01 + f11 * u11
                        kb[5, j] += f10 * u02 + f11 * u12
                        kb[6, j] += f20 * u00 + f21 * u10
                        kb[7, j] += f20 * u01 + f21 * u11
                        kb[8, j] += f20 * u02 + f21 * u12
                for j in range(width):
                    e = e0 + j
                    geo = kb[9, j]
                    k00, k01, k02 = kb[0, j] + geo, kb[1, j], kb[2, j]
                    k10, k11, k12 = kb[3, j], kb[4, j] + geo, kb[5, j]
                    k20, k21, k22 = kb[6, j], kb[7, j], kb[8, j] + geo
                    _add_row(values, position[e, 3 * na, nb], k00, k01, k02)
                    _add_row(values, position[e, 3 * na + 1, nb], k10, k11, k12)
                    _add_row(values, position[e, 3 * na + 2, nb], k20, k21, k22)
                    if nb != na:  # the mirror block K_ba = K_ab^T
                        _add_row(values, position[e, 3 * nb, na], k00, k10, k20)
                        _add_row(values, position[e, 3 * nb + 1, na], k01, k11, k21)
                        _add_row(values, position[e, 3 * nb + 2, na], k02, k12, k22)


@numba.njit(**JIT)
def _min_principal_stress(c, g, skip):
    """Smallest in-plane principal Cauchy stress over the points of elements not ``skip``-ped.

    :func:`.material.principal_cauchy_stresses`: the eigenvalues of ``m = C S``,
    ``tr m / 2 - sqrt(((m00 - m11) / 2)^2 + m01 m10)``.
    """
    ne, nq, _ = c.shape
    low = np.inf
    for e in range(ne):
        if skip[e]:
            continue
        for q in range(nq):
            c0, c1, c2 = c[e, q, 0], c[e, q, 1], c[e, q, 2]
            s00, s11, s01 = 2.0 * g[e, q, 0], 2.0 * g[e, q, 1], g[e, q, 2]
            m00, m01 = c0 * s00 + c2 * s01, c0 * s01 + c2 * s11
            m10, m11 = c2 * s00 + c1 * s01, c2 * s01 + c1 * s11
            half = 0.5 * (m00 - m11)
            value = 0.5 * (m00 + m11) - np.sqrt(max(half * half + m01 * m10, 0.0))
            low = min(low, value)
    return low


@numba.njit(**JIT)
def _energy(c, wt, maxwell, c10, c20, c30):
    """``sum_q t0 w_q Psi(c_q)`` with ``Psi = Y(I - 3) - k det C`` (:func:`.material.energy_density`)."""
    ne, nq, _ = c.shape
    total = 0.0
    for e in range(ne):
        for q in range(nq):
            det = c[e, q, 0] * c[e, q, 1] - c[e, q, 2] ** 2
            xi = c[e, q, 0] + c[e, q, 1] + 1.0 / det - 3.0
            total += wt[e, q] * (xi * (c10 + xi * (c20 + xi * c30)) - maxwell[e] * det)
    return total


@numba.njit(**JIT)
def _electrode_sums(c, weight, element_unit, area, peak):
    """Per unit ``k``: ``area[k] = sum_q w_q det C_q`` and ``peak[k] = max_q det C_q`` over the points of
    the elements with ``element_unit == k`` (passive ones, -1, skipped)."""
    area[:] = 0.0
    peak[:] = -np.inf
    ne, nq, _ = c.shape
    for e in range(ne):
        k = element_unit[e]
        if k < 0:
            continue
        for q in range(nq):
            det = c[e, q, 0] * c[e, q, 1] - c[e, q, 2] ** 2
            area[k] += weight[e, q] * det
            peak[k] = max(peak[k], det)


def electrode_sums(disc: Discretisation, point: PointState, n_units: int) -> tuple[np.ndarray, np.ndarray]:
    """Per unit: ``sum_q w_q det C_q`` over its electrode (the deformed area in the reference
    thickness's units, eq. 7's integral) [m^2] and the largest ``det C`` there [-]."""
    area, peak = np.empty(n_units), np.empty(n_units)
    _electrode_sums(point.c, disc.weight, disc.mesh.element_unit, area, peak)
    return area, peak


@numba.njit(**JIT)
def solve_small(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """``a^-1 b`` for small dense systems (the biased heights' ``n_b x n_b``, :mod:`.indenters`):
    LAPACK's gesv as in ``np.linalg.solve``, whose call costs ~10 us from Python, several times
    the solve itself.  Raises ``numpy.linalg.LinAlgError`` if ``a`` is singular."""
    return np.linalg.solve(a, b)


def min_principal_stress(point: PointState, skip: np.ndarray) -> float:
    """Smallest principal Cauchy stress [Pa] over the elements where ``skip`` is False."""
    return float(_min_principal_stress(point.c, point.g, skip))


def energy(disc: Discretisation, point: PointState, yeoh: Yeoh, maxwell: np.ndarray, thickness: float) -> float:
    """Stored energy ``t0 sum_q w_q Psi`` [J] of a point state; ``maxwell`` per element [Pa]."""
    return float(_energy(point.c, thickness * disc.weight, maxwell, yeoh.c10, yeoh.c20, yeoh.c30))


def internal_forces(disc: Discretisation, x: np.ndarray, yeoh: Yeoh, maxwell: np.ndarray,
                    thickness: float) -> tuple[np.ndarray, PointState]:
    """Compiled :func:`.assembly.internal_forces`: internal forces [N] and the point state."""
    ne, nq = disc.weight.shape
    r = np.empty(disc.n_dofs)
    c, g = np.empty((ne, nq, 3)), np.empty((ne, nq, 3))
    grad, weight = disc.grad_blocks
    _residual(x, disc.mesh.elements, grad, thickness * weight, maxwell, yeoh.c10, yeoh.c20, yeoh.c30, r, c, g)
    return r, PointState(c, g)


def tangent_values(disc: Discretisation, pattern: SparsePattern, x: np.ndarray, yeoh: Yeoh,
                   maxwell: np.ndarray, thickness: float) -> tuple[np.ndarray, np.ndarray]:
    """Internal forces [N] and the global tangent's nonzeros [N/m] in ``pattern`` order.

    The compiled form of ``pattern.values(element_tangents(...)[1])`` (:mod:`.assembly`).
    """
    ne, nq = disc.weight.shape
    r = np.empty(disc.n_dofs)
    c, g = np.empty((ne, nq, 3)), np.empty((ne, nq, 3))
    values = np.empty(pattern.rows.size)
    grad, weight = disc.grad_blocks
    _tangent(x, disc.mesh.elements, grad, thickness * weight, maxwell, yeoh.c10, yeoh.c20, yeoh.c30,
             pattern.element_block_positions, r, c, g, values)
    return r, values
