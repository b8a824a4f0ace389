"""Training a :class:`~.reduced.ReducedModel` from finite-element snapshots (arrays in, arrays out).

Given FE equilibria ``x_s`` at commands ``(d_s, V_s)`` spread over an
:class:`~.reduced.Envelope`:

1. **Lifting** (:func:`linear_responses` at the flat state, 0 V): ``L_k = e_k - K_ff^-1
   K_fp e_k`` for each driven unit, so ``x_ref + sum_k d_k L_k`` meets eqs. 8-9 exactly
   and is the linear answer of the pre-stretched membrane.
2. **POD**: the left singular vectors of ``[x_s - x_ref - L d_s]`` give the orthonormal
   basis ``V`` (first r) and the first enrichment vectors (the next ones).
3. **Enrichment** ``W`` for the error indicator: the next POD modes, the linear
   responses to each unit's Maxwell coefficient at the flat state and at the most
   deflected snapshot, and how each lifting changes there, orthonormalised against
   ``V``.
4. **Hyper-reduction** (:mod:`.ecsw`): at the snapshots projected on the basis, each
   quadrature point's contributions to ``dE/dq``, ``dE/dd`` (forces), ``dE/dw`` and
   ``dE/dm`` (electrode integrals, i.e. capacitances), each row scaled by its full
   scale (force reference, electrode integral), form ``G``; sparse non-negative
   weights reproduce ``G 1`` to ``hr_tolerance``.
5. **Monitor points**: per snapshot the point of largest ``det C`` on each electrode
   and of smallest principal stress, added with weight 0 so the reduced model reads
   the peak field and the wrinkling check where they occur.
"""

from __future__ import annotations

from collections import Counter
from dataclasses import dataclass
from typing import Callable

import numpy as np

from .ecsw import sparse_nnls
from .kernels import internal_forces, tangent_values
from .linsolve import Factoriser
from .material import energy_gradient, principal_cauchy_stresses
from .membrane import DRIVEN, FREE, MembraneModel
from .reduced import Envelope, ReducedModel, config_hash
from .rom_kernels import point_maps

#: Memory allowed for the hyper-reduction matrix G [bytes]: snapshots are thinned to fit.
HR_MATRIX_BYTES = 1e9


@dataclass(frozen=True)
class Snapshots:
    """FE equilibria for training or validation (SI units).

    Attributes
    ----------
    displacement, voltage : ndarray, shape (n, n_units)
        Commands [m], [V].
    positions : ndarray, shape (n, n_dofs)
        Converged FE positions [m].
    force, capacitance : ndarray, shape (n, n_units)
        FE outputs [N], [F].
    """

    displacement: np.ndarray
    voltage: np.ndarray
    positions: np.ndarray
    force: np.ndarray
    capacitance: np.ndarray


def _unit_maxwell(model: MembraneModel, unit: int) -> np.ndarray:
    """Per element Maxwell coefficient of 1 Pa on ``unit``'s electrode, 0 elsewhere."""
    return (model.mesh.element_unit == unit).astype(float)


def linear_responses(model: MembraneModel, x: np.ndarray, modes: tuple, voltage: np.ndarray) -> np.ndarray:
    """Linear responses at state ``x``: one per driven indenter, then one per unit's Maxwell coefficient.

    Returns an array (n_dofs, nd + n_units): column k (driven unit k) is
    ``e_k - K_ff^-1 K_fp e_k`` [m/m], ``e_k`` the z dofs of its disk; column nd + u is
    ``-K_ff^-1 dr_f/dm_u`` [m/Pa], the response to the Maxwell coefficient of unit u
    (the internal forces are linear in it).
    """
    prescribed, free = model.prescribed_dofs(modes)
    maxwell = model.maxwell(voltage)
    _, values = tangent_values(model.disc, model.pattern, x, model.yeoh, maxwell, model.thickness)
    factor = Factoriser(model.pattern, free).factor(values)
    k_fp = model.pattern.block(values, free, prescribed)
    driven = [k for k, m in enumerate(modes) if m == DRIVEN]
    out = np.zeros((model.disc.n_dofs, len(driven) + model.n_units))
    for col, k in enumerate(driven):
        e = np.isin(prescribed, 3 * model.mesh.indenter_nodes[k] + 2).astype(float)
        out[free, col] = -factor.solve(k_fp @ e)
        out[prescribed, col] = e
    r0, _ = internal_forces(model.disc, x, model.yeoh, maxwell, model.thickness)
    for u in range(model.n_units):
        r1, _ = internal_forces(model.disc, x, model.yeoh, maxwell + _unit_maxwell(model, u), model.thickness)
        out[free, len(driven) + u] = -factor.solve((r1 - r0)[free])
    return out


def _orthonormal(vectors: np.ndarray, against: np.ndarray, rtol: float = 1e-6) -> np.ndarray:
    """An orthonormal basis of ``vectors`` minus their projection on the orthonormal ``against``."""
    rest = vectors - against @ (against.T @ vectors)
    rest /= np.maximum(np.linalg.norm(rest, axis=0), 1e-300)
    u, s, _ = np.linalg.svd(rest, full_matrices=False)
    return u[:, s > rtol * s.max(initial=0.0)]


def _point_state(model: MembraneModel, amap: np.ndarray, z: np.ndarray, maxwell_point: np.ndarray):
    """``F``, ``c`` and ``g`` at every point of ``amap`` for coefficients ``z``."""
    f = amap @ z  # (n, 6)
    f1, f2 = f[:, 0::2], f[:, 1::2]
    c = np.stack([np.sum(f1 * f1, 1), np.sum(f2 * f2, 1), np.sum(f1 * f2, 1)], axis=1)
    return f1, f2, c, energy_gradient(c, model.yeoh, maxwell_point)


def hyper_reduction_matrix(model: MembraneModel, amap: np.ndarray, nc: int, coefficients: np.ndarray,
                           voltages: np.ndarray, weight: np.ndarray, unit: np.ndarray,
                           row_scale: np.ndarray) -> np.ndarray:
    """``G``: each point's scaled contributions to ``[dE/dd, dE/dq, dE/dw, dE/dm]`` at each state.

    Parameters
    ----------
    amap : ndarray, shape (n_points, 6, nc + nw)
        ``A_p`` over ``[1, d, q, w]`` for every candidate point.
    nc : int
        Columns of ``[1, d, q]``.
    coefficients : ndarray, shape (n_states, nc)
        ``[1, d, q]`` of each state.
    voltages : ndarray, shape (n_states, n_units)
    weight : ndarray, shape (n_points,)
        ``t0`` times the reference area of each point [m^3].
    unit : ndarray of int, shape (n_points,)
    row_scale : ndarray, shape (nc - 1 + nw + n_units,)
        Multiplies each row of a state's block.

    Returns
    -------
    ndarray, shape (n_states * len(row_scale), n_points)
    """
    n_units = model.n_units
    rows = []
    for z, v in zip(coefficients, voltages):
        m_unit = 0.5 * model.cfg.permittivity * (v / model.thickness) ** 2
        m_point = np.where(unit >= 0, m_unit[np.maximum(unit, 0)], 0.0)
        f1, f2, c, g = _point_state(model, amap[:, :, :nc], z, m_point)
        s00, s11, s01 = 2.0 * g[:, 0], 2.0 * g[:, 1], g[:, 2]
        pk = np.empty((len(weight), 6))
        pk[:, 0::2] = f1 * s00[:, None] + f2 * s01[:, None]
        pk[:, 1::2] = f1 * s01[:, None] + f2 * s11[:, None]
        block = np.einsum("pc,pck->kp", weight[:, None] * pk, amap[:, :, 1:])  # (nc - 1 + nw, n_points)
        det = c[:, 0] * c[:, 1] - c[:, 2] ** 2
        m_rows = np.zeros((n_units, len(weight)))
        on = unit >= 0
        m_rows[unit[on], np.flatnonzero(on)] = -weight[on] * det[on]
        rows.append(np.vstack([block, m_rows]) * row_scale[:, None])
    return np.vstack(rows)


def _monitor_points(model: MembraneModel, snaps: Snapshots, held: np.ndarray, per_kind: int = 4) -> np.ndarray:
    """Flat point indices that most often hold a unit's largest ``det C`` or the smallest principal stress.

    For each unit (largest ``det C``) and for the smallest stress outside held disks,
    the ``per_kind`` points that are the extreme in the most snapshots.
    """
    ne, nq = model.disc.weight.shape
    unit = np.repeat(model.mesh.element_unit, nq)
    free_points = np.flatnonzero(~np.repeat(held, nq))
    counts = [Counter() for _ in range(model.n_units + 1)]
    for x, v in zip(snaps.positions, snaps.voltage):
        _, point = internal_forces(model.disc, x, model.yeoh, model.maxwell(v), model.thickness)
        c, g = point.c.reshape(-1, 3), point.g.reshape(-1, 3)
        det = c[:, 0] * c[:, 1] - c[:, 2] ** 2
        for u in range(model.n_units):
            idx = np.flatnonzero(unit == u)
            counts[u][int(idx[np.argmax(det[idx])])] += 1
        sigma = principal_cauchy_stresses(c[free_points], g[free_points])[:, 0]
        counts[-1][int(free_points[np.argmin(sigma)])] += 1
    return np.unique([p for count in counts for p, _ in count.most_common(per_kind)]).astype(np.int64)


def held_elements(model: MembraneModel, modes: tuple) -> np.ndarray:
    """Elements inside the disk of a driven unit (rigidly held: left out of the smallest stress)."""
    mesh = model.mesh
    driven = np.array([m == DRIVEN for m in modes] + [False])
    return mesh.element_in_indenter & driven[mesh.element_unit]


def build_reduced_model(model: MembraneModel, envelope: Envelope, snaps: Snapshots, n_modes: int,
                        tolerance: float, hr_tolerance: float | None = None, n_extra_modes: int = 8,
                        progress: Callable[[str], None] | None = None) -> ReducedModel:
    """Lifting, POD basis, enrichment and ECSW weights from FE snapshots (see the module docstring).

    Parameters
    ----------
    model : MembraneModel
        The FE model the snapshots come from.
    envelope : Envelope
        The commands the snapshots were sampled from.
    snaps : Snapshots
        The training equilibria.
    n_modes : int
        POD modes r (at most the number of snapshots).
    tolerance : float
        Relative output error the indicator tests against (stored in the ROM).
    hr_tolerance : float, optional
        ECSW relative tolerance (default ``tolerance / 20``).
    n_extra_modes : int
        POD modes after the first r that join the enrichment.
    progress : callable, optional
        Called with a line of text at each stage.
    """
    say = progress or (lambda text: None)
    modes = envelope.modes
    if any(m not in (DRIVEN, FREE) for m in modes):
        raise ValueError(f"a ROM is trained with driven and free units only (a biased unit is trained as driven: "
                         f"the reduced twin solves for its height), got {list(modes)}")
    n = snaps.positions.shape[0]
    if not 1 <= n_modes <= n:
        raise ValueError(f"n_modes must be in [1, {n}] (the number of snapshots), got {n_modes}")
    if model.cfg.slip_factor:
        raise ValueError("a ROM cannot represent the slip correction (eq. 11): its frame moves with the "
                         "displacement; train without slip_displacement/slip_factor")
    driven = envelope.driven
    nd = driven.size
    reference = model.flat_state()
    say("lifting: linear response of the pre-stretched membrane to each indenter")
    flat = linear_responses(model, reference, modes, np.zeros(model.n_units))
    lift = flat[:, :nd]
    d = snaps.displacement[:, driven]
    residual = snaps.positions - reference - d @ lift.T  # (n, n_dofs)
    say(f"POD of {n} snapshots")
    _, s, vt = np.linalg.svd(residual, full_matrices=False)
    basis = np.ascontiguousarray(vt[:n_modes].T)
    q = residual @ basis
    deep = int(np.argmax(np.abs(d).sum(axis=1))) if nd else int(np.argmax(snaps.voltage.sum(axis=1)))
    say("enrichment: responses to each voltage and indenter, flat and at the deepest snapshot")
    bent = linear_responses(model, snaps.positions[deep], modes, snaps.voltage[deep])
    extra = [vt[n_modes:n_modes + n_extra_modes].T, flat[:, nd:], bent[:, nd:], bent[:, :nd] - lift]
    enrichment = np.ascontiguousarray(_orthonormal(np.hstack(extra), basis))
    held = held_elements(model, modes)
    ne, nq = model.disc.weight.shape
    elements, points = np.divmod(np.arange(ne * nq), nq)
    vectors = np.hstack([reference[:, None], lift, basis, enrichment])
    amap = point_maps(model.disc, elements, points, vectors)
    nc = 1 + nd + n_modes
    unit = np.repeat(model.mesh.element_unit, nq)
    weight = model.thickness * model.disc.weight.ravel()
    force_ref = np.abs(snaps.force).max(axis=0)
    force_ref = np.where(force_ref > 0, force_ref, force_ref.max(initial=0.0) or model.force_scale)
    flat_integral = model.thickness * model.cfg.prestretch**4 * model.electrode_area
    row_scale = np.concatenate([1.0 / force_ref[driven], np.full(n_modes + enrichment.shape[1],
                                                                 1.0 / force_ref.mean()), 1.0 / flat_integral])
    rows_per_state = row_scale.size
    n_hr = int(max(1, min(n, HR_MATRIX_BYTES // (8 * rows_per_state * weight.size))))
    chosen = np.linspace(0, n - 1, n_hr).round().astype(int)
    coefficients = np.hstack([np.ones((n, 1)), d, q])
    say(f"hyper-reduction: {weight.size} candidate points, {n_hr} snapshots x {rows_per_state} rows")
    g = hyper_reduction_matrix(model, amap, nc, coefficients[chosen], snaps.voltage[chosen], weight, unit,
                               row_scale)
    hr_tol = hr_tolerance if hr_tolerance is not None else tolerance / 20.0
    sparse = sparse_nnls(g, g.sum(axis=1), hr_tol)
    del g
    say(f"ECSW kept {sparse.index.size} points (relative error {sparse.relative_error:.2e})")
    monitors = np.setdiff1d(_monitor_points(model, snaps, held), sparse.index)
    index = np.concatenate([sparse.index, monitors])
    xi = np.concatenate([sparse.weight * weight[sparse.index], np.zeros(monitors.size)])
    order = np.argsort(index)
    index, xi = index[order], xi[order]
    return ReducedModel(
        config=model.cfg.to_dict(), config_hash=config_hash(model.cfg), envelope=envelope, reference=reference,
        lift=np.ascontiguousarray(lift), basis=basis, enrichment=enrichment, point_element=elements[index],
        point_index=points[index], point_weight=xi, force_reference=force_ref, tolerance=float(tolerance),
        train_parameters=np.hstack([d, snaps.voltage]), train_coordinates=q, singular_values=s,
        validation={"snapshots": int(n), "hr_snapshots": int(n_hr), "hr_relative_error": sparse.relative_error,
                    "hr_tolerance": hr_tol})
