"""The twin node over real DDS, each test on its own ROS domain (see dea_array_twin.ros.testing)."""

import math
import subprocess
import sys
import time

import numpy as np
import pytest
from conftest import COARSE
from rcl_interfaces.msg import Parameter as ParameterMsg
from rcl_interfaces.msg import ParameterType, ParameterValue
from rcl_interfaces.srv import GetParameters, ListParameters, SetParameters

from dea_array_twin import ArrayConfig, ArrayTwin
from dea_array_twin.ros.params import config_parameters
from dea_array_twin.ros.testing import TwinHarness, diagnostic_values

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
        ref = ArrayTwin().solve([0, 0.012, 0], [0, 2730.0, 0], tuple(FREE_CENTRE))
        # each topic waited for on its own: outputs of one update may arrive in any order
        cap = h.wait_for("capacitance", lambda m: m.data[1] == pytest.approx(ref.capacitance[1], rel=1e-6),
                         timeout=20)
        force = h.wait_for("force", lambda m: m.data[1] == pytest.approx(ref.force[1], rel=1e-5))
        states = h.wait_for("unit_states", lambda m: m.position[1] == pytest.approx(0.012))
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
        msg = h.wait_for("/diagnostics", lambda m: diagnostic_values(m)[f"rejected_{kind}"] == "1", timeout=10)
        assert msg.status[0].level == b"\x00"
        assert list(h.messages("force")[-1].data) == list(good.data)
        # still alive and obeying valid commands
        h.send_displacement([0.0, 0.006, 0.0])
        h.wait_for("force", lambda m: m.data[1] > good.data[1] + 1e-3, timeout=20)
        assert all(np.all(np.isfinite(m.data)) for m in h.messages("force"))


def test_a_publish_cut_off_by_the_context_shutdown_is_the_stop_not_a_solver_error():
    """Ctrl-C and SIGTERM shut the context down while the solver thread may be publishing: that publish
    ends quietly instead of stopping the thread with a warning at every Ctrl-C."""
    with TwinHarness(parameters={"update_rate": 20.0, "marker_rate": 0.0}) as h:
        h.wait_for("force", timeout=20)
        node = h.twin_node
        node.updater.stop()
        n = len(h.messages("force"))
        node._publish_outputs(node.result)  # context up: published
        h.wait_for("force", after=n, timeout=10)
        h.context.try_shutdown()
        node._publish_outputs(node.result)  # context down: rcl refuses the publish, which is the stop


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


def test_reset_pre_empts_a_slow_solve():
    """6 kV at 15 mm is accepted (breakdown_field raised) and Newton fails slowly (about a second on
    the default mesh); nothing newer waits, so the solve runs on until reset abandons it: it never
    gets to fail, and reset answers with the flat membrane."""
    with TwinHarness(parameters=dict(update_rate=20.0, breakdown_field=300e6, marker_rate=0.0)) as h:
        h.send_displacement([0.0, 0.015, 0.0])
        h.wait_for("unit_states", lambda m: m.position[1] == 0.015, timeout=30)
        h.send_voltage([0.0, 6000.0, 0.0])
        time.sleep(0.2)
        response = h.reset()
        assert response.success, response.message
        _, values = _diag(h, key_values_after=len(h.messages("/diagnostics")))
        assert values["failed_solves"] == "0"  # pre-empted, not failed
        flat = ArrayTwin().model.flat_capacitance
        cap = h.wait_for("capacitance", after=len(h.messages("capacitance")), timeout=5)
        assert list(cap.data) == pytest.approx(flat.tolist(), rel=1e-9)


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


@pytest.mark.parametrize("content, reason", [
    (None, "Error opening YAML file"),
    ("/**:\n  ros__parameters:\n    update_rate: [1, \n", "Error parsing"),
    ("update_rate: 20\n", "Cannot have a value before ros__parameters"),
], ids=["missing", "not YAML", "no ros__parameters"])
def test_a_broken_params_file_exits_2_with_one_line_naming_it(tmp_path, content, reason):
    params = tmp_path / "twin.yaml"
    if content is not None:
        params.write_text(content)
    proc = subprocess.run([sys.executable, "-m", "dea_array_twin.ros.node", "--ros-args", "--params-file",
                           str(params)], capture_output=True, text=True, timeout=60)
    assert proc.returncode == 2
    assert f"dea_array_twin: error: invalid ROS arguments: Couldn't parse params file: '--params-file {params}'" \
        in proc.stderr and reason in proc.stderr
    assert "Traceback" not in proc.stderr


def test_a_pinned_domain_is_used_and_an_invalid_one_refused():
    from domain_coordinator import domain_id

    with pytest.raises(ValueError, match="domain_id must be an integer in \\[0, 232\\]"):
        TwinHarness(domain_id=233)
    with domain_id() as free:  # a free id, as a user would pick one no other test uses
        with TwinHarness(parameters={"update_rate": 20.0, "marker_rate": 0.0}, domain_id=free) as h:
            assert h.domain_id == free == h.context.get_domain_id()
            h.send_displacement([0.0, 0.002, 0.0])
            h.wait_for("unit_states", lambda m: m.position[1] == 0.002, timeout=30)


def test_invalid_parameter_stops_the_start_naming_it(tmp_path):
    proc = subprocess.run([sys.executable, "-m", "dea_array_twin.ros.node", "--ros-args",
                           "-p", "indenter_radius:=0.02"],
                          capture_output=True, text=True, timeout=60)
    assert proc.returncode == 2
    assert "indenter_radius" in proc.stderr


def _call(h, srv_type, service, request, timeout=10.0):
    """Call a twin service from the harness's node and wait for the answer."""
    client = h.node.create_client(srv_type, service)
    assert client.wait_for_service(timeout_sec=timeout), service
    future = client.call_async(request)
    deadline = time.monotonic() + timeout
    while not future.done() and time.monotonic() < deadline:
        time.sleep(0.01)
    assert future.done(), f"{service} did not answer"
    return future.result()


def _set(h, name, ptype, **value):
    request = SetParameters.Request(parameters=[ParameterMsg(name=name, value=ParameterValue(type=ptype, **value))])
    return _call(h, SetParameters, "dea_array_twin/set_parameters", request).results[0]


def _get(h, names):
    return _call(h, GetParameters, "dea_array_twin/get_parameters", GetParameters.Request(names=names)).values


def test_every_parameter_answers_get_parameters_as_ros2_param_dump_asks():
    """``ros2 param dump`` lists the names, then gets all of them in one request: rclpy answers an empty
    list if a single one is unset (the empty slip table was).  Integer overrides of float parameters are
    stored as doubles, so the dump shows the types the node reads."""
    with TwinHarness(parameters={"update_rate": 20, "prestretch": 1.2, "marker_rate": 0.0}) as h:
        names = _call(h, ListParameters, "dea_array_twin/list_parameters", ListParameters.Request()).result.names
        values = dict(zip(names, _get(h, names)))
    assert len(values) == len(names) > len(ArrayConfig().to_dict())
    flattened = set(config_parameters(ArrayConfig()))  # per-unit fields one entry per unit, bias as bias.*
    assert flattened | {"update_rate", "solve_budget", "unit_modes", "record"} <= set(names)
    assert values["contact"].type == ParameterType.PARAMETER_BOOL_ARRAY
    assert values["bias.stiffness"].type == ParameterType.PARAMETER_DOUBLE_ARRAY
    for table in ("slip_displacement", "slip_factor"):
        assert values[table].type == ParameterType.PARAMETER_DOUBLE_ARRAY
        assert list(values[table].double_array_value) == []
    assert values["update_rate"].type == ParameterType.PARAMETER_DOUBLE and values["update_rate"].double_value == 20.0
    assert values["prestretch"].type == ParameterType.PARAMETER_DOUBLE and values["prestretch"].double_value == 1.2
    assert values["solve_budget"].double_value == pytest.approx(5 / 20)  # default: 5 update periods
    assert values["rows"].type == ParameterType.PARAMETER_INTEGER
    assert list(values["unit_modes"].string_array_value) == ["driven"] * 3


def test_runtime_parameters_are_checked_like_a_config_file_and_keep_their_type():
    with TwinHarness(parameters={"update_rate": 20.0, "marker_rate": 0.0}) as h:
        refused = {
            "unit_modes": _set(h, "unit_modes", ParameterType.PARAMETER_STRING_ARRAY,
                               string_array_value=["free", "loose", "x"]),
            "unit_modes as text": _set(h, "unit_modes", ParameterType.PARAMETER_STRING, string_value="free"),
            "max_displacement": _set(h, "max_displacement", ParameterType.PARAMETER_BOOL, bool_value=True),
            "breakdown_field": _set(h, "breakdown_field", ParameterType.PARAMETER_DOUBLE, double_value=-1.0),
            "spacing": _set(h, "spacing", ParameterType.PARAMETER_DOUBLE, double_value=0.01),
        }
        for name, result in refused.items():
            assert not result.successful and name.split()[0] in result.reason, (name, result.reason)
        assert "must be a finite number > 0" in refused["breakdown_field"].reason
        assert "read-only" in refused["spacing"].reason
        # ros2 param set max_displacement 1 (an integer) and breakdown_field 1e8 (YAML 1.1 reads it as text)
        assert _set(h, "max_displacement", ParameterType.PARAMETER_INTEGER, integer_value=1).successful
        assert _set(h, "breakdown_field", ParameterType.PARAMETER_STRING, string_value="1e8").successful
        limits = _get(h, ["max_displacement", "breakdown_field"])
        assert [(v.type, v.double_value) for v in limits] == [(ParameterType.PARAMETER_DOUBLE, 1.0),
                                                             (ParameterType.PARAMETER_DOUBLE, 1e8)]
        assert h.twin_node.config.max_displacement == 1.0 and h.twin_node.config.breakdown_field == 1e8
        assert _set(h, "unit_modes", ParameterType.PARAMETER_STRING_ARRAY, string_array_value=FREE_CENTRE).successful
        h.send_displacement([0.002, 0.01, 0.0])  # unit 1 is free now: its 2 mm are ignored, with a warning
        msg = h.wait_for("force", lambda m: m.data[1] > 0.1, timeout=30)
        assert msg.data[0] == 0.0 and msg.data[2] == 0.0  # free units carry no force
        _, values = _diag(h, key_values_after=len(h.messages("/diagnostics")))
        assert values["displacement_on_free_unit"] == "1"


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
        h.wait_for("unit_states", lambda m: m.position[1] == last, timeout=30,
                   after=len(h.messages("unit_states")))
        # ~1000 commands were sent: worked off one by one at 50 Hz they would take 20 s;
        # sampled, the last one is answered within a few update periods (5 s: a loaded machine)
        assert time.monotonic() - t0 < 5.0
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
        for d in (0.001, 0.002, 0.003):
            h.send_displacement([0.0, d, 0.0])
            h.wait_for("unit_states", lambda m, d=d: m.position[1] == d, timeout=10)
        time.sleep(0.5)
        # the start-up output (flat state) may or may not have reached the harness: count from the first command's
        states = h.messages("unit_states")
        first = next(i for i, m in enumerate(states) if m.position[1] == 0.001)
        assert [m.position[1] for m in states[first:]] == [0.001, 0.002, 0.003]  # one output per command


def test_namespaced_twin_publishes_the_deformed_membrane_marker():
    with TwinHarness(parameters={"update_rate": 20.0, "marker_rate": 10.0}, namespace="/left_array") as h:
        assert h.topic("force") == "/left_array/force"
        h.send_displacement([0.0, 0.008, 0.0])
        marker = h.wait_for("membrane", lambda m: max(p.z for p in m.points) > 0.0079, timeout=20)
        n_elements = h.twin_node.model.mesh.n_elements
        assert len(marker.points) == 3 * n_elements == len(marker.colors)
        assert max(p.z for p in marker.points) == pytest.approx(0.008)
        assert marker.type == marker.TRIANGLE_LIST and marker.header.frame_id == "dea_array"


def test_diagnostics_warn_of_wrinkling_and_field_and_report_rates():
    """15 mm at the eq. 14 voltage (3306 V at lp 1.10) wrinkles the membrane near the indenter
    and drives the field above 150 V/um: a WARN naming both, with the flags and the field in
    the values, and the update and output rates of a node publishing at 20 Hz."""
    ref = ArrayTwin().solve([0, 0.015, 0], [0, 3306.0, 0], tuple(FREE_CENTRE))
    assert ref.wrinkled and ref.field_exceeded and ref.stable
    with TwinHarness(parameters={"update_rate": 20.0, "unit_modes": FREE_CENTRE, "marker_rate": 0.0}) as h:
        h.send_displacement([0.0, 0.015, 0.0])
        h.send_voltage([0.0, 3306.0, 0.0])
        msg = h.wait_for("/diagnostics", lambda m: m.status[0].level == b"\x01", timeout=30)
        status, values = msg.status[0], diagnostic_values(msg)
        assert "wrinkle" in status.message and "breakdown" in status.message, status.message
        assert values["wrinkled"] == "True" and values["field_exceeded"] == "True" and values["failed_solves"] == "0"
        assert float(values["peak_field_V_per_m"]) == pytest.approx(ref.peak_field.max(), rel=1e-5)
        # a second later, with no new command, the outputs go on at the update rate
        msg = h.wait_for("/diagnostics", after=len(h.messages("/diagnostics")), timeout=10)
        values = diagnostic_values(msg)
        assert 0.25 * 20.0 <= float(values["outputs_per_s"]) <= 1.5 * 20.0, values
        assert values["update_rate_hz"] == "20.0" and int(values["updates"]) >= 1


def test_best_effort_peers_connect_both_ways():
    """A best-effort command publisher (a typical controller's sensor-data QoS) drives the twin,
    and a best-effort subscriber receives its outputs (the README's QoS claim)."""
    from rclpy.qos import QoSProfile, ReliabilityPolicy
    from std_msgs.msg import Float64MultiArray

    best_effort = QoSProfile(depth=5, reliability=ReliabilityPolicy.BEST_EFFORT)
    with TwinHarness(parameters={"update_rate": 20.0, "marker_rate": 0.0}) as h:
        received = []
        h.node.create_subscription(Float64MultiArray, h.topic("force"), received.append, best_effort)
        pub = h.node.create_publisher(Float64MultiArray, h.topic("command/displacement"), best_effort)
        command = Float64MultiArray(data=[0.0, 0.004, 0.0])
        deadline = time.monotonic() + 30.0
        while time.monotonic() < deadline:  # best effort may drop a message: resend until it is seen
            pub.publish(command)
            try:
                h.wait_for("unit_states", lambda m: m.position[1] == 0.004, timeout=0.5)
                break
            except TimeoutError:
                continue
        state = h.wait_for("unit_states", lambda m: m.position[1] == 0.004, timeout=1.0)
        deadline = time.monotonic() + 10.0
        while not any(m.data[1] > 0.0 for m in received) and time.monotonic() < deadline:
            time.sleep(0.05)
    assert any(list(m.data) == pytest.approx(list(state.effort), rel=1e-12) for m in received)


def test_the_executor_waits_only_on_the_event_handlers_the_twin_uses():
    """rclpy's default QoS event handlers (two per publisher and subscription, walked in Python at
    every wake-up of the executor) are left out: the outputs have none; the command subscriptions
    keep their publisher-matched handler (it publishes diagnostics) when the executor takes the
    commands (update_rate 0), and have none when the solver thread does (a handler of an unread
    subscription would wake the executor's wait at once, again and again)."""
    handlers = {}
    for rate in (20.0, 0.0):
        with TwinHarness(parameters={"update_rate": rate, "marker_rate": 0.0, **COARSE}) as h:
            node = h.twin_node
            outputs = {p.topic_name: len(p.event_handlers) for p in node.publishers
                       if p.topic_name != "/parameter_events"}
            handlers[rate] = {s.topic_name: len(s.event_handlers) for s in node.subscriptions}
        assert outputs == {"/force": 0, "/capacitance": 0, "/unit_states": 0, "/membrane": 0, "/diagnostics": 0}
    assert handlers[20.0] == {"/command/displacement": 0, "/command/voltage": 0, "/command/force": 0}
    assert handlers[0.0] == {"/command/displacement": 1, "/command/voltage": 1, "/command/force": 1}


def test_at_an_update_rate_the_solver_thread_takes_the_commands_and_says_when_a_publisher_comes():
    """At a quasi-static update rate no executor runs a command callback (500-1000 of them a second
    cost the solver thread its ticks): the solver thread takes the latest command at each tick and
    checks it; a command publisher that comes or goes is still reported in /diagnostics at once."""
    import threading

    from std_msgs.msg import Float64MultiArray

    with TwinHarness(parameters={"update_rate": 50.0, "marker_rate": 0.0, **COARSE}) as h:
        node = h.twin_node
        assert node.commands_taken_by_solver
        assert not any(h.executor.can_execute(sub) for sub in node.subscriptions if "command" in sub.topic_name)
        threads = []
        on_command = node._on_command
        node._on_command = lambda kind, msg: (threads.append(threading.current_thread().name),
                                              on_command(kind, msg))
        h.send_displacement([0.0, 0.003, 0.0])
        h.wait_for("unit_states", lambda m: m.position[1] == 0.003, timeout=20)
        h.send_displacement([0.0, 1.0, 0.0])  # beyond the limits: rejected, counted
        msg = h.wait_for("/diagnostics", lambda m: diagnostic_values(m)["rejected_displacement"] == "1",
                         timeout=20)
        assert set(threads) == {"twin-solver"}
        assert diagnostic_values(msg)["command_publishers_voltage"] == "1"

        reports = []
        node._publish_diagnostics = lambda: reports.append(node._command_subs["voltage"].get_publisher_count())
        pub = h.node.create_publisher(Float64MultiArray, h.topic("command/voltage"), 1)
        deadline = time.monotonic() + 20
        while 2 not in reports and time.monotonic() < deadline:
            time.sleep(0.01)
        h.node.destroy_publisher(pub)
        while 1 not in reports[reports.index(2) if 2 in reports else 0:] and time.monotonic() < deadline:
            time.sleep(0.01)
    assert 2 in reports and 1 in reports[reports.index(2):]
