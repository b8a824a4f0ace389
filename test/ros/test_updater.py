"""The solver thread's rules, without DDS: a stand-in twin whose solves take as long as a test says.

A command value says how long its solve takes (seconds, in ``displacement[0]``); the
stand-in asks ``cancel()`` every millisecond, as the Newton loop does every iteration.
"""

import threading
import time
from concurrent.futures import Future
from types import SimpleNamespace

import pytest

from dea_array_twin.model.config import ArrayConfig
from dea_array_twin.model.solver import SolveCancelled
from dea_array_twin.ros.updater import TwinUpdater


class SlowTwin:
    """Solves ``displacement=[seconds, ...]`` in that many seconds unless cancelled; records what it did."""

    def __init__(self):
        self.config = ArrayConfig()
        self.log: list[tuple[str, float]] = []  # (what, seconds asked for)
        self.resets = 0
        self.started = threading.Event()

    def reset(self):
        self.resets += 1

    def solve(self, modes, check_stability, cancel, displacement, voltage):
        seconds = float(displacement[0])
        self.started.set()
        end = time.monotonic() + seconds
        while time.monotonic() < end:
            if cancel():
                self.log.append(("cancelled", seconds))
                raise SolveCancelled("cancelled")
            time.sleep(0.001)
        self.log.append(("solved", seconds))
        return seconds  # the "result": what the publish callback sees


def wait_until(condition, timeout=10.0):
    deadline = time.monotonic() + timeout
    while not condition():
        assert time.monotonic() < deadline, "condition not met in time"
        time.sleep(0.005)


@pytest.fixture
def make_updater():
    made = []

    def make(budget=0.05, period=0.0):
        twin, published = SlowTwin(), []
        updater = TwinUpdater(twin, {"displacement": [0.0, 0.0, 0.0], "voltage": [0.0, 0.0, 0.0]},
                              ("driven",) * 3, published.append, lambda key, text: None, budget,
                              stability_period=1.0, period=period)
        updater.start()
        made.append(updater)
        wait_until(lambda: published)  # the start-up solve of the zero command
        return updater, twin, published

    yield make
    for updater in made:
        updater.stop()


def test_a_long_solve_with_nothing_newer_runs_to_its_end(make_updater):
    updater, twin, published = make_updater(budget=0.05)
    updater.post("displacement", [0.3, 0, 0])
    wait_until(lambda: published[-1] == 0.3)
    assert ("solved", 0.3) in twin.log and updater.stats().budget_overruns == 0


def test_past_its_budget_a_solve_is_abandoned_for_a_newer_command_which_is_solved_next(make_updater):
    updater, twin, published = make_updater(budget=0.05)
    twin.started.clear()
    updater.post("displacement", [5.0, 0, 0])  # would take 5 s
    twin.started.wait(5)
    tic = time.monotonic()
    updater.post("displacement", [0.01, 0, 0])
    wait_until(lambda: published[-1] == 0.01)
    assert time.monotonic() - tic < 1.0
    assert ("cancelled", 5.0) in twin.log and updater.stats().budget_overruns == 1
    assert updater.stats().last_error == ""  # the newer command solved


def test_consecutive_abandonments_double_the_budget_so_a_stream_of_long_solves_is_answered(make_updater):
    """Every solve needs 0.15 s, a newer command comes every 10 ms, the budget is 0.05 s: the
    third attempt has 0.2 s and finishes."""
    updater, twin, published = make_updater(budget=0.05)
    stop = threading.Event()

    def stream():
        while not stop.is_set():
            updater.post("displacement", [0.15, 0, 0])
            time.sleep(0.01)

    thread = threading.Thread(target=stream)
    thread.start()
    try:
        wait_until(lambda: ("solved", 0.15) in twin.log, timeout=5.0)
    finally:
        stop.set()
        thread.join()
    first = twin.log.index(("solved", 0.15))
    assert twin.log[first - 2:first] == [("cancelled", 0.15)] * 2  # after 0.05 s and 0.1 s (or later ones)
    assert updater.stats().budget_overruns >= 2


def test_reset_pre_empts_a_running_solve_and_answers_at_once(make_updater):
    updater, twin, published = make_updater(budget=0.0)  # no budget: only reset can stop it
    twin.started.clear()
    updater.post("displacement", [30.0, 0, 0])
    twin.started.wait(5)
    answers = []
    tic = time.monotonic()
    updater.reset(lambda ok, text: answers.append((ok, text, time.monotonic() - tic)))
    wait_until(lambda: answers)
    ok, text, seconds = answers[0]
    assert ok and "reset" in text and seconds < 1.0
    assert twin.resets == 1 and ("cancelled", 30.0) in twin.log
    assert published[-1] == 0.0  # the zero command, solved after the reset
    assert updater.stats().budget_overruns == 0  # a pre-emption is no overrun


def test_with_a_period_the_thread_updates_once_per_tick_and_counts_the_ticks_a_solve_outlasted(make_updater):
    """Idle, it publishes the held state once per period and skips no tick; a 1 s solve at a
    0.05 s period outlasts 20 ticks, of which the first is the next update and 19 are skipped."""
    period = 0.05
    updater, twin, published = make_updater(budget=0.0, period=period)
    wait_until(lambda: len(published) >= 11)  # ten periods idle after the start-up solve
    assert updater.stats().skipped_ticks == 0
    twin.started.clear()
    updater.post("displacement", [1.0, 0, 0])
    twin.started.wait(5)
    during = len(published)
    wait_until(lambda: published[-1] == 1.0)
    assert set(published[during:]) == {1.0}  # nothing published while the solve ran
    assert updater.stats().skipped_ticks in (19, 20)  # 1 s / 0.05 s, less the next update (+1 if late)


def test_commands_taken_by_the_thread_itself_are_used_at_the_next_tick_and_end_a_solve_past_its_budget():
    """With ``take_commands`` (the node at an update rate: the solver thread reads the command
    subscriptions itself) nothing is posted from outside: the thread takes the latest command at
    each tick, and a solve past its budget looks for a newer one, finds it and is abandoned for it."""
    inbox, lock, takers = [], threading.Lock(), set()
    twin, published = SlowTwin(), []

    def take():  # a subscription of depth 1: the latest command, once
        takers.add(threading.current_thread().name)
        with lock:
            latest = inbox[-1] if inbox else None
            inbox.clear()
        if latest is not None:
            updater.post("displacement", latest)

    with pytest.raises(ValueError, match="period"):
        TwinUpdater(twin, {"displacement": [0.0] * 3}, ("driven",) * 3, published.append, lambda k, t: None,
                    0.05, stability_period=1.0, period=0.0, take_commands=take)
    updater = TwinUpdater(twin, {"displacement": [0.0] * 3, "voltage": [0.0] * 3}, ("driven",) * 3,
                          published.append, lambda key, text: None, 0.05, stability_period=1.0, period=0.01,
                          take_commands=take)
    updater.start()
    try:
        wait_until(lambda: published)
        twin.started.clear()
        with lock:
            inbox.append([5.0, 0, 0])  # would take 5 s
        twin.started.wait(5)
        tic = time.monotonic()
        with lock:
            inbox.append([0.02, 0, 0])
        wait_until(lambda: published[-1] == 0.02)
        assert time.monotonic() - tic < 1.0
        assert ("cancelled", 5.0) in twin.log and updater.stats().budget_overruns == 1
        assert takers == {"twin-solver"}
    finally:
        updater.stop()


class CheckingTwin:
    """Records whether each solve checked stability; hands out the background checks' verdicts as futures the
    test settles (``background``), or has none (returns None, as a twin holding a biased unit)."""

    def __init__(self, background: bool):
        self.config = ArrayConfig()
        self.background = background
        self.checked: list[bool] = []
        self.verdicts: list[Future] = []

    def reset(self):
        pass

    def solve(self, modes, check_stability, cancel, displacement, voltage):
        self.checked.append(check_stability)
        return SimpleNamespace(stable=True if check_stability else None)

    def check_in_background(self):
        if not self.background:
            return None
        self.verdicts.append(Future())
        return self.verdicts[-1]


def _checking_updater(twin):
    published = []
    updater = TwinUpdater(twin, {"displacement": [0.0] * 3, "voltage": [0.0] * 3}, ("driven",) * 3,
                          published.append, lambda key, text: None, 0.05, stability_period=0.0, background_checks=True)
    updater.start()
    wait_until(lambda: published)
    return updater, published


def test_background_checks_leave_the_updates_unchecked_and_report_the_newest_verdict():
    """Every update due for a check (stability_period 0): none is checked in the update, each asks the twin
    for a background check; the stats report the verdict of the newest state judged, not of an older one
    settled later, and none from before a reset."""
    twin = CheckingTwin(background=True)
    updater, published = _checking_updater(twin)
    try:
        for k in range(1, 4):
            updater.post("displacement", [k * 1e-3, 0, 0])
            wait_until(lambda: len(twin.verdicts) == k + 1)
        assert twin.checked == [False] * 4 and updater.stats().stable is None
        twin.verdicts[2].set_result(False)
        assert updater.stats().stable is False and 0 <= updater.stats().stability_age < 10
        twin.verdicts[1].set_result(True)  # an older state's verdict, settled later
        assert updater.stats().stable is False
        twin.verdicts[3].set_result(True)
        assert updater.stats().stable is True
        answers = []
        updater.reset(lambda ok, text: answers.append(ok))
        wait_until(lambda: answers)
        twin.verdicts[0].set_result(False)  # from before the reset
        assert updater.stats().stable is None
    finally:
        updater.stop()


def test_an_update_the_twin_cannot_check_in_the_background_has_the_next_one_checked_in_it():
    twin = CheckingTwin(background=False)
    updater, published = _checking_updater(twin)
    try:
        for k in range(1, 4):
            updater.post("displacement", [k * 1e-3, 0, 0])
            wait_until(lambda: len(twin.checked) == k + 1)
        assert twin.checked == [False, True, False, True]
        assert updater.stats().stable is True
    finally:
        updater.stop()
