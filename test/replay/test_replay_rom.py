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
