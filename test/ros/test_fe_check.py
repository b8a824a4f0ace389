"""The FE check behind a reduced twin (ros/fe_check.py): prompt after an idle wait, at most ``rate`` checks a
second, and no wake-up of its thread per posted result (the node posts one per update, up to 1 kHz)."""

import threading
import time

import numpy as np

from dea_array_twin.model.reduced_twin import ReducedTwin
from dea_array_twin.ros.fe_check import FeCheck


class _CountingCondition(threading.Condition):
    """A condition that counts the returns from ``wait`` (the check thread's wake-ups)."""

    def __init__(self):
        super().__init__()
        self.wakeups = 0

    def wait(self, timeout=None):
        woken = super().wait(timeout)
        self.wakeups += 1
        return woken


def _wait_until(predicate, timeout=30.0):
    deadline = time.monotonic() + timeout
    while not predicate():
        assert time.monotonic() < deadline, "condition not reached in time"
        time.sleep(0.01)


def test_fe_check_agrees_with_the_rom_checks_at_its_rate_and_sleeps_through_a_stream_of_results(coarse_rom):
    cfg, rom, _, _ = coarse_rom
    twin = ReducedTwin(cfg, rom)
    res = twin.solve([0.002, 0.005, 0.003], [0.0, 1200.0, 600.0])
    resyncs, logs = [], []
    check = FeCheck(cfg, rom.force_reference, rom.tolerance, 4.0, resyncs.append, lambda *a: logs.append(a))
    check._cond = cond = _CountingCondition()
    check.start()
    try:
        check.post(res)  # the thread waited for a result: it checks at once
        _wait_until(lambda: check.stats().checks == 1)
        stats = check.stats()
        assert stats.last_force_difference <= rom.tolerance and stats.last_capacitance_difference <= rom.tolerance
        assert stats.last_force_difference > 0.0  # a real FE solve, not the ROM compared with itself
        # results at 1 kHz until four more checks: about rate checks a second, and wake-ups for the checks only,
        # not one per result
        wakeups, before, start, posts = cond.wakeups, check.stats().checks, time.monotonic(), 0
        while check.stats().checks < before + 4:
            assert time.monotonic() - start < 30.0, "the checks stopped"
            check.post(res)
            posts += 1
            time.sleep(0.001)
        elapsed, checks = time.monotonic() - start, check.stats().checks - before
        assert checks <= 4.0 * elapsed + 1 and posts >= 200
        assert cond.wakeups - wakeups <= 5 * checks
        # idle again (the last result of the stream checked by now): a new result is checked at once, not at the
        # next post
        _wait_until(lambda: check._idle)
        checks = check.stats().checks
        check.post(res)
        _wait_until(lambda: check.stats().checks == checks + 1, timeout=10.0)
    finally:
        check.stop()
    assert not resyncs and not logs and np.isfinite(check.stats().max_force_difference)
