"""The LDL^T factorisations of K_ff (model/linsolve.py): qdldl against the SuperLU answer."""

import importlib.util

import numpy as np
import pytest
import scipy.sparse.linalg as spla
from conftest import COARSE, FREE_CENTRE

from dea_array_twin import ArrayConfig, ArrayTwin, NewtonSettings
from dea_array_twin.model import kernels
from dea_array_twin.model.linsolve import Factoriser, resolve_backend
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


def test_qdldl_inertia_and_solves_equal_superlu_on_stable_and_unstable_states():
    """The negative pivot count of qdldl's D equals the count from SuperLU's U diagonal (the
    answer before qdldl) on two stable and two unstable tangents; both solve K_ff x = b to
    1e-10 of |x| against each other.  The saddle's count is checked against eigsh too."""
    counts = {}
    for name, model, free, values in _states():
        ours = Factoriser(model.pattern, free, "qdldl").factor(values)
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


def test_superlu_fallback_gives_the_same_curve_and_stability_flags():
    """Without qdldl the solver factors with SuperLU: same forces (solver tolerance) and flags."""
    results = {}
    for backend in ("qdldl", "superlu"):
        twin = ArrayTwin(ArrayConfig(**COARSE), NewtonSettings(linear_solver=backend))
        results[backend] = [twin.solve([0, d, 0], [0, 2730.0, 0], FREE_CENTRE) for d in (0.004, 0.008, 0.012)]
    for a, b in zip(results["qdldl"], results["superlu"]):
        assert a.force[1] == pytest.approx(b.force[1], rel=1e-7)
        assert a.stable is True and b.stable is True


def test_auto_backend_falls_back_to_superlu_when_qdldl_is_missing(monkeypatch):
    real = importlib.util.find_spec
    monkeypatch.setattr(importlib.util, "find_spec", lambda name, *a: None if name == "qdldl" else real(name, *a))
    assert resolve_backend("auto") == "superlu"
    with pytest.raises(ValueError, match="pip install qdldl"):
        resolve_backend("qdldl")
    with pytest.raises(ValueError, match="linear_solver must be one of"):
        NewtonSettings(linear_solver="cholmod")


def test_a_factorisation_overwritten_by_a_newer_one_refuses_to_solve():
    """qdldl refactors in place: the solver keeps the converged state's factor (``keep``) and
    refactors in another slot; a factor whose slot was reused raises instead of answering
    with another matrix."""
    model = MembraneModel(ArrayConfig(layout="circular"))
    _, free = model.prescribed_dofs(("driven",))
    factoriser = Factoriser(model.pattern, free, "qdldl")
    stiff = _tangent(model, model.flat_state() * 1.2 / 1.1, np.zeros(1))
    first = factoriser.factor(_tangent(model, model.flat_state(), np.zeros(1)))
    b = np.ones(free.size)
    x_first = first.solve(b)
    second = factoriser.factor(stiff, keep=first)
    assert np.array_equal(first.solve(b), x_first)  # kept
    assert not np.allclose(second.solve(b), x_first)
    factoriser.factor(stiff, keep=second)  # reuses the first slot
    with pytest.raises(RuntimeError, match="overwritten"):
        first.solve(b)
