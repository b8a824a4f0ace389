"""The reduced model's building blocks: sparse non-negative weights (ECSW) and the hyper-reduced
energy's gradient and Hessian (model/rom_kernels.py) against finite differences and numpy."""

import numpy as np
import pytest
from conftest import coarse_point_maps

from dea_array_twin.model import rom_kernels
from dea_array_twin.model.ecsw import sparse_nnls


def test_sparse_nnls_finds_a_sparse_quadrature_and_a_positive_quadrature_rule():
    """b made of 12 of 300 columns: the greedy active set finds those columns (and at most a few more).
    Integrals of 10 polynomials over 300 cells: a positive rule of at most 10 of the cells."""
    rng = np.random.default_rng(4)
    g = rng.random((200, 300))
    truth = np.zeros(300)
    support = np.sort(rng.choice(300, 12, replace=False))
    truth[support] = rng.uniform(0.5, 2.0, 12)
    sparse = sparse_nnls(g, g @ truth, 1e-10)
    assert sparse.relative_error <= 1e-10
    assert set(support) <= set(sparse.index) and sparse.index.size <= 16 and np.all(sparse.weight > 0)
    np.testing.assert_allclose(g[:, sparse.index] @ sparse.weight, g @ truth, rtol=1e-9)
    # A quadrature: integrals of the Legendre polynomials P_0..P_9 over 300 equal cells of [-1, 1].
    # A positive rule with as many points as conditions exists (Caratheodory), and ECSW finds one.
    x = np.linspace(-1.0, 1.0, 300)
    cells = np.polynomial.legendre.legvander(x, 9).T * (2.0 / 300)
    b = cells.sum(axis=1)
    rule = sparse_nnls(cells, b, 1e-8)
    assert rule.relative_error <= 1e-8 and np.all(rule.weight > 0) and rule.index.size <= 10
    assert rule.weight.sum() * 2.0 / 300 == pytest.approx(2.0, rel=1e-8)  # the integral of P_0 = 1
    with pytest.raises(ValueError, match="tol"):
        sparse_nnls(cells, b, 0.0)


@pytest.fixture(scope="module")
def reduced_points():
    """Point maps of 60 quadrature points of the coarse array (:func:`conftest.coarse_point_maps`)."""
    return coarse_point_maps(60, 5)


def test_reduced_gradient_is_the_derivative_of_the_reduced_energy(reduced_points):
    """dE/dz (every column but the constant) and dE/dm_u = -sum xi det C by central differences."""
    model, fmap, wmap, xi, unit = reduced_points
    held = np.zeros(xi.size, dtype=bool)
    z = np.array([1.0, 0.5, -0.3, 0.2, 0.1, -0.4, 0.3, 0.2])
    maxwell = np.array([2e4, 3e4, 0.0])

    def energy(zz, mm):
        out = (np.empty(8), np.empty(3), np.empty(3), np.empty(3))
        e, _ = rom_kernels.evaluate(fmap, wmap, xi, unit, held, zz, mm, model.yeoh, out)
        return e, out

    _, (grad, grad_m, grad_w, _) = energy(z, maxwell)
    for j in range(1, 8):
        h = 1e-6
        step = h * np.eye(8)[j]
        fd = (energy(z + step, maxwell)[0] - energy(z - step, maxwell)[0]) / (2 * h)
        assert grad[j] == pytest.approx(fd, rel=1e-6, abs=1e-9 * np.abs(grad).max())
    for u in range(3):
        dm = 10.0
        step = dm * np.eye(3)[u]
        fd = (energy(z, maxwell + step)[0] - energy(z, maxwell - step)[0]) / (2 * dm)
        assert grad_m[u] == pytest.approx(fd, rel=1e-6, abs=1e-15)
    assert np.abs(grad_m).max() > 0 and np.abs(grad_w).max() > 0


def _pass(points, team, kind, single, z, maxwell):
    """One pass of ``kind`` by the calling thread: (energy, sigma_min, grad, grad_m, grad_w, det_max)."""
    nc, nw, nu = points[0].shape[2], points[1].shape[2], maxwell.size
    out = (np.empty(nc), np.empty(nu), np.full(nw, np.nan), np.empty(nu))
    energy, sigma = rom_kernels._pass(*points, *team, kind, single, z, maxwell, *out)
    return (energy, sigma, *out)


@pytest.mark.parametrize("dtype", [np.float64, np.float32])
def test_an_update_sums_the_gradient_along_w_from_the_stresses_it_kept(reduced_points, dtype):
    """An update's first evaluation leaves the gradient along W (the indicator's) for later, keeping each
    point's weighted stress (a ``_GRADIENT_DEFER`` pass), and sums it over the enrichment's maps alone
    when no second evaluation follows (an ``_ENRICHMENT`` pass): the same gradient as an evaluation that
    sums it, in float64 and in the float32 arithmetic of float32 maps, and the same rest."""
    model, fmap, wmap, xi, unit = reduced_points
    fmap, wmap, xi = fmap.astype(dtype), wmap.astype(dtype), xi.copy()
    xi[:3] = 0.0  # monitor points too
    held = np.zeros(xi.size, dtype=bool)
    y = model.yeoh
    points = (fmap, wmap, xi, unit, held, y.c10, y.c20, y.c30)
    z = np.array([1.0, 0.5, -0.3, 0.2, 0.1, -0.4, 0.3, 0.2])
    maxwell = np.array([2e4, 3e4, 0.0])
    single = dtype == np.float32
    team = rom_kernels.team_arrays(1, xi.size, z.size, wmap.shape[2], 3)
    team[3][:] = np.nan
    now = _pass(points, team, rom_kernels._GRADIENT, single, z, maxwell)
    deferred = list(_pass(points, team, rom_kernels._GRADIENT_DEFER, single, z, maxwell))
    assert np.all(team[3][0, :3] == 0.0) and np.isfinite(team[3][0]).all()
    assert np.all(deferred[4] == 0.0)
    out = (np.empty(z.size), np.empty(3), deferred[4], np.empty(3))
    rom_kernels._pass(*points, *team, rom_kernels._ENRICHMENT, single, z, maxwell, *out)
    for a, b in zip(now, deferred):
        np.testing.assert_allclose(b, a, rtol=1e-13, atol=0)
    assert np.abs(now[4]).max() > 0


@pytest.mark.parametrize("blas", [True, False])
def test_compiled_reduced_hessian_equals_the_numpy_reference_and_the_gradient_difference(reduced_points, blas):
    """Both ways of summing the points (BLAS products, a rank-6 update per point)."""
    model, fmap, wmap, xi, unit = reduced_points
    held = np.zeros(xi.size, dtype=bool)
    z = np.array([1.0, 0.5, -0.3, 0.2, 0.1, -0.4, 0.3, 0.2])
    maxwell = np.array([2e4, 3e4, 0.0])
    hz, hm = rom_kernels.hessian(fmap, wmap, xi, unit, z, maxwell, model.yeoh, 3, blas)
    hz_ref, hm_ref = rom_kernels.hessian_reference(fmap, wmap, xi, unit, z, maxwell, model.yeoh, 3)
    assert np.abs(hz - hz_ref).max() <= 1e-12 * np.abs(hz_ref).max()
    assert np.abs(hm - hm_ref).max() <= 1e-12 * np.abs(hm_ref).max()
    assert np.array_equal(hz, hz.T)

    def gradient(zz, mm):
        out = (np.empty(8), np.empty(3), np.empty(3), np.empty(3))
        rom_kernels.evaluate(fmap, wmap, xi, unit, held, zz, mm, model.yeoh, out)
        return np.concatenate([out[0], out[2]]), out[1]

    h = 1e-6
    for j in (1, 4, 7):
        step = h * np.eye(8)[j]
        fd = (gradient(z + step, maxwell)[0] - gradient(z - step, maxwell)[0]) / (2 * h)
        np.testing.assert_allclose(hz[j, 1:], fd[1:], rtol=1e-5, atol=1e-7 * np.abs(hz).max())
    dm = 10.0
    fd = (gradient(z, maxwell + dm * np.eye(3)[1])[0] - gradient(z, maxwell - dm * np.eye(3)[1])[0]) / (2 * dm)
    np.testing.assert_allclose(hm[1:, 1], fd[1:], rtol=1e-5, atol=1e-7 * np.abs(hm).max())


def test_reduced_hessian_by_panels_of_its_upper_triangle_equals_the_reference(reduced_points, monkeypatch):
    """The BLAS products by row panels (here 3 columns: two whole panels and a partial one over the 8
    columns) give the reference Hessian, exactly symmetric."""
    model, fmap, wmap, xi, unit = reduced_points
    monkeypatch.setattr(rom_kernels, "PANEL", 3)
    z = np.array([1.0, 0.5, -0.3, 0.2, 0.1, -0.4, 0.3, 0.2])
    maxwell = np.array([2e4, 3e4, 0.0])
    hz, _ = rom_kernels.hessian(fmap, wmap, xi, unit, z, maxwell, model.yeoh, 3)
    hz_ref, _ = rom_kernels.hessian_reference(fmap, wmap, xi, unit, z, maxwell, model.yeoh, 3)
    assert fmap.shape[2] > 2 * rom_kernels.PANEL
    assert np.abs(hz - hz_ref).max() <= 1e-12 * np.abs(hz_ref).max()
    assert np.array_equal(hz, hz.T)


def test_reduced_hessian_skips_monitor_points_and_keeps_its_accuracy_from_float32_maps(reduced_points):
    """Points of weight 0 (monitor points) add nothing (both ways of summing); float32 maps
    (reduced_twin.MAP_DTYPE) give the float64 maps' Hessian to the BLAS products' rounding, ~1e-7 of the
    largest entry (bound 1e-6), exactly symmetric."""
    model, fmap, wmap, xi, unit = reduced_points
    z = np.array([1.0, 0.5, -0.3, 0.2, 0.1, -0.4, 0.3, 0.2])
    maxwell = np.array([2e4, 3e4, 0.0])
    monitor = xi.copy()
    monitor[::7] = 0.0
    live = monitor > 0
    hz_ref, hm_ref = rom_kernels.hessian_reference(fmap[live], wmap[live], monitor[live], unit[live], z, maxwell,
                                                   model.yeoh, 3)
    for blas in (True, False):
        hz, hm = rom_kernels.hessian(fmap, wmap, monitor, unit, z, maxwell, model.yeoh, 3, blas)
        assert np.abs(hz - hz_ref).max() <= 1e-12 * np.abs(hz_ref).max()
        assert np.abs(hm - hm_ref).max() <= 1e-12 * np.abs(hm_ref).max()
    hz32, hm32 = rom_kernels.hessian(fmap.astype(np.float32), wmap.astype(np.float32), xi, unit, z, maxwell,
                                     model.yeoh, 3)
    hz64, hm64 = rom_kernels.hessian(fmap, wmap, xi, unit, z, maxwell, model.yeoh, 3)
    assert hz32.dtype == np.float64 and np.array_equal(hz32, hz32.T)
    assert 0 < np.abs(hz32 - hz64).max() <= 1e-6 * np.abs(hz64).max()
    assert np.abs(hm32 - hm64).max() <= 1e-6 * np.abs(hm64).max()


def _tangent_reference(hz, hm, nd, r, cap_factor, output_scale):
    """The update's matrices from the reduced Hessian, by numpy (inverse, products, pinv)."""
    q, dsl, w = slice(1 + nd, 1 + nd + r), slice(1, 1 + nd), slice(1 + nd + r, None)
    hqq_inv = np.linalg.inv(hz[q, q])
    sensitivity = -hqq_inv @ np.hstack([hz[q, dsl], hm[q]])
    out_q = np.vstack([hz[dsl, q], -cap_factor * hm[q].T])
    out_w = np.vstack([hz[dsl, w], -cap_factor * hm[w].T])
    schur = hz[w, w] - hz[w, q] @ hqq_inv @ hz[q, w]
    indicator = (out_q @ hqq_inv @ hz[q, w] - out_w) @ np.linalg.pinv(schur, rcond=1e-12, hermitian=True)
    return sensitivity, hqq_inv, out_q, hz[w, q], indicator / output_scale[:, None]


@pytest.mark.parametrize("case", ["positive definite", "indefinite H_qq", "singular Schur complement", "45 modes"])
def test_compiled_reduced_tangent_equals_inverse_sensitivities_and_indicator_by_numpy(case):
    """H_qq^-1 (Cholesky, or LU when H_qq is indefinite: an unstable state), the predictor dq/dp, the
    output rows and the indicator's matrix with the pseudo-inverse of S = H_ww - H_wq H_qq^-1 H_qw
    (an enrichment vector inside the basis makes S singular: its direction must be dropped, not inverted);
    also at a size where the row-oriented loops run over many rows and columns."""
    rng = np.random.default_rng(7)
    nd, r, nw, nu = (2, 6, 4, 3) if case != "45 modes" else (5, 45, 11, 6)
    k = 1 + nd + r + nw
    m = rng.normal(size=(k, k))
    hz = m @ m.T + 0.5 * np.eye(k)
    if case == "indefinite H_qq":
        hz[1 + nd, 1 + nd] = -3.0
    if case == "singular Schur complement":  # w_0 = q_0 + 2 q_1: Hessian of a dependent vector
        t = np.eye(k)
        t[1 + nd + r, :] = 0.0
        t[1 + nd + r, 1 + nd] = 1.0
        t[1 + nd + r, 2 + nd] = 2.0
        hz = t @ hz @ t.T
    hz[0], hz[:, 0] = 0.0, 0.0
    hm = rng.normal(size=(k, nu))
    cap_factor, scale = 0.3, rng.uniform(0.5, 2.0, nd + nu)
    stable, arrays = rom_kernels.reduced_tangent(hz, hm, nd, r, cap_factor, scale)
    assert stable == (case != "indefinite H_qq")
    reference = _tangent_reference(hz, hm, nd, r, cap_factor, scale)
    q = slice(1 + nd, 1 + nd + r)
    np.testing.assert_allclose(arrays[1] @ hz[q, q], np.eye(r), atol=1e-10)
    for name, got, want in zip(("dq/dp", "H_qq^-1", "dO/dq", "H_wq", "indicator"), arrays, reference):
        np.testing.assert_allclose(got, want, rtol=1e-8, atol=1e-10 * np.abs(want).max(), err_msg=name)
    if case == "singular Schur complement":
        assert np.isfinite(arrays[4]).all() and np.abs(arrays[4]).max() < 1e3 * np.abs(hz).max()


def test_combine_and_project_are_the_matrix_vector_products():
    """The field from reduced coordinates and the coordinates of a field, on the calling thread (no BLAS
    threads): numpy's products to round-off."""
    rng = np.random.default_rng(7)
    vectors, base, z, x = rng.normal(size=(3001, 37)), rng.normal(size=3001), rng.normal(size=37), rng.normal(size=3001)
    np.testing.assert_allclose(rom_kernels.combine(base, vectors, z), base + vectors @ z, rtol=1e-12, atol=1e-12)
    np.testing.assert_allclose(rom_kernels.project(vectors, x), vectors.T @ x, rtol=1e-12, atol=1e-11)
