"""The solver's cancel point: a solve abandoned between Newton iterations leaves the twin untouched.

The ROS node gives each solve a time budget through ``ArrayTwin.solve(cancel=...)``;
these tests count calls instead of timing them, so they are exact.
"""

import numpy as np
import pytest
from conftest import COARSE, FREE_CENTRE

from dea_array_twin import ArrayConfig, ArrayTwin, ConvergenceError, NewtonSettings, SolveCancelled


class CancelAfter:
    """A cancel callback that answers True from its ``n``-th call on, counting every call."""

    def __init__(self, n: int):
        self.n, self.calls = n, 0

    def __call__(self) -> bool:
        self.calls += 1
        return self.calls >= self.n


def test_a_cancelled_solve_leaves_the_twin_where_it_was():
    """Cancelled after the first converged load step on the way to a voltage beyond
    electromechanical stability: positions, command and result are the old ones, and the
    next command gives what a twin that never saw the cancelled one gives."""
    cfg = ArrayConfig(**COARSE)
    twin, reference = ArrayTwin(cfg), ArrayTwin(cfg)
    for t in (twin, reference):
        t.solve([0, 0.005, 0], [0, 0, 0], FREE_CENTRE)
    before, tangent = twin.last, twin.solver.factorisation
    with pytest.raises(SolveCancelled):
        # True once a load step on the way has converged (its tangent replaced the old one)
        twin.solve([0, 0.005, 0], [0, 10000.0, 0], FREE_CENTRE, cancel=lambda: twin.solver.factorisation is not tangent)
    assert twin.last is before
    assert twin.solver.factorisation is tangent  # the one it started from, not the tangent of a step on the way
    moved = twin.solve([0, 0.006, 0], None, FREE_CENTRE)
    expected = reference.solve([0, 0.006, 0], None, FREE_CENTRE)
    np.testing.assert_allclose(moved.force, expected.force, rtol=1e-6, atol=1e-12)  # to solver tolerance
    np.testing.assert_allclose(moved.capacitance, expected.capacitance, rtol=1e-7)
    assert np.array_equal(moved.voltage, [0.0, 0.0, 0.0])  # the cancelled 10 kV never took hold


def test_cancel_is_asked_once_per_newton_iteration_and_stops_a_failing_solve_early():
    """The command that makes Newton fail slowly (beyond electromechanical stability) runs
    many iterations before its ConvergenceError; with a cancel it stops after k - 1."""
    cfg = ArrayConfig(**COARSE)
    command = ([0, 0.005, 0], [0, 10000.0, 0], FREE_CENTRE)
    failing = ArrayTwin(cfg)
    failing.solve([0, 0.005, 0], [0, 0, 0], FREE_CENTRE)
    count = CancelAfter(10**9)  # never cancels: counts the iterations of the full failure
    with pytest.raises(ConvergenceError):
        failing.solve(*command, cancel=count)
    assert count.calls > 50

    twin = ArrayTwin(cfg)
    twin.solve([0, 0.005, 0], [0, 0, 0], FREE_CENTRE)
    cancel = CancelAfter(6)
    with pytest.raises(SolveCancelled, match="after 5 Newton iterations"):
        twin.solve(*command, cancel=cancel)
    assert cancel.calls == 6
    again = twin.solve([0, 0.005, 0], [0, 0, 0], FREE_CENTRE)
    assert again.iterations <= 1  # still at the converged 5 mm, 0 V state


def test_the_solve_after_an_abandoned_one_starts_from_the_tangent_the_twin_had():
    """A node abandons a solve past its budget for a newer command (cancelled here at its second
    Newton iteration): the next update starts from the tangent the twin held before, so a warm
    0.1 mm update costs no factorisation (one that started with a factorisation of its start
    state made the node's next solve overrun again) and reaches the same force as a twin that
    never saw the abandoned command (to the solver's tolerance)."""
    cfg = ArrayConfig(**COARSE)
    twin, reference = (ArrayTwin(cfg, NewtonSettings(check_stability=False)) for _ in range(2))
    for t in (twin, reference):
        for d in (0.004, 0.005, 0.0051):
            t.solve([0, d, 0], 0.0, FREE_CENTRE)
    with pytest.raises(SolveCancelled):
        twin.solve([0, 0.009, 0], 0.0, FREE_CENTRE, cancel=CancelAfter(2))
    moved = twin.solve([0, 0.0052, 0], 0.0, FREE_CENTRE)
    expected = reference.solve([0, 0.0052, 0], 0.0, FREE_CENTRE)
    assert moved.factorisations == expected.factorisations == 0
    np.testing.assert_allclose(moved.force, expected.force, rtol=1e-6, atol=1e-12)
