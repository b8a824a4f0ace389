"""Verification of actuator mode (issue 11): biased units, bias laws, snap-through, contact, dynamics.

Every biased answer is checked against something computed another way: root-finding
and finite differences on *driven* solves (the characterisation rig, verified by the
issue-2 tests), the analytic period and decay of a linear oscillator, and energy
conservation.  Most checks use the single circular unit (286 P2 elements, ~30 ms a
solve); contact uses the coarse 1-by-3.
"""

import math

import numpy as np
import pytest
from conftest import COARSE, DOME
from scipy.optimize import brentq, minimize_scalar

from dea_array_twin import ArrayConfig, ArrayTwin, NewtonSettings
from dea_array_twin.model.bias import bias_from_entry
from dea_array_twin.model.response import rest_state

CIRCULAR = {"layout": "circular", "frame_radius": 0.025}
#: Newton tolerances 100x tighter than the default, for the 1e-6 comparisons.
TIGHT = NewtonSettings(residual_tol=1e-10, increment_tol=1e-9)
#: DOME (test/conftest.py), the bistable dome on the circular unit: stable near 5 mm at
#: 0 V; a voltage ramp takes that branch past a limit point near 2140 V and the unit snaps
#: to about 10 mm.
NBS = {"type": "linear", "stiffness": -30.0, "free_position": 0.0007}


def biased_twin(bias, settings=TIGHT, **changes):
    return ArrayTwin(ArrayConfig(**{**CIRCULAR, "unit_modes": ["biased"], "bias": [bias], **changes}), settings)


class DrivenCurve:
    """F(w) of the circular unit from driven solves (the rig): the independent reference."""

    def __init__(self, voltage):
        self.twin = ArrayTwin(ArrayConfig(**CIRCULAR), TIGHT)
        self.voltage = voltage

    def force(self, w):
        return self.twin.solve([w], [self.voltage], ["driven"], check_stability=False).force[0]

    def stiffness(self, w, h=1e-6):
        """dF/dw by a central difference over +-1 um (truncation ~ (h / 10 mm)^2)."""
        return (self.force(w + h) - self.force(w - h)) / (2 * h)

    def equilibrium(self, law, external, lo, hi):
        """The root of F(w) - B(w) - f in [lo, hi] (Brent, 1e-13 m)."""
        return brentq(lambda w: self.force(w) - law.force(w) - external, lo, hi, xtol=1e-13, rtol=1e-13)


@pytest.mark.parametrize("bias, external, voltage, start, bracket", [
    ({"type": "none"}, 0.2, 0.0, 0.0, (0.005, 0.010)),
    ({"type": "linear", "stiffness": 40.0, "free_position": 0.020}, 0.0, 0.0, 0.0, (0.008, 0.014)),
    ({"type": "linear", "stiffness": 40.0, "free_position": 0.020}, 0.0, 2730.0, 0.0, (0.008, 0.014)),
    (NBS, 0.0, 0.0, 0.006, (0.0055, 0.0075)),
    ({"type": "constant", "force": 0.3}, 0.0, 0.0, 0.0, (0.007, 0.012)),
    (DOME, 0.0, 0.0, 0.005, (0.0045, 0.0055)),
    ({"type": "sum", "terms": [{"type": "linear", "stiffness": 40.0, "free_position": 0.020},
                               {"type": "constant", "force": -0.1}]}, 0.0, 0.0, 0.0, (0.006, 0.012)),
], ids=["force-control", "LBS", "LBS-2730V", "NBS", "dead-weight", "table-dome", "sum"])
def test_biased_equilibrium_is_where_the_driven_force_curve_meets_the_bias(bias, external, voltage, start,
                                                                          bracket):
    """F(w, V) = B(w) + f: the biased solve against Brent's method on driven solves, 1e-6 in w."""
    twin = biased_twin(bias)
    rest_state(twin, start=start, force=external)
    res = twin.solve(voltage=[voltage], check_stability=True)
    law = bias_from_entry(bias)
    expected = DrivenCurve(voltage).equilibrium(law, external, *bracket)
    assert res.position[0] == pytest.approx(expected, rel=1e-6)
    assert res.force[0] == pytest.approx(res.bias_force[0] + external, abs=1e-9)
    assert res.bias_force[0] == pytest.approx(law.force(res.position[0]), abs=1e-12)
    assert res.stable


def test_stability_flag_is_the_sign_of_the_net_stiffness_from_driven_solves():
    """``stable`` equals sign(dF/dw - dB/dw), dF/dw from central differences of driven solves.

    The bistable dome: its 0 V equilibrium near 5 mm is stable, and so is the lower branch
    at 2000 V; the middle equilibrium at 2000 V (the unit released exactly there) is not."""
    law = bias_from_entry(DOME)
    twin = biased_twin(DOME)
    states = [(0.0, rest_state(twin, start=0.005)),
              (2000.0, twin.solve(voltage=[2000.0], check_stability=True))]
    middle = DrivenCurve(2000.0).equilibrium(law, 0.0, 0.0061, 0.0065)
    released = biased_twin(DOME)
    released.solve([middle], [2000.0], ["driven"])
    states.append((2000.0, released.solve(modes=["biased"], check_stability=True)))
    assert states[2][1].position[0] == pytest.approx(middle, rel=1e-6)
    net = []
    for voltage, res in states:
        w = res.position[0]
        net.append(DrivenCurve(voltage).stiffness(w) - law.slope(w))
        assert abs(net[-1]) > 5.0  # N/m: the sign is not in doubt
        assert res.stable == (net[-1] > 0)
    assert states[0][1].stable and not states[2][1].stable


def test_snap_through_is_reported_and_lands_on_the_stable_upper_branch():
    """0 -> 2730 V on the dome: the lower branch ends at a limit point; the twin reports the snap
    (from where to where, at which voltage) and lands where Brent's method on driven solves puts
    the upper equilibrium at that voltage; nothing lies in between; the landed state is stable."""
    law = bias_from_entry(DOME)
    twin = biased_twin(DOME)
    rest_state(twin, start=0.005)
    res = twin.solve(voltage=[2730.0], check_stability=True)
    assert len(res.snaps) == 1 and res.snapped.tolist() == [True]
    assert "snapped through from" in res.events[0]
    snap = res.snaps[0]
    v_snap = 2730.0 * snap.load_fraction
    curve = DrivenCurve(v_snap)
    assert 0.0055 < snap.start < 0.0065 < 0.009 < snap.end
    assert snap.end == pytest.approx(curve.equilibrium(law, 0.0, 0.009, 0.0115), rel=1e-6)
    gap = [curve.force(w) - law.force(w) for w in np.linspace(snap.start, snap.end, 40)[1:-1]]
    assert max(gap) < 0  # no equilibrium left between: the snap was forced
    assert curve.stiffness(snap.end) - law.slope(snap.end) > 5.0
    assert res.stable
    assert res.position[0] == pytest.approx(DrivenCurve(2730.0).equilibrium(law, 0.0, 0.0095, 0.0115), rel=1e-6)
    back = twin.solve(voltage=[0.0], check_stability=True)  # bistable: it stays up
    assert not back.snaps and back.stable and back.position[0] > 0.009


def test_an_indenter_pulled_up_by_raised_neighbours_lifts_off_instead_of_pulling():
    """Unit 2 held at 0 while its neighbours rise to 8 mm: bonded it would pull the membrane down
    (F2 < 0); with contact it lifts off, reports 0 N and the membrane there is exactly the free
    solution; when the neighbours come back, contact resumes."""
    neighbours_up = [0.008, 0.0, 0.008]
    bonded = ArrayTwin(ArrayConfig(**COARSE)).solve(neighbours_up, 0.0, ["driven"] * 3)
    free = ArrayTwin(ArrayConfig(**COARSE)).solve(neighbours_up, 0.0, ["driven", "free", "driven"])
    twin = ArrayTwin(ArrayConfig(**COARSE, contact=[False, True, False]))
    res = twin.solve(neighbours_up, 0.0, ["driven"] * 3)
    assert bonded.force[1] < -0.03
    assert res.lifted_off.tolist() == [False, True, False] and res.force[1] == 0.0
    assert res.position[1] == 0.0 < free.centre_deflection[1]
    assert res.centre_deflection[1] == pytest.approx(free.centre_deflection[1], rel=1e-6)
    assert res.force[0] == pytest.approx(free.force[0], rel=1e-6)
    back = twin.solve([0.0, 0.0, 0.0])
    assert not back.lifted_off.any() and np.abs(back.force).max() < 1e-9


def test_a_biased_indenter_lifts_off_and_rests_on_its_spring():
    """Unit 2 on a spring free at 1 mm; its neighbours rise to 8 mm and pull the membrane above
    1 mm: the spring would have to pull, so the indenter lets go and rests at its free position."""
    cfg = ArrayConfig(**COARSE, contact=[False, True, False], unit_modes=["driven", "biased", "driven"],
                      bias=[{"type": "linear", "stiffness": 40.0, "free_position": 0.001}])
    twin = ArrayTwin(cfg)
    flat = twin.solve([0.0, 0.0, 0.0], 0.0)
    assert 0 < flat.position[1] < 0.001 and flat.force[1] > 0 and not flat.lifted_off.any()
    up = twin.solve([0.008, 0.0, 0.008], 0.0)
    assert up.lifted_off[1] and up.force[1] == 0.0 and up.bias_force[1] == pytest.approx(0.0, abs=1e-12)
    assert up.position[1] == pytest.approx(0.001, rel=1e-9)
    assert up.centre_deflection[1] > 0.0012
    down = twin.solve([0.0, 0.0, 0.0], 0.0)
    assert not down.lifted_off.any() and down.position[1] == pytest.approx(flat.position[1], rel=1e-6)


LBS = {"type": "linear", "stiffness": 40.0, "free_position": 0.020}
MASS = 0.005  # kg: an indenter and its spring


def oscillate(damping, periods, amplitude=1e-4):
    """The circular unit on the LBS with 5 g, at rest at 0 V, hit by a force step that moves its
    equilibrium by ``amplitude``; dt = T / 50 from the stiffness dF/dw - dB/dw of driven solves."""
    law = bias_from_entry(LBS)
    twin = biased_twin(LBS, mass=[MASS], damping=[damping])
    rest = rest_state(twin)
    stiffness = DrivenCurve(0.0).stiffness(rest.position[0] + amplitude) - law.slope(rest.position[0] + amplitude)
    period = 2 * math.pi * math.sqrt(MASS / stiffness)
    dt = period / 50
    force = stiffness * amplitude
    runs = [rest] + [twin.step(dt, voltage=[0.0], force=[force]) for _ in range(int(periods * 50))]
    t = dt * np.arange(len(runs))
    return law, force, stiffness, period, t, runs


def test_undamped_oscillation_has_the_analytic_period_and_conserves_energy():
    """Small oscillation (0.1 mm) about the equilibrium: the period equals 2 pi sqrt(m / (dF/dw -
    dB/dw)) within 0.5% at dt = T / 50 (Newmark's period error is (omega dt)^2 / 12 = 0.13%), and
    membrane + bias + kinetic energy stays constant to 1e-4 of the oscillation's energy over 10 periods
    (from the end of the first step: a command changes linearly over the step it arrives in)."""
    law, force, stiffness, period, t, runs = oscillate(0.0, 10)
    w = np.array([r.position[0] for r in runs])
    v = np.array([r.velocity[0] for r in runs])
    u = w - 0.5 * (w.max() + w.min())
    up = np.flatnonzero((u[:-1] < 0) & (u[1:] >= 0))
    crossings = t[up] - u[up] * (t[up + 1] - t[up]) / (u[up + 1] - u[up])
    measured = np.diff(crossings).mean()
    assert len(crossings) >= 9
    assert measured == pytest.approx(period, rel=5e-3)
    energy = np.array([r.energy - law.work(r.position[0]) - force * r.position[0] + 0.5 * MASS * r.velocity[0] ** 2
                       for r in runs])
    oscillation = 0.5 * MASS * np.abs(v).max() ** 2
    assert oscillation == pytest.approx(0.5 * stiffness * 1e-4**2, rel=0.02)
    assert np.abs(energy[1:] - energy[1]).max() < 1e-4 * oscillation


def test_damped_oscillation_decays_at_c_over_2m():
    """With c = 0.05 N s/m the oscillation decays as exp(-c t / (2 m)): a least-squares fit of
    A exp(-lambda t) cos(omega_d t + phi) + w_inf over 5 periods gives lambda = c / (2 m) within 1%."""
    from scipy.optimize import curve_fit

    damping = 0.05
    _, _, stiffness, period, t, runs = oscillate(damping, 5)
    w = np.array([r.position[0] for r in runs])
    rate = damping / (2 * MASS)
    omega = math.sqrt(stiffness / MASS - rate**2)

    def model(time, amplitude, decay, frequency, phase, offset):
        return amplitude * np.exp(-decay * time) * np.cos(frequency * time + phase) + offset

    guess = (w[0] - w[-1], rate, omega, 0.0, w[-1])
    (_, decay, frequency, _, _), _ = curve_fit(model, t, w, p0=guess)
    assert decay == pytest.approx(rate, rel=1e-2)
    assert frequency == pytest.approx(omega, rel=5e-3)


#: Coarse 1-by-3, units 2 and 3 on the LBS, unit 2 with MASS and unit 3 massless: one Newmark
#: step solves both, with unit 3's snap-through handling on.
MIXED = ArrayConfig(**COARSE, unit_modes=["free", "biased", "biased"], bias=[None, LBS, LBS], mass=[0.0, MASS, 0.0])
PULSE_DT = 0.002


def _pulse_command(i: int) -> dict:
    """Step ``i`` of the pulse: 0.1 N on unit 2 from the start (it swings at up to 0.16 m/s, 0.3 mm a
    step), 1500 V on units 2 and 3 from step 6 (moving up at full speed) to 18, off at 19 (moving down)."""
    voltage = 1500.0 if 6 <= i < 19 else 0.0
    return {"voltage": [0.0, voltage, voltage], "force": [0.0, 0.1, 0.0]}


def _pulse(steps: int, substeps: int = 1) -> list:
    """The results of the first ``steps`` steps of the pulse at 2 ms, the last one as ``substeps`` of
    2 ms / ``substeps`` (the state before it is the same: the same commands in a fresh twin)."""
    twin = ArrayTwin(MIXED)
    twin.solve()
    runs = [twin.step(PULSE_DT, **_pulse_command(i)) for i in range(steps - 1)]
    return runs + [[twin.step(PULSE_DT / substeps, **_pulse_command(steps - 1)) for _ in range(substeps)][-1]]


def test_a_voltage_pulse_on_a_moving_newmark_unit_is_no_snap_and_matches_short_substeps():
    """A voltage switched on or off while a massive unit moves 0.3 mm a step moves the equilibrium
    continuously: no snap-through is reported, no step is cut, at most 8 Newton iterations and one
    factorisation (the stability check's) a step (measured: 7 at most; the false snaps this
    replaces, on the two switch steps and the ones after them: 42-69 iterations, 8 step cuts, 10
    factorisations, because the jump test measured the Newmark unit's height from the last state
    instead of from its guess w + dt v + dt^2 a / 2).  Both switch steps agree with the same step
    taken as 10 sub-steps of 0.2 ms to 5 um.  Newmark's error on one step against the exact motion:
    dt^3 omega^2 |v| / 12 = 1.5 um (omega = 120 rad/s from the swing's half period of 26 ms,
    v = 0.16 m/s), plus dt^2 |dF| / (4 m) = 2.5 um for the membrane force jumping by dF = 0.0125 N
    at the step's start (driven solves at the heights of the switch; the scheme averages the
    acceleration before and after the jump); the sub-steps' own error is 100x smaller (measured:
    3.7 and 3.8 um on unit 2, 0.14 um on unit 3)."""
    runs = _pulse(21)
    assert not any(r.snaps for r in runs)
    assert max(r.step_cuts for r in runs) == 0
    assert max(r.iterations for r in runs) <= 8
    assert max(r.factorisations for r in runs) <= 1
    assert np.ptp([r.position[1] for r in runs]) > 1.5e-3  # the unit did swing (mm, not um)
    for switch in (6, 19):
        reference = _pulse(switch + 1, substeps=10)[-1]
        assert not reference.snaps
        step = runs[switch]
        assert abs(step.position[1] - runs[switch - 1].position[1]) > 0.25e-3  # a long step
        np.testing.assert_allclose(step.position, reference.position, rtol=0.0, atol=5e-6)


@pytest.mark.parametrize("changes, message", [
    ({"unit_modes": ["biased", "loose", "free"]}, r"^unit_modes\[1\]: must be one of"),
    ({"unit_modes": ["biased", "free"]}, r"^unit_modes: needs 1 entry \(for every unit\) or 3"),
    ({"bias": [{"type": "spring"}]}, r"^bias\[0\]: unknown bias type 'spring'"),
    ({"bias": [{"type": "linear", "stiffness": 40.0, "free_positon": 0.02}]},
     r"^bias\[0\]: unknown field\(s\) \['free_positon'\] for a linear bias"),
    ({"bias": [{"type": "constant"}]}, r"^bias\[0\]: a constant bias needs \['force'\]"),
    ({"bias": [None, {"type": "table", "position": [0.0, 0.01, 0.005], "force": [0, 1, 2]}, None]},
     r"^bias\[1\]: position: must be strictly increasing"),
    ({"bias": [{"type": "sum", "terms": [{"type": "linear", "stiffness": "stiff", "free_position": 0.0}]}]},
     r"^bias\[0\]: terms\[0\]: stiffness: expected a finite number"),
    ({"mass": [0.005, -0.001, 0.0]}, r"^mass\[1\]: must be a finite number >= 0"),
    ({"damping": float("nan")}, r"^damping\[0\]: must be a finite number >= 0"),
    ({"contact": ["yes"]}, r"^contact\[0\]: expected true or false"),
])
def test_bad_actuator_config_names_the_key(changes, message):
    from dea_array_twin import ConfigError

    with pytest.raises(ConfigError, match=message):
        ArrayConfig.from_dict(changes)


def test_actuator_config_from_yaml_values_one_entry_for_all_and_back():
    cfg = ArrayConfig.from_dict({"unit_modes": ["biased"], "mass": 0.004, "contact": True,
                                 "bias": [{"type": "linear", "stiffness": -30.0, "free_position": 0.001}]})
    assert cfg.modes == ("biased",) * 3 and cfg.per_unit("mass") == (0.004,) * 3
    assert cfg.per_unit("bias")[2].force(0.002) == pytest.approx(0.03)
    assert ArrayConfig.from_dict(cfg.to_dict()) == cfg
    assert ArrayConfig().modes == ("driven",) * 3


def test_table_bias_is_monotone_cubic_and_refuses_to_extrapolate():
    from dea_array_twin.model.bias import BiasRangeError

    law = bias_from_entry({"type": "table", "position": [0.0, 0.002, 0.004, 0.010], "force": [0.0, 0.3, 0.31, 0.32]})
    w = np.linspace(0.0, 0.010, 201)
    b = np.array([law.force(v) for v in w])
    assert np.all(np.diff(b) >= 0) and b.max() <= 0.32  # PCHIP: no overshoot of monotone data
    assert law.force(0.002) == 0.3 and law.work(0.010) == pytest.approx(np.trapezoid(b, w), rel=1e-4)
    with pytest.raises(BiasRangeError, match="outside the bias table"):
        law.force(0.0101)


def test_an_equilibrium_beyond_the_bias_table_is_an_error_not_an_extrapolation():
    from dea_array_twin import ConvergenceError

    twin = biased_twin({"type": "table", "position": [0.0, 0.004], "force": [0.5, 0.5]}, NewtonSettings())
    with pytest.raises(ConvergenceError, match=r"unit 1: position 0\.004\d* m is outside the bias table \[0, 0\.004\]"):
        twin.solve(voltage=[0.0])
    assert twin.last is None


#: A soft dome under unit 2 of the coarse 1-by-3: F - B of the lower branch peaks at a few mN.
SOFT_DOME_W = [0.00025 * i for i in range(49)]
SOFT_DOME = {"type": "table", "position": SOFT_DOME_W,
             "force": [0.0868 + 0.02 * math.tanh((w - 0.004) / 0.0005) for w in SOFT_DOME_W]}


def test_a_force_step_whose_prediction_reaches_past_the_limit_point_is_reported_as_a_snap():
    """Unit 2 of the coarse 1-by-3 on the soft dome, its neighbours held at 0: the lower branch
    ends where F - B has its local maximum f* (bounded search on driven solves).  A force step
    from 0 to 5 mN > f* in one solve: near the fold the stiffness is small, the linear
    prediction reaches the upper branch and Newton converged there without a mismatch, so the
    snap went unreported (the height moved 1.4 mm in one step).  Now it is reported, starting
    at f* (its load fraction times 5 mN, within 1 %) near the maximum's height, and the twin
    lands where Brent's method on driven solves puts the upper equilibrium at 5 mN."""
    law = bias_from_entry(SOFT_DOME)
    rig = ArrayTwin(ArrayConfig(**COARSE), TIGHT)

    def gap(w, force=0.0):
        return rig.solve([0.0, w, 0.0], 0.0, ["driven"] * 3, check_stability=False).force[1] - law.force(w) - force

    peak = minimize_scalar(lambda w: -gap(w), bounds=(0.003, 0.0045), method="bounded", options={"xatol": 1e-6})
    w_star, f_star = peak.x, -peak.fun
    assert 0.002 < f_star < 0.005
    twin = ArrayTwin(ArrayConfig(**COARSE, bias=(SOFT_DOME,)))
    twin.solve([0.0, 0.003, 0.0], 0.0)
    start = twin.solve(modes=("driven", "biased", "driven"), force=[0.0, 0.0, 0.0])
    assert not start.snaps and start.position[1] < w_star
    res = twin.solve(force=[0.0, 0.005, 0.0])
    assert len(res.snaps) == 1
    snap = res.snaps[0]
    assert 0.005 * snap.load_fraction == pytest.approx(f_star, rel=0.01)
    assert abs(snap.start - w_star) < 1e-4 and snap.end > 0.0045
    assert res.position[1] == pytest.approx(brentq(gap, 0.0045, 0.0055, args=(0.005,), xtol=1e-13), rel=1e-6)
