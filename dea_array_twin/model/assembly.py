"""Energy, internal forces and consistent tangent of the membrane, vectorised.

The unknowns are the deformed positions ``x`` (3 per node, node-major: ``3 i + j``)
of every node of the reference mesh.  At a quadrature point with reference shape
gradients ``dN_a = (dN_a/dX, dN_a/dY)`` the membrane's deformation gradient is the
3x2 matrix ``F = sum_a x_a dN_a^T`` and ``C = F^T F``.  With ``g = dPsi/dc`` and
``H = d2Psi/dc2`` from :mod:`.material` (Voigt ``c = (C11, C22, C12)``):

    dc/dx_a = B_a = [2 F_1 dN_a1,  2 F_2 dN_a2,  F_1 dN_a2 + F_2 dN_a1]      (3 x 3)
    r_a  = t0 sum_q w_q  B_a^T g                                             (internal force)
    K_ab = t0 sum_q w_q (B_a^T H B_b + (dN_a . S dN_b) I_3)                   (tangent)

where ``S = [[2 g0, g2], [g2, 2 g1]]`` is the second Piola-Kirchhoff stress, so the
second term is the geometric stiffness, and ``w_q`` the reference area of the point.
"""

from __future__ import annotations

import functools
from dataclasses import dataclass

import numpy as np
import scipy.sparse as sp

from .elements import triangle
from .material import Yeoh, energy_density, energy_derivatives, energy_gradient
from .mesh import Mesh

#: Elements per block of the compiled kernels' layout (:attr:`Discretisation.grad_blocks`): one
#: vector lane each.
LANES = 64


@dataclass(frozen=True)
class Discretisation:
    """Quadrature data of a mesh, computed once.

    Attributes
    ----------
    mesh : Mesh
    grad : ndarray, shape (n_elements, nq, nen, 2)
        Reference gradients ``dN_a/dX`` at the quadrature points.
    weight : ndarray, shape (n_elements, nq)
        Reference area [m^2] carried by each quadrature point.
    dofs : ndarray, shape (n_elements, 3 nen)
        Global dof numbers of each element, node-major.
    """

    mesh: Mesh
    grad: np.ndarray
    weight: np.ndarray
    dofs: np.ndarray

    @property
    def n_dofs(self) -> int:
        """Number of dofs (3 per node)."""
        return 3 * self.mesh.n_nodes

    @functools.cached_property
    def grad_blocks(self) -> tuple[np.ndarray, np.ndarray]:
        """``grad`` as (n_blocks, nen, 2, nq, LANES) and ``weight`` as (n_blocks, nq, LANES).

        Blocks of :data:`LANES` consecutive elements, the last one padded with zeros: the
        layout of the compiled residual and tangent (:mod:`.kernels`), which work on a
        block at a time with its elements in the vector lanes and read its gradients as
        one contiguous run.
        """
        ne, nq, nen, _ = self.grad.shape
        blocks = -(-ne // LANES)
        grad = np.zeros((blocks * LANES, nq, nen, 2))
        weight = np.zeros((blocks * LANES, nq))
        grad[:ne], weight[:ne] = self.grad, self.weight
        return (np.ascontiguousarray(grad.reshape(blocks, LANES, nq, nen, 2).transpose(0, 3, 4, 2, 1)),
                np.ascontiguousarray(weight.reshape(blocks, LANES, nq).transpose(0, 2, 1)))

    @functools.cached_property
    def _grad_by_node(self) -> np.ndarray:
        """``grad`` as (ne, nen, nq*2), for ``F = x_e^T G`` as one batched product."""
        ne, nq, nen, _ = self.grad.shape
        return np.ascontiguousarray(self.grad.transpose(0, 2, 1, 3).reshape(ne, nen, nq * 2))

    @functools.cached_property
    def _grad_by_point(self) -> np.ndarray:
        """``grad`` as (ne, nq*2, nen), for ``r_e = P G^T``."""
        return np.ascontiguousarray(self._grad_by_node.transpose(0, 2, 1))


@dataclass(frozen=True)
class PointState:
    """Kinematics and stress at every quadrature point of a state.

    Attributes
    ----------
    c : ndarray, shape (ne, nq, 3)
        Voigt ``(C11, C22, C12)``.
    g : ndarray, shape (ne, nq, 3)
        ``dPsi/dc``; the second Piola-Kirchhoff stress is ``[[2 g0, g2], [g2, 2 g1]]``.
    """

    c: np.ndarray
    g: np.ndarray


def discretise(mesh: Mesh) -> Discretisation:
    """Compute reference gradients and quadrature weights of every element."""
    el = triangle(mesh.order)
    xe = mesh.nodes[mesh.elements]  # (ne, nen, 2)
    jac = np.einsum("eai,qaj->eqij", xe, el.grad)  # dX/dxi, (ne, nq, 2, 2)
    det = jac[..., 0, 0] * jac[..., 1, 1] - jac[..., 0, 1] * jac[..., 1, 0]
    if np.any(det <= 0):
        raise ValueError("mesh has an inverted or degenerate element (reference Jacobian <= 0)")
    inv = np.empty_like(jac)
    inv[..., 0, 0], inv[..., 1, 1] = jac[..., 1, 1] / det, jac[..., 0, 0] / det
    inv[..., 0, 1], inv[..., 1, 0] = -jac[..., 0, 1] / det, -jac[..., 1, 0] / det
    grad = np.einsum("qak,eqkj->eqaj", el.grad, inv)
    dofs = (3 * mesh.elements[:, :, None] + np.arange(3)).reshape(mesh.n_elements, -1)
    return Discretisation(mesh, grad, det * el.weights, dofs)


def deformation_gradient(disc: Discretisation, x: np.ndarray) -> np.ndarray:
    """``F`` (shape (ne, 3, nq, 2)) of positions ``x`` (shape (n_dofs,))."""
    xe = x.reshape(-1, 3)[disc.mesh.elements]  # (ne, nen, 3)
    ne, nq = disc.weight.shape
    return np.matmul(xe.transpose(0, 2, 1), disc._grad_by_node).reshape(ne, 3, nq, 2)


def cauchy_green(f: np.ndarray) -> np.ndarray:
    """Voigt ``(C11, C22, C12)`` (shape (ne, nq, 3)) of ``C = F^T F``."""
    f1, f2 = f[..., 0], f[..., 1]
    return np.stack([np.einsum("eiq,eiq->eq", f1, f1), np.einsum("eiq,eiq->eq", f2, f2),
                     np.einsum("eiq,eiq->eq", f1, f2)], axis=-1)


def total_energy(disc: Discretisation, x: np.ndarray, yeoh: Yeoh, maxwell: np.ndarray, thickness: float) -> float:
    """Stored energy ``t0 sum_q w_q Psi`` [J]; ``maxwell`` per element [Pa]."""
    c = cauchy_green(deformation_gradient(disc, x))
    return float(thickness * np.sum(disc.weight * energy_density(c, yeoh, maxwell[:, None])))


def _scatter(disc: Discretisation, f: np.ndarray, g: np.ndarray, thickness: float) -> np.ndarray:
    """Global internal forces from ``r_e = t0 sum_q w_q F S dN^T`` (first Piola-Kirchhoff)."""
    w = thickness * disc.weight  # (ne, nq)
    s00, s11, s01 = 2.0 * g[..., 0] * w, 2.0 * g[..., 1] * w, g[..., 2] * w
    f1, f2 = f[..., 0], f[..., 1]  # (ne, 3, nq)
    p = np.stack([f1 * s00[:, None] + f2 * s01[:, None], f1 * s01[:, None] + f2 * s11[:, None]], axis=-1)
    ne = f.shape[0]
    re = np.matmul(p.reshape(ne, 3, -1), disc._grad_by_point)  # (ne, 3, nen)
    return np.bincount(disc.dofs.ravel(), re.transpose(0, 2, 1).ravel(), minlength=disc.n_dofs)


def internal_forces(disc: Discretisation, x: np.ndarray, yeoh: Yeoh, maxwell: np.ndarray,
                    thickness: float) -> tuple[np.ndarray, PointState]:
    """Internal force vector ``dE/dx`` [N] (shape (n_dofs,)) and the point state."""
    f = deformation_gradient(disc, x)
    c = cauchy_green(f)
    g = energy_gradient(c, yeoh, maxwell[:, None])
    return _scatter(disc, f, g, thickness), PointState(c, g)


def element_tangents(disc: Discretisation, x: np.ndarray, yeoh: Yeoh, maxwell: np.ndarray,
                     thickness: float) -> tuple[np.ndarray, np.ndarray]:
    """Internal forces (n_dofs,) and element tangents (ne, 3 nen, 3 nen)."""
    f = deformation_gradient(disc, x)
    g, h = energy_derivatives(cauchy_green(f), yeoh, maxwell[:, None])
    grad = disc.grad  # (ne, nq, nen, 2)
    ne, nq, nen, _ = grad.shape
    k = 3 * nen
    f1 = f[..., 0].transpose(0, 2, 1)[:, :, None, :]  # (ne, nq, 1, 3)
    f2 = f[..., 1].transpose(0, 2, 1)[:, :, None, :]
    dn1, dn2 = grad[..., 0, None], grad[..., 1, None]  # (ne, nq, nen, 1)
    b = np.stack([2.0 * dn1 * f1, 2.0 * dn2 * f2, dn2 * f1 + dn1 * f2], axis=2).reshape(ne, nq, 3, k)
    w = thickness * disc.weight
    hb = np.matmul(h * w[..., None, None], b)  # (ne, nq, 3, k)
    ke = np.matmul(b.reshape(ne, nq * 3, k).transpose(0, 2, 1), hb.reshape(ne, nq * 3, k))
    # Geometric stiffness (dN_a . S dN_b) w, on the diagonal of every 3x3 node block.
    s00, s11, s01 = 2.0 * g[..., 0] * w, 2.0 * g[..., 1] * w, g[..., 2] * w
    s_dn = np.stack([s00[..., None] * grad[..., 0] + s01[..., None] * grad[..., 1],
                     s01[..., None] * grad[..., 0] + s11[..., None] * grad[..., 1]], axis=-1)
    geo = np.matmul(grad.transpose(0, 2, 1, 3).reshape(ne, nen, -1),
                    s_dn.transpose(0, 1, 3, 2).reshape(ne, -1, nen))
    ke = ke.reshape(ne, nen, 3, nen, 3)
    idx = np.arange(3)
    ke[:, :, idx, :, idx] += geo[None]
    return _scatter(disc, f, g, thickness), ke.reshape(ne, k, k)


class SparsePattern:
    """Sparsity pattern of the global tangent, reused by every assembly.

    ``values(ke)`` sums element matrices into the pattern's nonzeros;
    ``block(values, rows_mask, cols_mask)`` cuts a CSR block (e.g. free-free)
    without rebuilding its structure.
    """

    def __init__(self, dofs: np.ndarray, n_dofs: int):
        k = dofs.shape[1]
        rows = np.repeat(dofs, k, axis=1).ravel()
        cols = np.tile(dofs, (1, k)).ravel()
        keys, self._inverse = np.unique(rows * n_dofs + cols, return_inverse=True)
        self.rows, self.cols = keys // n_dofs, keys % n_dofs
        #: Index into the nonzeros of entry ``(p, s)`` of element ``e``'s matrix, shape (ne, k, k).
        self.element_positions = self._inverse.reshape(dofs.shape[0], k, k)
        #: ``element_positions[:, :, ::3]``, shape (ne, k, k / 3): where row ``p``'s three columns of
        #: node ``b`` start.  Dofs ``3 i + j`` of one node are neighbours in the sorted keys, and an
        #: element couples all three of each of its nodes, so those columns follow it.
        self.element_block_positions = np.ascontiguousarray(self.element_positions[:, :, ::3])
        self.n_dofs = n_dofs
        self._blocks: dict[tuple[bytes, bytes], tuple] = {}
        self._sums: dict[tuple[bytes, bytes], tuple] = {}

    def values(self, ke: np.ndarray) -> np.ndarray:
        """Global nonzero values from element matrices ``ke``."""
        return np.bincount(self._inverse, ke.ravel(), minlength=self.rows.size)

    def block(self, values: np.ndarray, row_dofs: np.ndarray, col_dofs: np.ndarray) -> sp.csr_matrix:
        """The CSR block ``K[row_dofs][:, col_dofs]`` (dof arrays sorted ascending)."""
        key = (row_dofs.tobytes(), col_dofs.tobytes())
        if key not in self._blocks:
            rmap = np.full(self.n_dofs, -1)
            rmap[row_dofs] = np.arange(row_dofs.size)
            cmap = np.full(self.n_dofs, -1)
            cmap[col_dofs] = np.arange(col_dofs.size)
            sel = np.flatnonzero((rmap[self.rows] >= 0) & (cmap[self.cols] >= 0))
            indptr = np.concatenate([[0], np.cumsum(np.bincount(rmap[self.rows[sel]], minlength=row_dofs.size))])
            self._blocks[key] = (sel, cmap[self.cols[sel]], indptr, (row_dofs.size, col_dofs.size))
        sel, indices, indptr, shape = self._blocks[key]
        return sp.csr_matrix((values[sel], indices, indptr), shape=shape)

    def column_sum(self, values: np.ndarray, row_dofs: np.ndarray, col_dofs: np.ndarray) -> np.ndarray:
        """``K[row_dofs][:, col_dofs] @ 1`` without forming the block (``row_dofs`` sorted ascending)."""
        key = (row_dofs.tobytes(), col_dofs.tobytes())
        if key not in self._sums:
            rmap = np.full(self.n_dofs, -1)
            rmap[row_dofs] = np.arange(row_dofs.size)
            cols = np.zeros(self.n_dofs, bool)
            cols[col_dofs] = True
            sel = np.flatnonzero((rmap[self.rows] >= 0) & cols[self.cols])
            self._sums[key] = (sel, rmap[self.rows[sel]], row_dofs.size)
        sel, rows, size = self._sums[key]
        return np.bincount(rows, values[sel], minlength=size)
