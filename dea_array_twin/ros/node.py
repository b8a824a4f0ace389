"""The twin as a ROS 2 node: per-unit commands in, force and capacitance out.

Interface (relative names, so ``-r __ns:=/left_array`` runs several arrays; SI units):

* ``command/displacement``, ``command/voltage`` (std_msgs/Float64MultiArray, one value
  per unit, m and V), subscribed best-effort with depth 1: reliable and best-effort
  publishers both connect, and only the latest command is kept (sample and hold).
* ``force``, ``capacitance`` (std_msgs/Float64MultiArray, dim "unit"), ``unit_states``
  (sensor_msgs/JointState: position = centre deflection, effort = force), published
  reliable/volatile after each update; ``membrane`` (visualization_msgs/Marker
  TRIANGLE_LIST) at ``marker_rate``; ``/diagnostics`` at 1 Hz.
* service ``reset`` (std_srvs/Trigger): all units to 0 m, 0 V, flat membrane.

The node only translates messages: validation rules live in :func:`~dea_array_twin.model.twin.command_error`,
physics in :class:`~dea_array_twin.model.twin.ArrayTwin`.
"""

from __future__ import annotations

import math
import time
from typing import Sequence

import numpy as np
from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus, KeyValue
from geometry_msgs.msg import Point
from rcl_interfaces.msg import ParameterDescriptor, SetParametersResult
from rclpy.node import Node
from rclpy.qos import QoSProfile, ReliabilityPolicy
from sensor_msgs.msg import JointState
from std_msgs.msg import ColorRGBA, Float64MultiArray, MultiArrayDimension
from std_srvs.srv import Trigger
from visualization_msgs.msg import Marker

from ..configfile import load_config
from ..model.config import ArrayConfig, ConfigError
from ..model.membrane import DRIVEN, check_modes
from ..model.solver import ConvergenceError
from ..model.twin import ArrayTwin, TwinResult, command_error
from .params import RUNTIME_FIELDS, config_descriptor, declare_number, declared_default
from .spin import spin_node

COMMAND_QOS = QoSProfile(depth=1, reliability=ReliabilityPolicy.BEST_EFFORT)
OUTPUT_QOS = QoSProfile(depth=10, reliability=ReliabilityPolicy.RELIABLE)


def unit_array(values: Sequence[float]) -> Float64MultiArray:
    """A Float64MultiArray with one value per unit (layout dim labelled "unit")."""
    msg = Float64MultiArray()
    msg.layout.dim = [MultiArrayDimension(label="unit", size=len(values), stride=len(values))]
    msg.data = [float(v) for v in values]
    return msg


class TwinNode(Node):
    """ROS 2 node wrapping an :class:`ArrayTwin`."""

    def __init__(self, **kwargs):
        super().__init__("dea_array_twin", **kwargs)
        cfg = self._declare_config()
        self.twin = ArrayTwin(cfg)
        n = cfg.n_units
        self.update_rate = declare_number(self, "update_rate", 100.0, "updates per second [Hz]; 0 = one per command")
        self.marker_rate = declare_number(self, "marker_rate", 5.0, "membrane marker rate [Hz]; 0 = off")
        self.frame_id = self.declare_parameter(
            "frame_id", "dea_array", ParameterDescriptor(description="frame of unit_states and membrane",
                                                         read_only=True)).value
        self.stability_period = declare_number(self,
            "stability_check_period", 1.0,
            "seconds between stability checks of the equilibrium (a tangent factorisation, ~7 ms on the "
            "default mesh); 0 = every update")
        modes = self.declare_parameter(
            "unit_modes", [DRIVEN] * n,
            ParameterDescriptor(description="per unit 'driven' (indenter follows command/displacement) or "
                                            "'free' (no indenter)")).value
        self._check_modes(modes)
        self.modes = tuple(modes)
        self.add_on_set_parameters_callback(self._on_set_parameters)

        self.displacement = np.zeros(n)
        self.voltage = np.zeros(n)
        self._dirty = True
        self.counters = {"rejected_displacement": 0, "rejected_voltage": 0, "failed_solves": 0,
                         "updates": 0, "skipped_ticks": 0}
        self._last_warn: dict[str, float] = {}
        self.last_error = ""
        self.result: TwinResult | None = None
        self._last_stability_time = -math.inf
        self._last_tick = None
        self._update_times: list[float] = []

        self.pub_force = self.create_publisher(Float64MultiArray, "force", OUTPUT_QOS)
        self.pub_cap = self.create_publisher(Float64MultiArray, "capacitance", OUTPUT_QOS)
        self.pub_states = self.create_publisher(JointState, "unit_states", OUTPUT_QOS)
        self.pub_marker = self.create_publisher(Marker, "membrane", OUTPUT_QOS)
        self.pub_diag = self.create_publisher(DiagnosticArray, "/diagnostics", OUTPUT_QOS)
        self.create_subscription(Float64MultiArray, "command/displacement",
                                 lambda m: self._on_command("displacement", m), COMMAND_QOS)
        self.create_subscription(Float64MultiArray, "command/voltage",
                                 lambda m: self._on_command("voltage", m), COMMAND_QOS)
        self.create_service(Trigger, "reset", self._on_reset)
        if self.update_rate > 0:
            self.create_timer(1.0 / self.update_rate, self._on_tick)
        if self.marker_rate > 0:
            self.create_timer(1.0 / self.marker_rate, self._publish_marker)
        self.create_timer(1.0, self._publish_diagnostics)
        self.recorder = None
        self.recording_error = ""
        self._start_recording()
        self._update()
        self.get_logger().info(
            f"twin of {cfg.rows if cfg.layout == 'array' else 1}x{cfg.cols if cfg.layout == 'array' else 1} "
            f"{cfg.layout} ready: {self.twin.model.mesh.n_elements} elements, {self.twin.model.disc.n_dofs} dofs, "
            f"update_rate {self.update_rate} Hz")

    # ---------------------------------------------------------------- parameters
    def _declare_config(self) -> ArrayConfig:
        path = self.declare_parameter(
            "config_file", "", ParameterDescriptor(description="twin config YAML; parameters below override it",
                                                   read_only=True)).value
        base = load_config(path or None)
        values = {}
        for name, default in base.to_dict().items():
            value = self.declare_parameter(name, declared_default(default), config_descriptor(name, default)).value
            values[name] = default if value is None else value  # None: an unset (empty) table
        return ArrayConfig.from_dict(values)

    def _check_modes(self, modes: Sequence[str]) -> None:
        try:
            check_modes(modes, self.twin.n_units)
        except ValueError as exc:
            raise ConfigError(f"unit_modes: {exc}") from None

    def _on_set_parameters(self, params) -> SetParametersResult:
        changes = {}
        modes = None
        for p in params:
            if p.name == "unit_modes":
                try:
                    self._check_modes(p.value)
                except ConfigError as exc:
                    return SetParametersResult(successful=False, reason=str(exc))
                modes = tuple(p.value)
            elif p.name in RUNTIME_FIELDS:
                changes[p.name] = p.value
        if changes:
            try:
                cfg = self.twin.config.replace(**changes)
            except (ConfigError, TypeError) as exc:
                return SetParametersResult(successful=False, reason=str(exc))
            self.twin.config = cfg
        if modes is not None:
            self.modes = modes
            self._dirty = True
        return SetParametersResult(successful=True)

    def _start_recording(self) -> None:
        record = self.declare_parameter("record", False, ParameterDescriptor(
            description="record commands, outputs and diagnostics to MCAP", read_only=True)).value
        directory = self.declare_parameter("record_dir", "recordings", ParameterDescriptor(
            description="folder of the MCAP recordings", read_only=True)).value
        split_size = declare_number(self, "record_split_size", 0.0, "start a new file after this many bytes; 0 = never")
        split_duration = declare_number(self, "record_split_duration", 0.0,
                                      "start a new file after this many seconds; 0 = never")
        if not record:
            return
        from ..bag.twin_config import metadata_from_config
        from ..bag.writer import RecordingError
        from .recorder import TopicRecorder

        metadata = metadata_from_config(self.twin.config, self.modes, self.update_rate)
        try:
            self.recorder = TopicRecorder(self, directory, metadata, self._on_recording_error,
                                          split_size=split_size, split_duration=split_duration)
            self.get_logger().info(f"recording to {self.recorder.writer.path}")
        except RecordingError as exc:
            self._on_recording_error(f"recording not started: {exc}")

    def _on_recording_error(self, text: str) -> None:
        self.recording_error = text
        self.recorder = None
        self.get_logger().error(f"{text}; the twin keeps running without recording")

    def destroy_node(self) -> None:
        """Finish the recording (if any), then destroy the node."""
        if self.recorder is not None:
            self.recorder.close()
            self.recorder = None
        super().destroy_node()

    # ---------------------------------------------------------------- callbacks
    def _warn(self, key: str, text: str, period: float = 1.0) -> None:
        now = time.monotonic()
        if now - self._last_warn.get(key, -math.inf) >= period:
            self._last_warn[key] = now
            self.get_logger().warning(text)

    def _on_command(self, kind: str, msg: Float64MultiArray) -> None:
        error = command_error(kind, msg.data, self.twin.config)
        if error:
            self.counters[f"rejected_{kind}"] += 1
            self._warn(kind, f"rejected {kind} command: {error}")
            return
        setattr(self, kind, np.array(msg.data, dtype=float))
        self._dirty = True
        if self.update_rate == 0:
            self._update()

    def _on_reset(self, request, response):
        self.twin.reset()
        self.displacement[:] = 0.0
        self.voltage[:] = 0.0
        self._dirty = True
        self._update()
        response.success = self.last_error == ""
        response.message = "twin reset to 0 m, 0 V" if response.success else self.last_error
        return response

    def _on_tick(self) -> None:
        now = time.monotonic()
        if self._last_tick is not None:
            missed = int((now - self._last_tick) * self.update_rate + 0.5) - 1
            if missed > 0:
                self.counters["skipped_ticks"] += missed
        self._last_tick = now
        self._update()

    # ---------------------------------------------------------------- the update
    def _update(self) -> None:
        if self._dirty:
            now = time.monotonic()
            check = now - self._last_stability_time >= self.stability_period
            try:
                self.result = self.twin.solve(self.displacement, self.voltage, self.modes, check_stability=check)
                self.last_error = ""
                if check:
                    self._last_stability_time = now
            except (ConvergenceError, ValueError) as exc:
                self.counters["failed_solves"] += 1
                self.last_error = str(exc)
                self._warn("solve", f"solve failed, keeping the last state: {exc}")
            self._dirty = False
            self._update_times.append(now)
            self.counters["updates"] += 1
        self._publish_outputs()

    def _publish_outputs(self) -> None:
        res = self.result
        if res is None:
            return
        stamp = self.get_clock().now().to_msg()
        self.pub_force.publish(unit_array(res.force))
        self.pub_cap.publish(unit_array(res.capacitance))
        states = JointState()
        states.header.stamp = stamp
        states.header.frame_id = self.frame_id
        states.name = [f"unit_{k + 1}" for k in range(self.twin.n_units)]
        states.position = [float(v) for v in res.centre_deflection]
        states.effort = [float(v) for v in res.force]
        self.pub_states.publish(states)

    def _publish_marker(self) -> None:
        res = self.result
        if res is None:
            return
        model = self.twin.model
        pts = res.positions[model.mesh.elements[:, :3]].reshape(-1, 3)
        level = np.clip(model.corner_area_stretch(res.positions) / self.twin.config.prestretch ** 2 - 1.0, 0.0, 1.0)
        # 0 at the pre-stretch, 1 at twice its area
        marker = Marker()
        marker.header.stamp = self.get_clock().now().to_msg()
        marker.header.frame_id = self.frame_id
        marker.ns, marker.id, marker.type, marker.action = "membrane", 0, Marker.TRIANGLE_LIST, Marker.ADD
        marker.pose.orientation.w = 1.0
        marker.scale.x = marker.scale.y = marker.scale.z = 1.0
        marker.points = [Point(x=float(p[0]), y=float(p[1]), z=float(p[2])) for p in pts]
        marker.colors = [ColorRGBA(r=float(v), g=0.3, b=float(1.0 - v), a=1.0) for v in np.repeat(level, 3)]
        self.pub_marker.publish(marker)

    def _publish_diagnostics(self) -> None:
        res = self.result
        status = DiagnosticStatus(name=f"{self.get_fully_qualified_name()}: solver", hardware_id="dea_array_twin")
        if self.last_error:
            status.level, status.message = DiagnosticStatus.ERROR, f"last solve failed: {self.last_error}"
        elif self.recording_error:
            status.level, status.message = DiagnosticStatus.WARN, self.recording_error
        elif res is not None and not res.ok:
            status.level, status.message = DiagnosticStatus.WARN, "; ".join(res.warnings)
        else:
            status.level, status.message = DiagnosticStatus.OK, "ok"
        now = time.monotonic()
        recent = [t for t in self._update_times if now - t <= 1.0]
        self._update_times = recent
        values = dict(self.counters)
        values["achieved_update_rate_hz"] = len(recent)
        values["recording"] = str(self.recorder.writer.path) if self.recorder else (self.recording_error or "off")
        if res is not None:
            values.update(iterations=res.iterations, residual_N=res.residual, solve_time_ms=1e3 * res.solve_time,
                          stable=res.stable, wrinkled=res.wrinkled, field_exceeded=res.field_exceeded,
                          min_principal_stress_Pa=res.min_principal_stress,
                          peak_field_V_per_m=float(res.peak_field.max()))
        status.values = [KeyValue(key=k, value=str(v)) for k, v in values.items()]
        msg = DiagnosticArray(status=[status])
        msg.header.stamp = self.get_clock().now().to_msg()
        self.pub_diag.publish(msg)


def main(args: Sequence[str] | None = None) -> None:
    """Entry point of ``twin_node`` (``ros2 run dea_array_twin twin_node``)."""
    spin_node(TwinNode, "dea_array_twin", args)


if __name__ == "__main__":
    main()
