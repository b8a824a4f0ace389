"""Biased units in the reduced twin: their heights solved on the ROM, against the FE twin's biased states.

The ROM is conftest's ``coarse_rom`` (every unit trained as driven, d in [0, 8] mm, units 2
and 3 up to 2500 V).  A biased unit's height w solves ``F_k(w) = B_k(w) + f_k`` with the
reduced equilibrium; the FE twin solves the same equations on the full mesh.  A force error
dF moves the height by dF / (K - dB/dw), so with an LBS of 40 N/m (and a membrane that only
adds stiffness) the ROM's height may differ from the FE's by at most TOLERANCE * F_ref / 40.
"""

import numpy as np
import pytest

from dea_array_twin import ArrayTwin
from dea_array_twin.model.reduced_twin import ReducedTwin

TOLERANCE = 2e-3
LBS = {"type": "linear", "stiffness": 40.0, "free_position": 0.010}


@pytest.fixture(scope="module")
def rom(coarse_rom):
    return coarse_rom[1]


def _compare(res, ref, rom, stiffness):
    """The ROM's state against the FE's: force over its reference, capacitance, height (force error over stiffness)."""
    f_tol = TOLERANCE * rom.force_reference
    assert np.all(np.abs(res.force - ref.force) <= f_tol)
    np.testing.assert_allclose(res.capacitance, ref.capacitance, rtol=TOLERANCE)
    assert np.all(np.abs(res.position - ref.position) <= f_tol / stiffness)


def test_biased_equilibria_of_the_reduced_twin_equal_the_fe_biased_equilibria(coarse_rom, rom):
    """Unit 2 then units 2 and 3 on an LBS of 40 N/m with force commands, unit 1 driven: every answer from
    the ROM (no fallback), in equilibrium F_k = B_k(w_k) + f_k, equal to the FE twin's within the ROM's
    tolerance; warm updates of a controller's size cost one evaluation."""
    cfg = coarse_rom[0].replace(bias=(LBS,))
    twin, fe = ReducedTwin(cfg, rom), ArrayTwin(cfg)
    one, two = ("driven", "biased", "driven"), ("driven", "biased", "biased")
    commands = [(one, [0.002, 0, 0.003], [0, 1500, 800], [0, 0.0, 0]),
                (one, [0.002, 0, 0.003], [0, 1500, 800], [0, 0.03, 0])]  # a force command on unit 2
    commands += [(two, [0.002 + 1e-4 * i, 0, 0], [0, 1500 + 20 * i, 800 - 20 * i], [0, 0.03, -0.002 * i])
                 for i in range(12)]
    warm = []
    for i, (modes, d, v, f) in enumerate(commands):
        res, ref = twin.solve(d, v, modes, force=f), fe.solve(d, v, modes, force=f)
        assert res.fallback == "" and res.modes == modes
        _compare(res, ref, rom, 40.0)
        biased = np.array(modes) == "biased"
        w = res.position[biased]
        np.testing.assert_allclose(res.bias_force[biased], 40.0 * (0.010 - w), rtol=1e-12)
        np.testing.assert_array_equal(res.external_force, np.where(biased, f, 0.0))
        assert np.all(np.abs(res.force[biased] - res.bias_force[biased] - res.external_force[biased])
                      <= TOLERANCE * rom.force_reference[biased])
        assert res.position[0] == d[0] and 0.004 < w.min() and w.max() < 0.008  # inside the envelope
        if i > 2:
            warm.append(res.iterations)
    assert np.mean(warm) <= 1.2 and twin.fallbacks == {}
    assert twin.solve(check_stability=True).stable is True


def test_a_biased_height_pushed_outside_the_envelope_is_answered_by_the_fe_and_says_so(coarse_rom, rom):
    """A force command that pushes unit 2 beyond the trained 8 mm: the FE answers (counted, the reason names the
    unit and the range); back inside, the ROM answers again, equal to the FE."""
    cfg = coarse_rom[0].replace(bias=(LBS,))
    twin, fe = ReducedTwin(cfg, rom), ArrayTwin(cfg)
    modes = ("driven", "biased", "driven")
    for f, answered_by_rom in ((0.0, True), (0.15, False), (0.0, True)):
        res = twin.solve([0.002, 0, 0.003], [0, 1000, 0], modes, force=[0, f, 0])
        ref = fe.solve([0.002, 0, 0.003], [0, 1000, 0], modes, force=[0, f, 0])
        if answered_by_rom:
            assert res.fallback == ""
            _compare(res, ref, rom, 40.0)
        else:
            assert res.fallback.startswith("envelope: height") and "biased unit 2" in res.fallback
            assert "[0, 0.008] m" in res.fallback and res.position[1] > 0.008
            np.testing.assert_allclose(res.position, ref.position, rtol=1e-6)
            np.testing.assert_allclose(res.force, ref.force, rtol=1e-6)
    assert twin.fallbacks == {"envelope": 1}
    with pytest.raises(ValueError, match="force must be finite"):
        twin.solve(force=[0, np.nan, 0])


def test_a_limit_point_of_a_negative_rate_bias_is_not_crossed_silently(coarse_rom, rom):
    """An NBS (B = -25 N/m (x0 - w)) holding unit 2 near 7 mm at 2500 V: lowering the voltage takes the
    equilibrium to its limit point K = 25 N/m, where it snaps below the envelope.  The ROM answers while
    K - dB/dw > 0 and hands the step across the limit point to the FE ("snap"), which reports the jump."""
    cfg = coarse_rom[0].replace(bias=({"type": "linear", "stiffness": -25.0, "free_position": 0.001044},))
    twin, fe = ReducedTwin(cfg, rom), ArrayTwin(cfg)
    modes = ("driven", "biased", "driven")
    for t in (twin, fe):
        t.solve([0, 0.007, 0], [0, 2500, 0])  # held at 7 mm, then released onto the bias
    res, ref = twin.solve(modes=modes), fe.solve(modes=modes)
    assert res.fallback == "" and abs(res.position[1] - 0.007) < 5e-4
    # near the limit point K - dB/dw is about 3.5 N/m: the height error is the force error over that
    _compare(res, ref, rom, 3.0)
    res = twin.solve(voltage=[0, 2250, 0], modes=modes)
    assert res.fallback.startswith("snap: units [2]") and "not positive definite" in res.fallback
    assert [s.unit for s in res.snaps] == [1] and res.position[1] < 0  # the FE's snap, landed below
    assert res.snaps[0].describe().startswith("unit 2 snapped through from 5.")


def test_a_jump_to_the_other_branch_of_a_bistable_dome_is_not_returned_silently(coarse_rom, rom):
    """A narrow bistable dome (a table: B = 86.8 mN + 8 mN tanh((w - 4 mm) / 0.2 mm)) under unit 2: on its
    lower branch the ROM answers as the FE; a 10 mN force step beyond its limit point lands Newton on the upper
    branch, 0.36 mm from the heights' linear prediction: more than jump_tol (0.01 D, the FE's test), so the FE
    answers ("snap") and lands where the FE twin, which reports a snap-through, lands."""
    heights = [1e-4 * i for i in range(81)]
    dome = {"type": "table", "position": heights,
            "force": [0.0868 + 0.008 * np.tanh((w - 0.004) / 0.0002) for w in heights]}
    twin, fe = ReducedTwin(coarse_rom[0].replace(bias=(dome,)), rom), ArrayTwin(coarse_rom[0].replace(bias=(dome,)))
    modes = ("driven", "biased", "driven")
    for t in (twin, fe):
        t.solve([0, 0.003, 0], 0.0)  # held at 3 mm, then released onto the dome
    res, ref = twin.solve(modes=modes), fe.solve(modes=modes)
    assert res.fallback == "" and res.position[1] < 0.0038  # the lower branch
    _compare(res, ref, rom, 5.0)  # K - dB/dw is above 5 N/m there (the dome's slope at 3.7 mm: 6 N/m)
    res, ref = twin.solve(force=[0, 0.01, 0]), fe.solve(modes=modes, force=[0, 0.01, 0])
    assert res.fallback.startswith("snap: biased heights") and "from their linear prediction" in res.fallback
    assert [s.unit for s in ref.snaps] == [1] and ref.position[1] > 0.0042  # the FE's snap, to the upper branch
    np.testing.assert_allclose(res.position, ref.position, rtol=1e-6)


def test_an_indenter_in_contact_that_would_pull_the_membrane_is_answered_by_the_fe(coarse_rom, rom):
    """With unilateral contact, driven indenters at 0 m under a membrane lifted by unit 2's bias would
    pull it: the FE answers (they lift off) and keeps answering while they are off."""
    cfg = coarse_rom[0].replace(bias=({"type": "linear", "stiffness": 20.0, "free_position": 0.002},),
                                contact=(True,))
    twin, fe = ReducedTwin(cfg, rom), ArrayTwin(cfg)
    modes = ("driven", "biased", "driven")
    res, ref = twin.solve([0, 0, 0], 0.0, modes), fe.solve([0, 0, 0], 0.0, modes)
    assert res.fallback.startswith("contact: the indenters of units [1, 3] would pull")
    np.testing.assert_array_equal(res.lifted_off, [True, False, True])
    np.testing.assert_allclose(res.position, ref.position, rtol=1e-6)
    res = twin.solve([0.001, 0, 0.001], 0.0, modes)
    assert res.fallback.startswith("contact: the indenters of units [1, 3] are lifted off")
    res, ref = twin.solve([0.008, 0, 0.008], 0.0, modes), fe.solve([0.008, 0, 0.008], 0.0, modes)
    assert res.fallback == "" and not res.lifted_off.any() and not ref.lifted_off.any()
    _compare(res, ref, rom, 20.0)
    assert twin.fallbacks == {"contact": 2}


def _period(w: np.ndarray, dt: float) -> float:
    """Mean period [s] of an oscillation sampled every ``dt``, from its upward mean crossings (interpolated)."""
    x = w - w.mean()
    up = np.flatnonzero((x[:-1] < 0) & (x[1:] >= 0))
    return float(np.mean(np.diff(up - x[up] / (x[up + 1] - x[up])))) * dt


def test_a_biased_indenter_with_mass_oscillates_with_the_period_of_its_stiffness_as_in_the_fe(coarse_rom, rom):
    """Unit 2 (5 g on an LBS of 40 N/m, undamped) released by a 2 mN force step: the ROM's Newmark steps
    (dt = T/50) give the period 2 pi sqrt(m / (K - dB/dw)), K = dF/dw from central differences of FE driven
    solves, within 1 % (Newmark's own period error is 0.13 %), and follow the FE twin's steps within the
    ROM's tolerance; a step that leaves the envelope is the FE's, from the reduced state."""
    mass = 0.005
    cfg = coarse_rom[0].replace(bias=(LBS,), mass=(mass,))
    twin, fe = ReducedTwin(cfg, rom), ArrayTwin(cfg)
    modes, d, v = ("driven", "biased", "driven"), [0.003, 0, 0.003], [0, 1000, 0]
    res, ref = twin.solve(d, v, modes), fe.solve(d, v, modes)
    w0 = ref.position[1]
    driven = ArrayTwin(coarse_rom[0])
    h = 1e-5
    k = (driven.solve([0.003, w0 + h, 0.003], v).force[1] - driven.solve([0.003, w0 - h, 0.003], v).force[1]) / (2 * h)
    k_eff = k + 40.0
    period = 2 * np.pi * np.sqrt(mass / k_eff)
    dt = period / 50
    w_rom, w_fe = [], []
    for _ in range(130):
        res, ref = twin.step(dt, force=[0, 0.002, 0]), fe.step(dt, force=[0, 0.002, 0])
        assert res.fallback == ""
        w_rom.append(res.position[1])
        w_fe.append(ref.position[1])
        _compare(res, ref, rom, k_eff)
        assert res.velocity[1] == pytest.approx(ref.velocity[1], abs=TOLERANCE * rom.force_reference[1] / k_eff / dt)
    amplitude = (max(w_rom) - min(w_rom)) / 2
    assert amplitude == pytest.approx(0.002 / k_eff, rel=0.05)  # released from rest: f / K
    assert _period(np.array(w_rom), dt) == pytest.approx(period, rel=0.01)
    assert twin.evaluations <= 1.2 * 130 + 20
    for _ in range(20):  # 0.15 N more: the indenter flies past 8 mm within a quarter period
        res, ref = twin.step(dt, force=[0, 0.15, 0]), fe.step(dt, force=[0, 0.15, 0])
        _compare(res, ref, rom, k_eff)
        assert res.velocity[1] == pytest.approx(ref.velocity[1], abs=TOLERANCE * rom.force_reference[1] / k_eff / dt)
        if res.fallback:
            break
    assert res.fallback.startswith("envelope: height") and twin.fallbacks == {"envelope": 1}
    res, ref = twin.step(dt), fe.step(dt)  # the FE's again, from its own state
    assert twin.fallbacks == {"envelope": 2} and res.position[1] > 0.008
    _compare(res, ref, rom, k_eff)


WARM_UP = """
import json, sys
import numba
from dea_array_twin import ArrayConfig
from dea_array_twin.model import rom_kernels
from dea_array_twin.model.reduced_twin import ReducedTwin
from dea_array_twin.romfile import load_rom

def compiled():
    return {name: len(f.signatures) for name, f in vars(rom_kernels).items()
            if isinstance(f, numba.core.registry.CPUDispatcher)}

cfg = ArrayConfig(**json.loads(sys.argv[1])).replace(bias=({"type": "linear", "stiffness": 40.0,
                                                           "free_position": 0.010},), mass=(0.005,))
twin = ReducedTwin(cfg, load_rom(sys.argv[2], cfg))
twin.warm_up()
before = compiled()
modes = ("driven", "biased", "driven")
answers = [twin.solve([0.002, 0, 0.003], [0, 1000, 0], modes, force=[0, 0.01, 0]), twin.solve(voltage=[0, 1100, 0]),
           twin.step(0.001), twin.step(0.001, force=[0, 0.02, 0])]
assert all(res.fallback == "" for res in answers), [res.fallback for res in answers]
print(json.dumps({"before": before, "after": compiled()}))
"""


def test_no_biased_update_of_the_reduced_twin_compiles_after_warm_up_in_a_fresh_interpreter(coarse_rom, tmp_path):
    import json
    import os
    import subprocess
    import sys
    from pathlib import Path

    from conftest import COARSE

    env = dict(os.environ, PYTHONPATH=str(Path(__file__).resolve().parents[2]))  # this checkout's source
    out = subprocess.run([sys.executable, "-c", WARM_UP, json.dumps(COARSE), str(coarse_rom[2])], capture_output=True,
                         text=True, timeout=280, cwd=tmp_path, env=env)
    assert out.returncode == 0, out.stderr
    counts = json.loads(out.stdout.strip().splitlines()[-1])
    assert counts["before"]["_heights"] == 1, counts
    assert counts["after"] == counts["before"], counts
