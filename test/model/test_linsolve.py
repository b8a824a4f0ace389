"""The LDL^T factorisations of K_ff (model/linsolve.py, model/ldl.py): 3x3-block LDL^T against SuperLU."""

import numpy as np
import pytest
import scipy.sparse.linalg as spla
from conftest import COARSE, FREE_CENTRE

from dea_array_twin import ArrayConfig, ArrayTwin, NewtonSettings
from dea_array_twin.model import kernels
from dea_array_twin.model.linsolve import Factoriser
from dea_array_twin.model.membrane import MembraneModel
from dea_array_twin.model.solver import SolveStats


def _tangent(model: MembraneModel, x: np.ndarray, voltage: np.ndarray) -> np.ndarray:
    return kernels.tangent_values(model.disc, model.pattern, x, model.yeoh, model.maxwell(voltage),
                                  model.thickness)[1]


def _states():
    """(name, model, free dofs, tangent nonzeros) of stable and unstable states."""
    circle = MembraneModel(ArrayConfig(layout="circular"))
    _, free_c = circle.prescribed_dofs(("driven",))
    for stretch in (1.1, 0.95):  # pre-stretched (stable) and compressed (many negative eigenvalues)
        yield f"circle lp {stretch}", circle, free_c, _tangent(circle, circle.flat_state() * stretch / 1.1, np.zeros(1))
    # Both outer indenters pulled 4 mm out of the flat membrane, full Newton from there
    # without a predictor (what the solver once did): a saddle, see test_array_physics.
    saddle = ArrayTwin(ArrayConfig(**COARSE))
    _, free_s = saddle.model.prescribed_dofs(["driven"] * 3)
    prescribed_s = np.setdiff1d(np.arange(saddle.model.disc.n_dofs), free_s)
    x = saddle.model.flat_state()
    saddle.model.apply_prescribed(x, ["driven"] * 3, np.array([0.004, 0.0, 0.004]))
    x = saddle.solver._newton(x, free_s, prescribed_s, np.zeros(saddle.model.mesh.n_elements), None, SolveStats())[0]
    yield "saddle", saddle.model, free_s, _tangent(saddle.model, x, np.zeros(3))
    deflected = ArrayTwin(ArrayConfig(**COARSE))
    deflected.solve([0, 0.015, 0], [0, 2730.0, 0], FREE_CENTRE)
    _, free_d = deflected.model.prescribed_dofs(FREE_CENTRE)
    yield "15 mm at 2730 V", deflected.model, free_d, _tangent(deflected.model, deflected._x, np.array([0, 2730.0, 0]))


def test_block_ldl_inertia_and_solves_equal_superlu_on_stable_and_unstable_states():
    """The negative pivot count of the block LDL^T equals the count from SuperLU's U
    diagonal (the answer before it) on two stable and two unstable tangents; both solve
    K_ff x = b to 1e-10 of |x| against each other.  The saddle's count is checked against
    eigsh too."""
    counts = {}
    for name, model, free, values in _states():
        ours = Factoriser(model.pattern, free, "block")
        assert ours.backend == "block"
        ours = ours.factor(values)
        old = Factoriser(model.pattern, free, "superlu").factor(values)
        counts[name] = ours.negative_pivots()
        assert counts[name] == old.negative_pivots(), name
        b = np.random.default_rng(1).standard_normal(free.size)
        x_ours, x_old = ours.solve(b), old.solve(b)
        assert np.abs(x_ours - x_old).max() <= 1e-10 * np.abs(x_old).max(), name
        if name == "saddle":  # independent: that many eigenvalues below 0, and no more
            k_ff = model.pattern.block(values, free, free)
            low = np.sort(spla.eigsh(k_ff, k=counts[name] + 1, which="SA", return_eigenvectors=False))
            assert low[counts[name] - 1] < 0 < low[counts[name]]
    assert counts["circle lp 1.1"] == 0 and counts["15 mm at 2730 V"] == 0
    assert counts["saddle"] >= 1 and counts["circle lp 0.95"] > counts["saddle"]


def test_superlu_gives_the_same_curve_and_stability_flags():
    """The SuperLU back end (NewtonSettings.linear_solver) and the default give the same
    forces (solver tolerance) and flags."""
    results = {}
    for backend in ("block", "superlu"):
        twin = ArrayTwin(ArrayConfig(**COARSE), NewtonSettings(linear_solver=backend))
        results[backend] = [twin.solve([0, d, 0], [0, 2730.0, 0], FREE_CENTRE) for d in (0.004, 0.008, 0.012)]
    for a, b in zip(results["block"], results["superlu"]):
        assert a.force[1] == pytest.approx(b.force[1], rel=1e-7)
        assert a.stable is True and b.stable is True
    with pytest.raises(ValueError, match="linear_solver must be one of"):
        NewtonSettings(linear_solver="cholmod")


def test_free_dofs_that_are_not_whole_nodes_are_factored_by_superlu():
    """The block LDL^T needs all three dofs of each free node; otherwise SuperLU answers."""
    model = MembraneModel(ArrayConfig(layout="circular"))
    _, free = model.prescribed_dofs(("driven",))
    partial = free[free % 3 != 2]  # in-plane dofs only
    factoriser = Factoriser(model.pattern, partial, "block")
    assert factoriser.backend == "superlu"
    values = _tangent(model, model.flat_state(), np.zeros(1))
    b = np.ones(partial.size)
    x = factoriser.factor(values).solve(b)
    k = model.pattern.block(values, partial, partial)
    assert np.abs(k @ x - b).max() <= 1e-10


@pytest.mark.parametrize("backend", ["block", "block-uplooking"])
def test_nodes_coupled_in_some_components_only_are_factored_by_superlu(backend):
    """Whole free nodes whose coupling is not a full 3x3 block (here node 2 couples with node 0's
    x dof only) do not fit the block LDL^T's value map: SuperLU factors them, and solves."""
    from dea_array_twin.model.assembly import SparsePattern

    elements = np.array([[0, 1, 2, 3, 4, 5], [3, 4, 5, 6, 7, 8], [0, 6, 6, 6, 6, 6]])  # nodes 0-1, 1-2, x0-node 2
    pattern = SparsePattern(elements, 9)
    factoriser = Factoriser(pattern, np.arange(9), backend)
    assert factoriser.backend == "superlu"
    rng = np.random.default_rng(3)
    k = pattern.block(np.ones(pattern.rows.size), np.arange(9), np.arange(9)).toarray()
    k = k * rng.uniform(0.1, 0.2, (9, 9))
    k = k + k.T + 9.0 * np.eye(9)  # symmetric, diagonally dominant, on the same pattern
    values = k[pattern.rows, pattern.cols]
    b = np.arange(1.0, 10.0)
    assert factoriser.factor(values).solve(b) == pytest.approx(np.linalg.solve(k, b), rel=1e-12)


def test_a_zero_pivot_falls_back_to_superlu_which_solves_and_reports_the_inertia_unknown():
    """K = [[0, I], [I, 0]] (two nodes, eigenvalues +-1): the block LDL^T meets a zero 3x3 pivot
    and hands over to SuperLU, which has to pivot off the diagonal; its U then says nothing
    about the inertia, so the count is -1 (unknown), never a guess, and the solve is exact."""
    from dea_array_twin.model.assembly import SparsePattern

    pattern = SparsePattern(np.arange(6)[None, :], 6)
    k = np.block([[np.zeros((3, 3)), np.eye(3)], [np.eye(3), np.zeros((3, 3))]])
    factor = Factoriser(pattern, np.arange(6), "block").factor(pattern.values(k[None]))
    assert factor.negative_pivots() == -1
    b = np.arange(1.0, 7.0)
    assert np.abs(k @ factor.solve(b) - b).max() <= 1e-12


def test_a_checked_solve_whose_inertia_is_unknown_reports_stability_unknown(monkeypatch):
    """``stable`` is None (not True, not False) when the factorisation cannot count the
    negative eigenvalues; the force is the same as with the count known."""
    import dea_array_twin.model.solver as solver

    known = ArrayTwin(ArrayConfig(**COARSE)).solve([0, 0.004, 0], [0, 0, 0], FREE_CENTRE, check_stability=True)
    monkeypatch.setattr(solver, "negative_eigenvalues", lambda *args, **kwargs: -1)
    unknown = ArrayTwin(ArrayConfig(**COARSE)).solve([0, 0.004, 0], [0, 0, 0], FREE_CENTRE, check_stability=True)
    assert known.stable is True and unknown.stable is None
    assert "unstable" not in unknown.flags
    assert unknown.force[1] == pytest.approx(known.force[1], rel=1e-9)


def test_multifrontal_ldl_equals_the_uplooking_reference_on_stable_and_unstable_states():
    """The multifrontal factorisation (the default) and the one-block-at-a-time up-looking
    one (model/ldl.py) are the same LDL^T: equal negative pivot counts (0 on the stable
    tangents, several on the compressed circle and the saddle) and solves of K_ff x = b
    equal to 1e-12 of |x|.  Some of these factors have relaxed supernodes (explicit zeros
    stored in L), so the padded layout is exercised too."""
    padded = False
    for name, model, free, values in _states():
        fronts, reference = Factoriser(model.pattern, free, "block"), Factoriser(model.pattern, free, "block-uplooking")
        assert fronts.backend == "block" and reference.backend == "block-uplooking"
        padded |= fronts._lp[-1] > reference._lp[-1]
        ours, ref = fronts.factor(values), reference.factor(values)
        assert ours.negative_pivots() == ref.negative_pivots(), name
        b = np.random.default_rng(2).standard_normal(free.size)
        x_ours, x_ref = ours.solve(b), ref.solve(b)
        assert np.abs(x_ours - x_ref).max() <= 1e-12 * np.abs(x_ref).max(), name
    assert padded


def test_coupling_to_a_rigid_disk_move_equals_the_column_sum_of_k_fp():
    """Factorisation.coupling (K_fp 1_idx from the pattern's nonzeros, without cutting K_fp)
    equals the sum of K_fp's columns over idx, to rounding."""
    twin = ArrayTwin(ArrayConfig(**COARSE))
    twin.solve([0, 0.004, 0], 0.0, FREE_CENTRE)
    fact = twin.solver.factorisation
    idx = twin.solver.disk_groups(tuple(FREE_CENTRE))[0]
    expected = np.asarray(fact.k_fp[:, idx].sum(axis=1)).ravel()
    np.testing.assert_allclose(fact.coupling(idx), expected, rtol=0, atol=1e-12 * np.abs(expected).max())
    assert np.abs(expected).max() > 0


@pytest.mark.parametrize("below", [0, 25])
def test_large_fronts_give_the_reference_factor_and_inertia(below):
    """A 20-by-20 grid of nodes coupled through quadrilaterals (all 3x3 blocks), whose top
    fronts are larger than the membrane meshes' in the other tests.  K: random couplings
    (|row sum| < 2) on a diagonal of +-10 with ``below`` negative entries, so by Gershgorin
    exactly ``below`` negative eigenvalues (numpy's eigvalsh agrees); the multifrontal
    factorisation counts them and solves K x = b as the up-looking reference to 1e-12 of |x|."""
    from dea_array_twin.model.assembly import SparsePattern

    side = 20
    node = np.arange(side * side).reshape(side, side)
    quads = np.stack([node[:-1, :-1], node[1:, :-1], node[1:, 1:], node[:-1, 1:]], axis=-1).reshape(-1, 4)
    n_dofs = 3 * side * side
    pattern = SparsePattern((3 * quads[:, :, None] + np.arange(3)).reshape(-1, 12), n_dofs)
    mask = pattern.block(np.ones(pattern.rows.size), np.arange(n_dofs), np.arange(n_dofs)).toarray()
    rng = np.random.default_rng(16)
    k = 0.05 * mask * rng.uniform(-1.0, 1.0, (n_dofs, n_dofs))
    k = k + k.T - np.diag(np.diag(k))
    diagonal = np.full(n_dofs, 10.0)
    diagonal[rng.choice(n_dofs, below, replace=False)] = -10.0
    k[np.diag_indices(n_dofs)] = diagonal
    assert np.abs(k - np.diag(diagonal)).sum(axis=1).max() < 2.0
    assert np.count_nonzero(np.linalg.eigvalsh(k) < 0) == below
    values = k[pattern.rows, pattern.cols]

    ours = Factoriser(pattern, np.arange(n_dofs), "block").factor(values)
    reference = Factoriser(pattern, np.arange(n_dofs), "block-uplooking").factor(values)
    assert ours.negative_pivots() == reference.negative_pivots() == below
    b = rng.standard_normal(n_dofs)
    x_ours, x_ref = ours.solve(b), reference.solve(b)
    assert np.abs(x_ours - x_ref).max() <= 1e-12 * np.abs(x_ref).max()
    assert np.abs(k @ x_ours - b).max() <= 1e-9 * np.abs(k).max() * np.abs(x_ours).max()


def test_two_subtrees_factored_at_once_give_the_same_factors_to_the_last_bit():
    """Where a split pays, the factorisation deals subtrees (each a contiguous range of the
    postorder, every supernode's parent inside it but its root's) to two threads, then
    factors the top of the tree (closed upwards) on their update matrices: the same
    arithmetic in the same order, so the solves are equal bit for bit and the inertia too
    (stable and unstable states; the default 1-by-3 mesh and the 20-by-20 grid are large
    enough to split)."""
    from dea_array_twin.model.assembly import SparsePattern

    cases = [(name, model.pattern, free, values) for name, model, free, values in _states()]
    default = ArrayTwin(ArrayConfig())
    default.solve([0.0, 0.004, 0.0], [0.0, 1500.0, 0.0])
    _, free = default.model.prescribed_dofs(["driven"] * 3)
    cases.append(("1x3 default", default.model.pattern, free,
                  _tangent(default.model, default._x, np.array([0.0, 1500.0, 0.0]))))
    side = 20
    node = np.arange(side * side).reshape(side, side)
    quads = np.stack([node[:-1, :-1], node[1:, :-1], node[1:, 1:], node[:-1, 1:]], axis=-1).reshape(-1, 4)
    grid = SparsePattern((3 * quads[:, :, None] + np.arange(3)).reshape(-1, 12), 3 * side * side)
    rng = np.random.default_rng(21)
    k = np.diag(np.where(rng.uniform(size=grid.n_dofs) < 0.1, -10.0, 10.0)) + 0.05 * rng.uniform(
        -1.0, 1.0, (grid.n_dofs, grid.n_dofs))
    cases.append(("grid", grid, np.arange(grid.n_dofs), (k + k.T)[grid.rows, grid.cols]))
    split, negative = [], {}
    for name, pattern, free, values in cases:
        factoriser = Factoriser(pattern, free, "block")
        if factoriser._split is not None:
            (a, b, top, _), n_super = factoriser._split, factoriser._frontal[3].size - 1
            start, fp, fn = factoriser._frontal[3:6]
            supernode = np.repeat(np.arange(n_super), np.diff(start))
            parent = [supernode[fn[fp[s] + start[s + 1] - start[s]]] if fp[s + 1] - fp[s] > start[s + 1] - start[s]
                      else -1 for s in range(n_super)]
            owner = np.full(n_super, -1)
            for k, (begins, ends) in enumerate((a, b, top)):
                for lo, hi in zip(begins, ends):
                    assert (owner[lo:hi] == -1).all(), name  # the ranges do not overlap
                    owner[lo:hi] = k
                    if k < 2:  # a whole subtree: parents inside, but its root's, which is in the top
                        assert all(lo <= parent[s] < hi for s in range(lo, hi - 1)), name
                        assert parent[hi - 1] == -1 or parent[hi - 1] >= hi, name
            assert (owner >= 0).all(), name  # they cover every supernode
            assert all(parent[s] == -1 or owner[parent[s]] == 2 for s in np.flatnonzero(owner == 2)), name
            split.append(name)
        one, two = factoriser.factor(values, threads=1), factoriser.factor(values, threads=2)
        b = rng.standard_normal(free.size)
        assert np.array_equal(one.solve(b), two.solve(b)), name
        assert one.negative_pivots() == two.negative_pivots(), name
        negative[name] = two.negative_pivots()
    assert "1x3 default" in split and "grid" in split, split
    assert negative["1x3 default"] == 0 and negative["grid"] > 0 and negative["saddle"] > 0, negative
