"""The twin node with ``model: rom``: the reduced twin in the solver thread, checked by the FE."""

import dataclasses
import subprocess
import sys

import numpy as np
import pytest

from dea_array_twin import ArrayTwin
from dea_array_twin.romfile import save_rom
from dea_array_twin.ros.testing import TwinHarness, diagnostic_values


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
        # the stability check, judged in the reduced twin's worker thread (check_in_background)
        _diag(h, lambda kv: kv.get("stable") == "True" and float(kv.get("stability_checked_s_ago", "inf")) < 5.0)
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
    # the node's process holds its OpenBLAS (the wheels' two) to one thread; the coarse ROM is too small
    # for BLAS products (BLAS_COLUMNS), so its worker sums the Hessian point by point all the same
    assert values["blas_single_threaded"] == "True" and values["rom_hessian"] == "per point"
    assert values["rom_threads"] == "1" and values["rom_helper_chunks"] == "0"  # a small ROM: one thread
    deep_fe = ArrayTwin(cfg).solve([0.002, 0.012, 0.003], v)
    assert list(deep.effort) == pytest.approx(deep_fe.force.tolist(), rel=1e-5, abs=1e-8)
    assert after["rom_fallback"].startswith("envelope:")


def test_a_node_with_a_rom_validated_beyond_its_tolerance_warns_at_start_and_in_diagnostics(coarse_rom, tmp_path):
    _, rom, _, yaml_path = coarse_rom
    table = dict(rom.validation, force_error_max=0.0056, over_tolerance=4, over_tolerance_unflagged=3)
    path = save_rom(dataclasses.replace(rom, validation=table), tmp_path / "loose")
    params = {"config_file": str(yaml_path), "model": "rom", "rom_file": str(path), "update_rate": 50.0,
              "fe_check_rate": 0.0, "marker_rate": 0.0}
    with TwinHarness(parameters=params, process=True) as h:
        _, values = _diag(h, lambda kv: "rom_validation" in kv)
        output = h.output()
    assert "force up to 0.560%" in values["rom_validation"] and "3 of them missed" in values["rom_validation"]
    assert f"rom_file {path}: its validation found errors above its tolerance" in output


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


def test_rom_second_step_reaches_the_reduced_twin(coarse_rom):
    """``rom_second_step`` sets the reduced twin's ``second_step`` (0, the default: the ROM's tolerance, at most
    1e-3) and the diagnostics show it."""
    cfg, rom, path, yaml_path = coarse_rom
    params = {"config_file": str(yaml_path), "model": "rom", "rom_file": str(path), "fe_check_rate": 0.0,
              "marker_rate": 0.0}
    with TwinHarness(parameters=params) as h:
        assert h.twin_node.rom_twin.second_step == min(1e-3, rom.tolerance)
    with TwinHarness(parameters=dict(params, rom_second_step=0.002)) as h:
        assert h.twin_node.rom_twin.second_step == 0.002
        diag = h.wait_for("/diagnostics", lambda m: "rom_second_step" in diagnostic_values(m), timeout=30)
        assert float(diagnostic_values(diag)["rom_second_step"]) == 0.002


def test_a_rom_node_answers_biased_units_from_the_rom_quasi_statically_and_in_time_steps(coarse_rom, tmp_path):
    """unit_modes [driven, biased, driven] on a ROM trained all driven: the node's updates are the ROM's (no
    fallback), the biased height equals the FE twin's within the force tolerance over the bias stiffness, and
    the FE check (re-solving with the force command) agrees; with a moving mass the node steps the ROM."""
    import yaml

    from dea_array_twin.configfile import load_config

    cfg, rom, path, yaml_path = coarse_rom
    lbs = {"type": "linear", "stiffness": 40.0, "free_position": 0.010}
    quasi = tmp_path / "biased.yaml"
    modes = ["driven", "biased", "driven"]
    quasi.write_text(yaml.safe_dump({**yaml.safe_load(yaml_path.read_text()), "unit_modes": modes, "bias": [lbs]}))
    params = {"config_file": str(quasi), "model": "rom", "rom_file": str(path), "update_rate": 50.0,
              "fe_check_rate": 5.0, "marker_rate": 0.0}
    d, v, f = [0.002, 0.0, 0.003], [0.0, 1200.0, 600.0], [0.0, 0.02, 0.0]
    with TwinHarness(parameters=params) as h:
        h.send_voltage(v)
        h.send_force(f)
        h.send_displacement(d)
        h.wait_for("unit_states", lambda m: m.position[0] == pytest.approx(0.002)
                   and list(h.twin_node.result.external_force) == f, timeout=60)
        status, values = _diag(h, lambda kv: int(kv.get("fe_checks", 0)) >= 1)
        res = h.twin_node.result
    ref = ArrayTwin(load_config(quasi)).solve(d, v, force=f)
    assert res.fallback == "" and values["rom_fallbacks_envelope"] == "0" and int(values["rom_updates"]) >= 1
    assert abs(res.position[1] - ref.position[1]) <= rom.tolerance * rom.force_reference[1] / 40.0
    assert float(values["rom_fe_force_difference"]) <= rom.tolerance and status.level in (0, b"\x00")
    dynamic = tmp_path / "dynamic.yaml"
    dynamic.write_text(yaml.safe_dump({**yaml.safe_load(quasi.read_text()), "mass": [0.005]}))
    params.update(config_file=str(dynamic), update_rate=100.0)
    with TwinHarness(parameters=params) as h:
        assert h.twin_node.dynamics_dt == pytest.approx(0.01)
        h.send_force(f)
        h.wait_for("unit_states", lambda m: abs(m.velocity[1]) > 1e-6, timeout=60)
        res = h.twin_node.result
        assert res.fallback == "" and h.twin_node.rom_twin.updates >= 2
