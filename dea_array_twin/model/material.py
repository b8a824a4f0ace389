"""Electro-elastic membrane material: Yeoh elasticity plus electrostatic co-energy.

The membrane is incompressible and in plane stress, so its state at a point is the
in-plane right Cauchy-Green tensor ``C`` (2x2) with ``l1^2, l2^2 = eig(C)`` and the
thickness stretch ``l3 = 1 / sqrt(det C)``.  The energy per reference volume
(paper eqs. 4 and 5, with ``J = 1`` and ``1 / l3 = l1 l2``) is

    Psi(C) = sum_i c_i0 (I - 3)^i  -  0.5 eps0 epsr (V / t0)^2 det C,
    I = tr C + 1 / det C,

where the second term is present on electrode areas only.  All functions take ``C``
in Voigt form ``c = (C11, C22, C12)`` as arrays of shape ``(..., 3)`` and broadcast
over leading axes, so one call evaluates every quadrature point of a mesh.

Derivatives are with respect to the three independent Voigt components, so the
second Piola-Kirchhoff stress is ``S = [[2 g0, g2], [g2, 2 g1]]`` with ``g = dPsi/dc``.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

#: Vacuum permittivity [F/m] (CODATA 2018).
EPS0 = 8.8541878128e-12


@dataclass(frozen=True)
class Yeoh:
    """Yeoh coefficients [Pa] of ``Psi_M = c10 (I-3) + c20 (I-3)^2 + c30 (I-3)^3``."""

    c10: float
    c20: float
    c30: float

    def derivatives(self, x: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Return ``Y(x), Y'(x), Y''(x)`` for ``x = I - 3``."""
        c1, c2, c3 = self.c10, self.c20, self.c30
        y = x * (c1 + x * (c2 + x * c3))
        dy = c1 + x * (2.0 * c2 + 3.0 * c3 * x)
        ddy = 2.0 * c2 + 6.0 * c3 * x
        return y, dy, ddy


def _invariants(c: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Return ``det C`` and ``I = tr C + 1/det C`` of Voigt tensors ``c``."""
    det = c[..., 0] * c[..., 1] - c[..., 2] ** 2
    return det, c[..., 0] + c[..., 1] + 1.0 / det


def energy_density(c: np.ndarray, yeoh: Yeoh, maxwell: np.ndarray | float) -> np.ndarray:
    """Energy per reference volume [J/m^3].

    Parameters
    ----------
    c : ndarray, shape (..., 3)
        Voigt components ``(C11, C22, C12)`` of the in-plane right Cauchy-Green tensor.
    yeoh : Yeoh
        Elastic coefficients.
    maxwell : ndarray or float
        ``k = 0.5 eps0 epsr (V/t0)^2`` [Pa] per point, zero on passive membrane.
        Broadcast against ``c[..., 0]``.

    Returns
    -------
    ndarray, shape (...)
        ``Psi = Y(I - 3) - k det C``.
    """
    det, inv = _invariants(c)
    return yeoh.derivatives(inv - 3.0)[0] - maxwell * det


def energy_gradient(c: np.ndarray, yeoh: Yeoh, maxwell: np.ndarray | float) -> np.ndarray:
    """First derivatives ``g = Y' dI - k dJ2`` of ``Psi`` w.r.t. ``(C11, C22, C12)`` (see below)."""
    det, inv = _invariants(c)
    dy = yeoh.derivatives(inv - 3.0)[1]
    a = dy / det**2
    g = np.empty_like(c)
    g[..., 0] = dy - (a + maxwell) * c[..., 1]
    g[..., 1] = dy - (a + maxwell) * c[..., 0]
    g[..., 2] = 2.0 * (a + maxwell) * c[..., 2]
    return g


def energy_derivatives(
    c: np.ndarray, yeoh: Yeoh, maxwell: np.ndarray | float
) -> tuple[np.ndarray, np.ndarray]:
    """First and second derivatives of ``Psi`` with respect to ``(C11, C22, C12)``.

    With ``J2 = det C`` and ``I = tr C + 1/J2``,

        dI  = (1, 1, 0) - J2^-2 dJ2,        dJ2 = (C22, C11, -2 C12),
        d2I = 2 J2^-3 dJ2 dJ2^T - J2^-2 d2J2,
        g   = Y' dI - k dJ2,
        H   = Y'' dI dI^T + Y' d2I - k d2J2,

    where ``d2J2 = [[0, 1, 0], [1, 0, 0], [0, 0, -2]]``.

    Returns
    -------
    g : ndarray, shape (..., 3)
    h : ndarray, shape (..., 3, 3)
    """
    det, inv = _invariants(c)
    _, dy, ddy = yeoh.derivatives(inv - 3.0)
    maxwell = np.broadcast_to(maxwell, det.shape)
    d_det = np.stack([c[..., 1], c[..., 0], -2.0 * c[..., 2]], axis=-1)
    dd_det = np.array([[0.0, 1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, -2.0]])
    inv_det2 = 1.0 / det**2
    d_inv = -inv_det2[..., None] * d_det
    d_inv[..., :2] += 1.0
    g = dy[..., None] * d_inv - maxwell[..., None] * d_det
    outer = d_det[..., :, None] * d_det[..., None, :]
    h = (
        ddy[..., None, None] * d_inv[..., :, None] * d_inv[..., None, :]
        + dy[..., None, None] * (2.0 * (inv_det2 / det)[..., None, None] * outer)
        - (dy * inv_det2 + maxwell)[..., None, None] * dd_det
    )
    return g, h


def pk2_stress(g: np.ndarray) -> np.ndarray:
    """Second Piola-Kirchhoff stress ``S`` [Pa] (2x2) from Voigt derivatives ``g``."""
    s = np.empty(g.shape[:-1] + (2, 2))
    s[..., 0, 0] = 2.0 * g[..., 0]
    s[..., 1, 1] = 2.0 * g[..., 1]
    s[..., 0, 1] = s[..., 1, 0] = g[..., 2]
    return s


def principal_cauchy_stresses(c: np.ndarray, g: np.ndarray) -> np.ndarray:
    """In-plane principal Cauchy stresses [Pa], ascending, shape ``(..., 2)``.

    For an incompressible membrane ``sigma = F S F^T``; its in-plane eigenvalues are
    those of ``C S`` (a product of a positive definite and a symmetric matrix, so
    they are real).  A negative smallest value means compression: the real membrane
    wrinkles there, which this model does not represent.
    """
    s = pk2_stress(g)
    cm = np.empty_like(s)
    cm[..., 0, 0], cm[..., 1, 1] = c[..., 0], c[..., 1]
    cm[..., 0, 1] = cm[..., 1, 0] = c[..., 2]
    m = cm @ s
    half_trace = 0.5 * (m[..., 0, 0] + m[..., 1, 1])
    # sqrt(((m00 - m11)/2)^2 + m01 m10) avoids the cancellation of sqrt(tr^2/4 - det).
    root = np.sqrt(np.maximum((0.5 * (m[..., 0, 0] - m[..., 1, 1])) ** 2 + m[..., 0, 1] * m[..., 1, 0], 0.0))
    return np.stack([half_trace - root, half_trace + root], axis=-1)


def equibiaxial_cauchy_stress(stretch: float, yeoh: Yeoh, maxwell: float) -> float:
    """Closed-form in-plane Cauchy stress [Pa] of a homogeneous equi-biaxial stretch.

    With ``l1 = l2 = l`` and ``l3 = l^-2``:

        sigma = 2 Y'(I - 3) (l^2 - l^-4) - 2 k l^4,   I = 2 l^2 + l^-4,

    the Yeoh stress minus the Maxwell stress ``eps0 epsr (V / (t0 l3))^2``.
    """
    inv = 2.0 * stretch**2 + stretch**-4
    dy = yeoh.derivatives(np.asarray(inv - 3.0))[1]
    return float(2.0 * dy * (stretch**2 - stretch**-4) - 2.0 * maxwell * stretch**4)
