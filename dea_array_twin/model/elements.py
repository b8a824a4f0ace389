"""Lagrange triangles (3-node linear, 6-node quadratic) and their quadrature rules.

Node order follows gmsh: corners 0, 1, 2, then the mid-edge nodes of edges
(0, 1), (1, 2), (2, 0).  Quadratic elements are isoparametric, so edges that gmsh
placed on a circle are curved.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

# Dunavant degree-4 rule, 6 points (weights sum to 1, multiplied by the reference
# triangle area 1/2 below).
_A1, _B1, _W1 = 0.445948490915965, 0.108103018168070, 0.223381589678011
_A2, _B2, _W2 = 0.091576213509771, 0.816847572980459, 0.109951743655322
_DUNAVANT4 = (
    np.array([[_A1, _A1], [_A1, _B1], [_B1, _A1], [_A2, _A2], [_A2, _B2], [_B2, _A2]]),
    np.array([_W1, _W1, _W1, _W2, _W2, _W2]),
)


@dataclass(frozen=True)
class TriangleElement:
    """A Lagrange triangle with a quadrature rule.

    Attributes
    ----------
    order : int
        Polynomial order, 1 or 2.
    points : ndarray, shape (nq, 2)
        Quadrature points in the reference triangle ``(xi, eta)``.
    weights : ndarray, shape (nq,)
        Quadrature weights (they sum to the reference area 1/2).
    shape : ndarray, shape (nq, nen)
        Shape functions at the quadrature points.
    grad : ndarray, shape (nq, nen, 2)
        Reference gradients of the shape functions at the quadrature points.
    """

    order: int
    points: np.ndarray
    weights: np.ndarray
    shape: np.ndarray
    grad: np.ndarray


def shape_functions(order: int, xi: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Shape functions and their reference gradients at points ``xi`` (shape (n, 2)).

    Returns
    -------
    n : ndarray, shape (n, nen)
    dn : ndarray, shape (n, nen, 2)
    """
    x, y = xi[:, 0], xi[:, 1]
    l1, l2, l3 = 1.0 - x - y, x, y
    one, zero = np.ones_like(x), np.zeros_like(x)
    if order == 1:
        n = np.stack([l1, l2, l3], axis=1)
        dn = np.stack([np.stack([-one, -one], 1), np.stack([one, zero], 1), np.stack([zero, one], 1)], 1)
        return n, dn
    if order == 2:
        n = np.stack(
            [l1 * (2 * l1 - 1), l2 * (2 * l2 - 1), l3 * (2 * l3 - 1), 4 * l1 * l2, 4 * l2 * l3, 4 * l3 * l1],
            axis=1,
        )
        dn = np.stack(
            [
                np.stack([1 - 4 * l1, 1 - 4 * l1], 1),
                np.stack([4 * l2 - 1, zero], 1),
                np.stack([zero, 4 * l3 - 1], 1),
                np.stack([4 * (l1 - l2), -4 * l2], 1),
                np.stack([4 * l3, 4 * l2], 1),
                np.stack([-4 * l3, 4 * (l1 - l3)], 1),
            ],
            axis=1,
        )
        return n, dn
    raise ValueError(f"element order must be 1 or 2, got {order}")


def triangle(order: int) -> TriangleElement:
    """Return the triangle of ``order`` with a quadrature rule exact for its energy.

    Linear triangles have a constant deformation gradient, so one point is exact.
    Quadratic ones use the 6-point degree-4 Dunavant rule.
    """
    if order == 1:
        points, weights = np.array([[1.0 / 3.0, 1.0 / 3.0]]), np.array([1.0])
    else:
        points, weights = _DUNAVANT4
    n, dn = shape_functions(order, points)
    return TriangleElement(order, points, 0.5 * weights, n, dn)
