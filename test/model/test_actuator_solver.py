"""The Newton machinery of biased units: the bordered step and the predictors of consecutive updates.

The bordered step (block elimination with the influence vectors, ``model/indenters.py``) is
checked against a dense solve of the augmented system; the continuation predictors against
an exact quadratic and by the work they leave to Newton (iterations and factorisations per
update: counts, not timings; ``benchmarks/bench_actuator.py`` has the timings).  The
physics of biased units is verified in ``test_actuator.py``.
"""

import numpy as np
import pytest
from conftest import COARSE

from dea_array_twin import ArrayConfig, ArrayTwin, NewtonSettings
from dea_array_twin.model.actuator import ActuatorLoad, UnitLoad
from dea_array_twin.model.bias import bias_from_entry
from dea_array_twin.model.kernels import internal_forces
from dea_array_twin.model.response import rest_state
from dea_array_twin.model.solver import SolveStats, _extrapolate, _residual

LBS = {"type": "linear", "stiffness": 40.0, "free_position": 0.020}
CIRCULAR = {"layout": "circular", "frame_radius": 0.025}


def _bordered_system(balanced: bool):
    """A circular biased unit at rest, its external force raised by 0.02 N and (unless ``balanced``)
    its free dofs disturbed by up to 1 um; the tangent factored there, the border and residual."""
    twin = ArrayTwin(ArrayConfig(**CIRCULAR, unit_modes=["biased"], bias=[LBS]), NewtonSettings(check_stability=False))
    rest_state(twin)
    model, solver = twin.model, twin.solver
    modes = ("biased",)
    prescribed, free = model.prescribed_dofs(modes)
    x = twin._x.copy()
    if not balanced:
        x[free] += 1e-6 * np.sin(np.arange(free.size))
    maxwell = model.maxwell(np.zeros(1))
    load = ActuatorLoad({0: UnitLoad(bias_from_entry(LBS), 0.02, 0.02)})
    border = solver._border(modes, prescribed, load)
    border.begin(1.0)
    fact = solver.factorise_at(x, maxwell, free, prescribed, SolveStats())
    r, _ = internal_forces(model.disc, x, model.yeoh, maxwell, model.thickness)
    res = _residual(r, x, free, border)
    return model, fact, border, x, free, prescribed, res


def _augmented_step(model, fact, border, x, free, prescribed, res) -> np.ndarray:
    """``[K_ff K_fw; K_wf K_ww - dG/dw] [dx; dw] = -[R_f; R_w]`` solved densely."""
    k_ff = model.pattern.block(fact.values, free, free).toarray()
    disk = np.isin(prescribed, model.disk_z_dofs(0))
    k_fw = model.pattern.block(fact.values, free, prescribed).toarray()[:, disk].sum(axis=1)
    k_ww = model.pattern.block(fact.values, prescribed, prescribed).toarray()[np.ix_(disk, disk)].sum()
    k_ww -= border.load(0, border.heights(x)[0], 1.0)[1]
    n = free.size
    augmented = np.zeros((n + 1, n + 1))
    augmented[:n, :n], augmented[:n, n], augmented[n, :n], augmented[n, n] = k_ff, k_fw, k_fw, k_ww
    return np.linalg.solve(augmented, -res)


def test_bordered_newton_step_equals_the_direct_solve_of_the_augmented_system():
    """Block elimination with the cached influence vectors Y = K_ff^-1 K_fw gives the Newton step
    of the augmented (membrane + height) system to 1e-10, free dofs and height alike."""
    model, fact, border, x, free, prescribed, res = _bordered_system(balanced=False)
    assert np.abs(res[:free.size]).max() > 1e-4  # the disturbance leaves a real free residual
    dx, dw = border.direction(fact, res[:free.size], res[free.size:], x)
    direct = _augmented_step(model, fact, border, x, free, prescribed, res)
    assert not border.skipped_solve
    assert np.abs(dx - direct[:-1]).max() <= 1e-10 * np.abs(direct[:-1]).max()
    assert dw[0] == pytest.approx(direct[-1], rel=1e-10)


def test_height_step_of_a_balanced_membrane_is_the_newton_step_without_a_membrane_solve():
    """With the free residual within tolerance (a converged membrane whose indenter's force changed)
    the step skips the K_ff solve: it equals the augmented Newton step with R_f set to 0, to 1e-10."""
    model, fact, border, x, free, prescribed, res = _bordered_system(balanced=True)
    tolerance = 1e-8 * model.force_scale
    assert np.abs(res[:free.size]).max() <= tolerance and abs(res[-1]) > 1e-3
    dx, dw = border.direction(fact, res[:free.size], res[free.size:], x, balanced=tolerance)
    res[:free.size] = 0.0
    direct = _augmented_step(model, fact, border, x, free, prescribed, res)
    assert border.skipped_solve
    assert np.abs(dx - direct[:-1]).max() <= 1e-10 * np.abs(direct[:-1]).max()
    assert dw[0] == pytest.approx(direct[-1], rel=1e-10)


@pytest.mark.parametrize("ratio", [1.0, 0.35, -0.5, 3.8])
@pytest.mark.parametrize("scale", [1.0, -1.0, 0.4, 2.6, -2.2])
def test_continuation_through_three_states_is_exact_on_a_quadratic_path(ratio, scale):
    """The predictor's quadratic through the states at lambda = 0, -1, -1 - a (the last two solves'
    changes, the earlier one a times the last) reproduces any quadratic q(lambda) and its slope at
    lambda = s to 1e-12, for the ratios and reaches of smooth motions, reversals and turning points."""
    c0, c1, c2 = np.array([0.3, -2.0]), np.array([1.5, 0.7]), np.array([-0.8, 2.2])
    q = lambda lam: c0 + c1 * lam + c2 * lam**2  # noqa: E731
    last, before = q(0.0) - q(-1.0), q(-1.0) - q(-1.0 - ratio)
    change = _extrapolate(scale, ratio, last, before)
    slope = _extrapolate(scale, ratio, last, before, slope=True)
    assert np.abs(change - (q(scale) - q(0.0))).max() < 1e-12
    assert np.abs(slope - (c1 + 2.0 * c2 * scale)).max() < 1e-12


def _coarse_biased(mass: float, settings: NewtonSettings | None = None) -> tuple[ArrayTwin, float]:
    """The coarse 1-by-3, unit 2 on a 40 N/m spring with ``mass``, at rest; its k_eff [N/m]."""
    cfg = ArrayConfig(**COARSE, unit_modes=("free", "biased", "free"), bias=(LBS,), mass=(mass,))
    twin = ArrayTwin(cfg, settings or NewtonSettings(check_stability=False))
    rest = rest_state(twin)
    probe = ArrayTwin(cfg.replace(unit_modes=("free", "driven", "free")), NewtonSettings(check_stability=False))
    w = rest.position[1]
    slope = (probe.solve([0, w + 1e-6, 0]).force[1] - probe.solve([0, w - 1e-6, 0]).force[1]) / 2e-6
    return twin, slope + 40.0


def _force_steps(twin: ArrayTwin, stiffness: float, dt: float | None, count: int) -> list:
    """``count`` updates whose external force steps by k_eff * 0.1 mm, reversing every 20."""
    out, force = [], 0.0
    for i in range(count):
        force += stiffness * 1e-4 * (1 if (i // 20) % 2 == 0 else -1)
        out.append(twin.solve(force=[0.0, force, 0.0]) if dt is None else twin.step(dt, force=[0.0, force, 0.0]))
    return out


def test_quasi_static_force_steps_continue_the_last_updates_in_one_or_two_newton_iterations():
    """Force-controlled updates of a biased unit (0.1 mm each, reversing after 20) start from the
    quadratic through the last three states, and the height's row converges on the errors it leaves
    (:func:`solver._balanced`): after the first three, at most 2 of 57 updates take more than 1
    Newton iteration, 1.2 on average at most, and none refactors (measured: 1.05, one update at 3
    after a reversal; with the height's force row held to the nodal tolerance: 1.65, 4 at most; with
    the secant predictor before that: 2.82)."""
    twin, stiffness = _coarse_biased(0.0)
    runs = _force_steps(twin, stiffness, None, 60)[3:]
    its = np.array([r.iterations for r in runs])
    assert np.mean(its) <= 1.2
    assert np.count_nonzero(its > 1) <= 2
    assert sum(r.factorisations for r in runs) == 0


def test_newmark_steps_start_from_the_heights_equation_and_converge_in_few_newton_iterations():
    """Newmark steps of 2 ms (5 g on the spring, up to 0.3 mm per step, turning points included) start
    from the heights' equation with the membrane force extrapolated from the last states and the
    free dofs following them: at most 2 Newton iterations, 1.5 on average at most, no factorisation
    (measured: 1.33; with the height's force row held to the nodal tolerance, 1.91 and 3 at most,
    the second iteration a heights-only step for picometres; with the constant-acceleration guess
    before that: 3.42 on average, 5 at most, one factorisation)."""
    twin, stiffness = _coarse_biased(0.005)
    runs = _force_steps(twin, stiffness, 0.002, 60)[3:]
    its = np.array([r.iterations for r in runs])
    assert np.mean(its) <= 1.5
    assert its.max() <= 2
    assert sum(r.factorisations for r in runs) == 0


@pytest.mark.parametrize("mass, dt", [(0.005, 0.002), (0.0, None)])
def test_a_converged_height_is_within_the_increment_tolerance_and_its_force_within_the_residual_one(mass, dt):
    """The height's row converges when the height error R_w / S it leaves is within ``increment_tol``
    and the membrane force error K_m R_w / S within ``residual_tol`` (both scaled): the same steps
    solved with both tolerances 1000 times tighter give positions within ``x_tol`` and membrane
    forces within ``r_tol`` per disk node (the force is the resultant of the disk nodes' forces,
    and the free rows next to them are each converged to ``r_tol``).  Measured: 5e-11 m and 2.4e-8 N
    (Newmark), 1.7e-10 m and 6.8e-9 N (quasi-static); with the height's force row held to ``r_tol``
    itself: 7.5e-11 m and 2.5e-8 N, 1.7e-10 m and 6.8e-9 N."""
    loose, stiffness = _coarse_biased(mass)
    tight, _ = _coarse_biased(mass, NewtonSettings(check_stability=False, residual_tol=1e-11, increment_tol=1e-10))
    a, b = _force_steps(loose, stiffness, dt, 30), _force_steps(tight, stiffness, dt, 30)
    model, settings = loose.model, loose.solver.settings
    x_tol, r_tol = settings.increment_tol * model.length_scale, settings.residual_tol * model.force_scale
    assert max(abs(p.position[1] - q.position[1]) for p, q in zip(a, b)) <= x_tol
    disk_nodes = len(model.disk_z_dofs(1))
    assert max(abs(p.force[1] - q.force[1]) for p, q in zip(a, b)) <= disk_nodes * r_tol
