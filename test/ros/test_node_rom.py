"""The twin node with ``model: rom``: the reduced twin in the solver thread, checked by the FE."""

import subprocess
import sys

import numpy as np
import pytest

from dea_array_twin import ArrayTwin
from dea_array_twin.ros.testing import TwinHarness


def _diag(h, predicate, timeout=30.0):
    msg = h.wait_for("/diagnostics", lambda m: predicate({kv.key: kv.value for kv in m.status[0].values}),
                     timeout=timeout)
    return msg.status[0], {kv.key: kv.value for kv in msg.status[0].values}


def test_node_with_a_rom_answers_within_its_tolerance_and_publishes_the_fe_check(coarse_rom):
    cfg, rom, path, yaml_path = coarse_rom
    params = {"config_file": str(yaml_path), "model": "rom", "rom_file": str(path), "update_rate": 50.0,
              "fe_check_rate": 5.0, "marker_rate": 0.0}
    d, v = [0.002, 0.005, 0.003], [0.0, 1200.0, 600.0]
    with TwinHarness(parameters=params, process=True) as h:
        h.send_voltage(v)
        h.send_displacement(d)
        h.wait_for("unit_states", lambda m: m.position[1] == pytest.approx(0.005), timeout=60)
        status, values = _diag(h, lambda kv: int(kv.get("fe_checks", 0)) >= 1 and kv.get("model") == "rom")
        force = h.messages("force")[-1]
        cap = h.messages("capacitance")[-1]
        # outside the envelope (deeper than trained): the FE answers and the node counts it
        h.send_displacement([0.002, 0.012, 0.003])
        deep = h.wait_for("unit_states", lambda m: m.position[1] == pytest.approx(0.012), timeout=60)
        _, after = _diag(h, lambda kv: int(kv.get("rom_fallbacks_envelope", 0)) >= 1)
    fe = ArrayTwin(cfg).solve(d, v)
    assert np.max(np.abs(np.array(force.data) - fe.force) / rom.force_reference) <= rom.tolerance
    assert np.max(np.abs(np.array(cap.data) - fe.capacitance) / fe.capacitance) <= rom.tolerance
    assert status.level == b"\x00" or status.level == 0  # OK
    assert float(values["rom_fe_force_difference"]) <= rom.tolerance
    assert float(values["rom_fe_capacitance_difference"]) <= rom.tolerance
    assert values["rom_fallbacks_envelope"] == "0" and int(values["rom_updates"]) >= 1
    deep_fe = ArrayTwin(cfg).solve([0.002, 0.012, 0.003], v)
    assert list(deep.effort) == pytest.approx(deep_fe.force.tolist(), rel=1e-5, abs=1e-8)
    assert after["rom_fallback"].startswith("envelope:")


def test_node_refuses_a_rom_trained_for_another_config(coarse_rom):
    _, _, path, _ = coarse_rom
    proc = subprocess.run([sys.executable, "-m", "dea_array_twin.ros.node", "--ros-args", "-p", "model:=rom",
                           "-p", f"rom_file:={path}"], capture_output=True, text=True, timeout=120)
    assert proc.returncode == 2
    assert "trained for another configuration" in proc.stderr and "mesh_size" in proc.stderr
    assert "Traceback" not in proc.stderr
    proc = subprocess.run([sys.executable, "-m", "dea_array_twin.ros.node", "--ros-args", "-p", "model:=rom"],
                          capture_output=True, text=True, timeout=120)
    assert proc.returncode == 2 and "rom_file" in proc.stderr


def test_an_in_process_rom_node_lowers_the_switch_interval_only_while_it_lives(coarse_rom):
    """The ROM node lowers the interpreter's switch interval for its solver thread; the process it
    is embedded in gets its own back when the node is destroyed."""
    cfg, rom, path, yaml_path = coarse_rom
    before = sys.getswitchinterval()
    params = {"config_file": str(yaml_path), "model": "rom", "rom_file": str(path), "update_rate": 200.0,
              "fe_check_rate": 0.0, "marker_rate": 0.0}
    with TwinHarness(parameters=params):
        assert sys.getswitchinterval() == pytest.approx(0.1 / 200.0)
    assert sys.getswitchinterval() == before
