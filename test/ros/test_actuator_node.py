"""The node in actuator mode: command/force, dynamics on the node's clock, unit_states of biased units."""

import time

import numpy as np
import pytest
import yaml
from rosgraph_msgs.msg import Clock

from dea_array_twin import ArrayConfig, ArrayTwin
from dea_array_twin.ros.testing import TwinHarness

#: The circular unit on a 40 N/m spring with 5 g and light damping (the issue's verification unit).
UNIT = {"layout": "circular", "frame_radius": 0.025, "unit_modes": ["biased"], "mass": 0.005, "damping": 0.05,
        "bias": [{"type": "linear", "stiffness": 40.0, "free_position": 0.020}]}


def _config_file(tmp_path, **changes):
    path = tmp_path / "unit.yaml"
    path.write_text(yaml.safe_dump({**UNIT, **changes}))
    return str(path)


def _wait(predicate, timeout=20.0):
    deadline = time.monotonic() + timeout
    while not predicate():
        if time.monotonic() > deadline:
            raise TimeoutError("condition not met")
        time.sleep(0.005)


def test_dynamics_advance_one_step_of_one_over_update_rate_per_tick_of_the_simulated_clock(tmp_path):
    """With use_sim_time the test owns the clock: each 10 ms it publishes is one Newmark step of
    dt = 1/update_rate, with the force command held; the positions, velocities and membrane forces
    equal the library's ArrayTwin.step sequence (same start: the quasi-static rest state) within the
    Newton tolerance (increment 2e-9 m: the node checks stability, and so refactors, on its own schedule)."""
    force, steps, rate = [0.02], 12, 100.0
    params = {"config_file": _config_file(tmp_path), "update_rate": rate, "use_sim_time": True,
              "marker_rate": 0.0, "solve_budget": 0.0}
    with TwinHarness(parameters=params) as h:
        clock = h.node.create_publisher(Clock, "/clock", 10)
        # The quasi-static rest state, solved and published at start: before the harness's subscription
        # matched, maybe (outputs are volatile), so read from the node.
        _wait(lambda: h.twin_node.result is not None, timeout=30)
        first = h.twin_node.result
        h.send_force(force)
        _wait(lambda: h.twin_node.updater.held("force").tolist() == force)
        for i in range(1, steps + 1):
            n = len(h.messages("unit_states"))
            clock.publish(Clock(clock=rclpy_time(i / rate)))
            h.wait_for("unit_states", after=n, timeout=20)
        states = h.messages("unit_states")[-steps:]
    twin = ArrayTwin(ArrayConfig.from_dict(UNIT))
    rest = twin.solve()
    assert first.position[0] == pytest.approx(rest.position[0], rel=1e-12)
    expected = [twin.step(1.0 / rate, force=force) for _ in range(steps)]
    np.testing.assert_allclose([s.position[0] for s in states], [r.position[0] for r in expected], rtol=0, atol=1e-8)
    np.testing.assert_allclose([s.velocity[0] for s in states], [r.velocity[0] for r in expected], rtol=0,
                               atol=1e-8 * rate * 4)  # Newmark: dv = 2 dw / dt
    np.testing.assert_allclose([s.effort[0] for s in states], [r.force[0] for r in expected], rtol=0, atol=1e-6)
    assert max(abs(s.velocity[0]) for s in states) > 1e-3  # it moves: dynamics, not a quasi-static jump


def rclpy_time(seconds: float):
    from builtin_interfaces.msg import Time

    return Time(sec=int(seconds), nanosec=int(round((seconds - int(seconds)) * 1e9)))


def test_a_force_command_moves_a_massless_biased_unit_to_its_equilibrium_and_counts_snaps(tmp_path):
    """Quasi-static (mass 0): command/force gives the library's equilibrium; unit_states carries w and
    the membrane force; a bistable dome's snap is counted in /diagnostics."""
    w = np.linspace(0.0, 0.016, 33)
    dome = {"type": "table", "position": w.tolist(), "force": (0.2035 + 0.08 * np.tanh((w - 0.007) / 0.001)).tolist()}
    params = {"config_file": _config_file(tmp_path, mass=0.0, bias=[dome]), "update_rate": 50.0, "marker_rate": 0.0}
    twin = ArrayTwin(ArrayConfig.from_dict({**UNIT, "mass": 0.0, "bias": [dome]}))
    rest = twin.solve()
    pushed = twin.solve(force=[0.05])
    assert pushed.snaps  # a 50 mN push takes the dome over its limit point
    with TwinHarness(parameters=params) as h:
        h.wait_for("unit_states", lambda m: m.position[0] == pytest.approx(rest.position[0], rel=1e-9), timeout=30)
        h.send_force([0.05])
        msg = h.wait_for("unit_states", lambda m: m.position[0] > 0.008, timeout=30)
        n = len(h.messages("/diagnostics"))
        diag = h.wait_for("/diagnostics", lambda m: any(kv.key == "snaps" and kv.value == "1"
                                                        for kv in m.status[0].values), after=n, timeout=10)
    assert msg.position[0] == pytest.approx(pushed.position[0], rel=1e-6)
    assert msg.effort[0] == pytest.approx(pushed.force[0], rel=1e-6)
    assert diag.status[0].level == b"\x00"
