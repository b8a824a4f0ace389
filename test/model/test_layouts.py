"""Other layouts: N x M grids, square electrodes, unit numbering and geometry checks."""

import math
from pathlib import Path

import numpy as np
import pytest
import yaml

from dea_array_twin import ArrayConfig, ArrayTwin, ConfigError, load_config
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


def test_experimental_hv_is_the_papers_voltage_per_prestretch_and_refuses_other_prestretches():
    """Section 5.1: 2730 V at lp = 1.10, 2300 V at lp = 1.20; no rule in between is invented."""
    assert ArrayConfig(prestretch=1.10).experimental_hv() == 2730.0
    assert ArrayConfig(prestretch=1.2).experimental_hv() == 2300.0
    with pytest.raises(ConfigError, match="no experimental HV for prestretch 1.15.*1.1, 1.2"):
        ArrayConfig(prestretch=1.15).experimental_hv()
    own = ArrayConfig(prestretch=1.3, experimental_hv_prestretch=[1.3], experimental_hv_voltage=[2000])
    assert own.experimental_hv() == 2000.0 and isinstance(own.experimental_hv_voltage[0], float)


@pytest.mark.parametrize("changes, field", [
    ({"experimental_hv_voltage": (2730.0,)}, "experimental_hv_voltage"),
    ({"experimental_hv_prestretch": (1.2, 1.1)}, "experimental_hv_prestretch"),
    ({"experimental_hv_prestretch": (1.0, 1.2)}, "experimental_hv_prestretch"),
    ({"experimental_hv_voltage": (2730.0, -1.0)}, "experimental_hv_voltage"),
    ({"experimental_hv_voltage": (2730.0, float("nan"))}, "experimental_hv_voltage"),
    ({"experimental_hv_voltage": "2730"}, "experimental_hv_voltage"),
])
def test_a_bad_experimental_hv_table_names_the_field(changes, field):
    with pytest.raises(ConfigError, match=f"^{field}"):
        ArrayConfig(**changes)


def test_the_shipped_default_yaml_holds_the_config_defaults():
    """config/default.yaml shows the defaults, the experimental HV table included."""
    path = Path(__file__).resolve().parents[2] / "config" / "default.yaml"
    assert load_config(path) == ArrayConfig()
    assert {"experimental_hv_prestretch", "experimental_hv_voltage"} <= set(yaml.safe_load(path.read_text()))
