"""The reduced twin (a hyper-reduced model trained from the FE) against the FE it was trained from.

The ROM is conftest's ``coarse_rom``, trained once per session: every unit driven, d in
[0, 8] mm, units 2 and 3 up to 2500 V and unit 1 never energised, so that "voltage on an
untrained unit" is a command outside its envelope.
"""

import dataclasses

import numpy as np
import pytest

from dea_array_twin import ArrayTwin
from dea_array_twin.model import reduced_twin, rom_kernels
from dea_array_twin.model.reduced import Envelope, ReducedModel, RomMismatchError
from dea_array_twin.model.reduced_twin import ReducedTwin
from dea_array_twin.model.rom_build import Snapshots
from dea_array_twin.model.solver import SolveCancelled
from dea_array_twin.rom.train import Validation, indicator_scale, validate
from dea_array_twin.romfile import RomFileError, load_rom, save_rom

TOLERANCE = 2e-3
D_MAX, V_MAX = 0.008, 2500.0


@pytest.fixture(scope="module")
def cfg(coarse_rom):
    return coarse_rom[0]


@pytest.fixture(scope="module")
def rom(coarse_rom):
    return coarse_rom[1]


def _errors(res, fe, rom):
    """Force error over each unit's force reference and relative capacitance error, largest over units."""
    return (float(np.max(np.abs(res.force - fe.force) / rom.force_reference)),
            float(np.max(np.abs(res.capacitance - fe.capacitance) / fe.capacitance)))


def test_training_validates_within_the_tolerance_on_held_out_commands(rom):
    table = rom.validation
    assert table["commands"] == 6 and table["snapshots"] == 26
    assert table["force_error_max"] <= TOLERANCE and table["capacitance_error_max"] <= TOLERANCE
    # the errors are real numbers, not zeros from comparing the model with itself
    assert table["force_error_max"] > 1e-7 and table["capacitance_error_max"] > 1e-8


def test_reduced_twin_reproduces_the_fe_on_new_commands(cfg, rom):
    """Commands of another sample than training and validation: force, capacitance, centre deflection
    and the recovered field agree with the FE within the tolerance, and the reduced model answered."""
    twin = ReducedTwin(cfg, rom)
    fe = ArrayTwin(cfg)
    d, v = rom.envelope.sample(4, seed=11)
    for k in range(4):
        res, ref = twin.solve(d[k], v[k]), fe.solve(d[k], v[k])
        assert res.fallback == "" and res.error_indicator <= TOLERANCE
        force_error, cap_error = _errors(res, ref, rom)
        assert force_error <= TOLERANCE and cap_error <= TOLERANCE
        np.testing.assert_allclose(res.displacement, d[k])
        assert np.abs(res.centre_deflection - ref.centre_deflection).max() <= TOLERANCE * D_MAX
        assert np.abs(res.positions - ref.positions).max() <= TOLERANCE * D_MAX
        np.testing.assert_allclose(res.delta_capacitance, res.capacitance - fe.model.flat_capacitance)
    assert twin.updates == 4 and not twin.fallbacks


def test_warm_updates_follow_the_fe_along_a_trajectory_with_one_or_two_evaluations(cfg, rom):
    """0.1 mm steps on every indenter and 20 V steps on units 2 and 3, as a controller would send them."""
    twin, fe = ReducedTwin(cfg, rom), ArrayTwin(cfg)
    start_d, start_v = np.array([0.002, 0.004, 0.006]), np.array([0.0, 500.0, 1500.0])
    worst = 0.0
    for i in range(40):
        d = start_d + 1e-4 * i * np.array([1.0, 1.0, -1.0])
        v = start_v + 20.0 * i * np.array([0.0, 1.0, 1.0])
        res, ref = twin.solve(d, v), fe.solve(d, v, check_stability=False)
        assert res.fallback == ""
        assert i == 0 or res.iterations <= 2
        worst = max(worst, *_errors(res, ref, rom))
    assert worst <= TOLERANCE


def test_secant_updates_of_the_predictor_save_second_evaluations_on_a_smooth_path(cfg, rom, monkeypatch):
    """With the refresh in the calling thread, an update that ends converged corrects the predictor's
    ``dq/dp`` by a secant (Broyden) update, so that it maps the step to the change of ``q`` the update made
    (``S dp = q1 - q0`` after it, to round-off).  On a smooth path (every indenter and voltage moving, steps
    of up to 0.2 mm) the next predictions then need fewer second evaluations than from the refreshed
    ``dq/dp`` alone (``second_step`` 1e-4: the coarse ROM's predictions rarely miss by its default 1e-3;
    measured 56 against 74 for 39 updates), and the updates are as close to the FE's (forces of each
    unit's scale, capacitances; 6.2e-5 / 1.5e-4 against 6.5e-5 / 1.6e-4)."""
    t = np.linspace(0.0, 1.0, 40)
    d = 4e-3 + 2.5e-3 * np.sin(np.pi * t[:, None] + np.array([0.0, 0.5, 1.0]))
    v = np.column_stack([np.zeros_like(t), 1500 + 700 * np.sin(2 * np.pi * t), 1200 - 600 * np.sin(np.pi * t)])
    fe = ArrayTwin(cfg)
    truth = [fe.solve(d[k], v[k]) for k in range(t.size)]
    nd, factor = rom.envelope.driven.size, 0.5 * cfg.permittivity / cfg.thickness**2
    runs = {}
    for step in (reduced_twin.SECANT_STEP, np.inf):
        monkeypatch.setattr(reduced_twin, "SECANT_STEP", step)
        twin = ReducedTwin(cfg, rom, tolerance=np.inf, second_step=1e-4)
        twin.solve(d[0], v[0])
        start, force, capacitance, secants = twin.evaluations, 0.0, 0.0, 0
        for k in range(1, t.size):
            q0 = twin._z[1 + nd:].copy()
            res = twin.solve(d[k], v[k])
            assert res.fallback == ""
            force = max(force, np.max(np.abs(res.force - truth[k].force) / rom.force_reference))
            capacitance = max(capacitance, np.max(np.abs(res.capacitance / truth[k].capacitance - 1)))
            dp = np.concatenate([d[k] - d[k - 1], factor * (v[k] ** 2 - v[k - 1] ** 2)])
            moved = twin._tangent.arrays[0] @ dp
            if np.array_equal(moved, twin._z[1 + nd:] - q0) or np.allclose(moved, twin._z[1 + nd:] - q0,
                                                                            rtol=1e-9, atol=1e-12):
                secants += 1
        runs[step] = (twin.evaluations - start, force, capacitance, secants)
    (evals, force, capacitance, secants), (evals_off, force_off, capacitance_off, secants_off) = runs.values()
    assert secants == t.size - 1 and secants_off < t.size // 4  # (a step whose q changed as dq/dp predicted)
    assert evals <= 0.85 * evals_off
    assert force <= max(1.25 * force_off, 2e-4) and capacitance <= max(1.25 * capacitance_off, 2e-4)


def test_a_cold_solve_reuses_a_converging_hessian_and_lands_where_full_newton_does(cfg, rom, monkeypatch):
    """Cold solves (Newton from the nearest snapshot) keep a Hessian while the steps contract by 10 (modified
    Newton: fewer refreshes, each a full Hessian) and reach full Newton's state (SETTLE_CONTRACTION 0:
    a refresh every step) to its tolerance."""
    d, v = rom.envelope.sample(6, seed=13)

    def cold_solves():
        twin = ReducedTwin(cfg, rom)
        answers, refreshes = [], 0
        for k in range(6):
            twin.reset()
            before = twin.refreshes
            res = twin.solve(d[k], v[k])
            assert res.fallback == ""
            answers.append((res.force, res.capacitance))
            refreshes += twin.refreshes - before
        return np.array(answers), refreshes

    modified, fewer = cold_solves()
    monkeypatch.setattr(reduced_twin, "SETTLE_CONTRACTION", 0.0)
    full, every = cold_solves()
    assert fewer < every, (fewer, every)
    np.testing.assert_allclose(modified[:, 0], full[:, 0], rtol=1e-9, atol=1e-9 * np.abs(full[:, 0]).max())
    np.testing.assert_allclose(modified[:, 1], full[:, 1], rtol=1e-9)


def test_point_maps_in_float32_move_the_outputs_by_their_round_off_only(cfg, rom, monkeypatch):
    """The sampled points' maps are stored in float32 (``MAP_DTYPE``: an update is bound by streaming
    them from memory), and an update's products with them are float32 arithmetic.  Along the path above,
    forces, capacitances and energies stay within 1e-5 of those with float64 maps and products (relative;
    measured ~1e-7, the maps' rounding being 6e-8; the ROM's tolerance is 2e-3), with the same number of
    evaluations and refreshes."""
    runs = {}
    for dtype in (np.float64, np.float32):
        monkeypatch.setattr(reduced_twin, "MAP_DTYPE", dtype)
        twin = ReducedTwin(cfg, rom)
        assert twin._fmap.dtype == dtype and twin._wmap.dtype == dtype
        out = [twin.solve([0.002, 0.004, 0.006] + 1e-4 * i * np.array([1.0, 1.0, -1.0]),
                          [0.0, 500.0, 1500.0] + 20.0 * i * np.array([0.0, 1.0, 1.0])) for i in range(40)]
        runs[dtype] = (np.array([r.force for r in out]), np.array([r.capacitance for r in out]),
                       twin.evaluations, twin.refreshes, np.array([r.energy for r in out]))
    (f64, c64, e64, r64, w64), (f32, c32, e32, r32, w32) = runs[np.float64], runs[np.float32]
    assert np.abs(f32 - f64).max() <= 1e-5 * np.abs(f64).max()
    assert np.abs(c32 / c64 - 1.0).max() <= 1e-5
    assert np.abs(w32 / w64 - 1.0).max() <= 1e-5
    assert (e32, r32) == (e64, r64)
    assert np.abs(f32 - f64).max() > 0.0  # the float32 maps were used


def test_a_real_time_twin_computes_its_hessians_without_blas_unless_told_its_blas_has_one_thread(cfg, rom,
                                                                                                monkeypatch):
    """With ``background_refresh`` (a control loop's twin) every Hessian, the worker's and the calling
    thread's (a cold start, a stability check), is summed point by point by default: no BLAS product, after
    which OpenBLAS's helper thread would spin on the core beside the updates (the 1-by-3 ROM node at 1 kHz:
    1.1 cores instead of 0.35, docs/rom.md).  Without it, or told ``blas=True`` (a process whose BLAS was set
    to one thread, as the ROM node's), a large ROM's Hessians are BLAS products; all answer the same to 1e-6
    of the largest force (the products round in the maps' float32, ~1e-7 of the Hessian's entries, and
    that moves an update by as much of its last Newton correction: 1.1e-9 seen; and an update's own
    products are float32 too, whose rounding, ~1e-7 of the outputs, differs between two updates that
    evaluate at states a few round-offs apart: 8e-8 seen).  (The coarse ROM is
    small: it gets the products only with ``BLAS_COLUMNS`` lowered; by default a small ROM's Hessian is
    summed point by point, whatever ``blas`` says.)"""
    assert not ReducedTwin(cfg, rom)._blas and not ReducedTwin(cfg, rom, blas=True).blas_products
    monkeypatch.setattr(reduced_twin, "BLAS_COLUMNS", 1)
    # the secant updates of the predictor (calling-thread refreshes only) move a one-step update within its
    # tolerance, not by round-off: off here, where the Hessians' arithmetic is compared
    monkeypatch.setattr(reduced_twin, "SECANT_STEP", np.inf)
    calls = []

    def recorded(*args, blas=True):
        calls.append(blas)
        return rom_kernels.hessian(*args, blas=blas)

    def forces(twin: ReducedTwin) -> np.ndarray:
        try:
            out = []
            for i in range(30):
                if twin._pending is not None:
                    twin._pending.result(timeout=60)
                out.append(twin.solve([0.002, 0.004, 0.006] + 1e-4 * i * np.array([1.0, 1.0, -1.0]),
                                      [0.0, 500.0, 1500.0] + 20.0 * i * np.array([0.0, 1.0, 1.0]),
                                      check_stability=i == 15))
        finally:
            twin.close()
        return np.array([r.force for r in out])

    monkeypatch.setattr(reduced_twin, "hessian", recorded)
    results = {}
    for background, blas, expected in ((False, None, True), (True, None, False), (True, True, True)):
        twin = ReducedTwin(cfg, rom, background_refresh=background, blas=blas)
        assert twin.blas_products == expected
        results[background, blas] = forces(twin)
        assert calls and set(calls) == {expected}, (background, blas, calls)
        calls.clear()
    for key, force in results.items():
        np.testing.assert_allclose(force, results[False, None], rtol=0, atol=1e-6 * np.abs(force).max(),
                                   err_msg=str(key))


def test_a_twin_whose_worker_lags_refreshes_itself_before_its_hessian_is_too_stale(cfg, rom, monkeypatch):
    """With ``background_refresh``, a worker that never delivers (its requests dropped): once the command is
    ``STALE_LIMIT`` times ``refresh_distance`` from where the Hessian was taken, the update refreshes it in
    the calling thread (a stale Hessian's Newton corrections understate the error left: the 4-by-4 was
    0.35 % off at the default ``second_step``, docs/rom.md), and the path stays within the tolerance."""
    twin, fe = ReducedTwin(cfg, rom, background_refresh=True), ArrayTwin(cfg)
    monkeypatch.setattr(twin, "_request_refresh", lambda z, m: 0)
    try:
        start_d, start_v = np.array([0.001, 0.001, 0.007]), np.array([0.0, 300.0, 2200.0])
        twin.solve(start_d, start_v)
        after_start, worst, refreshed_at = twin.refreshes, 0.0, []
        for i in range(1, 61):  # 6 mm of the 8 mm range on every indenter, 1200 V of 2500 on units 2 and 3
            d, v = start_d + 1e-4 * i * np.array([1.0, 1.0, -1.0]), start_v + 20.0 * i * np.array([0.0, 1.0, -1.0])
            before = twin.refreshes
            res, ref = twin.solve(d, v), fe.solve(d, v, check_stability=False)
            if twin.refreshes > before:
                refreshed_at.append(i)
            worst = max(worst, *_errors(res, ref, rom))
    finally:
        twin.close()
    limit = reduced_twin.STALE_LIMIT * twin.refresh_distance * D_MAX / 1e-4  # updates to the first refresh
    assert refreshed_at and twin.refreshes - after_start == len(refreshed_at)
    assert limit - 1 <= refreshed_at[0] <= limit + 1, (refreshed_at, limit)
    assert worst <= TOLERANCE


def test_a_background_check_gives_the_verdict_of_a_checked_solve(cfg, rom, monkeypatch):
    """``check_in_background`` judges the state the last solve left, in the worker thread: the verdict a
    checked solve of the same command gives, from the Hessian at that state (which becomes the next
    refresh); a Hessian made negative definite gives False.  None without a worker, before a reduced
    state and after an FE answer (the node then checks in the next update)."""
    twin = ReducedTwin(cfg, rom, background_refresh=True)
    try:
        assert ReducedTwin(cfg, rom).check_in_background() is None
        assert twin.check_in_background() is None
        for d, v in (([0.002, 0.004, 0.006], [0.0, 500.0, 1500.0]), ([0.007, 0.001, 0.005], [0.0, 2400.0, 0.0])):
            twin.solve(d, v)
            if twin._pending is not None:
                twin._pending.result(timeout=60)
                twin._collect_refresh()
            verdict = twin.check_in_background()
            checked = ReducedTwin(cfg, rom).solve(d, v, check_stability=True)
            assert checked.fallback == "" and checked.stable is True
            assert verdict.result(timeout=60) is True
            _, at = twin._pending.result()
            np.testing.assert_allclose(at, np.concatenate([d, twin._maxwell_factor * np.square(v)]), rtol=1e-12)
        monkeypatch.setattr(reduced_twin, "hessian", lambda *args, **kw: tuple(-h for h in rom_kernels.hessian(
            *args, **kw)))
        assert twin.check_in_background().result(timeout=60) is False
        assert twin.solve([0.002, 0.012, 0.004], [0.0, 1000.0, 0.0]).fallback.startswith("envelope")
        assert twin.check_in_background() is None
    finally:
        twin.close()


def test_energy_consistent_force_and_capacitance_are_derivatives_of_the_reduced_energy(cfg, rom, monkeypatch):
    """F_k = dE/dd_k (paper eq. 10 as the derivative of the reduced energy at equilibrium) and
    C_u = -(eps/t0^2) dE/dm_u with m_u = eps V_u^2 / (2 t0^2) (eq. 7), by central differences of
    the converged reduced energy (each solve from a reset, so Newton runs to convergence).  With float64
    maps, so float64 products: float32's rounding of the energy, ~1e-7 of it, is as large as the change
    a 1 um step makes (the float32 twin's energy is bounded against this one in the float32 test below)."""
    monkeypatch.setattr(reduced_twin, "MAP_DTYPE", np.float64)
    twin = ReducedTwin(cfg, rom, tolerance=np.inf)
    d, v = np.array([0.003, 0.006, 0.004]), np.array([0.0, 1800.0, 900.0])

    def energy(dd, vv):
        twin.reset()
        return twin.solve(dd, vv).energy

    twin.reset()
    res = twin.solve(d, v)
    h = 1e-6
    for k in range(3):
        step = h * np.eye(3)[k]
        derivative = (energy(d + step, v) - energy(d - step, v)) / (2 * h)
        assert res.force[k] == pytest.approx(derivative, rel=1e-5, abs=1e-7)
    mf = 0.5 * cfg.permittivity / cfg.thickness**2
    for u in (1, 2):
        m = mf * v[u] ** 2
        dm = 1e-4 * m
        up, down = v.copy(), v.copy()
        up[u], down[u] = np.sqrt((m + dm) / mf), np.sqrt((m - dm) / mf)
        derivative = (energy(d, up) - energy(d, down)) / (2 * dm)
        assert res.capacitance[u] == pytest.approx(-cfg.permittivity / cfg.thickness**2 * derivative, rel=1e-6)


def test_commands_outside_the_envelope_are_answered_by_the_fe_and_say_so(cfg, rom):
    twin = ReducedTwin(cfg, rom)
    cases = [([0.002, 0.012, 0.004], [0.0, 1000.0, 0.0], "displacement", "unit 2"),  # deeper than trained
             ([0.002, 0.004, 0.004], [1500.0, 1000.0, 0.0], "voltage", "unit 1"),  # an untrained unit
             ([0.002, 0.004, 0.004], [0.0, 3000.0, 0.0], "voltage", "unit 2")]  # above the trained voltage
    for count, (d, v, what, unit) in enumerate(cases, start=1):
        res = twin.solve(d, v)
        assert res.fallback.startswith("envelope:") and what in res.fallback and unit in res.fallback
        ref = ArrayTwin(cfg).solve(d, v)
        np.testing.assert_allclose(res.force, ref.force, rtol=1e-6, atol=1e-8)
        np.testing.assert_allclose(res.capacitance, ref.capacitance, rtol=1e-8)
        assert twin.fallbacks["envelope"] == count and np.isnan(res.error_indicator)
    res = twin.solve([0.002, 0.004, 0.004], [0.0, 0.0, 0.0], modes=("free", "driven", "free"))
    assert "unit modes" in res.fallback and res.modes == ("free", "driven", "free")
    back = twin.solve([0.002, 0.004, 0.004], [0.0, 1000.0, 0.0], modes=("driven",) * 3)
    assert back.fallback == ""  # inside again: the reduced model answers
    assert max(_errors(back, ArrayTwin(cfg).solve([0.002, 0.004, 0.004], [0.0, 1000.0, 0.0]), rom)) <= TOLERANCE


def test_an_indicator_above_the_tolerance_sends_the_update_to_the_fe(cfg, rom):
    twin = ReducedTwin(cfg, rom, tolerance=1e-12)
    res = twin.solve([0.002, 0.005, 0.003], [0.0, 1200.0, 600.0])
    assert res.fallback.startswith("indicator:") and res.error_indicator > 1e-12
    assert twin.fallbacks == {"indicator": 1}
    ref = ArrayTwin(cfg).solve([0.002, 0.005, 0.003], [0.0, 1200.0, 600.0])
    np.testing.assert_allclose(res.force, ref.force, rtol=1e-6, atol=1e-8)


def test_indicator_flags_every_command_whose_error_exceeds_the_tolerance(cfg, rom):
    """With the envelope check widened away, the reduced model answers commands it was never trained
    for (deeper indentation, higher voltage, voltage on unit 1): each whose error exceeds the
    tolerance must have an indicator above it."""
    wide = dataclasses.replace(rom, envelope=Envelope(("driven",) * 3, np.zeros(3), np.full(3, 0.014),
                                                      np.zeros(3), np.full(3, 3300.0)))
    twin = ReducedTwin(cfg, wide, tolerance=np.inf)
    commands = [([0.002, 0.011, 0.004], [0.0, 1000.0, 0.0]), ([0.002, 0.014, 0.013], [0.0, 0.0, 0.0]),
                ([0.002, 0.004, 0.004], [2500.0, 1000.0, 0.0]), ([0.006, 0.006, 0.006], [3300.0, 0.0, 0.0]),
                ([0.002, 0.004, 0.007], [0.0, 3300.0, 3300.0]), ([0.004, 0.004, 0.004], [0.0, 1500.0, 0.0])]
    exceeded = 0
    for d, v in commands:
        twin.reset()
        res, ref = twin.solve(d, v), ArrayTwin(cfg).solve(d, v)
        error = max(_errors(res, ref, rom))
        if error > TOLERANCE:
            exceeded += 1
            assert res.error_indicator > TOLERANCE, (d, v, error, res.error_indicator)
    assert exceeded >= 3  # the commands do leave the model's accuracy


def test_the_indicator_scale_is_the_largest_ratio_of_error_to_indicator_on_the_calibration_commands():
    """Errors below a tenth of the tolerance do not count, and the scale is never below 1."""
    def calibration(worst, indicator):
        worst, indicator = np.array(worst), np.array(indicator)
        zeros = np.zeros((worst.size, 3))
        return Validation(np.column_stack([worst, zeros[:, :2]]), zeros, zeros, indicator, np.zeros(worst.size))

    tol = 1e-3
    assert indicator_scale(calibration([5e-4, 2e-3, 3e-4], [2e-4, 1e-3, 3e-4]), tol) == pytest.approx(2.5)
    # 5e-5 is below 0.1 tol: its ratio of 50 is left out
    assert indicator_scale(calibration([5e-5, 2e-3], [1e-6, 1e-3]), tol) == pytest.approx(2.0)
    assert indicator_scale(calibration([5e-4, 2e-3], [1e-3, 4e-3]), tol) == 1.0  # already above the error
    assert indicator_scale(calibration([1e-5], [1e-9]), tol) == 1.0  # nothing to calibrate on
    assert indicator_scale(calibration([5e-4], [0.0]), tol) > 1e100  # an indicator blind to an error


def test_training_calibrates_the_indicator_and_the_twin_applies_it(cfg, rom, tmp_path):
    """The coarse ROM's scale comes from its own calibration sample (6 commands, ``train``'s default of
    as many as validated), is saved with it, and multiplies the indicator of every reduced answer."""
    assert rom.validation["calibration_commands"] == 6
    assert rom.indicator_scale > 1.0  # 1.27: the raw indicator fell short on a calibration command
    raw, tripled = dataclasses.replace(rom, indicator_scale=1.0), dataclasses.replace(rom, indicator_scale=3.0)
    d, v = [0.003, 0.006, 0.002], [0.0, 1800.0, 900.0]
    scaled, plain = ReducedTwin(cfg, tripled).solve(d, v), ReducedTwin(cfg, raw).solve(d, v)
    assert scaled.fallback == plain.fallback == "" and plain.error_indicator > 0.0
    assert scaled.error_indicator == pytest.approx(3.0 * plain.error_indicator, rel=1e-12)
    np.testing.assert_allclose(scaled.force, plain.force, rtol=0, atol=0)  # the answer itself is the same
    doubled = load_rom(save_rom(dataclasses.replace(rom, indicator_scale=2.0), tmp_path / "doubled"), cfg)
    assert doubled.indicator_scale == 2.0
    arrays = dict(np.load(save_rom(rom, tmp_path / "old")))
    del arrays["indicator_scale"]  # a file written before the calibration: the raw indicator
    assert ReducedModel.from_arrays(arrays).indicator_scale == 1.0


def over_tolerance(rom, force=0.0056, capacitance=0.0031, over=43, unflagged=25):
    """``rom`` with a validation table whose errors exceeded its tolerance (as the 4-by-4's in docs/rom.md)."""
    table = dict(rom.validation, force_error_max=force, capacitance_error_max=capacitance, commands=60,
                 over_tolerance=over, over_tolerance_unflagged=unflagged)
    return dataclasses.replace(rom, validation=table)


def test_validation_counts_the_commands_the_reduced_model_hands_to_the_fe(cfg, rom):
    """A held-out command the reduced model does not answer (here one outside its envelope: voltage on
    unit 1, which it was never trained with; in training, a reduced Newton that did not converge) is
    counted with its reason and left out of the errors, instead of ending a training in a traceback;
    the table and the ROM's warning say so.  A set it answers none of is an error."""
    fe = ArrayTwin(cfg)
    commands = [([0.003, 0.004, 0.005], [0.0, 1000.0, 500.0]), ([0.003, 0.004, 0.005], [800.0, 1000.0, 500.0])]
    results = [fe.solve(d, v) for d, v in commands]
    snaps = Snapshots(np.array([d for d, _ in commands]), np.array([v for _, v in commands]),
                      np.array([r.positions.ravel() for r in results]), np.array([r.force for r in results]),
                      np.array([r.capacitance for r in results]))
    checked = validate(ReducedTwin(cfg, rom, tolerance=np.inf), snaps)
    assert checked.force_error.shape == (1, 3) and len(checked.fallbacks) == 1
    assert checked.fallbacks[0].startswith("envelope")
    table = checked.table(TOLERANCE)
    assert table["commands"] == 2 and table["rom_fallbacks"] == 1
    assert table["force_error_max"] <= TOLERANCE
    warning = dataclasses.replace(rom, validation=dict(rom.validation, **table)).validation_warning()
    assert "handed 1 of 2 held-out commands to the FE" in warning
    with pytest.raises(RuntimeError, match="answered none of the 1 commands"):
        validate(ReducedTwin(cfg, rom, tolerance=np.inf), dataclasses.replace(
            snaps, **{f.name: getattr(snaps, f.name)[1:] for f in dataclasses.fields(snaps)}))


def test_a_rom_validated_beyond_its_tolerance_says_how_far_and_what_the_indicator_missed(rom):
    assert rom.validation_warning() == ""  # the coarse ROM validated within its tolerance
    text = over_tolerance(rom).validation_warning()
    assert f"tolerance {rom.tolerance:.3%}" in text and "force up to 0.560%" in text
    assert "capacitance up to 0.310%" in text and "on 43 of 60 held-out commands, 25 of them missed" in text
    edge = over_tolerance(rom, force=rom.tolerance, capacitance=rom.tolerance, over=0, unflagged=0)
    assert edge.validation_warning() == ""  # at the tolerance: within it


def test_a_rom_for_another_config_is_refused_and_a_file_round_trips(cfg, rom, tmp_path):
    path = save_rom(rom, tmp_path / "array")
    assert path.name == "array.npz"
    again = load_rom(path, cfg)
    for name in ("basis", "lift", "point_weight", "train_coordinates"):
        np.testing.assert_array_equal(getattr(again, name), getattr(rom, name))
    assert again.envelope.modes == rom.envelope.modes and again.validation == rom.validation
    stiffer = cfg.replace(c10=0.2e6)
    with pytest.raises(RomMismatchError, match="c10"):
        load_rom(path, stiffer)
    with pytest.raises(RomMismatchError, match="prestretch"):
        ReducedTwin(cfg.replace(prestretch=1.2), rom)
    # Command limits are not part of the model: a node changes them at run time.
    twin = ReducedTwin(cfg.replace(max_displacement=0.02), rom)
    twin.config = cfg.replace(breakdown_field=100e6)
    assert twin.fe.config.breakdown_field == 100e6
    with pytest.raises(RomMismatchError, match="epsr"):
        twin.config = cfg.replace(epsr=3.0)
    (tmp_path / "bad.npz").write_text("not a zip")
    with pytest.raises(RomFileError, match="bad.npz"):
        load_rom(tmp_path / "bad.npz")
    with pytest.raises(RomFileError, match="does not exist"):
        load_rom(tmp_path / "missing.npz")


def test_a_resync_restarts_the_reduced_state_from_the_fe_and_a_cancel_keeps_the_last_state(cfg, rom):
    """The node's FE check hands an FE result to the reduced twin (from another thread): the next
    solve starts from it, converges and agrees with the FE; a cancelled cold start changes nothing."""
    twin, fe = ReducedTwin(cfg, rom), ArrayTwin(cfg)
    first = twin.solve([0.003, 0.004, 0.002], [0.0, 900.0, 300.0])
    d, v = [0.004, 0.006, 0.003], [0.0, 1500.0, 800.0]
    twin.request_resync(fe.solve(d, v))
    res = twin.solve(d, v)
    assert twin.resyncs == 1 and res.fallback == "" and res.factorisations >= 1  # a cold start: refreshed
    assert max(_errors(res, fe.solve(d, v), rom)) <= TOLERANCE
    twin.reset()
    with pytest.raises(SolveCancelled):
        twin.solve(d, v, cancel=lambda: True)
    assert twin.last is None and twin.updates == 2 and first.fallback == ""
    again = twin.solve(d, v)
    np.testing.assert_allclose(again.force, res.force, rtol=1e-6, atol=1e-9)


def test_warm_up_leaves_the_reduced_twin_as_a_new_one(cfg, rom):
    """warm_up solves (reduced and FE) to compile its kernels, then resets: the next answer and the
    counters are those of a twin that never solved."""
    fresh, warmed = ReducedTwin(cfg, rom), ReducedTwin(cfg, rom)
    warmed.warm_up()
    assert (warmed.updates, warmed.evaluations, warmed.refreshes, sum(warmed.fallbacks.values())) == (0, 0, 0, 0)
    command = ([0.0, 0.006, 0.0], [0.0, 1500.0, 0.0])
    a, b = fresh.solve(*command), warmed.solve(*command)
    np.testing.assert_array_equal(a.force, b.force)
    np.testing.assert_array_equal(a.capacitance, b.capacitance)
    assert (warmed.updates, warmed.evaluations) == (fresh.updates, fresh.evaluations)


def test_an_edges_share_of_the_sample_is_dense_at_the_bounds_and_the_rest_is_the_uniform_sample():
    env = Envelope(("driven", "free", "driven"), np.zeros(3), np.full(3, 0.01), np.zeros(3), np.full(3, 2000.0))
    n = 400
    d0, v0 = env.sample(n, 5)
    d, v = env.sample(n, 5, edges=0.5)
    np.testing.assert_array_equal(d[:200], d0[:200])  # the uniform share is the plain sample's ...
    np.testing.assert_array_equal(v[:200], v0[:200])
    stretch = lambda x, hi: 0.5 * (1 - np.cos(np.pi * x / hi)) * hi  # noqa: E731
    np.testing.assert_allclose(d[200:], stretch(d0[200:], 0.01), rtol=0, atol=1e-15)  # ... the rest stretched
    np.testing.assert_allclose(v[200:], stretch(v0[200:], 2000.0), rtol=0, atol=1e-9)
    assert np.all(d[:, 1] == 0.0) and np.all((d >= 0) & (d <= 0.01)) and np.all((v >= 0) & (v <= 2000.0))

    def near_bounds(x, hi):  # share of the values within 5 % of the range from a bound
        return np.mean((x < 0.05 * hi) | (x > 0.95 * hi))

    # a Latin hypercube has one value per 1/n stratum of each input, so the shares are exact to 2/n:
    # uniform 0.1; Chebyshev 2 acos(0.9) / pi = 0.2871
    d1, v1 = env.sample(n, 5, edges=1.0)
    for x, hi, share in ((d0[:, [0, 2]], 0.01, 0.1), (v0, 2000.0, 0.1),
                         (d1[:, [0, 2]], 0.01, 2 * np.arccos(0.9) / np.pi), (v1, 2000.0, 2 * np.arccos(0.9) / np.pi)):
        assert near_bounds(x, hi) == pytest.approx(share, abs=2 / n)
    with pytest.raises(ValueError, match="edges"):
        env.sample(n, 5, edges=1.5)
