"""The circular single unit (cone DEA) against an independent axisymmetric solution.

``axisym_reference`` solves the meridional equations of the same membrane with
scipy's collocation BVP solver (tolerance 1e-9, no FE discretisation).  The 2D FE
model on its default mesh must match force and capacitance to 0.1% over 0-15 mm; the
observed difference is below 0.04% (F) and 0.02% (C), the FE discretisation error.
"""

import numpy as np
import pytest
from axisym_reference import axisymmetric_curve

from dea_array_twin import ArrayConfig, ArrayTwin

DISPLACEMENTS = np.linspace(0.0, 0.015, 16)


@pytest.mark.parametrize("prestretch, voltage", [(1.10, 0.0), (1.10, 2730.0), (1.20, 0.0), (1.20, 2300.0)])
def test_cone_dea_matches_axisymmetric_solution(prestretch, voltage):
    force_ref, cap_ref = axisymmetric_curve(DISPLACEMENTS, voltage, prestretch)
    twin = ArrayTwin(ArrayConfig(layout="circular", prestretch=prestretch))
    results = [twin.solve([d], [voltage]) for d in DISPLACEMENTS]
    force = np.array([r.force[0] for r in results])
    cap = np.array([r.capacitance[0] for r in results])
    assert abs(force[0]) < 1e-9
    assert np.allclose(force[1:], force_ref[1:], rtol=1e-3, atol=0)
    assert np.allclose(cap, cap_ref, rtol=1e-3, atol=0)
    assert all(r.ok for r in results)
