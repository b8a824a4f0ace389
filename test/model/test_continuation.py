"""The solver along a command path (model/solver.py): continuation predictors and tangent reuse."""

import numpy as np
import pytest
from conftest import COARSE, FREE_CENTRE

from dea_array_twin import ArrayConfig, ArrayTwin, NewtonSettings
from dea_array_twin.model import solver
from dea_array_twin.model.solver import _iterations_left, _step_length


def _prediction_errors(states: tuple[float, ...], target: float, degree: int,
                       monkeypatch: pytest.MonkeyPatch) -> tuple[float, float]:
    """Largest error of the free dofs' secant and polynomial continuation (of at most ``degree``) after
    solves to ``states`` (driven unit [m], coarse 1-by-3, V = 0) against the converged state at ``target``."""
    monkeypatch.setattr(solver, "CONTINUATION_DEGREE", degree)
    twin = ArrayTwin(ArrayConfig(**COARSE), NewtonSettings(check_stability=False))
    for d in states:
        twin.solve([0, d, 0], 0.0, FREE_CENTRE)
    x = twin._x
    prescribed, free = twin.model.prescribed_dofs(FREE_CENTRE)
    command = np.array([0.0, target, 0.0])
    scale, dx, _, along, _ = twin.solver._secant(x, free, prescribed, command, command, np.zeros(3), np.zeros(3),
                                              FREE_CENTRE)
    twin.solve(command, 0.0, FREE_CENTRE)
    reached = twin._x[free]
    return np.abs(x[free] + scale * dx - reached).max(), np.abs(x[free] + along - reached).max()


def test_quadratic_through_the_last_three_states_predicts_the_next_closer_than_the_secant(monkeypatch):
    """Unequal steps of the driven unit (5 -> 6 -> 6.5 mm, then 7.25 mm: the step before is twice
    the last, the new one 1.5 times) on the coarse 1-by-3 at V = 0: the quadratic through the
    three states puts the free dofs at least 3x closer to the converged state than the secant
    ``x + s dx`` (measured: 4.7x; it is exact for a quadratic path); a sign or scale error in
    its curvature term puts them farther."""
    secant, quadratic = _prediction_errors((0.005, 0.006, 0.0065), 0.00725, 2, monkeypatch)
    assert quadratic < secant / 3.0


def test_cubic_through_the_last_four_states_predicts_the_next_closer_than_the_quadratic(monkeypatch):
    """As above with one more state (3 -> 5 -> 6 -> 6.5 mm, then 7.25 mm): the cubic through the four
    states puts the free dofs at least 3x closer to the converged state than the quadratic through
    the last three (measured: 5.3x, 2.3e-7 against 1.2e-6 m)."""
    states = (0.003, 0.005, 0.006, 0.0065)
    _, quadratic = _prediction_errors(states, 0.00725, 2, monkeypatch)
    _, cubic = _prediction_errors(states, 0.00725, 3, monkeypatch)
    assert cubic < quadratic / 3.0


def test_a_motion_that_turned_back_retraces_the_states_it_passed(monkeypatch):
    """Back and forth along one direction (5 -> 6 -> 7 -> 6 mm, then 5 mm): the new command is one the
    twin solved three solves before, and without biased units that is the same state.  The
    continuation leaves out the state that repeats a newer one's command (6 mm) and passes through
    the others, so the free dofs land on the 5 mm state to within 1e-9 m (measured 4.7e-12 m); with
    the repeated state the polynomial was refused and the secant predicted (1.4e-5 m)."""
    secant, retraced = _prediction_errors((0.005, 0.006, 0.007, 0.006), 0.005, 3, monkeypatch)
    assert retraced < 1e-9 < secant


def test_across_a_turn_the_polynomial_interpolates_the_states_it_passed(monkeypatch):
    """Without biased units the state is a function of the command, so a path that turned (0 -> 4 -> 6
    -> 5.5 mm) still gives a polynomial through distinct states; 5 mm lies between them: at least
    5x closer than the secant with the quadratic through the last three (measured: 12.6x) and with
    the cubic through all four (23x)."""
    for degree in (2, 3):
        secant, polynomial = _prediction_errors((0.004, 0.006, 0.0055), 0.0050, degree, monkeypatch)
        assert polynomial < secant / 5.0


def test_warm_updates_along_a_curve_reach_the_cold_solves_state():
    """The continued solves converge to the same equilibrium as a solve from scratch (forces to
    1e-6, the solver's tolerance): the predictor only changes where Newton starts."""
    warm = ArrayTwin(ArrayConfig(**COARSE), NewtonSettings(check_stability=False))
    for d in (0.005, 0.006, 0.0065, 0.00725):
        res = warm.solve([0, d, 0], 0.0, FREE_CENTRE)
    cold = ArrayTwin(ArrayConfig(**COARSE), NewtonSettings(check_stability=False)).solve([0, 0.00725, 0], 0.0,
                                                                                        FREE_CENTRE)
    assert res.force[1] == pytest.approx(cold.force[1], rel=1e-6)


def test_a_solve_of_the_command_the_twin_holds_keeps_its_tangent():
    """Solving again for the command the twin is at (a held command, a re-sent one) takes one
    Newton step from an equilibrium whose residual is at its round-off floor, so the step does
    not contract it by ``contraction``: that says nothing about the tangent, which is kept (no
    factorisation; on the default 1-by-3 at 10 mm it was one per repeat from the fifth on, ~5 ms
    each), and the state stays where it was (force to 1e-6)."""
    twin = ArrayTwin(ArrayConfig(), NewtonSettings(check_stability=False))
    for d in np.linspace(0.0, 0.010, 11):
        first = twin.solve([0, d, 0], 0.0, FREE_CENTRE)
    repeats = [twin.solve([0, 0.010, 0], 0.0, FREE_CENTRE) for _ in range(8)]
    assert [res.factorisations for res in repeats] == [0] * 8
    assert all(res.force[1] == pytest.approx(first.force[1], rel=1e-6) for res in repeats)


def test_a_stale_tangent_needs_the_iterations_of_its_linear_rate():
    """Modified Newton converges linearly: at a ratio of 0.1 per iteration a residual falls from 1
    to 1e-4 in 4 iterations; one already below the tolerance needs none; a ratio of 1 never gets there."""
    assert _iterations_left(1.0, 1e-4, 0.1) == pytest.approx(4.0)
    assert _iterations_left(1e-5, 1e-4, 0.5) == 0.0
    assert _iterations_left(1.0, 1e-4, 1.0) == float("inf")


def test_a_checked_curve_refactors_only_where_a_stale_tangent_costs_more_than_a_factorisation():
    """Checked at every point, each solve of the 0-15 mm curve (coarse 1-by-3, 1 mm steps) factors
    its converged state anyway, and the next starts from that: an extra factorisation in Newton
    serves one solve.  Kept only when the iterations the stale tangent still needs at its rate
    exceed ``factorisation_cost`` (10), the curve takes at least 3 fewer factorisations than with
    the plain contraction rule (``factorisation_cost=0``; measured 17 against 20, 67 iterations
    against 56: about 30 iterations' worth less work), none but the check after 2 mm, and reaches
    the same equilibria (forces to 1e-6) and the same stability answers."""
    runs = {}
    for cost in (0.0, 10.0):
        twin = ArrayTwin(ArrayConfig(**COARSE), NewtonSettings(check_stability=True, factorisation_cost=cost))
        runs[cost] = [twin.solve([0, d, 0], 0.0, FREE_CENTRE) for d in np.linspace(0.0, 0.015, 16)]
    old, new = runs[0.0], runs[10.0]
    assert sum(r.factorisations for r in new) <= sum(r.factorisations for r in old) - 3
    assert [r.factorisations for r in new[3:]] == [1] * 13
    work = {cost: sum(10 * r.factorisations + r.iterations for r in rs) for cost, rs in runs.items()}
    assert work[10.0] < work[0.0]
    assert all(a.force[1] == pytest.approx(b.force[1], rel=1e-6) for a, b in zip(old, new))
    assert [r.stable for r in new] == [r.stable for r in old] == [True] * 16


@pytest.mark.parametrize("nodes", [(0.0, -1.0, -2.0, -3.0), (0.0, -1.0, -1.6, -4.3), (0.0, -1.0, 0.5, 2.0)])
@pytest.mark.parametrize("lam", [1.0, -0.5, 2.6, -3.4])
def test_the_continuation_through_four_states_is_exact_on_a_cubic_path(nodes, lam):
    """Commands along one direction at the path parameters ``nodes`` (equal steps, unequal ones, a
    path that turned back), states on a cubic of the parameter: the new command ``lam dp`` is placed
    at ``lam`` and the states' change there is the cubic's, to 1e-12 (:func:`_on_command_path`)."""
    dp = np.array([0.4, -1.0, 0.25])
    c0, c1, c2, c3 = (np.array(v) for v in ([0.3, -2.0], [1.5, 0.7], [-0.8, 2.2], [0.6, -0.35]))
    q = lambda t: c0 + c1 * t + c2 * t**2 + c3 * t**3  # noqa: E731
    commands = [(s - t) * dp for s, t in zip(nodes, nodes[1:])]
    states = [q(s) - q(t) for s, t in zip(nodes, nodes[1:])]
    coefficients, dp_along = solver._on_command_path(lam * dp, commands, lam)
    assert np.abs(dp_along - lam * dp).max() < 1e-12
    assert np.abs(solver._on_path(coefficients, states) - (q(lam) - q(0.0))).max() < 1e-12


def test_units_moving_out_of_phase_continue_on_the_curve_through_the_last_commands(monkeypatch):
    """The node's command stream: every unit driven on a 1 Hz sine, a third of a period apart, a
    command every 2 ms (coarse 1-by-3, V = 0).  Consecutive steps are not along one direction, so
    a polynomial along the last step alone does not apply; placing the new command on the curve
    through the last four (:func:`_on_command_path`) and extrapolating the states to it takes at
    most 0.7x the Newton iterations of the secant with the tangent for the rest (measured: 1.04
    against 2.54 per update; the quadratic through the last three: 1.11) and reaches the same
    equilibria (forces to 1e-6 of a cold solve's)."""
    def stream(twin: ArrayTwin) -> tuple[float, np.ndarray]:
        its = []
        for i in range(60):
            t = i / 500.0
            res = twin.solve([0.005 + 0.004 * np.sin(2 * np.pi * (t + k / 3.0)) for k in range(3)], 0.0,
                             ("driven",) * 3)
            its.append(res.iterations)
        return float(np.mean(its[3:])), res.force

    settings = NewtonSettings(check_stability=False)
    curve_its, curve_force = stream(ArrayTwin(ArrayConfig(**COARSE), settings))
    monkeypatch.setattr(solver, "_on_command_path", lambda *args: None)
    secant_its, secant_force = stream(ArrayTwin(ArrayConfig(**COARSE), settings))
    cold = ArrayTwin(ArrayConfig(**COARSE), settings).solve(
        [0.005 + 0.004 * np.sin(2 * np.pi * (59 / 500.0 + k / 3.0)) for k in range(3)], 0.0, ("driven",) * 3)
    assert curve_its <= 0.7 * secant_its
    np.testing.assert_allclose(curve_force, cold.force, rtol=1e-6)
    np.testing.assert_allclose(secant_force, cold.force, rtol=1e-6)


def test_on_the_node_stream_the_cubic_leaves_a_first_residual_a_fifth_of_the_quadratics(monkeypatch):
    """The node's stream as above, solved tightly (``residual_tol`` 1e-11, so that the converged states'
    own residuals, which the extrapolation carries along, stay below its error): the first residual of
    an update from the cubic through the last four states is at most a fifth of the quadratic's through
    three (measured: 4.8e-10 against 1.1e-8 N at the median; the cubic's error is one order higher in
    the 2 ms step), and the updates take fewer Newton iterations (3.0 against 3.8)."""
    settings = NewtonSettings(check_stability=False, residual_tol=1e-11, increment_tol=1e-10)
    internal_forces, first = solver.internal_forces, []

    def recorded(disc, x, *args):
        r, point = internal_forces(disc, x, *args)
        if not first:
            first.append(r)
        return r, point

    monkeypatch.setattr(solver, "internal_forces", recorded)
    runs = {}
    for degree in (2, 3):
        monkeypatch.setattr(solver, "CONTINUATION_DEGREE", degree)
        twin = ArrayTwin(ArrayConfig(**COARSE), settings)
        free = twin.model.prescribed_dofs(("driven",) * 3)[1]
        residuals, its = [], []
        for i in range(40):
            first.clear()
            res = twin.solve([0.005 + 0.004 * np.sin(2 * np.pi * (i / 500.0 + k / 3.0)) for k in range(3)], 0.0,
                             ("driven",) * 3)
            residuals.append(np.abs(first[0][free]).max())
            its.append(res.iterations)
        runs[degree] = (np.median(residuals[5:]), np.mean(its[5:]))
    assert runs[3][0] < runs[2][0] / 5.0, runs
    assert runs[3][1] < runs[2][1], runs


def test_a_stale_tangent_too_soft_by_a_factor_gives_the_inverse_step_length():
    """On a quadratic energy (residual ``K x - b``) a modified-Newton step with a tangent 1.25x too
    soft, ``dx = -(K / 1.25)^-1 r``, is 1.25x too long: the energy along it is least at 0.8 of it,
    what :func:`_step_length` finds from the residuals before and after the step (to round-off)."""
    rng = np.random.default_rng(3)
    a = rng.standard_normal((12, 12))
    k, b, x = a @ a.T + 12 * np.eye(12), rng.standard_normal(12), rng.standard_normal(12)
    r0 = k @ x - b
    dx = -np.linalg.solve(k / 1.25, r0)
    assert _step_length(dx, r0, k @ (x + dx) - b, 1.0, 1.0) == pytest.approx(0.8, rel=1e-12)
    assert _step_length(0.8 * dx, r0, k @ (x + 0.8 * dx) - b, 0.8, 1.0) == pytest.approx(0.8, rel=1e-12)


def test_warm_updates_with_a_stale_tangent_take_fewer_iterations_at_the_energy_minimum_along_its_step(monkeypatch):
    """The warm updates of ``bench_core.py`` (coarse 1-by-3, from 10 mm in 0.1 mm steps, 20 up and
    20 down, no stability check): scaling a stale tangent's step by the length that minimised the
    energy along the last one saves at least 5 of ~116 Newton iterations over 100 updates (measured
    107 against 116) and ends at the same equilibrium (force to 1e-6)."""
    def updates() -> tuple[int, float]:
        twin = ArrayTwin(ArrayConfig(**COARSE), NewtonSettings(check_stability=False))
        for d in np.linspace(0.0, 0.010, 11):
            twin.solve([0, d, 0], 0.0, FREE_CENTRE)
        d, its = 0.010, 0
        for i in range(100):
            d += 1e-4 if (i // 20) % 2 == 0 else -1e-4
            res = twin.solve([0, d, 0], 0.0, FREE_CENTRE)
            its += res.iterations
        return its, res.force[1]

    scaled_its, scaled_force = updates()
    monkeypatch.setattr(solver, "_step_length", lambda *args: 1.0)
    plain_its, plain_force = updates()
    assert scaled_its <= plain_its - 5
    assert scaled_force == pytest.approx(plain_force, rel=1e-6)


@pytest.mark.parametrize("skipped", [1.2, 1.6])
def test_a_node_that_missed_a_tick_continues_on_the_curve_over_the_longer_step(skipped):
    """The node's stream as above, then a command ``1 + skipped`` periods on (a tick missed, the sender's
    clock a little ahead): the new command lies more than twice the last step along it, within the
    quadratic's reach, so the states are still extrapolated along the curve.  The update's first
    residual stays within 10 times that of the single steps: the quadratic's error grows as
    ``lambda (lambda + 1) (lambda + 2)``, 4.9 and 7.2 times that of a single step at 2.2 and 2.6 steps
    (measured 4.2 and 5.8).  The tangent alone left it ~1700 times larger here, and the update took
    6-8 Newton iterations instead of 2 on the default mesh."""
    twin = ArrayTwin(ArrayConfig(**COARSE), NewtonSettings(check_stability=False))
    first = []
    internal_forces = solver.internal_forces

    def recorded(disc, x, *args):
        r, point = internal_forces(disc, x, *args)
        if not first:
            first.append(np.abs(r[twin.model.prescribed_dofs(("driven",) * 3)[1]]).max())
        return r, point

    def command(t: float) -> list[float]:
        return [0.005 + 0.004 * np.sin(2 * np.pi * (t + k / 3.0)) for k in range(3)]

    def first_residual(t: float) -> float:
        first.clear()
        twin.solve(command(t), 0.0, ("driven",) * 3)
        return first[0]

    with pytest.MonkeyPatch.context() as mp:
        mp.setattr(solver, "internal_forces", recorded)
        single = [first_residual(i / 500.0) for i in range(40)]
        missed = first_residual((40 + skipped) / 500.0)
    assert missed <= 10 * np.median(single[5:]), (missed, np.median(single[5:]))
