"""The compiled element kernels (model/kernels.py) against the numpy reference (model/assembly.py)."""

import numpy as np
import pytest

from dea_array_twin import ArrayConfig
from dea_array_twin.model import kernels
from dea_array_twin.model.assembly import element_tangents, internal_forces
from dea_array_twin.model.material import energy_density, principal_cauchy_stresses
from dea_array_twin.model.membrane import MembraneModel


def _wavy_state(model: MembraneModel) -> np.ndarray:
    """A pre-stretched membrane with an out-of-plane bump and in-plane shear (no symmetry)."""
    nodes = model.mesh.nodes
    x = np.zeros((nodes.shape[0], 3))
    x[:, :2] = 1.1 * nodes
    x[:, 2] = 0.005 * np.cos(nodes[:, 0] / 0.02) * np.cos(nodes[:, 1] / 0.03)
    x[:, 0] += 0.001 * np.sin(nodes[:, 1] / 0.01)
    return x.ravel()


@pytest.mark.parametrize("order", [1, 2])
def test_compiled_residual_and_tangent_equal_the_numpy_reference(order):
    """Residual, point state and every tangent nonzero to 1e-12 of their largest entry, with
    the electrostatic term on the electrode (Maxwell coefficient 4e4 Pa, about 2700 V)."""
    model = MembraneModel(ArrayConfig(layout="circular", element_order=order))
    x = _wavy_state(model)
    maxwell = np.where(model.mesh.element_unit >= 0, 4e4, 0.0)
    args = (model.yeoh, maxwell, model.thickness)
    r_ref, point_ref = internal_forces(model.disc, x, *args)
    r, point = kernels.internal_forces(model.disc, x, *args)
    for ours, ref in ((r, r_ref), (point.c, point_ref.c), (point.g, point_ref.g)):
        assert np.abs(ours - ref).max() <= 1e-12 * np.abs(ref).max()
    _, ke = element_tangents(model.disc, x, *args)
    values_ref = model.pattern.values(ke)
    r_k, values = kernels.tangent_values(model.disc, model.pattern, x, *args)
    assert np.abs(values - values_ref).max() <= 1e-12 * np.abs(values_ref).max()
    assert np.abs(r_k - r_ref).max() <= 1e-12 * np.abs(r_ref).max()
    # A test that can fail: the Maxwell term changes the tangent far above that tolerance.
    _, off = kernels.tangent_values(model.disc, model.pattern, x, model.yeoh, 0.0 * maxwell, model.thickness)
    assert np.abs(off - values_ref).max() > 1e-6 * np.abs(values_ref).max()


def test_compiled_energy_and_smallest_principal_stress_equal_the_numpy_reference():
    """What every result reports besides forces: the stored energy (sum of t0 w Psi) and the
    smallest principal Cauchy stress outside held disks, to 1e-12 relative."""
    model = MembraneModel(ArrayConfig(layout="circular"))
    x = _wavy_state(model)
    maxwell = np.where(model.mesh.element_unit >= 0, 4e4, 0.0)
    _, point = internal_forces(model.disc, x, model.yeoh, maxwell, model.thickness)
    reference = model.thickness * np.sum(model.disc.weight * energy_density(point.c, model.yeoh, maxwell[:, None]))
    assert kernels.energy(model.disc, point, model.yeoh, maxwell, model.thickness) == pytest.approx(
        reference, rel=1e-12)
    held = model.mesh.element_in_indenter
    sigma = principal_cauchy_stresses(point.c[~held], point.g[~held])[..., 0]
    assert kernels.min_principal_stress(point, held) == pytest.approx(sigma.min(), rel=1e-12)
    assert kernels.min_principal_stress(point, np.zeros_like(held)) <= sigma.min()


def test_node_block_columns_follow_their_first_in_the_tangent_pattern():
    """The compiled tangent adds each row of a 3x3 node block at ``element_block_positions`` and
    the two entries after it: that must be where the pattern keeps columns 3 b + 1 and 3 b + 2."""
    pattern = MembraneModel(ArrayConfig(layout="circular", element_order=2)).pattern
    ne, k, _ = pattern.element_positions.shape
    starts = pattern.element_block_positions
    assert starts.shape == (ne, k, k // 3)
    for j in range(3):
        assert np.array_equal(pattern.element_positions[:, :, j::3], starts + j)
    assert np.array_equal(pattern.cols[starts] % 3, np.zeros_like(starts))


def test_compiled_electrode_sums_equal_the_numpy_reference():
    """Eq. 7's integral per unit (sum of w det C over its electrode) and the largest det C there
    (the peak field's stretch), to 1e-12 relative, on a 1-by-3 whose units deform differently."""
    model = MembraneModel(ArrayConfig(element_order=1))
    x = _wavy_state(model)
    _, point = internal_forces(model.disc, x, model.yeoh, np.zeros(model.mesh.n_elements), model.thickness)
    det = point.c[..., 0] * point.c[..., 1] - point.c[..., 2] ** 2
    area, peak = kernels.electrode_sums(model.disc, point, 3)
    for k in range(3):
        electrode = model.mesh.element_unit == k
        assert area[k] == pytest.approx(np.sum(model.disc.weight[electrode] * det[electrode]), rel=1e-12)
        assert peak[k] == pytest.approx(det[electrode].max(), rel=1e-12)
    assert len(set(np.round(area / area[0], 9))) == 3  # the units differ: a mix-up of units would show
