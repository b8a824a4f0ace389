"""The condensed stiffness dF_i/dw_j of held indenters (model/stiffness.py) against driven solves."""

import numpy as np
import pytest
from conftest import COARSE

from dea_array_twin import ArrayConfig, ArrayTwin, NewtonSettings
from dea_array_twin.model.stiffness import indenter_stiffness

TIGHT = NewtonSettings(residual_tol=1e-10, increment_tol=1e-9)


def test_indenter_stiffness_equals_central_differences_of_driven_forces_and_is_symmetric():
    """1-by-3 at 2730 V on unit 2, disks at (3, 6, 2) mm: dF_i/dw_j by +-1 um moves of disk j (all nine)."""
    twin = ArrayTwin(ArrayConfig(**COARSE), TIGHT)
    w = np.array([0.003, 0.006, 0.002])
    voltage = [0.0, 2730.0, 0.0]
    twin.solve(w, voltage, check_stability=True)
    units, stiffness = indenter_stiffness(twin)
    assert units.tolist() == [0, 1, 2]
    h = 1e-6
    reference = np.empty((3, 3))
    probe = ArrayTwin(ArrayConfig(**COARSE), TIGHT)
    for j in range(3):
        up, down = w.copy(), w.copy()
        up[j] += h
        down[j] -= h
        reference[:, j] = (probe.solve(up, voltage).force - probe.solve(down, voltage).force) / (2 * h)
    np.testing.assert_allclose(stiffness, reference, rtol=1e-4, atol=1e-4 * np.abs(reference).max())
    np.testing.assert_allclose(stiffness, stiffness.T, rtol=1e-8, atol=1e-10)
    assert stiffness[0, 1] < 0 < stiffness[1, 1]  # raising a neighbour unloads a disk


def test_indenter_stiffness_needs_a_solved_state():
    with pytest.raises(ValueError, match="needs a solved state"):
        indenter_stiffness(ArrayTwin(ArrayConfig(**COARSE)))
