"""The twin node over real DDS, each test on its own ROS domain (see dea_array_twin.ros.testing)."""

import math
import subprocess
import sys
import time

import numpy as np
import pytest
from rcl_interfaces.msg import Parameter as ParameterMsg
from rcl_interfaces.msg import ParameterType, ParameterValue
from rcl_interfaces.srv import SetParameters

from dea_array_twin import ArrayConfig, ArrayTwin
from dea_array_twin.ros.testing import TwinHarness

FREE_CENTRE = ["free", "driven", "free"]


def _diag(h, key_values_after=0, timeout=5.0):
    msg = h.wait_for("/diagnostics", timeout=timeout, after=key_values_after)
    status = msg.status[0]
    return status, {kv.key: kv.value for kv in status.values}


def test_commands_from_another_process_give_the_cores_direct_solve():
    """The twin runs as a subprocess (as under ros2 run); this process commands it."""
    with TwinHarness(parameters={"update_rate": 50.0, "unit_modes": FREE_CENTRE}, process=True) as h:
        h.send_voltage([0.0, 2730.0, 0.0])
        h.send_displacement([0.0, 0.012, 0.0])
        cap = h.wait_for("capacitance", lambda m: m.data[1] > 3.2e-10, timeout=20)
        force = h.messages("force")[-1]
        states = h.wait_for("unit_states", lambda m: m.position[1] == pytest.approx(0.012))
    ref = ArrayTwin().solve([0, 0.012, 0], [0, 2730.0, 0], tuple(FREE_CENTRE))
    assert list(force.data) == pytest.approx(ref.force.tolist(), rel=1e-5, abs=1e-9)
    assert list(cap.data) == pytest.approx(ref.capacitance.tolist(), rel=1e-6)
    assert force.layout.dim[0].label == "unit" and force.layout.dim[0].size == 3
    assert states.name == ["unit_1", "unit_2", "unit_3"]
    assert list(states.effort) == pytest.approx(ref.force.tolist(), rel=1e-5, abs=1e-9)
    assert list(states.position) == pytest.approx(ref.centre_deflection.tolist(), rel=1e-5)


@pytest.mark.parametrize("kind, values, reason", [
    ("displacement", [0.0, 0.01], "expected 3"),
    ("displacement", [0.0, math.nan, 0.0], "NaN"),
    ("displacement", [0.0, math.inf, 0.0], "NaN or inf"),
    ("displacement", [0.0, 0.05, 0.0], "max_displacement"),
    ("voltage", [0.0, -100.0, 0.0], "negative"),
    ("voltage", [0.0, 9000.0, 0.0], "breakdown_field"),
])
def test_bad_commands_are_rejected_counted_and_change_nothing(kind, values, reason):
    from dea_array_twin.model.twin import command_error

    assert reason in command_error(kind, values, ArrayConfig())
    with TwinHarness(parameters={"update_rate": 50.0}) as h:
        h.send_displacement([0.0, 0.005, 0.0])
        good = h.wait_for("force", lambda m: m.data[1] > 0.05, timeout=20)
        getattr(h, f"send_{kind}")(values)
        time.sleep(0.3)
        n = len(h.messages("/diagnostics"))
        status, values_seen = _diag(h, key_values_after=n, timeout=3)
        assert values_seen[f"rejected_{kind}"] == "1"
        assert status.level == b"\x00"
        assert list(h.messages("force")[-1].data) == list(good.data)
        # still alive and obeying valid commands
        h.send_displacement([0.0, 0.006, 0.0])
        h.wait_for("force", lambda m: m.data[1] > good.data[1] + 1e-3, timeout=20)
        assert all(np.all(np.isfinite(m.data)) for m in h.messages("force"))


def test_reset_returns_to_the_flat_membrane():
    with TwinHarness(parameters={"update_rate": 50.0}) as h:
        h.send_displacement([0.004, 0.008, 0.0])
        h.wait_for("force", lambda m: m.data[1] > 0.1, timeout=20)
        response = h.reset()
        assert response.success, response.message
        flat = ArrayTwin().model.flat_capacitance
        n = len(h.messages("capacitance"))
        cap = h.wait_for("capacitance", after=n)
        assert list(cap.data) == pytest.approx(flat.tolist(), rel=1e-9)
        assert list(h.messages("force")[-1].data) == [0.0, 0.0, 0.0]


def test_a_failed_solve_keeps_the_last_state_reports_error_and_recovers():
    """A voltage below the breakdown limit but beyond electromechanical stability."""
    with TwinHarness(parameters={"update_rate": 20.0, "breakdown_field": 300e6}) as h:
        h.send_displacement([0.0, 0.005, 0.0])
        good = h.wait_for("force", lambda m: m.data[1] > 0.05, timeout=20)
        h.send_voltage([0.0, 10000.0, 0.0])
        status = h.wait_for("/diagnostics", lambda m: m.status[0].level == b"\x02", timeout=60).status[0]
        assert "failed" in status.message
        assert list(h.messages("force")[-1].data) == list(good.data)
        h.send_voltage([0.0, 0.0, 0.0])
        h.wait_for("/diagnostics", lambda m: m.status[0].level == b"\x00", timeout=30)


def test_params_file_is_honoured(tmp_path):
    params = tmp_path / "twin.yaml"
    params.write_text("/**:\n  ros__parameters:\n    update_rate: 25\n    prestretch: 1.2\n"
                      "    unit_modes: [free, driven, free]\n")
    with TwinHarness(process=True, parameters={}, params_file=str(params)) as h:
        cap = h.wait_for("capacitance", timeout=20)
    flat = ArrayTwin(ArrayConfig(prestretch=1.2)).model.flat_capacitance
    assert list(cap.data) == pytest.approx(flat.tolist(), rel=1e-9)


def test_invalid_parameter_stops_the_start_naming_it(tmp_path):
    proc = subprocess.run([sys.executable, "-m", "dea_array_twin.ros.node", "--ros-args",
                           "-p", "indenter_radius:=0.02"],
                          capture_output=True, text=True, timeout=60)
    assert proc.returncode == 2
    assert "indenter_radius" in proc.stderr


def test_runtime_parameters_validate_and_explain():
    with TwinHarness(parameters={"update_rate": 20.0}) as h:
        client = h.node.create_client(SetParameters, "dea_array_twin/set_parameters")
        assert client.wait_for_service(timeout_sec=10)

        def set_param(name, ptype, **value):
            req = SetParameters.Request(parameters=[ParameterMsg(name=name, value=ParameterValue(type=ptype, **value))])
            future = client.call_async(req)
            deadline = time.monotonic() + 10
            while not future.done() and time.monotonic() < deadline:
                time.sleep(0.01)
            return future.result().results[0]

        bad = set_param("unit_modes", ParameterType.PARAMETER_STRING_ARRAY, string_array_value=["free", "loose", "x"])
        assert not bad.successful and "unit_modes" in bad.reason
        assert not set_param("spacing", ParameterType.PARAMETER_DOUBLE, double_value=0.01).successful
        ok = set_param("unit_modes", ParameterType.PARAMETER_STRING_ARRAY, string_array_value=FREE_CENTRE)
        assert ok.successful
        h.send_displacement([0.0, 0.01, 0.0])
        msg = h.wait_for("force", lambda m: m.data[1] > 0.1, timeout=20)
        assert msg.data[0] == 0.0 and msg.data[2] == 0.0  # free units carry no force


def test_command_flood_leaves_no_backlog():
    """Commands at 10x the update rate: the twin samples the latest, never queues, and the
    last command's output arrives within a few update periods of the flood's end."""
    with TwinHarness(parameters={"update_rate": 50.0, "unit_modes": FREE_CENTRE}) as h:
        h.send_displacement([0.0, 0.002, 0.0])
        h.wait_for("force", lambda m: m.data[1] > 0.01, timeout=20)
        end = time.monotonic() + 2.0
        d = 0.002
        while time.monotonic() < end:
            d = 0.002 + 0.004 * (1 + math.sin(5 * time.monotonic())) / 2
            h.send_displacement([0.0, d, 0.0])
            time.sleep(0.002)
        last = d
        h.send_displacement([0.0, last, 0.0])
        t0 = time.monotonic()
        h.wait_for("unit_states", lambda m: m.position[1] == last, timeout=5,
                   after=len(h.messages("unit_states")))
        assert time.monotonic() - t0 < 0.5
        n = len(h.messages("/diagnostics"))
        _, values = _diag(h, key_values_after=n)
        assert int(values["updates"]) < 50 * 4  # sampled at the update rate, not per command


def test_shipped_params_file_starts_the_twin():
    from pathlib import Path

    params = Path(__file__).resolve().parents[2] / "config" / "twin.yaml"
    with TwinHarness(process=True, params_file=str(params)) as h:
        h.send_displacement([0.0, 0.003, 0.0])
        assert h.wait_for("force", lambda m: m.data[1] > 0.01, timeout=20).data[1] > 0


def test_update_rate_zero_updates_once_per_command():
    with TwinHarness(parameters={"update_rate": 0.0, "marker_rate": 0.0}) as h:
        n = len(h.messages("force"))
        for d in (0.001, 0.002, 0.003):
            h.send_displacement([0.0, d, 0.0])
            h.wait_for("unit_states", lambda m, d=d: m.position[1] == d, timeout=10)
        time.sleep(0.5)
        assert len(h.messages("force")) - n == 3  # one output per command, none in between


def test_namespaced_twin_publishes_the_deformed_membrane_marker():
    with TwinHarness(parameters={"update_rate": 20.0, "marker_rate": 10.0}, namespace="/left_array") as h:
        assert h.topic("force") == "/left_array/force"
        h.send_displacement([0.0, 0.008, 0.0])
        marker = h.wait_for("membrane", lambda m: max(p.z for p in m.points) > 0.0079, timeout=20)
        n_elements = h.twin_node.twin.model.mesh.n_elements
        assert len(marker.points) == 3 * n_elements == len(marker.colors)
        assert max(p.z for p in marker.points) == pytest.approx(0.008)
        assert marker.type == marker.TRIANGLE_LIST and marker.header.frame_id == "dea_array"
