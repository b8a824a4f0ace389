"""The axisymmetric reference itself is checked before it is used as a reference.

Each self-check asserts internally (see ``axisym_reference``): the flat state is exact,
the reaction force is the energy derivative, the axial force is constant along the
free membrane, and a separate 1D finite-element solution agrees."""

import pytest
from axisym_reference import (
    _selfcheck_energy,
    _selfcheck_fe_crosscheck,
    _selfcheck_flat_state,
    _selfcheck_force_constant,
)


@pytest.mark.parametrize("prestretch", [1.1, 1.2])
def test_reference_flat_state_is_exact(prestretch):
    out = _selfcheck_flat_state(prestretch)
    assert out["F"] == 0.0 and out["relC"] < 1e-12


def test_reference_force_is_its_energy_derivative_and_constant_along_the_meridian():
    _selfcheck_energy(1.1, 2730.0, 15e-3)
    _selfcheck_force_constant(1.1, 2730.0, 15e-3)


def test_reference_agrees_with_an_independent_1d_finite_element_solution():
    out = _selfcheck_fe_crosscheck(1.2, 2300.0, 15e-3)
    assert out["relF"] < 1e-6 and out["relC"] < 1e-6
