"""The mesh's region tags put every unit where the geometry says it is.

Forces, capacitances and boundary conditions are all read through these tags
(``indenter_nodes``, ``centre_nodes``, ``frame_nodes``, ``element_unit``), and a
symmetric array hides a swap between units from every mirror test.  So each tag is
checked against the geometry directly: unit k's disk and centre lie at
``unit_centres(cfg)[k]``, the frame nodes are exactly the nodes on the outer
boundary, and each unit's elements cover exactly its electrode.
"""

import math

import numpy as np
import pytest
from conftest import COARSE

from dea_array_twin import ArrayConfig
from dea_array_twin.model.geometry import unit_centres
from dea_array_twin.model.membrane import MembraneModel

LAYOUTS = {
    "1x3": ArrayConfig(**COARSE),
    "2x2": ArrayConfig(rows=2, cols=2, length=0.09, width=0.09, **COARSE),
    "2x3 square electrodes": ArrayConfig(rows=2, cols=3, length=0.12, width=0.08, electrode_shape="square",
                                         **COARSE),
    "circular": ArrayConfig(layout="circular", frame_radius=0.025),
}


@pytest.fixture(scope="module", params=sorted(LAYOUTS))
def model(request):
    return MembraneModel(LAYOUTS[request.param])


def _centroids(model):
    """Reference centroid of every element (its corner triangle) [m], shape (ne, 2)."""
    return model.mesh.nodes[model.mesh.elements[:, :3]].mean(axis=1)


def test_each_units_centre_node_sits_at_its_unit_centre(model):
    centres = unit_centres(model.cfg)
    nodes = model.mesh.nodes[model.mesh.centre_nodes]
    # The centre is an embedded point of the geometry, so exact up to gmsh's round-off.
    np.testing.assert_allclose(nodes, centres, atol=1e-12)


def test_each_units_disk_is_exactly_the_nodes_within_r_of_its_centre(model):
    cfg, mesh = model.cfg, model.mesh
    r = cfg.scaled("indenter_radius")
    for k, centre in enumerate(unit_centres(cfg)):
        dist = np.linalg.norm(mesh.nodes - centre, axis=1)
        inside = np.flatnonzero(dist <= r * (1 + 1e-9))
        assert np.array_equal(np.sort(mesh.indenter_nodes[k]), inside), f"unit {k + 1}"


def test_frame_nodes_are_exactly_the_nodes_on_the_outer_boundary(model):
    cfg, mesh = model.cfg, model.mesh
    x, y = mesh.nodes[:, 0], mesh.nodes[:, 1]
    if cfg.layout == "circular":
        on_edge = np.abs(np.hypot(x, y) - cfg.scaled("frame_radius")) <= 1e-9
    else:
        half_l, half_w = 0.5 * cfg.scaled("length"), 0.5 * cfg.scaled("width")
        on_edge = (np.abs(np.abs(x) - half_l) <= 1e-12) | (np.abs(np.abs(y) - half_w) <= 1e-12)
    assert np.array_equal(np.sort(mesh.frame_nodes), np.flatnonzero(on_edge))


def test_each_units_elements_cover_its_electrode_and_nothing_else(model):
    """Element centroids lie on their own unit's electrode, passive ones on none, and
    each unit's meshed area is the electrode's: exact for straight edges; a circle
    drawn with quadratic arcs loses O((h/R)^4) of its area, at most 1.1e-4 on the
    coarse mesh (edge h = R/2), so 3e-4."""
    cfg, mesh = model.cfg, model.mesh
    centres = unit_centres(cfg)
    centroid = _centroids(model)
    radius = 0.5 * cfg.scaled("electrode_diameter")
    half_side = 0.5 * cfg.square_side
    for k, centre in enumerate(centres):
        offset = centroid - centre
        if cfg.electrode_shape == "circle":
            on = np.hypot(offset[:, 0], offset[:, 1]) < radius
        else:
            on = np.all(np.abs(offset) < half_side, axis=1)
        assert np.array_equal(mesh.element_unit == k, on), f"unit {k + 1}"
        assert model.electrode_area[k] == pytest.approx(math.pi * radius**2, rel=3e-4)
        disk = (mesh.element_unit == k) & mesh.element_in_indenter
        in_disk = np.hypot(offset[:, 0], offset[:, 1]) < cfg.scaled("indenter_radius")
        assert np.array_equal(disk, in_disk), f"unit {k + 1} disk"
