"""Verification 6: a recorded biased run replays offline with the same positions (to 1e-6).

Quasi-statically each command is one update; with a moving mass the replay steps at the
recorded ticks with each command from the first tick after it (the node takes the
commands the mailbox holds at each tick), which a simulated clock makes exact.
"""

import numpy as np
import yaml
from conftest import COARSE
from mcap_ros2.reader import read_ros2_messages
from rosgraph_msgs.msg import Clock

from dea_array_twin import ArrayConfig, ArrayTwin
from dea_array_twin.cli.main import main
from dea_array_twin.ros.testing import TwinHarness

LBS = {"type": "linear", "stiffness": 40.0, "free_position": 0.020}


def _positions(path):
    return [list(m.ros_msg.position) for m in read_ros2_messages(str(path)) if m.channel.topic.endswith("unit_states")]


def _wait(predicate, timeout=20.0):
    import time

    deadline = time.monotonic() + timeout
    while not predicate():
        assert time.monotonic() < deadline, "condition not met in time"
        time.sleep(0.005)


def _replay(tmp_path, capsys):
    (path,) = sorted(tmp_path.glob("dea_twin_*.mcap"))
    capsys.readouterr()
    assert main(["replay", str(path), "--out", str(tmp_path / "re")]) == 0
    out = capsys.readouterr()
    return path, out


def test_a_quasi_static_biased_run_replays_with_the_recorded_positions(tmp_path, capsys):
    """Unit 2 on a spring, force and voltage commands: every recorded position is one of the replayed
    states to 1e-6 relative, and the positions' FIT is printed."""
    config = tmp_path / "array.yaml"
    config.write_text(yaml.safe_dump({**COARSE, "unit_modes": ["free", "biased", "free"], "bias": [LBS]}))
    params = {"config_file": str(config), "update_rate": 50.0, "record": True, "record_dir": str(tmp_path),
              "marker_rate": 0.0}
    with TwinHarness(parameters=params) as h:
        rest = h.wait_for("unit_states", timeout=30).position[1]
        for kind, values in (("force", [0.0, 0.02, 0.0]), ("voltage", [0.0, 2000.0, 0.0]),
                             ("force", [0.0, -0.01, 0.0]), ("voltage", [2000.0, 0.0, 0.0])):
            n = len(h.messages("unit_states"))
            last = h.messages("unit_states")[-1].position[1]
            h.send(kind, values)
            h.wait_for("unit_states", lambda m, last=last: abs(m.position[1] - last) > 1e-6, after=n, timeout=30)
    path, out = _replay(tmp_path, capsys)
    assert "position [%]" in out.out
    start = ArrayTwin(ArrayConfig.from_dict({**COARSE, "unit_modes": ["free", "biased", "free"], "bias": [LBS]}))
    replayed = np.vstack([start.solve().position, _positions(tmp_path / "re.mcap")])  # the state before any command
    recorded = np.array(_positions(path))
    assert abs(recorded[:, 1] - rest).max() > 1e-4  # it moved
    for row in recorded:
        assert np.abs(replayed - row).max(axis=1).min() <= 1e-6 * np.abs(row).max()


def test_a_dynamic_biased_run_on_a_simulated_clock_replays_step_by_step(tmp_path, capsys):
    """5 g on the spring, 50 Hz ticks of a clock the test owns, force commands between ticks: the
    replay steps at the recorded ticks and gives every recorded position to 1e-6 (the velocity
    is nonzero: a dynamic run)."""
    config = tmp_path / "array.yaml"
    config.write_text(yaml.safe_dump({**COARSE, "unit_modes": ["free", "biased", "free"], "bias": [LBS],
                                      "mass": 0.005, "damping": 0.02}))
    params = {"config_file": str(config), "update_rate": 50.0, "record": True, "record_dir": str(tmp_path),
              "marker_rate": 0.0, "use_sim_time": True, "solve_budget": 0.0}
    forces = {3: 0.02, 9: -0.01, 14: 0.0}
    with TwinHarness(parameters=params) as h:
        clock = h.node.create_publisher(Clock, "/clock", 10)
        _wait(lambda: h.twin_node.result is not None)  # the rest state (published before we matched, maybe)
        moving = 0.0
        for i in range(1, 20):
            if i in forces:
                h.send_force([0.0, forces[i], 0.0])
                _wait(lambda f=forces[i]: h.twin_node.updater.held("force")[1] == f)
            n = len(h.messages("unit_states"))
            stamp = Clock()
            stamp.clock.sec, stamp.clock.nanosec = divmod(i * 20_000_000, 1_000_000_000)
            clock.publish(stamp)
            moving = max(moving, abs(h.wait_for("unit_states", after=n, timeout=20).velocity[1]))
    path, out = _replay(tmp_path, capsys)
    assert "re-simulating the dynamics" in out.err
    assert moving > 1e-3
    replayed = np.array(_positions(tmp_path / "re.mcap"))
    recorded = np.array(_positions(path))
    assert len(recorded) == len(replayed) == 20
    np.testing.assert_allclose(replayed, recorded, rtol=1e-6, atol=1e-12)
