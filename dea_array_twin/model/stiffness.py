"""The membrane's stiffness at the indenters: how each unit's force answers every indenter's move.

At an equilibrium with the indenter disks of some units held (driven or biased), move
disk j rigidly by ``dw_j`` and let the membrane re-equilibrate: the force on disk i
(eq. 10) changes by ``K_ij dw_j`` with the condensed stiffness

    K_ij = dF_i/dw_j = 1_i^T (K_pp - K_pf K_ff^-1 K_fp) 1_j        [N/m],

``1_j`` the indicator of disk j's z dofs among the prescribed ones.  ``K`` is symmetric
(``F`` derives from the membrane's energy); its diagonal is the slope of a unit's driven
force curve with every other disk held, the off-diagonal entries the coupling between
units (the slope of a unit's force when a neighbour moves).  Bias design
(:mod:`dea_array_twin.design`) uses it to carry a unit's force curves to neighbour
heights it did not sweep; the stability of biased units is ``K - diag(dB/dw)``
(:mod:`.indenters`).
"""

from __future__ import annotations

import numpy as np

from .indenters import IndenterBorder
from .membrane import FREE, held
from .solver import SolveStats
from .twin import ArrayTwin

__all__ = ["indenter_stiffness"]


def indenter_stiffness(twin: ArrayTwin) -> tuple[np.ndarray, np.ndarray]:
    """The condensed stiffness ``dF_i/dw_j`` [N/m] of the held indenters at the twin's last state.

    Uses the solver's factorisation when it was computed at that state (a solve with
    ``check_stability``), otherwise factors the tangent there; the twin is not changed.

    Returns
    -------
    units : ndarray of int
        The units whose disks are held (driven or biased, not lifted off), 0-based.
    stiffness : ndarray, shape (len(units), len(units))
        ``dF_i/dw_j`` between them.

    Raises
    ------
    ValueError
        The twin has not solved yet.
    """
    res = twin.last
    if res is None:
        raise ValueError("indenter_stiffness needs a solved state: call twin.solve first")
    model = twin.model
    as_solved = tuple(FREE if lifted else mode for mode, lifted in zip(res.modes, res.lifted_off))
    units = np.array([k for k, mode in enumerate(as_solved) if held(mode)], dtype=int)
    x = res.positions.ravel()
    prescribed, free = model.prescribed_dofs(as_solved)
    fact = twin.solver.factorisation
    if (fact is None or fact.state is None or not np.array_equal(fact.free, free)
            or not np.array_equal(fact.state, x)):
        fact = twin.solver.factorise_at(x, model.maxwell(res.voltage), free, prescribed, SolveStats())
    border = IndenterBorder.for_units(model, units, prescribed, load=None)
    return units, border.membrane_stiffness(fact)
