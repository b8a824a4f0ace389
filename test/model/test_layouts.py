"""Other layouts: N x M grids, square electrodes, unit numbering and geometry checks."""

import math

import numpy as np
import pytest

from dea_array_twin import ArrayConfig, ArrayTwin
from dea_array_twin.model.geometry import edge_distance, unit_centres


def test_default_unit_centres_and_edge_distance_follow_table_1():
    cfg = ArrayConfig()
    assert np.allclose(unit_centres(cfg), [[-0.035, 0], [0, 0], [0.035, 0]])
    assert edge_distance(cfg) == pytest.approx(0.015)  # b: H = D + 2 b
    assert ArrayConfig(scale=0.1).pitch == pytest.approx(0.0035)


def test_square_electrodes_have_the_circle_area_and_the_same_centres():
    twin = ArrayTwin(ArrayConfig(electrode_shape="square"))
    # Straight edges: the meshed area is exact.
    assert np.allclose(twin.model.electrode_area, math.pi * 0.01**2, rtol=1e-12)
    res = twin.solve([0, 0.010, 0], [0, 2730.0, 0], ("free", "driven", "free"))
    assert res.ok and res.force[1] > 0
    assert res.capacitance[0] == pytest.approx(res.capacitance[2], rel=1e-4)


def test_two_by_two_array_couples_edge_neighbours_alike():
    """Square frame, 2 x 2 units, unit 1 (top left) pushed: units 2 (right of it) and
    3 (below it) are mirror images across the diagonal, unit 4 is farther away."""
    cfg = ArrayConfig(rows=2, cols=2, length=0.09, width=0.09)
    twin = ArrayTwin(cfg)
    assert twin.n_units == 4
    centres = unit_centres(cfg)
    assert centres[0, 0] < centres[1, 0] and centres[0, 1] > centres[2, 1]
    res = twin.solve([0.012, 0, 0, 0], 0.0, ("driven", "free", "free", "free"))
    dc = res.delta_capacitance
    assert dc[1] == pytest.approx(dc[2], rel=2e-3)
    assert 0 < dc[3] < dc[1] < dc[0]
    assert np.all(res.force[1:] == 0.0) and res.force[0] > 0


def test_linear_elements_converge_to_the_quadratic_result():
    """3-node triangles on a fine mesh agree with the default 6-node mesh to 0.5%
    (linear elements converge as h^2 in energy; the 6-node default is within 0.03%)."""
    quad = ArrayTwin(ArrayConfig(layout="circular")).solve([0.010], [0.0])
    lin = ArrayTwin(ArrayConfig(layout="circular", element_order=1, mesh_size=3e-3, mesh_size_electrode=1e-3,
                                mesh_size_indenter=0.3e-3)).solve([0.010], [0.0])
    assert lin.force[0] == pytest.approx(quad.force[0], rel=5e-3)
    assert lin.capacitance[0] == pytest.approx(quad.capacitance[0], rel=5e-3)


def test_paper_hv_voltage_gives_the_critical_flat_field():
    """Eq. 14: V = Ec t0 / lp^2, so the true flat-state field V lp^2 / t0 equals Ec = 80 V/um."""
    for lp in (1.1, 1.2, 1.8):
        cfg = ArrayConfig(prestretch=lp)
        v = cfg.hv_voltage()
        assert v == pytest.approx(80e6 * 50e-6 / lp**2)
        assert v * lp**2 / cfg.thickness == pytest.approx(80e6)
    assert ArrayConfig().hv_voltage() == pytest.approx(3305.785, rel=1e-6)
