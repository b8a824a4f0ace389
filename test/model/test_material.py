"""The constitutive law and the element kernels against closed forms and finite differences."""

import numpy as np
import pytest

from dea_array_twin import ArrayConfig
from dea_array_twin.model.assembly import (
    discretise,
    element_tangents,
    internal_forces,
    total_energy,
)
from dea_array_twin.model.material import (
    EPS0,
    Yeoh,
    energy_density,
    energy_derivatives,
    energy_gradient,
    equibiaxial_cauchy_stress,
    principal_cauchy_stresses,
)
from dea_array_twin.model.membrane import MembraneModel
from dea_array_twin.model.mesh import build_mesh

YEOH = Yeoh(0.18e6, 10.84e3, -0.11e3)


def test_energy_derivatives_match_central_differences():
    c = np.array([[1.3, 1.1, 0.2], [1.21, 1.21, 0.0], [2.5, 1.4, -0.6]])
    k = np.array([3e4, 0.0, 1e5])
    g, h = energy_derivatives(c, YEOH, k)
    assert np.allclose(energy_gradient(c, YEOH, k), g, rtol=1e-14)
    step = 1e-6
    for i in range(3):
        e = np.zeros(3)
        e[i] = step
        fd_g = (energy_density(c + e, YEOH, k) - energy_density(c - e, YEOH, k)) / (2 * step)
        fd_h = (energy_gradient(c + e, YEOH, k) - energy_gradient(c - e, YEOH, k)) / (2 * step)
        # Central differences: truncation ~ step^2 * Psi''' ~ 1e-12 relative, rounding ~ 1e-16 / 1e-6.
        assert np.allclose(g[:, i], fd_g, rtol=1e-7)
        assert np.allclose(h[:, :, i], fd_h, rtol=1e-7)


@pytest.mark.parametrize("voltage", [0.0, 2730.0])
@pytest.mark.parametrize("stretch", [1.1, 1.2, 1.8])
def test_equibiaxial_patch_stress_matches_closed_form(stretch, voltage):
    """A homogeneously stretched cone-DEA membrane: every point of the electrode carries
    the closed-form Yeoh-minus-Maxwell stress, the passive ring the Yeoh stress, and the
    frame reaction equals sigma * t * perimeter of the deformed frame."""
    cfg = ArrayConfig(layout="circular", prestretch=stretch)
    model = MembraneModel(cfg)
    x = model.flat_state()
    maxwell = model.maxwell(np.array([voltage]))
    _, point = internal_forces(model.disc, x, model.yeoh, maxwell, cfg.thickness)
    sigma = principal_cauchy_stresses(point.c, point.g)
    k = 0.5 * EPS0 * cfg.epsr * (voltage / cfg.thickness) ** 2
    electrode = model.mesh.element_unit >= 0
    assert np.allclose(sigma[electrode], equibiaxial_cauchy_stress(stretch, model.yeoh, k), rtol=1e-12)
    passive_sigma = equibiaxial_cauchy_stress(stretch, model.yeoh, 0.0)
    assert np.allclose(sigma[~electrode], passive_sigma, rtol=1e-12)
    # Hand check of the closed form itself at lp = 1.1, V = 0.
    if stretch == 1.1 and voltage == 0.0:
        i1 = 2 * 1.1**2 + 1.1**-4 - 3
        expected = 2 * (0.18e6 + 2 * 10.84e3 * i1 - 3 * 0.11e3 * i1**2) * (1.1**2 - 1.1**-4)
        assert passive_sigma == pytest.approx(expected, rel=1e-14)
    # Frame reaction (force the frame exerts outwards) = sigma * (t0 / lp^2) * 2 pi lp R.
    r, _ = internal_forces(model.disc, x, model.yeoh, maxwell, cfg.thickness)
    frame = model.mesh.frame_nodes
    radial = model.mesh.nodes[frame] / np.linalg.norm(model.mesh.nodes[frame], axis=1)[:, None]
    pull = np.sum(r.reshape(-1, 3)[frame, :2] * radial)
    exact = passive_sigma * cfg.thickness / stretch**2 * 2 * np.pi * stretch * cfg.frame_radius
    # The quadratic circle is not exactly a circle: allow the polygonal-perimeter error.
    assert pull == pytest.approx(exact, rel=1e-4)


def test_internal_forces_and_tangent_match_energy_differences():
    cfg = ArrayConfig(layout="circular")
    disc = discretise(build_mesh(cfg))
    nodes = disc.mesh.nodes
    x = np.zeros((nodes.shape[0], 3))
    x[:, :2] = 1.1 * nodes
    x[:, 2] = 0.005 * np.cos(nodes[:, 0] / 0.02) * np.cos(nodes[:, 1] / 0.03)
    x[:, 0] += 0.001 * np.sin(nodes[:, 1] / 0.01)
    x = x.ravel()
    maxwell = np.where(disc.mesh.element_unit >= 0, 4e4, 0.0)
    args = (YEOH, maxwell, cfg.thickness)
    r, ke = element_tangents(disc, x, *args)
    assert np.abs(r - internal_forces(disc, x, *args)[0]).max() <= 1e-12 * np.abs(r).max()
    v = np.random.default_rng(0).standard_normal(x.size)
    h = 1e-8
    fd = (total_energy(disc, x + h * v, *args) - total_energy(disc, x - h * v, *args)) / (2 * h)
    assert fd == pytest.approx(r @ v, rel=1e-6)
    h = 1e-7
    k_v = np.zeros_like(x)
    np.add.at(k_v, disc.dofs, np.einsum("eij,ej->ei", ke, v[disc.dofs]))
    fd_k = (internal_forces(disc, x + h * v, *args)[0] - internal_forces(disc, x - h * v, *args)[0]) / (2 * h)
    assert np.abs(fd_k - k_v).max() <= 1e-4 * np.abs(fd_k).max()
