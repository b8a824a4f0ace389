"""``dea-twin replay --rom``: a recorded run re-simulated with the reduced model, compared with the FE."""

import numpy as np
from rclpy.serialization import serialize_message
from std_msgs.msg import Float64MultiArray

from dea_array_twin.bag.twin_config import metadata_from_config
from dea_array_twin.bag.writer import CONFIG_RECORD, Ros2McapWriter
from dea_array_twin.cli.main import main

T0 = 1_700_000_000_000_000_000


def test_replay_with_the_rom_matches_the_fe_replay_within_the_tolerance(coarse_rom, tmp_path, capsys):
    cfg, rom, path, _ = coarse_rom
    bag = tmp_path / "run.mcap"
    with Ros2McapWriter(bag, metadata={CONFIG_RECORD: metadata_from_config(cfg, rom.envelope.modes)},
                        flush_period=None) as rec:
        topics = {k: rec.add_topic(f"/command/{k}", "std_msgs/msg/Float64MultiArray")
                  for k in ("displacement", "voltage")}
        for i in range(12):  # a slow ramp on every unit, voltages on units 2 and 3 (unit 1 untrained)
            t = T0 + i * 10_000_000
            rec.write(topics["displacement"], serialize_message(Float64MultiArray(
                data=[0.0005 * i, 0.0006 * i, 0.0004 * i])), t)
            rec.write(topics["voltage"], serialize_message(Float64MultiArray(data=[0.0, 150.0 * i, 90.0 * i])), t + 1)
    assert main(["replay", str(bag), "--rom", str(path), "--compare", "--out", str(tmp_path / "rom")]) == 0
    out = capsys.readouterr().out
    assert "FE fallbacks none" in out and "reduced model against the FE on the same 24 command(s)" in out
    table = out[out.index("force diff"):].splitlines()[1:4]
    diffs = np.array([[float(v) for v in line.split()[1:3]] for line in table])
    assert diffs.shape == (3, 2) and np.all(diffs <= 100 * rom.tolerance) and diffs[:, 0].max() > 0
    assert (tmp_path / "rom.csv").exists()
    assert main(["replay", str(bag), "--compare"]) == 2
    assert "--compare needs --rom" in capsys.readouterr().err


def test_a_dynamic_biased_run_replays_with_the_rom_step_by_step_as_with_the_fe(coarse_rom, tmp_path, capsys):
    """Unit 2 (5 g on an LBS, the ROM's units trained driven) recorded by the FE node on a clock the test owns,
    force commands between ticks: --rom re-simulates the dynamics at the recorded ticks with no fallback, and
    --compare (the FE stepping at the same ticks) differs by less than the ROM's tolerance."""
    import time

    import yaml
    from rosgraph_msgs.msg import Clock

    from dea_array_twin.ros.testing import TwinHarness

    cfg, rom, rom_path, yaml_path = coarse_rom
    config = tmp_path / "array.yaml"
    lbs = {"type": "linear", "stiffness": 40.0, "free_position": 0.010}
    config.write_text(yaml.safe_dump({**yaml.safe_load(yaml_path.read_text()), "bias": [lbs], "mass": 0.005,
                                      "unit_modes": ["driven", "biased", "driven"]}))
    params = {"config_file": str(config), "update_rate": 50.0, "record": True, "record_dir": str(tmp_path),
              "marker_rate": 0.0, "use_sim_time": True, "solve_budget": 0.0}
    with TwinHarness(parameters=params) as h:
        clock = h.node.create_publisher(Clock, "/clock", 10)
        deadline = time.monotonic() + 30
        while h.twin_node.result is None:  # the rest state
            assert time.monotonic() < deadline
            time.sleep(0.005)
        for i in range(1, 13):
            if i in (2, 7):
                h.send_force([0.0, 0.02 if i == 2 else -0.01, 0.0])
                while list(h.twin_node.updater.held("force"))[1] != (0.02 if i == 2 else -0.01):
                    assert time.monotonic() < deadline + 30
                    time.sleep(0.005)
            n = len(h.messages("unit_states"))
            stamp = Clock()
            stamp.clock.sec, stamp.clock.nanosec = divmod(i * 20_000_000, 1_000_000_000)
            clock.publish(stamp)
            h.wait_for("unit_states", after=n, timeout=20)
    (bag,) = sorted(tmp_path.glob("dea_twin_*.mcap"))
    capsys.readouterr()
    assert main(["replay", str(bag), "--rom", str(rom_path), "--compare", "--out", str(tmp_path / "rom")]) == 0
    out = capsys.readouterr()
    assert "re-simulating the dynamics" in out.err and "FE fallbacks none" in out.out
    table = out.out[out.out.index("force diff"):].splitlines()[1:4]
    diffs = np.array([[float(v) for v in line.split()[1:3]] for line in table])
    assert diffs.shape == (3, 2) and np.all(diffs <= 100 * rom.tolerance) and diffs[:, 0].max() > 0
