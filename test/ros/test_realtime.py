"""``realtime_priority``: every thread of the node's process under SCHED_FIFO, or a warning and normal scheduling."""

import os

import pytest
from conftest import COARSE

from dea_array_twin.ros import realtime
from dea_array_twin.ros.testing import TwinHarness, diagnostic_values


def _policies(pid: int) -> set[tuple[int, int]]:
    """(policy, priority) of every thread of process ``pid``."""
    out = set()
    for tid in os.listdir(f"/proc/{pid}/task"):
        try:
            out.add((os.sched_getscheduler(int(tid)), os.sched_getparam(int(tid)).sched_priority))
        except ProcessLookupError:
            continue
    return out


def _may_use_fifo() -> bool:
    """Whether this process may use SCHED_FIFO (tried on a child, so this process is left alone)."""
    pid = os.fork()
    if pid == 0:
        try:
            os.sched_setscheduler(0, os.SCHED_FIFO, os.sched_param(1))
            os._exit(0)
        except OSError:
            os._exit(1)
    return os.waitpid(pid, 0)[1] == 0


def test_with_a_realtime_priority_every_thread_of_the_node_process_runs_under_sched_fifo():
    """The node's own process (a real one: the test process must keep its normal scheduling): every
    thread, those started before the priority was set (DDS, executor) and after it (the solver,
    the recorder), runs SCHED_FIFO at the priority, and the diagnostics say so.  Where the system
    refuses it (no CAP_SYS_NICE, no rtprio limit), the node says why and runs normally."""
    params = {"update_rate": 100.0, "marker_rate": 0.0, "realtime_priority": 7, **COARSE}
    with TwinHarness(parameters=params, process=True) as h:
        h.send_displacement([0.0, 0.002, 0.0])
        h.wait_for("unit_states", lambda m: m.position[1] == 0.002, timeout=60)
        values = diagnostic_values(h.wait_for("/diagnostics", timeout=10))
        policies = _policies(h.process.pid)
    if _may_use_fifo():
        assert values["scheduling"] == "SCHED_FIFO 7"
        assert policies == {(os.SCHED_FIFO, 7)}
    else:
        assert values["scheduling"].startswith("normal: realtime_priority 7: SCHED_FIFO refused")
        assert policies == {(os.SCHED_OTHER, 0)}


def test_by_default_and_when_refused_the_node_runs_under_normal_scheduling(monkeypatch):
    """realtime_priority 0 (the default) changes nothing; a refusal is a warning in the log and in the
    diagnostics, not a failure (here the refusal is made: no thread of the test process is changed)."""
    with TwinHarness(parameters={"update_rate": 50.0, "marker_rate": 0.0, **COARSE}) as h:
        assert diagnostic_values(h.wait_for("/diagnostics", timeout=10))["scheduling"] == "normal"

    def refuse(pid, policy, param):
        raise PermissionError(1, "Operation not permitted")

    monkeypatch.setattr(realtime.os, "sched_setscheduler", refuse)
    before = _policies(os.getpid())
    with TwinHarness(parameters={"update_rate": 50.0, "marker_rate": 0.0, "realtime_priority": 20, **COARSE}) as h:
        h.send_displacement([0.0, 0.002, 0.0])
        h.wait_for("unit_states", lambda m: m.position[1] == 0.002, timeout=60)
        scheduling = diagnostic_values(h.wait_for("/diagnostics", timeout=10))["scheduling"]
    assert scheduling.startswith("normal: realtime_priority 20: SCHED_FIFO refused")
    assert "rtprio" in scheduling and "Operation not permitted" in scheduling
    assert _policies(os.getpid()) == before


def test_use_fifo_refuses_a_priority_linux_does_not_have():
    for priority in (0, 100, -3):
        with pytest.raises(ValueError, match="1-99"):
            realtime.use_fifo(priority)
