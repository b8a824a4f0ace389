"""Background tangents (``ArrayTwin(background_tangent=True)``, the node's twin): the same equilibria, fewer
factorisations in the calling thread.

The worker thread's timing is taken out: before each update the test waits for the tangent
under way (as a spare core would have finished it), so the counts are exact.
"""

import math
import os
import sys
import threading

import numpy as np
import pytest
from conftest import COARSE

from dea_array_twin import ArrayConfig, ArrayTwin
from dea_array_twin.model import twin as twin_module
from dea_array_twin.model.solver import Factorisation, NewtonSettings, SolveStats

DRIVEN3 = ("driven",) * 3


def _sine(i: int, period: int = 40) -> list[float]:
    """A 1 Hz sine on every unit, a third of a period apart, sampled ``period`` times a cycle [m]."""
    return [0.005 + 0.004 * math.sin(2 * math.pi * (i / period + k / 3)) for k in range(3)]


def test_background_tangents_keep_the_equilibria_and_take_factorisations_off_the_update():
    """60 updates of a sine on every unit: forces within the solver's own accuracy of a tightly
    converged reference (1e-6 of the largest force; the plain twin is 1.6e-7 from it), fewer Newton
    iterations and fewer factorisations in the updates than the plain twin."""
    cfg = ArrayConfig(**COARSE)
    plain, background = ArrayTwin(cfg), ArrayTwin(cfg, background_tangent=True)
    threads = []  # of the background factorisations: one (they run beside the updates)
    factorise = background.solver.factorise_at

    def recorded(*args):
        if threading.current_thread().name.startswith("fe-tangent"):
            threads.append(args[5] if len(args) > 5 else None)
        return factorise(*args)

    background.solver.factorise_at = recorded
    tight = ArrayTwin(cfg, NewtonSettings(residual_tol=1e-11, increment_tol=1e-10))
    counts = {"plain": [0, 0], "background": [0, 0]}  # iterations, factorisations
    try:
        for i in range(60):
            reference = tight.solve(_sine(i), 0.0, DRIVEN3, check_stability=False)
            if background._pending is not None:
                background._pending.result(timeout=60)
            for name, twin in (("plain", plain), ("background", background)):
                res = twin.solve(_sine(i), 0.0, DRIVEN3, check_stability=False)
                largest = np.abs(reference.force).max()
                np.testing.assert_allclose(res.force, reference.force, rtol=0, atol=1e-6 * largest)
                np.testing.assert_allclose(res.capacitance, reference.capacitance, rtol=1e-6, atol=0)
                counts[name][0] += res.iterations
                counts[name][1] += res.factorisations
    finally:
        background.close()
    assert background.tangents["installed"] > 0 and background.tangents["failed"] == 0
    assert len(threads) >= background.tangents["installed"] and set(threads) == {1}
    assert counts["background"][0] < counts["plain"][0]
    assert counts["background"][1] < counts["plain"][1] / 2


def test_a_background_tangent_under_way_at_a_reset_is_never_used():
    cfg = ArrayConfig(**COARSE)
    twin = ArrayTwin(cfg, background_tangent=True)
    try:
        for i in range(60):  # until a stale tangent is refreshed in the background
            twin.solve(_sine(i), 0.0, DRIVEN3, check_stability=False)
            if twin._pending is not None:
                break
        pending = twin._pending
        assert pending is not None
        twin.reset()
        pending.result(timeout=60)
        flat = twin.solve([0.0, 0.0, 0.0], 0.0, DRIVEN3, check_stability=False)
    finally:
        twin.close()
    assert twin.tangents["installed"] == 0
    assert twin.solver.factorisation is not pending.result()
    np.testing.assert_allclose(flat.force, 0.0, atol=1e-9)


def test_a_stale_tangent_is_kept_until_its_background_refresh_is_in():
    """The node's command stream (a 1 Hz sine at 500 updates a second: 1-2 Newton iterations): a
    tangent that contracts the residual by less than ``contraction`` is not refactored in the update
    (the plain twin does so 7 times in 300 updates, each a stall of several update periods at 500 Hz)
    but refreshed in the worker; the forces stay within 1e-6 of the largest of the plain twin's."""
    cfg = ArrayConfig(**COARSE)
    plain, background = ArrayTwin(cfg), ArrayTwin(cfg, background_tangent=True)
    factorisations = {"plain": 0, "background": 0}
    try:
        for i in range(300):
            if background._pending is not None:
                background._pending.result(timeout=60)
            results = {name: twin.solve(_sine(i, 500), 0.0, DRIVEN3, check_stability=False)
                       for name, twin in (("plain", plain), ("background", background))}
            largest = np.abs(results["plain"].force).max()
            np.testing.assert_allclose(results["background"].force, results["plain"].force, rtol=0,
                                       atol=1e-6 * largest)
            if i > 0:  # the first update jumps from the flat state
                for name, res in results.items():
                    factorisations[name] += res.factorisations
    finally:
        background.close()
    assert factorisations["plain"] >= 3 and factorisations["background"] == 0, factorisations
    assert background.tangents["installed"] >= 3 and background.tangents["failed"] == 0


def _node_stream(twin: ArrayTwin, updates: int) -> tuple[list[int], list[bool]]:
    """The node's stream (a 1 Hz sine at 500 updates a second) through ``twin``, each update after the
    tangent under way is in: its Newton iterations, and whether it started a background tangent."""
    iterations, started = [], []
    for i in range(updates):
        if twin._pending is not None:
            twin._pending.result(timeout=60)
        res = twin.solve(_sine(i, 500), 0.0, DRIVEN3, check_stability=False)
        iterations.append(res.iterations)
        started.append(twin._pending is not None)
        assert started[-1] == (i > 0 and res.factorisations == 0 and (
            res.iterations >= twin_module.BACKGROUND_ITERATIONS
            or twin.solver.stale_contraction > twin_module.BACKGROUND_CONTRACTION)), i
    return iterations[1:], started  # the first update jumps from the flat state


def test_a_tangent_going_stale_is_refreshed_before_updates_need_a_second_iteration(monkeypatch):
    """A step on the tangent that leaves more than BACKGROUND_CONTRACTION of its residual starts a
    background tangent although the update converged in one iteration; on the node's stream that
    leaves 1 of 299 updates with two iterations (measured; 21 with the iteration rule alone, which
    refreshes 3 times against 17).  Each update is checked against the rule."""
    cfg = ArrayConfig(**COARSE)
    counts = {}
    for rule in ("contraction", "iterations only"):
        if rule == "iterations only":
            monkeypatch.setattr(twin_module, "BACKGROUND_CONTRACTION", math.inf)
        twin = ArrayTwin(cfg, background_tangent=True)
        try:
            iterations, started = _node_stream(twin, 300)
        finally:
            twin.close()
        counts[rule] = (sum(i > 1 for i in iterations), sum(started))
        assert twin.tangents["failed"] == 0
    assert counts["contraction"][0] <= 3 and counts["iterations only"][0] >= 10, counts
    assert counts["contraction"][1] > counts["iterations only"][1], counts


def test_a_background_tangent_comes_with_the_influence_vectors_of_the_disks(monkeypatch):
    """The worker also solves for the driven disks' influence vectors (the predictor's), so an update
    that starts from its tangent solves only for its Newton steps (else three more solves, ~0.9 ms on
    the default mesh, in an update that has 2 ms at 500 Hz)."""
    cfg = ArrayConfig(**COARSE)
    twin = ArrayTwin(cfg, background_tangent=True)
    solves = []
    solve = Factorisation.solve

    def counted(self, b):
        if threading.current_thread() is threading.main_thread():
            solves.append(b)
        return solve(self, b)

    monkeypatch.setattr(Factorisation, "solve", counted)
    checked = 0
    try:
        for i in range(30):
            if twin._pending is not None:
                twin._pending.result(timeout=60)
            installed = twin.tangents["installed"]
            solves.clear()
            res = twin.solve(_sine(i), 0.0, DRIVEN3, check_stability=False)
            if twin.tangents["installed"] > installed and res.factorisations == 0:
                assert len(solves) == res.iterations, (i, len(solves), res.iterations)
                checked += 1
    finally:
        twin.close()
    assert checked >= 10


def test_a_stability_check_in_the_worker_gives_the_verdict_of_a_checked_solve():
    """A stable state (a checked solve says so) and, put in its place, a saddle (both outer indenters
    pulled 4 mm out by full Newton from the flat membrane, see test_array_physics): the worker's verdict
    is the checked solve's, True, then False; its tangent is installed for the next update; a twin
    without a worker, or holding a biased unit, has none."""
    cfg = ArrayConfig(**COARSE)
    twin = ArrayTwin(cfg, background_tangent=True)
    try:
        assert twin.check_in_background() is None  # no state yet
        checked = twin.solve([0.004, 0.0, 0.004], 0.0, DRIVEN3, check_stability=True)
        assert checked.stable is True and twin.check_in_background().result(timeout=60) is True
        prescribed, free = twin.model.prescribed_dofs(DRIVEN3)
        flat = twin.model.flat_state()
        twin.model.apply_prescribed(flat, DRIVEN3, np.array([0.004, 0.0, 0.004]))
        saddle = twin.solver._newton(flat, free, prescribed, np.zeros(twin.model.mesh.n_elements), None,
                                     SolveStats())[0]
        twin._x = saddle
        verdict = twin.check_in_background()
        assert verdict.result(timeout=60) is False
        twin.solve([0.004, 0.0, 0.004], 0.0, DRIVEN3, check_stability=False)
        assert twin.tangents["installed"] >= 1
    finally:
        twin.close()
    biased = ArrayTwin(ArrayConfig(**COARSE, unit_modes=("driven", "biased", "driven"),
                                   bias=[{"type": "linear", "stiffness": 40.0, "free_position": 0.001}]),
                       background_tangent=True)
    try:
        biased.solve([0.0, 0.0, 0.0], 0.0, check_stability=False)
        assert biased.check_in_background() is None
    finally:
        biased.close()
    plain = ArrayTwin(cfg)
    plain.solve([0.001, 0.0, 0.0], 0.0, DRIVEN3)
    assert plain.check_in_background() is None


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="per-thread nice values are Linux's")
def test_the_worker_thread_runs_at_a_lower_priority_than_the_updates():
    """The worker's refreshes and checks yield the core to the updates: its nice value is the
    process's plus BACKGROUND_NICE (at most 19); the calling thread's is untouched."""
    twin = ArrayTwin(ArrayConfig(**COARSE), background_tangent=True)
    own = os.getpriority(os.PRIO_PROCESS, threading.get_native_id())
    try:
        worker = twin._pool.submit(lambda: os.getpriority(os.PRIO_PROCESS, threading.get_native_id())).result(60)
    finally:
        twin.close()
    assert worker == min(19, own + twin_module.BACKGROUND_NICE)
    assert os.getpriority(os.PRIO_PROCESS, threading.get_native_id()) == own
