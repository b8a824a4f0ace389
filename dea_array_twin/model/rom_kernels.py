"""The reduced model's energy, gradient and Hessian summed over its sampled quadrature points.

The reduced state is ``x = x_ref + sum_k d_k L_k + V q + W w`` (:mod:`.reduced`): the
flat pre-stretched membrane, one lifting vector per driven indenter, the POD basis
``V`` and, for the error indicator only, enrichment vectors ``W`` (``w = 0`` in the
state).  At a quadrature point ``p`` the deformation gradient is linear in the
coefficients, ``F_p = A_p [1, d, q]`` (``A_p``: 6 x (1 + nd + r), :func:`point_maps`),
and the hyper-reduced energy is the weighted sum (energy-conserving sampling and
weighting, ECSW)

    E(d, q, m) = sum_p xi_p Psi(C_p, m_u(p)),       xi_p >= 0 (t0 times area times ECSW weight),

with ``Psi = Y(tr C + 1/det C - 3) - m det C`` (:mod:`.material`) and ``m_u`` the
Maxwell coefficient ``0.5 eps (V_u/t0)^2`` of the point's unit.  Its gradient is

    dE/dz_j = sum_p xi_p P_p : A_p[:, j],        P = F S (first Piola-Kirchhoff, 3x2),
    dE/dm_u = - sum_(p in u) xi_p det C_p,

so ``dE/dq`` is the reduced residual, ``dE/dd_k`` the energy-consistent indenter force
(paper eq. 10) and ``-dE/dm_u`` the electrode's ``t0 integral det C dA0``, which is the
capacitance (eq. 7) times ``t0^2 / eps``.  The Hessian is

    d2E/dz_i dz_j = sum_p xi_p A_p[:, i]^T D_p A_p[:, j],
    D = B^T H B + S (x) I_3,   B = dc/dF (3 x 6),  H = d2Psi/dc2,
    d2E/dz_j dm_u = - sum_(p in u) xi_p ddet/dF : A_p[:, j].

:func:`evaluate` (numba) gives energy, gradient, the gradient
along ``W``, the largest ``det C`` per unit and the smallest principal Cauchy stress
over the evaluated points, in float64 arithmetic; :func:`update` does the same (one or two
evaluations) with the map products in float32 when the maps are float32 (an update is bound
by them: half the operations per vector instruction), the stresses and the sums over the
points in float64; :func:`hessian` (when the tangent is refreshed) gives the
full Hessian over ``[q, d, w]`` and its ``m`` columns, and :func:`reduced_tangent` what
an update needs from it (``H_qq^-1``, the predictor's sensitivities, the output rows and
the indicator's matrix) in the same compiled call chain, without numpy's per-call cost.
"""

from __future__ import annotations

import numba
import numpy as np

from .assembly import Discretisation
from .atomics import atomic_load, atomic_store, compare_and_swap, fetch_add
from .kernels import JIT
from .material import Yeoh, energy_derivatives

_JIT = {**JIT, "fastmath": {"reassoc", "contract"}}


def point_maps(disc: Discretisation, elements: np.ndarray, points: np.ndarray, vectors: np.ndarray) -> np.ndarray:
    """``A_p``: the deformation gradient at points ``(elements[i], points[i])`` of each column of ``vectors``.

    Parameters
    ----------
    disc : Discretisation
    elements, points : ndarray of int, shape (n,)
        Element and quadrature point of each sampled point.
    vectors : ndarray, shape (n_dofs, k)
        Position vectors (node-major, 3 per node).

    Returns
    -------
    ndarray, shape (n, 6, k)
        ``F[i, alpha] = sum_a vectors[3 n_a + i] dN_a/dX_alpha``, flattened as ``2 i + alpha``.
    """
    nodes = disc.mesh.elements[elements]  # (n, nen)
    u = vectors.reshape(-1, 3, vectors.shape[1])[nodes]  # (n, nen, 3, k)
    grad = disc.grad[elements, points]  # (n, nen, 2)
    f = np.einsum("naik,nab->nibk", u, grad)  # (n, 3, 2, k)
    return np.ascontiguousarray(f.reshape(len(elements), 6, vectors.shape[1]))


@numba.njit(inline="always", **_JIT)
def _state(fmap, p, z, f, c10, c20, c30, k):
    """``F = A_p z`` into ``f``; returns ``(c0, c1, c2, det C, x = I - 3, Y'(x), g0, g1, g2)`` at point ``p``."""
    for c in range(6):
        acc = 0.0
        for j in range(fmap.shape[2]):
            acc += fmap[p, c, j] * z[j]
        f[c] = acc
    return _stress(f, c10, c20, c30, k)


@numba.njit(inline="always", **_JIT)
def _state_single(fmap, p, z32, f, c10, c20, c30, k):
    """:func:`_state` with ``F = A_p z`` summed in float32 (``z32``: ``z`` in float32)."""
    for c in range(6):
        acc = np.float32(0.0)
        for j in range(fmap.shape[2]):
            acc += fmap[p, c, j] * z32[j]
        f[c] = acc
    return _stress(f, c10, c20, c30, k)


@numba.njit(inline="always", **_JIT)
def _stress(f, c10, c20, c30, k):
    """``(c0, c1, c2, det C, x = I - 3, Y'(x), g0, g1, g2)`` of ``F = f`` (the second Piola-Kirchhoff stress is
    ``S = [[2 g0, g2], [g2, 2 g1]]``)."""
    c0 = f[0] * f[0] + f[2] * f[2] + f[4] * f[4]
    c1 = f[1] * f[1] + f[3] * f[3] + f[5] * f[5]
    c2 = f[0] * f[1] + f[2] * f[3] + f[4] * f[5]
    det = c0 * c1 - c2 * c2
    xv = c0 + c1 + 1.0 / det - 3.0
    dy = c10 + xv * (2.0 * c20 + 3.0 * c30 * xv)
    a = dy / det**2
    return c0, c1, c2, det, xv, dy, dy - (a + k) * c1, dy - (a + k) * c0, 2.0 * (a + k) * c2


#: Points whose contributions an evaluation sums in float32 before adding them to its float64 sums
#: (``single``): the rounding of a block's sum stays that of a few products.
SINGLE_BLOCK = 16

#: Points an evaluation hands out at a time (a multiple of :data:`SINGLE_BLOCK`): each chunk's sums are its
#: own, added in chunk order, so the outputs do not depend on which thread of a team
#: (:class:`.point_team.PointTeam`) evaluated which chunk.
CHUNK = 64

# A team's arrays (:func:`team_arrays`): ``control`` entries
_GENERATION, _KIND, _SINGLE, _HELPED, _TAKEN, _WAIT, _RUNNING, _LINGER = 0, 1, 2, 3, 4, 5, 6, 7
TEAM_CONTROL = 8
# ... the kinds of pass (the job of a generation)
_GRADIENT, _GRADIENT_DEFER, _ENRICHMENT = 1, 2, 3
# ... a chunk's state in generation g: 16 g + code; code 0 free, 1 + t claimed by thread t (0: the caller),
# 8 + t finished by helper t
_CLAIMED, _FINISHED = 1, 8


def team_arrays(n_threads: int, n_points: int, nc: int, nw: int, n_units: int) -> tuple:
    """The arrays through which ``n_threads`` threads (the caller and its helpers) share an evaluation's points.

    Returns ``(control, state, partial, stress, winner, job_z, job_z32, job_m)``: counters and the
    published pass (int64), each chunk's state (int64), each thread's sums per chunk, each thread's
    weighted stresses per point, the thread whose sums a chunk's result is, and the pass's ``z`` (float64
    and float32) and Maxwell coefficients.
    """
    chunks = -(-n_points // CHUNK)
    width = nc + nw + 2 * n_units + 2
    return (np.zeros(TEAM_CONTROL, dtype=np.int64), np.zeros(chunks, dtype=np.int64),
            np.zeros((n_threads, chunks, width)), np.zeros((n_threads, n_points, 6)),
            np.zeros(chunks, dtype=np.int64), np.zeros(nc), np.zeros(nc, dtype=np.float32), np.zeros(n_units))


@numba.njit(**_JIT)
def _chunk_gradient(fmap, wmap, xi, unit, held, z, z32, maxwell, c10, c20, c30, lo, hi, single, defer, row,
                    stress):
    """Points ``lo:hi`` of an evaluation into ``row = [grad, grad_w, grad_m, det_max, energy, sigma_min]``;
    with ``single``, the map products (``F = A_p z`` and ``A_p^T P``, nearly all the work) in float32
    arithmetic (twice the lanes of a vector instruction), the stress and the sums over blocks of
    :data:`SINGLE_BLOCK` points in float64.  With ``defer`` the gradient along ``W`` is left for
    :func:`_chunk_enrichment`: each point's weighted stress ``P`` goes into its row of ``stress`` instead
    (monitor points' rows: zeros)."""
    nc = fmap.shape[2]
    nw = wmap.shape[2]
    nu = maxwell.size
    om, od = nc + nw, nc + nw + nu
    row[:] = 0.0
    grad = row[:nc]
    grad_w = row[nc:om]
    energy = 0.0
    sigma_min = np.inf
    f = np.empty(6)
    g32 = np.zeros(nc if single else 0, dtype=np.float32)
    gw32 = np.zeros(nw if single and not defer else 0, dtype=np.float32)
    block = 0
    for p in range(lo, hi):
        u = unit[p]
        k = maxwell[u] if u >= 0 else 0.0
        if single:
            c0, c1, c2, det, xv, _, g0, g1, g2 = _state_single(fmap, p, z32, f, c10, c20, c30, k)
        else:
            c0, c1, c2, det, xv, _, g0, g1, g2 = _state(fmap, p, z, f, c10, c20, c30, k)
        s00, s11, s01 = 2.0 * g0, 2.0 * g1, g2
        if u >= 0 and det > row[od + u]:
            row[od + u] = det
        if not held[p]:  # smallest in-plane principal Cauchy stress: eigenvalues of C S
            m00 = c0 * s00 + c2 * s01
            m01 = c0 * s01 + c2 * s11
            m10 = c2 * s00 + c1 * s01
            m11 = c2 * s01 + c1 * s11
            half = 0.5 * (m00 + m11)
            disc = (0.5 * (m00 - m11)) ** 2 + m01 * m10
            low = half - np.sqrt(max(disc, 0.0))
            if low < sigma_min:
                sigma_min = low
        w = xi[p]
        if w == 0.0:  # a monitor point: read, not summed
            if defer:
                stress[p, :] = 0.0
            continue
        energy += w * (xv * (c10 + xv * (c20 + xv * c30)) - k * det)
        p0 = w * (f[0] * s00 + f[1] * s01)  # P = F S, times the weight
        p1 = w * (f[0] * s01 + f[1] * s11)
        p2 = w * (f[2] * s00 + f[3] * s01)
        p3 = w * (f[2] * s01 + f[3] * s11)
        p4 = w * (f[4] * s00 + f[5] * s01)
        p5 = w * (f[4] * s01 + f[5] * s11)
        if u >= 0:
            row[om + u] -= w * det
        if defer:
            stress[p, 0], stress[p, 1], stress[p, 2] = p0, p1, p2
            stress[p, 3], stress[p, 4], stress[p, 5] = p3, p4, p5
        if not single:
            _add_product(grad, fmap, p, p0, p1, p2, p3, p4, p5)
            if not defer:
                _add_product(grad_w, wmap, p, p0, p1, p2, p3, p4, p5)
            continue
        q0, q1, q2 = np.float32(p0), np.float32(p1), np.float32(p2)
        q3, q4, q5 = np.float32(p3), np.float32(p4), np.float32(p5)
        _add_product(g32, fmap, p, q0, q1, q2, q3, q4, q5)
        if not defer:
            _add_product(gw32, wmap, p, q0, q1, q2, q3, q4, q5)
        block += 1
        if block == SINGLE_BLOCK:
            _flush(g32, grad)
            _flush(gw32, grad_w)
            block = 0
    if block:
        _flush(g32, grad)
        _flush(gw32, grad_w)
    row[od + nu] = energy
    row[od + nu + 1] = sigma_min


@numba.njit(inline="always", **_JIT)
def _add_product(out, maps, p, p0, p1, p2, p3, p4, p5):
    """``out += A_p^T [p0, ..., p5]`` for the maps ``A_p`` of point ``p`` (one pass along the rows: vector
    instructions, in the arithmetic of the maps and the ``p``'s)."""
    for j in range(maps.shape[2]):
        out[j] += (p0 * maps[p, 0, j] + p1 * maps[p, 1, j] + p2 * maps[p, 2, j] + p3 * maps[p, 3, j]
                   + p4 * maps[p, 4, j] + p5 * maps[p, 5, j])


@numba.njit(**_JIT)
def _chunk_enrichment(wmap, xi, stress, lo, hi, single, grad_w):
    """The gradient along ``W`` of points ``lo:hi`` that :func:`_chunk_gradient` left in ``stress``:
    ``sum_p A_p^T P_p`` over the enrichment's maps, in the same arithmetic and order, into ``grad_w``."""
    grad_w[:] = 0.0
    gw32 = np.zeros(wmap.shape[2] if single else 0, dtype=np.float32)
    block = 0
    for p in range(lo, hi):
        if xi[p] == 0.0:  # a monitor point
            continue
        p0, p1, p2, p3, p4, p5 = stress[p, 0], stress[p, 1], stress[p, 2], stress[p, 3], stress[p, 4], stress[p, 5]
        if not single:
            _add_product(grad_w, wmap, p, p0, p1, p2, p3, p4, p5)
            continue
        _add_product(gw32, wmap, p, np.float32(p0), np.float32(p1), np.float32(p2), np.float32(p3), np.float32(p4),
                     np.float32(p5))
        block += 1
        if block == SINGLE_BLOCK:
            _flush(gw32, grad_w)
            block = 0
    if block:
        _flush(gw32, grad_w)


@numba.njit(inline="always", **_JIT)
def _flush(part, total):
    """``total += part``, then ``part = 0``."""
    for j in range(part.size):
        total[j] += part[j]
        part[j] = 0.0


@numba.njit(**_JIT)
def _run_chunk(fmap, wmap, xi, unit, held, c10, c20, c30, control, state, partial, stress, winner, job_z, job_z32,
               job_m, kind, k, t):
    """Chunk ``k`` of the pass ``kind`` into thread ``t``'s sums (and stresses)."""
    lo = k * CHUNK
    hi = min(fmap.shape[0], lo + CHUNK)
    nc = fmap.shape[2]
    single = control[_SINGLE] != 0
    if kind == _ENRICHMENT:
        _chunk_enrichment(wmap, xi, stress[winner[k]], lo, hi, single, partial[t, k, nc:nc + wmap.shape[2]])
    else:
        _chunk_gradient(fmap, wmap, xi, unit, held, job_z, job_z32, job_m, c10, c20, c30, lo, hi, single,
                        kind == _GRADIENT_DEFER, partial[t, k], stress[t])


@numba.njit(**_JIT)
def _claims(fmap, wmap, xi, unit, held, c10, c20, c30, control, state, partial, stress, winner, job_z, job_z32,
            job_m, t):
    """Thread ``t`` evaluates every chunk of the published pass it can claim; returns how many."""
    generation = atomic_load(control, _GENERATION)
    kind = atomic_load(control, _KIND)
    base = 16 * generation
    done = 0
    for k in range(state.size):
        if atomic_load(state, k) != base or compare_and_swap(state, k, base, base + _CLAIMED + t) != base:
            continue
        _run_chunk(fmap, wmap, xi, unit, held, c10, c20, c30, control, state, partial, stress, winner, job_z,
                   job_z32, job_m, kind, k, t)
        done += 1
        if t > 0 and compare_and_swap(state, k, base + _CLAIMED + t, base + _FINISHED + t) == base + _CLAIMED + t:
            fetch_add(control, _HELPED, 1)
    return done


@numba.njit(**_JIT)
def _assist(fmap, wmap, xi, unit, held, c10, c20, c30, control, state, partial, stress, winner, job_z, job_z32,
            job_m, t):
    """A helper's loop: claim chunks of every pass published while ``control[_RUNNING]`` is set; return once
    it has not been for ``control[_LINGER]`` spins."""
    seen = -1
    idle = 0
    while idle <= atomic_load(control, _LINGER):
        if not atomic_load(control, _RUNNING):
            idle += 1
            continue
        idle = 0
        generation = atomic_load(control, _GENERATION)
        if generation != seen:
            _claims(fmap, wmap, xi, unit, held, c10, c20, c30, control, state, partial, stress, winner, job_z,
                    job_z32, job_m, t)
            seen = generation


def assist(points: tuple, team: tuple, thread: int) -> None:
    """Run as helper ``thread`` (>= 1) of a team: evaluate chunks of the passes its caller publishes while
    the team runs, and return once it has not run for ``control[_LINGER]`` spins
    (:class:`.point_team.PointTeam`; the GIL is released meanwhile)."""
    _assist(*points, *team, thread)


@numba.njit(**_JIT)
def _publish(control, state, job_z, job_z32, job_m, kind, single, z, maxwell):
    """Publish a pass: its inputs, every chunk free, then its kind and generation; returns the generation."""
    if kind != _ENRICHMENT:
        for j in range(z.size):
            job_z[j] = z[j]
            job_z32[j] = z[j]
        for u in range(maxwell.size):
            job_m[u] = maxwell[u]
    generation = control[_GENERATION] + 1
    for k in range(state.size):
        atomic_store(state, k, 16 * generation)
    atomic_store(control, _SINGLE, 1 if single else 0)
    atomic_store(control, _KIND, kind)
    atomic_store(control, _GENERATION, generation)
    return generation


@numba.njit(**_JIT)
def wait_for(state, k, at_least, spins):
    """Read ``state[k]`` until it is at least ``at_least``, at most ``spins`` times; returns the last value."""
    s = atomic_load(state, k)
    for _ in range(spins):
        if s >= at_least:
            break
        s = atomic_load(state, k)
    return s


@numba.njit(**_JIT)
def _finish(fmap, wmap, xi, unit, held, c10, c20, c30, control, state, partial, stress, winner, job_z, job_z32,
            job_m, generation, kind, grad, grad_m, grad_w, det_max):
    """Wait for the chunks helpers are evaluating (each at most ``control[_WAIT]`` spins, then the caller
    takes it over) and add the chunks' sums in chunk order; returns (energy, smallest principal stress)."""
    base = 16 * generation
    for k in range(state.size):
        s = atomic_load(state, k)
        if s - base == _CLAIMED or s - base >= _FINISHED:
            continue
        s = wait_for(state, k, base + _FINISHED, control[_WAIT])
        if s - base < _FINISHED and compare_and_swap(state, k, s, base + _CLAIMED) == s:
            _run_chunk(fmap, wmap, xi, unit, held, c10, c20, c30, control, state, partial, stress, winner, job_z,
                       job_z32, job_m, kind, k, 0)
            fetch_add(control, _TAKEN, 1)
    nc, nw, nu = grad.size, grad_w.size, grad_m.size
    om, od = nc + nw, nc + nw + nu
    grad_w[:] = 0.0
    if kind != _ENRICHMENT:
        grad[:] = 0.0
        grad_m[:] = 0.0
        det_max[:] = 0.0
    energy = 0.0
    sigma_min = np.inf
    for k in range(state.size):
        code = atomic_load(state, k) - base
        t = code - _FINISHED if code >= _FINISHED else 0
        row = partial[t, k]
        for j in range(nw):
            grad_w[j] += row[nc + j]
        if kind == _ENRICHMENT:
            continue
        winner[k] = t
        for j in range(nc):
            grad[j] += row[j]
        for u in range(nu):
            grad_m[u] += row[om + u]
            det_max[u] = max(det_max[u], row[od + u])
        energy += row[od + nu]
        sigma_min = min(sigma_min, row[od + nu + 1])
    return energy, sigma_min


@numba.njit(**_JIT)
def _pass(fmap, wmap, xi, unit, held, c10, c20, c30, control, state, partial, stress, winner, job_z, job_z32, job_m,
          kind, single, z, maxwell, grad, grad_m, grad_w, det_max):
    """One pass over the points by the caller and whichever helpers join: energy, gradient, the gradient along
    ``W`` (not with ``_GRADIENT_DEFER``: each point's weighted stress kept instead; ``_ENRICHMENT`` sums it
    from those), the largest ``det C`` per unit and the smallest principal Cauchy stress; with ``single`` the
    map products in float32 (:func:`_chunk_gradient`)."""
    generation = _publish(control, state, job_z, job_z32, job_m, kind, single, z, maxwell)
    _claims(fmap, wmap, xi, unit, held, c10, c20, c30, control, state, partial, stress, winner, job_z, job_z32,
            job_m, 0)
    return _finish(fmap, wmap, xi, unit, held, c10, c20, c30, control, state, partial, stress, winner, job_z,
                   job_z32, job_m, generation, kind, grad, grad_m, grad_w, det_max)


@numba.njit(inline="always", **_JIT)
def _output_change(out_q, output_scale, dq):
    """Largest change of an output (relative to its scale) that the correction ``dq`` makes."""
    worst = 0.0
    for i in range(out_q.shape[0]):
        acc = 0.0
        for j in range(dq.size):
            acc += out_q[i, j] * dq[j]
        worst = max(worst, abs(acc) / output_scale[i])
    return worst


@numba.njit(inline="always", **_JIT)
def _secant(sensitivity, dp, input_scale, secant_step, reached, predicted):
    """``S += (q_reached - q_predicted) (W dp)^T / (dp^T W dp)``, ``W = diag(input_scale^-2)``: Broyden's
    update of the predictor's ``S = dq/dp``, after which ``S dp`` is the step's whole change of ``q``; not
    for a step shorter than ``secant_step`` (``sqrt(dp^T W dp)``; inf: never)."""
    wdp = np.empty(dp.size)
    norm = 0.0
    for j in range(dp.size):
        wdp[j] = dp[j] / input_scale[j] ** 2
        norm += wdp[j] * dp[j]
    if not norm > secant_step**2:
        return
    for i in range(sensitivity.shape[0]):
        e = (reached[i] - predicted[i]) / norm
        for j in range(dp.size):
            sensitivity[i, j] += e * wdp[j]


@numba.njit(**_JIT)
def _update(fmap, wmap, xi, unit, held, c10, c20, c30, z, m0, d1, v1, driven, centre, maxwell_factor, thickness,
            output_scale, input_scale, secant_step, sensitivity, hqq_inv, out_q, h_wq, indicator, cap_factor,
            second_step, grad, grad_m, grad_w, det_max, m1, result, info, control, state, partial, stress, winner,
            job_z, job_z32, job_m, defer):
    nd = driven.size
    nu = v1.size
    nc = z.size
    r = nc - 1 - nd
    dp = np.empty(nd + nu)
    for i in range(nd):
        dp[i] = d1[driven[i]] - z[1 + i]
        z[1 + i] = d1[driven[i]]
    for i in range(nu):
        m1[i] = maxwell_factor * v1[i] * v1[i]
        dp[nd + i] = m1[i] - m0[i]
    for i in range(r):  # predictor: q += dq/dp (p1 - p0)
        acc = 0.0
        for j in range(nd + nu):
            acc += sensitivity[i, j] * dp[j]
        z[1 + nd + i] += acc
    predicted = z[1 + nd:].copy()
    team = (control, state, partial, stress, winner, job_z, job_z32, job_m)
    single = fmap.itemsize == 4  # float32 maps: their products in float32 (see _chunk_gradient)
    # with defer, the gradient along W (the indicator's) only where the update ends, from the kept stresses
    first = _GRADIENT_DEFER if defer else _GRADIENT
    energy, sigma_min = _pass(fmap, wmap, xi, unit, held, c10, c20, c30, *team, first, single, z, m1, grad, grad_m,
                              grad_w, det_max)
    dq = np.empty(r)
    for i in range(r):  # Newton correction with the last refreshed H_qq
        acc = 0.0
        for j in range(r):
            acc -= hqq_inv[i, j] * grad[1 + nd + j]
        dq[i] = acc
    big = _output_change(out_q, output_scale, dq)
    evals = 1
    slow = 0.0
    if big > second_step:  # second evaluation, H_qq^-1 corrected by one Broyden update
        g1 = grad[1 + nd:].copy()
        for i in range(r):
            z[1 + nd + i] += dq[i]
        energy, sigma_min = _pass(fmap, wmap, xi, unit, held, c10, c20, c30, *team, _GRADIENT, single, z, m1, grad,
                                  grad_m, grad_w, det_max)
        evals = 2
        a = hqq_inv @ grad[1 + nd:]
        by = hqq_inv @ (grad[1 + nd:] - g1)
        denom = dq @ by
        coef = (dq @ a) / denom if denom != 0.0 else 0.0
        for i in range(r):
            dq[i] = -a[i] - (dq[i] - by[i]) * coef
        last = _output_change(out_q, output_scale, dq)
        if last > 0.1 * big:
            slow = 1.0
        big = last
    elif defer:
        _pass(fmap, wmap, xi, unit, held, c10, c20, c30, *team, _ENRICHMENT, single, z, m1, grad, grad_m,
              grad_w, det_max)
    res = 0.0
    de = 0.0
    for i in range(r):
        z[1 + nd + i] += dq[i]
        res = max(res, abs(grad[1 + nd + i]))
        de += grad[1 + nd + i] * dq[i]
    if big <= second_step:  # a secant (Broyden) update of dq/dp: it maps this step's dp to the q reached
        _secant(sensitivity, dp, input_scale, secant_step, z[1 + nd:], predicted)
    # outputs o = (F_driven, C) = (dE/dd, -(eps/t0^2) dE/dm) + dO/dq dq
    result[0, :] = 0.0
    for i in range(nd + nu):
        acc = grad[1 + i] if i < nd else -cap_factor * grad_m[i - nd]
        for j in range(r):
            acc += out_q[i, j] * dq[j]
        if i < nd:
            result[0, driven[i]] = acc
        else:
            result[1, i - nd] = acc
    for u in range(nu):
        acc = 0.0
        for j in range(nc):
            acc += centre[u, j] * z[j]
        result[2, u] = acc
        result[3, u] = acc  # displacement: the centre deflection of a free unit
        result[4, u] = np.sqrt(det_max[u]) * abs(v1[u]) / thickness
    for i in range(nd):
        result[3, driven[i]] = d1[driven[i]]
    nw = grad_w.size
    gw = grad_w.copy()
    for i in range(nw):
        acc = 0.0
        for j in range(r):
            acc += h_wq[i, j] * dq[j]
        gw[i] += acc
    worst = 0.0
    for i in range(indicator.shape[0]):
        acc = 0.0
        for j in range(nw):
            acc += indicator[i, j] * gw[j]
        worst = max(worst, abs(acc))
    info[0] = energy + 0.5 * de
    info[1] = sigma_min
    info[2] = worst
    info[3] = res
    info[4] = evals
    info[5] = slow
    info[6] = big


@numba.njit(**_JIT)
def _classify(d1, v1, limit, lo, hi, vlo, vhi, driven, maxwell_factor, tangent_at, refresh_step):
    """0: inside the envelope, 1: not finite, 2: beyond max_displacement, 3: outside the envelope;
    and how far the command has moved from where the tangent was refreshed, in ``refresh_step``s."""
    nd = driven.size
    for u in range(v1.size):
        if not (np.isfinite(d1[u]) and np.isfinite(v1[u])):
            return 1, 0.0
        if abs(d1[u]) > limit:
            return 2, 0.0
    code = 0
    for u in range(v1.size):
        if d1[u] < lo[u] or d1[u] > hi[u] or v1[u] < vlo[u] or v1[u] > vhi[u]:
            code = 3
    moved = 0.0
    for i in range(nd):
        moved = max(moved, abs(d1[driven[i]] - tangent_at[i]) / refresh_step[i])
    for u in range(v1.size):
        moved = max(moved, abs(maxwell_factor * v1[u] * v1[u] - tangent_at[nd + u]) / refresh_step[nd + u])
    return code, moved


def classify(d1: np.ndarray, v1: np.ndarray, limit: float, bounds: tuple, tangent_at: np.ndarray,
             refresh_step: np.ndarray) -> tuple[int, float]:
    """Check a command: ``(code, moved)``, code 0 inside the envelope, 1 not finite, 2 beyond
    ``limit`` [m], 3 outside the envelope; ``moved`` the largest change of an input from
    ``tangent_at`` (driven displacements, then Maxwell coefficients) in units of its ``refresh_step``
    (above 1: refresh).

    ``bounds`` is ``(lo, hi, vlo, vhi, driven, maxwell_factor)``: displacement bounds per
    unit (+-inf for free units), voltage bounds, driven unit indices and ``eps / (2 t0^2)``.
    """
    return _classify(d1, v1, limit, *bounds[:5], bounds[5], tangent_at, refresh_step)


def update(points: tuple, z: np.ndarray, m0: np.ndarray, d1: np.ndarray, v1: np.ndarray, layout: tuple,
           tangent: tuple, cap_factor: float, second_step: float, buffers: tuple, m1: np.ndarray,
           result: np.ndarray, info: np.ndarray, team: tuple, defer: bool = True) -> None:
    """One update from state ``z = [1, d0, q0]`` (at Maxwell coefficients ``m0``) to ``(d1, v1)``, in place.

    Predictor ``q += dq/dp (p1 - p0)``, one evaluation, the Newton correction with
    ``H_qq^-1``; if the correction changes an output by more than ``second_step`` of its
    scale, a second evaluation and a Broyden-corrected second step (see :mod:`.reduced_twin`).
    The evaluations' products with float32 maps are float32 arithmetic (``F = A_p z`` and
    ``A_p^T P`` per point; the stresses, and the sums over blocks of :data:`SINGLE_BLOCK`
    points, in float64): their rounding moves the outputs by ~1e-7 of their values.

    Parameters
    ----------
    points : tuple
        ``(fmap, wmap, xi, unit, held, c10, c20, c30)`` as for :func:`evaluate`.
    d1, v1 : ndarray, shape (n_units,)
        The command: displacements [m] (used for driven units), voltages [V].
    layout : tuple
        ``(driven, centre, maxwell_factor, thickness, output_scale, input_scale, secant_step)``:
        driven unit indices, the rows of ``[1, d, q]`` giving each unit's centre deflection,
        ``eps / (2 t0^2)``, ``t0``, the scale of each output (driven forces [N], capacitances
        [F]), the scale of each input (driven displacements [m], Maxwell coefficients [Pa]; inf:
        not counted) and the shortest step (in those scales) after which an update that ends
        converged corrects ``dq/dp`` by a secant (Broyden) update, so that it maps the step to
        the change of ``q`` it made (inf: never).
    tangent : tuple
        ``(dq/dp, H_qq^-1, dO/dq, H_wq, indicator matrix)`` of the last refresh (``dq/dp`` is
        updated in place by the secant updates).
    cap_factor : float
        ``eps / t0^2`` [F/m^3]: capacitance per ``-dE/dm``.
    buffers : tuple
        ``(grad, grad_m, grad_w, det_max)`` as for :func:`evaluate`, filled at the last evaluation.
    m1 : ndarray, shape (n_units,)
        Filled with the new Maxwell coefficients [Pa].
    result : ndarray, shape (5, n_units)
        Filled with force [N] (0 for free units), capacitance [F], centre deflection
        [m], displacement [m] (centre deflection for free units) and peak field [V/m].
    info : ndarray, shape (7,)
        Filled with energy [J], smallest principal stress [Pa], indicator, largest
        reduced residual [N], evaluations, 1.0 if the second step contracted slowly,
        and the relative output change of the last correction (how far from converged
        the evaluated state was).
    team : tuple
        :func:`team_arrays` of the threads that share the evaluations' points (the caller's alone for one
        thread; :class:`.point_team.PointTeam` while its helpers run).  The outputs do not depend on who
        evaluated which chunk of points.
    defer : bool
        Sum the gradient along ``W`` (the indicator's) after the last evaluation, from the stresses the
        first kept (cheaper when a second evaluation is likely), or with the first evaluation (cheaper
        when it is not).
    """
    _update(*points, z, m0, d1, v1, *layout, *tangent, cap_factor, second_step, *buffers, m1, result, info, *team,
            defer)


def evaluate(fmap: np.ndarray, wmap: np.ndarray, xi: np.ndarray, unit: np.ndarray, held: np.ndarray,
             z: np.ndarray, maxwell: np.ndarray, yeoh: Yeoh, out: tuple) -> tuple[float, float]:
    """Energy [J] and smallest principal Cauchy stress [Pa]; fills ``out = (grad, grad_m, grad_w, det_max)``.

    Parameters
    ----------
    fmap : ndarray, shape (n_points, 6, nc)
        ``A_p`` over ``[1, d, q]``.
    wmap : ndarray, shape (n_points, 6, nw)
        ``A_p`` over the enrichment vectors ``W``.
    xi : ndarray, shape (n_points,)
        Weights [m^3] (``t0`` times area times ECSW weight); 0 for monitor points.
    unit : ndarray of int, shape (n_points,)
        The point's unit, -1 on passive membrane.
    held : ndarray of bool, shape (n_points,)
        The point lies in a held indenter disk (left out of the smallest stress).
    z : ndarray, shape (nc,)
        ``[1, d, q]``.
    maxwell : ndarray, shape (n_units,)
        Maxwell coefficient per unit [Pa].
    yeoh : Yeoh
    out : tuple of ndarray
        ``grad`` (nc; entry 0 is the derivative along the constant column, unused),
        ``grad_m`` (n_units), ``grad_w`` (nw), ``det_max`` (n_units; largest ``det C``
        over the unit's points, sampled and monitor).
    """
    team = team_arrays(1, fmap.shape[0], fmap.shape[2], wmap.shape[2], maxwell.size)  # the caller alone
    return _pass(fmap, wmap, xi, unit, held, yeoh.c10, yeoh.c20, yeoh.c30, *team, _GRADIENT, False, z, maxwell,
                 *out)


@numba.njit(**_JIT)
def _combine(base, vectors, z, out):
    for i in range(vectors.shape[0]):
        acc = base[i]
        for j in range(vectors.shape[1]):
            acc += vectors[i, j] * z[j]
        out[i] = acc


@numba.njit(**_JIT)
def _project(vectors, x, out):
    out[:] = 0.0
    for i in range(vectors.shape[0]):
        xi = x[i]
        for j in range(vectors.shape[1]):
            out[j] += vectors[i, j] * xi


def combine(base: np.ndarray, vectors: np.ndarray, z: np.ndarray) -> np.ndarray:
    """``base + vectors @ z`` (a field from reduced coordinates) on the calling thread alone.

    A large ROM's field (27135 x 217 on the 4-by-4) is a product OpenBLAS spreads over its threads,
    and its helper thread then spins for ~0.1 s: a node drawing the field at 5 Hz kept a core busy.
    """
    out = np.empty(vectors.shape[0])
    _combine(base, vectors, z, out)
    return out


def project(vectors: np.ndarray, x: np.ndarray) -> np.ndarray:
    """``vectors.T @ x`` (coordinates of a field over orthonormal ``vectors``) on the calling thread alone
    (see :func:`combine`)."""
    out = np.empty(vectors.shape[1])
    _project(vectors, x, out)
    return out


@numba.njit(inline="always", **_JIT)
def _stiffness(fmap, p, z, w, u, maxwell, c10, c20, c30, f, b, h, bh, d, t):
    """The weighted stiffness of ``F`` at point ``p`` (weight ``w``, unit ``u``) into ``d`` (6 x 6) and, for a
    point on a unit (``u >= 0``), ``t = -w ddet/dF`` (the ``m`` derivative of the stress)."""
    km = maxwell[u] if u >= 0 else 0.0
    c0, c1, c2, det, xv, dy, g0, g1, g2 = _state(fmap, p, z, f, c10, c20, c30, km)
    ddy = 2.0 * c20 + 6.0 * c30 * xv
    inv2 = 1.0 / det**2
    # H = d2Psi/dc2 (material.energy_derivatives)
    dj0, dj1, dj2 = c1, c0, -2.0 * c2
    di0, di1, di2 = 1.0 - inv2 * dj0, 1.0 - inv2 * dj1, -inv2 * dj2
    bb = 2.0 * dy * inv2 / det
    mm = dy * inv2 + km
    h[0, 0] = ddy * di0 * di0 + bb * dj0 * dj0
    h[1, 1] = ddy * di1 * di1 + bb * dj1 * dj1
    h[2, 2] = ddy * di2 * di2 + bb * dj2 * dj2 + 2.0 * mm
    h[0, 1] = h[1, 0] = ddy * di0 * di1 + bb * dj0 * dj1 - mm
    h[0, 2] = h[2, 0] = ddy * di0 * di2 + bb * dj0 * dj2
    h[1, 2] = h[2, 1] = ddy * di1 * di2 + bb * dj1 * dj2
    # B = dc/dF, columns 2 i + alpha
    for i in range(3):
        b[0, 2 * i] = 2.0 * f[2 * i]
        b[1, 2 * i + 1] = 2.0 * f[2 * i + 1]
        b[2, 2 * i] = f[2 * i + 1]
        b[2, 2 * i + 1] = f[2 * i]
    s00, s11, s01 = 2.0 * g0, 2.0 * g1, g2
    for c in range(6):  # D = w (B^T H B + S (x) I_3)
        for x in range(3):
            bh[c, x] = b[0, c] * h[0, x] + b[1, c] * h[1, x] + b[2, c] * h[2, x]
    for c in range(6):
        for e in range(6):
            d[c, e] = w * (bh[c, 0] * b[0, e] + bh[c, 1] * b[1, e] + bh[c, 2] * b[2, e])
    for i in range(3):
        d[2 * i, 2 * i] += w * s00
        d[2 * i + 1, 2 * i + 1] += w * s11
        d[2 * i, 2 * i + 1] += w * s01
        d[2 * i + 1, 2 * i] += w * s01
    if u >= 0:  # ddet/dF = c1 dc0/dF + c0 dc1/dF - 2 c2 dc2/dF
        for c in range(6):
            t[c] = -w * (c1 * b[0, c] + c0 * b[1, c] - 2.0 * c2 * b[2, c])


#: Rows of ``H`` per matrix product in :func:`hessian`: the upper triangle of ``k`` panels costs
#: ``(k + 1) / 2k`` of the full product.
PANEL = 32


@numba.njit(**_JIT)
def _point_stiffness(fmap, wmap, xi, unit, z, maxwell, c10, c20, c30, df, dw, hm):
    """``D_p A_p`` of every sampled point into rows ``6 p .. 6 p + 5`` of ``df`` (the ``fmap`` columns) and
    ``dw`` (the ``wmap`` columns), ``D_p`` the weighted stiffness of ``F`` at the point (zero at monitor
    points); and ``h_m`` (see :func:`hessian`)."""
    np_, _, nc = fmap.shape
    nw = wmap.shape[2]
    hm[:, :] = 0.0
    f, b, h, bh, d, t = np.empty(6), np.zeros((3, 6)), np.empty((3, 3)), np.empty((6, 3)), np.empty((6, 6)), np.empty(6)
    for p in range(np_):
        w, u = xi[p], unit[p]
        if w == 0.0:  # a monitor point: not summed
            df[6 * p:6 * p + 6] = 0.0
            dw[6 * p:6 * p + 6] = 0.0
            continue
        _stiffness(fmap, p, z, w, u, maxwell, c10, c20, c30, f, b, h, bh, d, t)
        for c in range(6):  # the rows of D A (innermost loops along a row: vector instructions)
            d0, d1, d2, d3, d4, d5 = d[c, 0], d[c, 1], d[c, 2], d[c, 3], d[c, 4], d[c, 5]
            r = 6 * p + c
            for j in range(nc):
                df[r, j] = (d0 * fmap[p, 0, j] + d1 * fmap[p, 1, j] + d2 * fmap[p, 2, j] + d3 * fmap[p, 3, j]
                            + d4 * fmap[p, 4, j] + d5 * fmap[p, 5, j])
            for j in range(nw):
                dw[r, j] = (d0 * wmap[p, 0, j] + d1 * wmap[p, 1, j] + d2 * wmap[p, 2, j] + d3 * wmap[p, 3, j]
                            + d4 * wmap[p, 4, j] + d5 * wmap[p, 5, j])
        if u >= 0:
            for j in range(nc):
                hm[j, u] += (t[0] * fmap[p, 0, j] + t[1] * fmap[p, 1, j] + t[2] * fmap[p, 2, j]
                             + t[3] * fmap[p, 3, j] + t[4] * fmap[p, 4, j] + t[5] * fmap[p, 5, j])
            for j in range(nw):
                hm[nc + j, u] += (t[0] * wmap[p, 0, j] + t[1] * wmap[p, 1, j] + t[2] * wmap[p, 2, j]
                                  + t[3] * wmap[p, 3, j] + t[4] * wmap[p, 4, j] + t[5] * wmap[p, 5, j])


@numba.njit(**_JIT)
def _hessian(fmap, wmap, xi, unit, z, maxwell, c10, c20, c30, hz, hm):
    """:func:`hessian` without BLAS: the upper triangle of ``A_p^T D_p A_p`` added to ``hz`` point by point."""
    np_, _, nc = fmap.shape
    nw = wmap.shape[2]
    k = nc + nw
    hz[:, :] = 0.0
    hm[:, :] = 0.0
    a, da = np.empty((6, k)), np.empty((6, k))
    f, b, h, bh, d, t = np.empty(6), np.zeros((3, 6)), np.empty((3, 3)), np.empty((6, 3)), np.empty((6, 6)), np.empty(6)
    for p in range(np_):
        w, u = xi[p], unit[p]
        if w == 0.0:
            continue
        for c in range(6):
            for j in range(nc):
                a[c, j] = fmap[p, c, j]
            for j in range(nw):
                a[c, nc + j] = wmap[p, c, j]
        _stiffness(fmap, p, z, w, u, maxwell, c10, c20, c30, f, b, h, bh, d, t)
        # D A and the upper triangle of A^T D A; the innermost loops run along a row (vector instructions)
        for c in range(6):
            d0, d1, d2, d3, d4, d5 = d[c, 0], d[c, 1], d[c, 2], d[c, 3], d[c, 4], d[c, 5]
            for j in range(k):
                da[c, j] = d0 * a[0, j] + d1 * a[1, j] + d2 * a[2, j] + d3 * a[3, j] + d4 * a[4, j] + d5 * a[5, j]
        for i in range(k):
            a0, a1, a2, a3, a4, a5 = a[0, i], a[1, i], a[2, i], a[3, i], a[4, i], a[5, i]
            for j in range(i, k):
                hz[i, j] += (a0 * da[0, j] + a1 * da[1, j] + a2 * da[2, j] + a3 * da[3, j] + a4 * da[4, j]
                             + a5 * da[5, j])
        if u >= 0:
            for j in range(k):
                hm[j, u] += t[0] * a[0, j] + t[1] * a[1, j] + t[2] * a[2, j] + t[3] * a[3, j] + t[4] * a[4, j] \
                    + t[5] * a[5, j]
    for i in range(k):
        for j in range(i):
            hz[i, j] = hz[j, i]


def hessian(fmap: np.ndarray, wmap: np.ndarray, xi: np.ndarray, unit: np.ndarray, z: np.ndarray,
            maxwell: np.ndarray, yeoh: Yeoh, n_units: int, blas: bool = True) -> tuple[np.ndarray, np.ndarray]:
    """Hessian of the hyper-reduced energy over ``[1, d, q, w]`` and its mixed ``m`` derivatives.

    ``H = sum_p A_p^T D_p A_p``.  With ``blas``, matrix products of the stacked point maps
    ``A`` (6 rows per point) and ``D A`` (:func:`_point_stiffness`) in the maps' precision
    (the products' rounding: ~1e-7 of the largest entry with float32 maps), the ``[1, d, q]``
    block's upper triangle only, by row panels of :data:`PANEL` columns (the full product
    costs twice its flops; 200-mode 4-by-4: 4.5-4.9 ms for the block against 5.5 ms, ~9-12 ms
    in all).  Without, a compiled rank-6 update of ``H`` per point (:func:`_hessian`; 57-96 ms
    there, where ``H`` streams from memory once per point; the same on small ROMs), on the
    calling thread alone.  The products run on the process's BLAS
    threads, and OpenBLAS's helper threads then spin for ~0.1 s: a process refreshing every
    few tens of ms keeps a core busy (docs/rom.md), what a real-time process cannot afford,
    unless its BLAS is held to one thread (:mod:`dea_array_twin.blasthreads`, the ROM node).

    Returns
    -------
    h : ndarray, shape (nc + nw, nc + nw)
        ``d2E/dz_i dz_j`` (row and column 0 are those of the constant ``z_0 = 1``: never read).
    h_m : ndarray, shape (nc + nw, n_units)
        ``d2E/dz_j dm_u``.
    """
    n, nc, nw = fmap.shape[0], fmap.shape[2], wmap.shape[2]
    if not blas:
        hz, hm = np.empty((nc + nw, nc + nw)), np.empty((nc + nw, n_units))
        _hessian(fmap, wmap, xi, unit, z, maxwell, yeoh.c10, yeoh.c20, yeoh.c30, hz, hm)
        return hz, hm
    df, dw = np.empty((6 * n, nc), fmap.dtype), np.empty((6 * n, nw), wmap.dtype)
    hm = np.empty((nc + nw, n_units))
    _point_stiffness(fmap, wmap, xi, unit, z, maxwell, yeoh.c10, yeoh.c20, yeoh.c30, df, dw, hm)
    a_f, a_w = fmap.reshape(6 * n, nc), wmap.reshape(6 * n, nw)
    hz = np.empty((nc + nw, nc + nw))
    for i in range(0, nc, PANEL):  # the upper triangle by row panels (whole diagonal panels)
        j = min(i + PANEL, nc)
        hz[i:j, i:nc] = a_f[:, i:j].T @ df[:, i:]
    hz[:nc, :nc] = np.triu(hz[:nc, :nc])
    hz[:nc, :nc] += np.triu(hz[:nc, :nc], 1).T  # exactly symmetric
    hz[:nc, nc:] = a_f.T @ dw
    hz[nc:, :nc] = hz[:nc, nc:].T
    hz[nc:, nc:] = np.triu(a_w.T @ dw)
    hz[nc:, nc:] += np.triu(hz[nc:, nc:], 1).T
    return hz, hm


@numba.njit(**_JIT)
def _cholesky(a):
    """Lower Cholesky factor of ``a`` in place (its strict upper triangle is left as it was);
    False if ``a`` is not positive definite."""
    n = a.shape[0]
    for j in range(n):
        s = a[j, j]
        for k in range(j):
            s -= a[j, k] * a[j, k]
        if not s > 0.0:
            return False
        s = np.sqrt(s)
        a[j, j] = s
        for i in range(j + 1, n):
            t = a[i, j]
            for k in range(j):
                t -= a[i, k] * a[j, k]
            a[i, j] = t / s
    return True


@numba.njit(**_JIT)
def _inverse_from_cholesky(lower, out):
    """``out = (L L^T)^-1 = L^-T L^-1`` from the lower factor ``L``.

    Row-oriented (every inner loop runs along a row: contiguous, vector instructions):
    the rows of ``L^-1`` by forward substitution, then ``L^-T L^-1`` as a sum of the
    rows' outer products, upper triangle then mirrored."""
    n = lower.shape[0]
    linv = np.zeros((n, n))
    for i in range(n):  # row i of L^-1: (e_i - sum_k<i L_ik row_k) / L_ii
        linv[i, i] = 1.0
        for k in range(i):
            c = lower[i, k]
            for j in range(k + 1):
                linv[i, j] -= c * linv[k, j]
        d = 1.0 / lower[i, i]
        for j in range(i + 1):
            linv[i, j] *= d
    out[:, :] = 0.0
    for k in range(n):  # out += row_k^T row_k (row k of L^-1 is zero beyond k)
        for i in range(k + 1):
            c = linv[k, i]
            for j in range(i, k + 1):
                out[i, j] += c * linv[k, j]
    for i in range(n):
        for j in range(i):
            out[i, j] = out[j, i]


@numba.njit(**_JIT)
def _reduce_tangent(hz, hm, nd, cap_factor, output_scale, sensitivity, hqq_inv, out_q, h_wq, indicator):
    r = hqq_inv.shape[0]
    q0 = 1 + nd
    nc = q0 + r
    nw = hz.shape[0] - nc
    nu = hm.shape[1]
    no = nd + nu
    hqq = np.empty((r, r))
    for i in range(r):
        for j in range(r):
            hqq[i, j] = hz[q0 + i, q0 + j]
    stable = _cholesky(hqq)
    if stable:
        _inverse_from_cholesky(hqq, hqq_inv)
    else:
        for i in range(r):
            for j in range(r):
                hqq[i, j] = hz[q0 + i, q0 + j]
        hqq_inv[:, :] = np.linalg.inv(hqq)
    # outputs o = (F_driven, C): dF/dz = H_dz, dC/dz = -(eps/t0^2) H_mz; over q (out_q) and w (out_w)
    out_w = np.empty((no, nw))
    for i in range(no):
        for j in range(r):
            out_q[i, j] = hz[1 + i, q0 + j] if i < nd else -cap_factor * hm[q0 + j, i - nd]
        for j in range(nw):
            out_w[i, j] = hz[1 + i, nc + j] if i < nd else -cap_factor * hm[nc + j, i - nd]
    # The products below run along rows (contiguous): the q rows of [H_qp, H_qw] gathered first.
    hqp = np.empty((r, no + nw))  # [H_qd, H_qm, H_qw]
    for k in range(r):
        for j in range(no + nw):
            hqp[k, j] = hz[q0 + k, 1 + j] if j < nd else (hm[q0 + k, j - nd] if j < no else hz[q0 + k, nc + j - no])
    y = np.zeros((r, no + nw))  # H_qq^-1 [H_qp, H_qw]
    for i in range(r):
        for k in range(r):
            c = hqq_inv[i, k]
            for j in range(no + nw):
                y[i, j] += c * hqp[k, j]
    for i in range(r):  # dq/dp = -H_qq^-1 H_qp, p = (d, m)
        for j in range(no):
            sensitivity[i, j] = -y[i, j]
    x = y[:, no:]  # H_qq^-1 H_qw
    schur = np.empty((nw, nw))  # S = H_ww - H_wq H_qq^-1 H_qw
    for i in range(nw):
        for j in range(r):
            h_wq[i, j] = hz[nc + i, q0 + j]
        for j in range(nw):
            schur[i, j] = hz[nc + i, nc + j]
        for k in range(r):
            c = h_wq[i, k]
            for j in range(nw):
                schur[i, j] -= c * x[k, j]
    for i in range(nw):  # symmetric to rounding: make it exactly so for eigh
        for j in range(i):
            schur[i, j] = schur[j, i] = 0.5 * (schur[i, j] + schur[j, i])
    values, vectors = np.linalg.eigh(schur)  # S^+ over the eigenvalues above 1e-12 of the largest (numpy's pinv)
    cutoff = 1e-12 * np.abs(values).max()
    for j in range(nw):
        values[j] = 1.0 / values[j] if abs(values[j]) > cutoff else 0.0
    m = -out_w  # H_oq H_qq^-1 H_qw - H_ow
    for i in range(no):
        for k in range(r):
            c = out_q[i, k]
            for j in range(nw):
                m[i, j] += c * x[k, j]
    mv = m @ vectors
    for i in range(no):
        for j in range(nw):
            mv[i, j] *= values[j]
    for i in range(no):
        for j in range(nw):
            acc = 0.0
            for k in range(nw):
                acc += mv[i, k] * vectors[j, k]
            indicator[i, j] = acc / output_scale[i]
    return stable


def reduced_tangent(hz: np.ndarray, hm: np.ndarray, nd: int, n_modes: int, cap_factor: float,
                    output_scale: np.ndarray) -> tuple[bool, tuple]:
    """What an update needs from the reduced Hessian of :func:`hessian` (one compiled call).

    With ``q``, ``d``, ``w`` the blocks of ``[1, d, q, w]``, outputs ``o = (F_driven, C)``:

        H_qq^-1                        (by Cholesky when H_qq is positive definite, else LU),
        dq/dp = -H_qq^-1 [H_qd, H_qm]   (the predictor, p = (d, m)),
        dO/dq = [H_dq; -(eps/t0^2) H_mq],
        indicator matrix = (dO/dq H_qq^-1 H_qw - dO/dw) S^+ / o_scale,   S = H_ww - H_wq H_qq^-1 H_qw,

    ``S^+`` the pseudo-inverse over the eigenvalues above ``1e-12`` of the largest in magnitude.

    Parameters
    ----------
    hz, hm : ndarray
        :func:`hessian`'s output.
    nd, n_modes : int
        Number of driven units and of POD modes (``q``).
    cap_factor : float
        ``eps / t0^2`` [F/m^3].
    output_scale : ndarray, shape (nd + n_units,)
        Scale of each output (driven forces [N], capacitances [F]).

    Returns
    -------
    stable : bool
        Whether ``H_qq`` is positive definite.
    arrays : tuple
        ``(dq/dp, H_qq^-1, dO/dq, H_wq, indicator matrix)``, as :func:`update` takes them.

    Raises
    ------
    numpy.linalg.LinAlgError
        If ``H_qq`` is singular.
    """
    r, no = n_modes, nd + hm.shape[1]
    nw = hz.shape[0] - 1 - nd - r
    arrays = (np.empty((r, no)), np.empty((r, r)), np.empty((no, r)), np.empty((nw, r)), np.empty((no, nw)))
    stable = _reduce_tangent(hz, hm, nd, cap_factor, output_scale, *arrays)
    return bool(stable), arrays


@numba.njit(**_JIT)
def _cholesky_solve(lower, b, out):
    """``out = (L L^T)^-1 b`` from the lower factor ``L`` of :func:`_cholesky`."""
    n = b.size
    for i in range(n):
        s = b[i]
        for k in range(i):
            s -= lower[i, k] * out[k]
        out[i] = s / lower[i, i]
    for i in range(n - 1, -1, -1):
        s = out[i]
        for k in range(i + 1, n):
            s -= lower[k, i] * out[k]
        out[i] = s / lower[i, i]


@numba.njit(**_JIT)
def _heights(fmap, wmap, xi, unit, held, c10, c20, c30, z, m0, d1, v1, driven, centre, maxwell_factor, thickness,
             output_scale, input_scale, secant_step, sensitivity, hqq_inv, out_q, h_wq, indicator, cap_factor,
             second_step, grad, grad_m, grad_w, det_max, m1, result, info, outputs, centre_d, forces, units, slots,
             g0, g1, predict, first, max_updates, status, control, state, partial, stress, winner, job_z, job_z32,
             job_m, defer):
    nd = driven.size
    nu = v1.size
    nb = units.size
    nc = z.size
    r = nc - 1 - nd
    k = np.empty((nb, nb))
    rhs = np.empty(nb)
    dw = np.empty(nb)
    status[0] = 0.0  # evaluations
    status[1] = 0.0  # updates
    if predict:  # (K - dG/dw) dw = G(w0) - F0 - dF/dp dp, dp the change of the other inputs
        dp = np.empty(nd + nu)
        for i in range(nd):
            dp[i] = d1[driven[i]] - z[1 + i]
        for u in range(nu):
            dp[nd + u] = maxwell_factor * v1[u] * v1[u] - m0[u]
        for i in range(nb):
            acc = g0[i] + g1[i] * d1[units[i]] - forces[units[i]]
            for j in range(nd + nu):
                acc -= outputs[slots[i], j] * dp[j]
            rhs[i] = acc
            for j in range(nb):
                k[i, j] = outputs[slots[i], slots[j]]
            k[i, i] -= g1[i]
        if _cholesky(k):
            _cholesky_solve(k, rhs, dw)
            for i in range(nb):
                if np.isfinite(dw[i]):
                    d1[units[i]] += dw[i]
    for i in range(nb):
        status[3 + i] = d1[units[i]]  # the heights' linear prediction
    m_prev = m0.copy()
    for it in range(max_updates + 1):
        if first or it > 0:
            if it == max_updates:
                status[2] = 3.0  # not converged
                return
            _update(fmap, wmap, xi, unit, held, c10, c20, c30, z, m_prev, d1, v1, driven, centre, maxwell_factor,
                    thickness, output_scale, input_scale, secant_step, sensitivity, hqq_inv, out_q, h_wq, indicator,
                    cap_factor, second_step, grad, grad_m, grad_w, det_max, m1, result, info, control, state,
                    partial, stress, winner, job_z, job_z32, job_m, defer)
            status[0] += info[4]
            status[1] += 1.0
            for u in range(nu):
                m_prev[u] = m1[u]
            if info[6] > second_step:
                status[2] = 2.0  # a jump: converge in q with refreshed Hessians, then call again
                return
        small = True
        for i in range(nb):
            rhs[i] = g0[i] + g1[i] * d1[units[i]] - result[0, units[i]]
            small = small and abs(rhs[i]) <= second_step * output_scale[slots[i]]
            for j in range(nb):
                k[i, j] = outputs[slots[i], slots[j]]
            k[i, i] -= g1[i]
        if not _cholesky(k):
            status[2] = 1.0  # K - dG/dw not positive definite: a limit point
            return
        _cholesky_solve(k, rhs, dw)
        for i in range(nb):
            if not np.isfinite(dw[i]):
                status[2] = 3.0
                return
        if small:  # the last step to first order: heights, q and every output
            for i in range(nb):
                info[0] += result[0, units[i]] * dw[i]  # dE = F dw at the reduced equilibrium
                d1[units[i]] += dw[i]
                z[1 + slots[i]] += dw[i]
            for j in range(r):
                acc = 0.0
                for i in range(nb):
                    acc += sensitivity[j, slots[i]] * dw[i]
                z[1 + nd + j] += acc
            for o in range(nd + nu):
                acc = 0.0
                for i in range(nb):
                    acc += outputs[o, slots[i]] * dw[i]
                if o < nd:
                    result[0, driven[o]] += acc
                else:
                    result[1, o - nd] += acc
            for u in range(nu):
                acc = 0.0
                for i in range(nb):
                    acc += centre_d[u, slots[i]] * dw[i]
                result[2, u] += acc
                result[3, u] = result[2, u]
            for i in range(nd):
                result[3, driven[i]] = d1[driven[i]]
            status[2] = 0.0
            return
        for i in range(nb):
            d1[units[i]] += dw[i]


def heights(points: tuple, z: np.ndarray, m0: np.ndarray, d1: np.ndarray, v1: np.ndarray, layout: tuple,
            tangent: tuple, condensed: tuple, cap_factor: float, second_step: float, buffers: tuple, m1: np.ndarray,
            result: np.ndarray, info: np.ndarray, biased: tuple, predict: bool, first: bool, max_updates: int,
            status: np.ndarray, team: tuple, defer: bool = True) -> None:
    """Solve for the heights ``w = d1[units]`` of biased units, ``F_k(q(d), d) = G_k(w_k)``, in place.

    ``G_k(w) = g0_k + g1_k w`` (affine: a linear, constant or no bias law and a Newmark
    step's inertia are; a table's local linearisation), Newton on the heights with the
    condensed stiffness ``K = dF/dd = H_dd - H_dq H_qq^-1 H_qd`` of the last refresh,

        dw = (K - dG/dw)^-1 (G(w) - F(w)),

    each iterate one :func:`update` (usually one evaluation).  With ``predict`` the first
    iterate is the linear prediction from the last state, ``(K - dG/dw) dw = G(w0) - F0 -
    dF/dp dp`` (``dp``: the change of the other inputs); with ``first`` an update runs at
    the (predicted) heights before the first residual, else ``result`` holds that
    update.  When the residual is within ``second_step`` of each unit's force scale, the
    last ``dw`` is applied to the heights, ``z`` (``q`` by ``dq/dd``) and every output to
    first order, without another evaluation.

    Parameters
    ----------
    points, layout, tangent, buffers, m1, result, info
        As for :func:`update` (``m0``: the Maxwell coefficients of ``z``).
    condensed : tuple
        ``(dO/dp, dcentre/dd)`` with ``q`` at equilibrium: outputs (driven forces,
        capacitances) per input ``p = (d, m)``, centre deflections per driven ``d``.
    biased : tuple
        ``(forces, units, slots, g0, g1)``: the indenter forces at ``z`` [N] (the
        predictor's ``F0``), the biased units, their places among the driven inputs,
        and ``G``'s coefficients [N, N/m].
    max_updates : int
        Updates the solve may spend.
    status : ndarray, shape (3 + n_biased,)
        Filled with evaluations, updates, the outcome (0 converged, 1 ``K - dG/dw`` not
        positive definite: a limit point, 2 a jump in ``q``: converge it and call again
        without ``first``, 3 not converged) and the predicted heights [m].
    team, defer
        As for :func:`update`.
    """
    _heights(*points, z, m0, d1, v1, *layout, *tangent, cap_factor, second_step, *buffers, m1, result, info,
             *condensed, *biased, predict, first, max_updates, status, *team, defer)


def hessian_reference(fmap: np.ndarray, wmap: np.ndarray, xi: np.ndarray, unit: np.ndarray, z: np.ndarray,
                      maxwell: np.ndarray, yeoh: Yeoh, n_units: int) -> tuple[np.ndarray, np.ndarray]:
    """:func:`hessian` in numpy, from :func:`.material.energy_derivatives` (the tests' reference)."""
    live = xi > 0.0
    a = np.concatenate([fmap[live], wmap[live]], axis=2)  # (n, 6, k)
    w, u = xi[live], unit[live]
    f = a[:, :, :fmap.shape[2]] @ z  # (n, 6)
    f1, f2 = f[:, 0::2], f[:, 1::2]  # columns of F (3 each)
    c = np.stack([np.sum(f1 * f1, 1), np.sum(f2 * f2, 1), np.sum(f1 * f2, 1)], axis=1)
    m = np.where(u >= 0, maxwell[np.maximum(u, 0)], 0.0)
    g, h = energy_derivatives(c, yeoh, m)
    # B = dc/dF: rows c0, c1, c2; columns (i, alpha) -> 2 i + alpha.
    b = np.zeros((len(w), 3, 6))
    b[:, 0, 0::2] = 2.0 * f1
    b[:, 1, 1::2] = 2.0 * f2
    b[:, 2, 0::2] = f2
    b[:, 2, 1::2] = f1
    d = np.einsum("nvc,nvw,nwe->nce", b, h, b)
    s = np.stack([2.0 * g[:, 0], g[:, 2], g[:, 2], 2.0 * g[:, 1]], axis=1).reshape(-1, 2, 2)
    for i in range(3):
        d[:, 2 * i:2 * i + 2, 2 * i:2 * i + 2] += s
    wa = (w[:, None, None] * (d @ a)).reshape(-1, a.shape[2])
    hz = a.reshape(-1, a.shape[2]).T @ wa
    # ddet/dF with det = c0 c1 - c2^2.
    ddet = c[:, 1, None] * b[:, 0] + c[:, 0, None] * b[:, 1] - 2.0 * c[:, 2, None] * b[:, 2]  # (n, 6)
    col = -w[:, None] * np.einsum("nc,nck->nk", ddet, a)
    hm = np.zeros((a.shape[2], n_units))
    on = u >= 0
    np.add.at(hm.T, u[on], col[on])
    return hz, hm
