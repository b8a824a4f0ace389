"""The twin as a ROS 2 node: per-unit commands in, force and capacitance out.

Interface (relative names, so ``-r __ns:=/left_array`` runs several arrays; SI units):

* ``command/displacement``, ``command/voltage``, ``command/force``
  (std_msgs/Float64MultiArray, one value per unit, m, V and N: the displacement of
  driven units, the external force on biased indenters), subscribed best-effort with
  depth 1: reliable and best-effort publishers both connect, and only the latest
  command is kept (sample and hold).
* ``force``, ``capacitance`` (std_msgs/Float64MultiArray, dim "unit"), ``unit_states``
  (sensor_msgs/JointState: position = the unit's position, ``w`` of a biased indenter,
  the command of a driven one, the centre deflection of a free unit; velocity = ``w'``;
  effort = the membrane force), published reliable/volatile after each update; ``membrane`` (visualization_msgs/Marker
  TRIANGLE_LIST) at ``marker_rate``; ``/diagnostics`` at 1 Hz and when a command
  publisher connects or leaves.
* service ``reset`` (std_srvs/Trigger): all units to 0 m, 0 V, flat membrane.

A solver thread (:class:`~.updater.TwinUpdater`) owns the
:class:`~dea_array_twin.model.twin.ArrayTwin`, solves on the latest command, gives
each solve a time budget (``solve_budget``) and publishes when a solve finishes; the
executor never waits for it.  So commands, ``reset``, parameters, diagnostics and the
recorder never wait for a solve.  The update clock is the solver thread's own (every
``1/update_rate`` s of the steady clock, not a ROS timer), and at each tick the thread
takes the latest command of each kind from its subscription itself (:class:`TakenBySolver`:
no executor callback per command), checks it
(:func:`~dea_array_twin.model.twin.command_error`) and solves.  With ``update_rate: 0``
(an update per command) or dynamics, executor callbacks check each command as it comes
and hand it to the thread.  The FE twin refreshes stale tangents in a worker thread
(``ArrayTwin(background_tangent=True)``): at 500 Hz neither a callback per tick or per
command in the executor nor a factorisation in an update (5-10 ms) fits the 2 ms period.

With ``model: rom`` the solver thread runs a
:class:`~dea_array_twin.model.reduced_twin.ReducedTwin` from ``rom_file`` (a ROM
trained for another config stops the start, naming the fields that differ), and
:class:`~.fe_check.FeCheck` re-solves the latest command with the FE in a background
thread ``fe_check_rate`` times a second: the ROM-vs-FE difference goes to
``/diagnostics``, and a difference above the ROM's tolerance restarts the reduced
state from the FE state.  Biased units are answered by the ROM when it was trained with
them driven (their heights solved on it), in quasi-static solves and in time steps.

With biased units that have a moving mass (config ``mass`` > 0) and ``update_rate`` > 0
the node advances their dynamics: every tick of its update timer, on the node's clock
(``use_sim_time`` honoured), is one time step of ``dt = 1 / update_rate``
(:meth:`~dea_array_twin.model.twin.ArrayTwin.step`, or the reduced twin's); otherwise every update is a
quasi-static solve.
"""

from __future__ import annotations

import array
import functools
import math
import sys
import time
from typing import Sequence

import numpy as np
from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus, KeyValue
from geometry_msgs.msg import Point
from rcl_interfaces.msg import IntegerRange, ParameterDescriptor, ParameterType, SetParametersResult
from rclpy.callback_groups import CallbackGroup, MutuallyExclusiveCallbackGroup
from rclpy.event_handler import PublisherEventCallbacks, SubscriptionEventCallbacks
from rclpy.node import Node
from rclpy.qos import QoSProfile, ReliabilityPolicy
from rclpy.subscription import Subscription
from rclpy.task import Future
from rclpy.time import Time
from sensor_msgs.msg import JointState
from std_msgs.msg import ColorRGBA, Float64MultiArray, MultiArrayDimension
from std_srvs.srv import Trigger
from visualization_msgs.msg import Marker

from ..blasthreads import single_threaded_blas
from ..configfile import load_config
from ..model.config import ArrayConfig, ConfigError
from ..model.membrane import BIASED, FREE, MODES, check_modes
from ..model.reduced_twin import FALLBACKS, ReducedTwin
from ..model.twin import ArrayTwin, TwinResult, command_error
from ..romfile import load_rom
from .fe_check import FeCheck
from .params import (
    RUNTIME_FIELDS,
    coerce_doubles,
    config_descriptor,
    config_from_parameters,
    config_parameters,
    declare_number,
    declare_typed,
)
from .realtime import MAX_PRIORITY, use_fifo
from .spin import spin_node
from .updater import TwinUpdater

COMMAND_QOS = QoSProfile(depth=1, reliability=ReliabilityPolicy.BEST_EFFORT)
OUTPUT_QOS = QoSProfile(depth=10, reliability=ReliabilityPolicy.RELIABLE)
COMMAND_KINDS = ("displacement", "voltage", "force")
#: Longest wait [s] at start for the recorder to connect to the outputs (:meth:`TwinNode._wait_for_recorder`).
RECORDER_MATCH_TIMEOUT = 10.0
#: No QoS event handlers but the ones the node uses.  rclpy's default ones (a warning on an
#: incompatible QoS or type, which the other side's publisher or subscription also logs)
#: are two waitables per publisher and subscription that the executor walks through in
#: Python at every wake-up: with those 14 and a 500 Hz update timer its thread took 0.3-0.4
#: of a core at 500 commands a second, without them 0.15-0.2 (benchmarks/bench_core.py --node).
NO_DEFAULT_EVENTS = PublisherEventCallbacks(use_default_callbacks=False)
#: How often [Hz] the executor looks for command publishers that came or left, when the
#: solver thread takes the commands (no matched-event handler then: see :class:`TakenBySolver`).
PUBLISHER_WATCH_RATE = 10.0


class TakenBySolver(CallbackGroup):
    """A callback group whose subscriptions no executor runs: the solver thread takes their messages.

    An executor leaves an entity out of its wait set when its group says it cannot
    execute it (rclpy's ``Executor.can_execute``), so a command arriving costs the
    executor nothing; :meth:`TwinNode._take_commands` takes the latest one at each tick.
    Such a subscription must have no QoS event handler: a waitable of a subscription
    whose message is unread wakes the wait set at once, and the executor spun at a
    whole core (measured with a matched-event handler).
    """

    def can_execute(self, entity) -> bool:
        return not isinstance(entity, Subscription)

    def beginning_execution(self, entity) -> bool:
        return not isinstance(entity, Subscription)

    def ending_execution(self, entity) -> None:
        pass


def unit_array(values: Sequence[float]) -> Float64MultiArray:
    """A Float64MultiArray with one value per unit (layout dim labelled "unit")."""
    msg = Float64MultiArray()
    msg.layout.dim = [MultiArrayDimension(label="unit", size=len(values), stride=len(values))]
    msg.data = [float(v) for v in values]
    return msg


class TwinNode(Node):
    """ROS 2 node wrapping an :class:`ArrayTwin` that a solver thread drives."""

    def __init__(self, **kwargs):
        super().__init__("dea_array_twin", **kwargs)
        cfg = self._declare_config()
        twin = self._make_twin(cfg)
        # Compiled kernels now (Ctrl-C here ends the start): a first update that compiles (~10 s after an
        # install) would outlast the node's stop and leave the solver thread compiling at the exit.
        twin.warm_up()
        #: The mesh and operators (read-only; the marker and the log use them).  The twin's
        #: state belongs to the solver thread.
        self.model = twin.model
        #: The config as the executor sees it: command checks and run-time parameters.
        self.config = cfg
        n = cfg.n_units
        self.update_rate = declare_number(self, "update_rate", 100.0, "updates per second [Hz]; 0 = one per command")
        self.marker_rate = declare_number(self, "marker_rate", 5.0, "membrane marker rate [Hz]; 0 = off")
        self.frame_id = self.declare_parameter(
            "frame_id", "dea_array", ParameterDescriptor(description="frame of unit_states and membrane",
                                                         read_only=True)).value
        stability_period = declare_number(self,
            "stability_check_period", 1.0,
            "seconds between stability checks of the equilibrium (a tangent factorisation, ~7 ms on the "
            "default mesh); 0 = every update")
        self.solve_budget = declare_number(
            self, "solve_budget", 5.0 / self.update_rate if self.update_rate > 0 else 0.5,
            "seconds a solve may take while a newer command waits; past it the solve is abandoned for the newest "
            "command and the last good state kept; doubled after each consecutive abandonment; 0 = no limit "
            "(default: 5 update periods, 0.5 s at update_rate 0)")
        self.modes = cfg.modes
        self.add_pre_set_parameters_callback(lambda params: coerce_doubles(params, RUNTIME_FIELDS))
        self.add_on_set_parameters_callback(self._on_set_parameters)

        self.counters = {"rejected_displacement": 0, "rejected_voltage": 0, "rejected_force": 0,
                         "displacement_on_free_unit": 0}
        self._last_warn: dict[str, float] = {}
        self.recorder = None
        self.recording_error = ""
        self._duplicate = ""

        publisher = functools.partial(self.create_publisher, qos_profile=OUTPUT_QOS, event_callbacks=NO_DEFAULT_EVENTS)
        self.pub_force = publisher(Float64MultiArray, "force")
        self.pub_cap = publisher(Float64MultiArray, "capacitance")
        self.pub_states = publisher(JointState, "unit_states")
        self.pub_marker = publisher(Marker, "membrane")
        self.pub_diag = publisher(DiagnosticArray, "/diagnostics")
        # The outputs published after every update, built once and refilled by the solver thread (the only one
        # that publishes them; publish copies a message out before it returns): at 1 kHz a new message per
        # topic and field-by-field float conversions cost ~10 us of Python per update.
        self._force_msg, self._cap_msg = unit_array(np.zeros(n)), unit_array(np.zeros(n))
        self._states_msg = JointState(name=[f"unit_{k + 1}" for k in range(n)])
        self._states_msg.header.frame_id = self.frame_id
        masses = cfg.per_unit("mass")
        #: Time step of the dynamics [s] (biased units with mass, a timer, the FE model), else None: quasi-static.
        self.dynamics_dt = (1.0 / self.update_rate if self.update_rate > 0
                            and any(m > 0 for m, mode in zip(masses, cfg.modes) if mode == BIASED) else None)
        #: Whether the solver thread takes the commands at its ticks (quasi-static updates at a rate), else the
        #: executor posts each as it comes (an update per command, or dynamics on the node's clock).
        self.commands_taken_by_solver = self.update_rate > 0 and self.dynamics_dt is None
        self.updater = TwinUpdater(twin, {kind: np.zeros(n) for kind in COMMAND_KINDS}, self.modes,
                                   self._publish_outputs, self._warn, self.solve_budget, stability_period,
                                   period=1.0 / self.update_rate if self.update_rate > 0 else 0.0,
                                   dynamics_dt=self.dynamics_dt,
                                   take_commands=self._take_commands if self.commands_taken_by_solver else None,
                                   background_checks=True)
        check_rate = declare_number(self, "fe_check_rate", 1.0,
                                    "model rom: FE re-solves of the latest command per second, in a background "
                                    "thread (difference in /diagnostics, resync above the ROM's tolerance); 0 = off")
        #: The twin (its ``close`` runs at the end; the solver thread owns its state).
        self._twin = twin
        #: The reduced twin (model: rom) and its FE check, else None.
        self.rom_twin = twin if isinstance(twin, ReducedTwin) else None
        #: The interpreter's switch interval before this node lowered it (restored by destroy_node), else None.
        self._switch_interval = None
        if self.rom_twin is not None and self.update_rate > 0:
            # The solver thread needs the GIL for ~50 us of Python per update; with the default
            # 5 ms switch interval it can wait several ticks behind the executor's thread.
            self._switch_interval = sys.getswitchinterval()
            sys.setswitchinterval(min(self._switch_interval, 0.1 / self.update_rate))
        self.fe_check = None
        if self.rom_twin is not None and check_rate > 0:
            self.fe_check = FeCheck(cfg, twin.rom.force_reference, twin.tolerance, check_rate, twin.request_resync,
                                    self._warn)
            self.fe_check.start()
        if self.commands_taken_by_solver:
            group, events = TakenBySolver(), SubscriptionEventCallbacks(use_default_callbacks=False)
            self._publisher_counts: dict[str, int] = {}
            self.create_timer(1.0 / PUBLISHER_WATCH_RATE, self._watch_command_publishers)
        else:
            group, events = None, SubscriptionEventCallbacks(matched=lambda _: self._publish_diagnostics(),
                                                             use_default_callbacks=False)
        self._command_subs = {
            kind: self.create_subscription(
                Float64MultiArray, f"command/{kind}", lambda m, kind=kind: self._on_command(kind, m), COMMAND_QOS,
                event_callbacks=events, callback_group=group)
            for kind in COMMAND_KINDS}
        self.create_service(Trigger, "reset", self._on_reset, callback_group=MutuallyExclusiveCallbackGroup())
        if self.dynamics_dt is not None:  # dynamics step on the node's clock (use_sim_time honoured)
            self.create_timer(1.0 / self.update_rate, lambda: self.updater.tick(self.get_clock().now().nanoseconds))
        if self.marker_rate > 0:
            self.create_timer(1.0 / self.marker_rate, self._publish_marker)
        self.create_timer(1.0, self._publish_diagnostics)
        #: What the process runs under (``realtime_priority``), before the recorder's threads start (they inherit it).
        self.scheduling = self._use_realtime_priority()
        self._start_recording()
        self.updater.start()
        self.get_logger().info(
            f"twin of {cfg.rows if cfg.layout == 'array' else 1}x{cfg.cols if cfg.layout == 'array' else 1} "
            f"{cfg.layout} ready: {self.model.mesh.n_elements} elements, {self.model.disc.n_dofs} dofs, "
            f"update_rate {self.update_rate} Hz, solve_budget {self.solve_budget} s"
            + (f", dynamics with dt {self.dynamics_dt} s" if self.dynamics_dt is not None else ""))

    @property
    def result(self) -> TwinResult | None:
        """The last good result (None before the first solve)."""
        return self.updater.result

    def command_publishers(self, kind: str) -> int:
        """Publishers of ``command/<kind>`` that every subscription of this node to it (the twin's and, when
        recording, the recorder's) is connected to: once it is >= 1, a command sent is received."""
        count = self._command_subs[kind].get_publisher_count()
        if self.recorder is not None and not self.recording_error:
            count = min(count, self.recorder.publisher_count(f"command/{kind}"))
        return count

    # ---------------------------------------------------------------- parameters
    def _declare_config(self) -> ArrayConfig:
        path = self.declare_parameter(
            "config_file", "", ParameterDescriptor(description="twin config YAML; parameters below override it",
                                                   read_only=True)).value
        base = load_config(path or None)
        defaults = config_parameters(base)
        modes = self.declare_parameter(  # dynamically typed: _on_set_parameters checks it and names it
            "unit_modes", defaults.pop("unit_modes"),
            ParameterDescriptor(description="per unit 'driven' (indenter follows command/displacement), 'free' "
                                            "(no indenter) or 'biased' (indenter on its bias element); default: "
                                            "config_file's unit_modes, all driven", dynamic_typing=True)).value
        values = {name: declare_typed(self, name, default, config_descriptor(name, default))
                  for name, default in defaults.items()}
        values["unit_modes"] = list(self._check_modes(modes, base.n_units))
        return config_from_parameters(values, base)

    def _make_twin(self, cfg: ArrayConfig) -> ArrayTwin | ReducedTwin:
        """The FE twin, or with ``model: rom`` the reduced twin of ``rom_file`` (a ValueError says why not)."""
        model = self.declare_parameter("model", "fe", ParameterDescriptor(
            description="'fe': the finite-element twin; 'rom': the reduced model of rom_file (dea-twin rom train), "
                        "the FE answering outside its envelope", read_only=True)).value
        rom_file = self.declare_parameter("rom_file", "", ParameterDescriptor(
            description="ROM file (.npz) for model: rom", read_only=True)).value
        second_step = declare_number(self, "rom_second_step", 0.0,
                                     "model rom: output change (fraction of its scale) of an update's first Newton "
                                     "correction above which it evaluates a second time; 0 = the ROM's tolerance, "
                                     "at most 1e-3 (docs/rom.md: larger is faster and less exact; a 4-by-4 was "
                                     "0.08-0.10 % off at 2e-3 here, where the Hessian refreshes in a worker)")
        if model == "fe":  # the tangents of warm updates refreshed off the solver thread
            return ArrayTwin(cfg, background_tangent=True)
        if model != "rom":
            raise ConfigError(f"model: must be 'fe' or 'rom', got {model!r}")
        if not rom_file:
            raise ConfigError("rom_file: model 'rom' needs a ROM file (train one with dea-twin rom train)")
        # A refresh of the reduced Hessian (0.5-4 ms, ~10 a second on a smooth stream) would
        # hold the solver thread for one to four 1 kHz ticks: it runs in a worker thread, as
        # BLAS products where this process's BLAS can be held to one thread (no helper
        # threads spinning on the core beside the updates; else summed point by point).
        #: Whether every BLAS of this process was set to one thread (model rom only).
        self.blas_single_threaded = single_threaded_blas()
        twin = ReducedTwin(cfg, load_rom(rom_file, cfg), background_refresh=True, second_step=second_step or None,
                           blas=self.blas_single_threaded)
        warning = twin.rom.validation_warning()
        if warning:
            self.get_logger().warning(f"rom_file {rom_file}: {warning} (fe_check_rate compares it with the FE while "
                                      "it runs)")
        if not twin.answers(cfg.modes):
            self.get_logger().warning(
                f"unit_modes {list(cfg.modes)} differ from the modes the ROM was trained for ({list(twin.modes)}; "
                "a unit trained as driven may be biased): the FE answers every update until they match")
        return twin

    def _check_modes(self, modes: object, n_units: int | None = None) -> tuple[str, ...]:
        """``modes`` as a tuple, or ConfigError naming ``unit_modes``."""
        if not isinstance(modes, (list, tuple)) or not all(isinstance(m, str) for m in modes):
            raise ConfigError(f"unit_modes: expected a list of {' or '.join(repr(m) for m in MODES)}, one per unit, "
                              f"got {modes!r}")
        try:
            return check_modes(modes, self.config.n_units if n_units is None else n_units)
        except ValueError as exc:
            raise ConfigError(f"unit_modes: {exc}") from None

    def _on_set_parameters(self, params) -> SetParametersResult:
        """Run-time changes, checked as strictly as a config file (type, range; the reason names the parameter)."""
        changes = {}
        modes = None
        for p in params:
            if p.name == "unit_modes":
                try:
                    modes = self._check_modes(p.value)
                except ConfigError as exc:
                    return SetParametersResult(successful=False, reason=str(exc))
            elif p.name in RUNTIME_FIELDS:
                changes[p.name] = p.value
        if changes:
            try:
                cfg = ArrayConfig.from_dict({**self.config.to_dict(), **changes})
            except ConfigError as exc:
                return SetParametersResult(successful=False, reason=str(exc))
            self.config = cfg
            self.updater.set_config(cfg)
            if self.fe_check is not None:
                self.fe_check.set_config(cfg)
        if modes is not None:
            self.modes = modes
            self.config = self.config.replace(unit_modes=modes)
            self.updater.set_modes(modes)
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

        metadata = metadata_from_config(self.config, self.modes, self.update_rate)
        try:
            self.recorder = TopicRecorder(self, directory, metadata, self._on_recording_error,
                                          split_size=split_size, split_duration=split_duration,
                                          on_matched=self._publish_diagnostics)
            self.get_logger().info(f"recording to {self.recorder.writer.path}")
        except RecordingError as exc:
            self._on_recording_error(f"recording not started: {exc}")
            return
        self._wait_for_recorder(RECORDER_MATCH_TIMEOUT)

    def _wait_for_recorder(self, timeout: float) -> None:
        """Return once the recorder's subscriptions and this node's output publishers have matched.

        Outputs are volatile: a message published before the recorder's subscription is
        connected to its publisher never reaches the recording, and a dynamic node on a
        simulated clock publishes its rest state once, before its first tick.  Within one
        process the match takes milliseconds (seconds on a loaded machine); the solver
        thread, the only publisher of outputs, starts after this.  After ``timeout`` [s]
        the node goes on with a warning that the first outputs may be missing.
        """
        outputs = {"force": self.pub_force, "capacitance": self.pub_cap, "unit_states": self.pub_states,
                   "/diagnostics": self.pub_diag}
        deadline = time.monotonic() + timeout
        while not all(self.recorder.publisher_count(topic) >= 1 and publisher.get_subscription_count() >= 1
                      for topic, publisher in outputs.items()):
            if time.monotonic() > deadline:
                self.get_logger().warning(f"the recorder's subscriptions did not connect to the outputs within "
                                          f"{timeout:g} s: the first outputs may be missing from the recording")
                return
            time.sleep(0.002)

    def _use_realtime_priority(self) -> str:
        """Apply ``realtime_priority`` (:mod:`.realtime`) before the solver thread starts; what the process runs
        under, for the diagnostics (a refusal is a warning: the twin runs on under normal scheduling)."""
        priority = declare_typed(self, "realtime_priority", 0, ParameterDescriptor(
            description=f"SCHED_FIFO priority (1-{MAX_PRIORITY}) of every thread of the node's process, so that the "
                        "solver thread's ticks are not delayed by other processes (needs CAP_SYS_NICE or an rtprio "
                        "limit); 0 = normal scheduling", read_only=True, type=ParameterType.PARAMETER_INTEGER,
            integer_range=[IntegerRange(from_value=0, to_value=MAX_PRIORITY, step=1)]))
        if priority == 0:
            return "normal"
        try:
            threads = use_fifo(priority)
        except OSError as exc:
            text = (f"realtime_priority {priority}: SCHED_FIFO refused ({exc}); running under normal scheduling "
                    f"(allow it with CAP_SYS_NICE or an rtprio limit >= {priority} in /etc/security/limits.conf)")
            self.get_logger().warning(text)
            return f"normal: {text}"
        self.get_logger().info(f"SCHED_FIFO priority {priority} for the node's {threads} threads and those it starts")
        return f"SCHED_FIFO {priority}"

    def _on_recording_error(self, text: str) -> None:
        self.recording_error = text
        self.get_logger().error(f"{text}; the twin keeps running without recording")

    def destroy_node(self) -> None:
        """Stop the solver thread (and the FE check), finish the recording (if any), then destroy the node."""
        self.updater.stop()
        if self.fe_check is not None:
            self.fe_check.stop()
        self._twin.close()
        if self.recorder is not None:
            self.recorder.close()
            self.recorder = None
        if self._switch_interval is not None:
            sys.setswitchinterval(self._switch_interval)
        super().destroy_node()

    # ---------------------------------------------------------------- callbacks (executor)
    def _warn(self, key: str, text: str, period: float = 1.0) -> None:
        now = time.monotonic()
        if now - self._last_warn.get(key, -math.inf) >= period:
            self._last_warn[key] = now
            self.get_logger().warning(text)

    def _on_command(self, kind: str, msg: Float64MultiArray) -> None:
        error = command_error(kind, msg.data, self.config)
        if error:
            self.counters[f"rejected_{kind}"] += 1
            self._warn(kind, f"rejected {kind} command: {error}")
            return
        if kind == "displacement":
            ignored = [k + 1 for k, (mode, d) in enumerate(zip(self.modes, msg.data))
                       if mode in (FREE, BIASED) and d != 0.0]
            if ignored:
                self.counters["displacement_on_free_unit"] += 1
                self._warn("free", f"displacement for free or biased unit(s) {ignored} ignored: a free unit has no "
                                   f"indenter, a biased one is moved by its bias and force "
                                   f"(unit_modes {list(self.modes)})", period=5.0)
        self.updater.post(kind, msg.data)

    def _take_commands(self) -> None:
        """Take the latest message of each command subscription and handle it (on the solver thread).

        The subscriptions keep one message (depth 1), so this is the command an executor
        callback would have seen last.  rclpy has no public ``take``: this is the call its
        executor makes (``Subscription.handle.take_message``).  A take that fails because
        the context was shut down (Ctrl-C during it) is the stop, not an error."""
        for kind, sub in self._command_subs.items():
            try:
                with sub.handle:
                    taken = sub.handle.take_message(sub.msg_type, sub.raw)
            except Exception:
                if self.context.ok():
                    raise
                return
            if taken is not None:
                self._on_command(kind, taken[0])

    def _watch_command_publishers(self) -> None:
        """Publish diagnostics when a command publisher came or left (what a matched-event handler does
        when the executor takes the commands)."""
        counts = {kind: sub.get_publisher_count() for kind, sub in self._command_subs.items()}
        if counts != self._publisher_counts:
            self._publisher_counts = counts
            self._publish_diagnostics()

    async def _on_reset(self, request, response):
        """Pre-empt the solver thread and answer when the twin is flat again (the executor keeps running)."""
        done = Future()
        executor = self.executor

        def finished(ok: bool, text: str) -> None:  # on the solver thread
            done.set_result((ok, text))
            if executor is not None:
                executor.wake()

        self.updater.reset(finished)
        response.success, response.message = await done
        return response

    # ---------------------------------------------------------------- publishing
    def _publish_outputs(self, res: TwinResult, stamp_ns: int | None = None) -> None:
        """Force, capacitance and unit states of ``res`` (called on the solver thread).

        ``unit_states`` is stamped ``stamp_ns`` (a dynamic step: its tick), else now.  A publish that
        fails because the context was shut down (Ctrl-C or SIGTERM while it ran) is the stop, not an error."""
        states = self._states_msg
        states.header.stamp = self.get_clock().now().to_msg() if stamp_ns is None else Time(
            nanoseconds=stamp_ns).to_msg()
        force = array.array("d", res.force)
        self._force_msg.data = force
        self._cap_msg.data = array.array("d", res.capacitance)
        states.position = array.array("d", res.position)
        states.velocity = array.array("d", res.velocity)
        states.effort = force
        try:
            self.pub_force.publish(self._force_msg)
            self.pub_cap.publish(self._cap_msg)
            self.pub_states.publish(states)
        except Exception:
            if self.context.ok():
                raise
            return
        if self.fe_check is not None:
            self.fe_check.post(res)

    def _publish_marker(self) -> None:
        res = self.result
        if res is None:
            return
        model = self.model
        pts = res.positions[model.mesh.elements[:, :3]].reshape(-1, 3)
        level = np.clip(model.corner_area_stretch(res.positions) / self.config.prestretch ** 2 - 1.0, 0.0, 1.0)
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

    def _check_duplicate_name(self) -> None:
        me = (self.get_name(), self.get_namespace())
        count = sum(1 for entry in self.get_node_names_and_namespaces() if entry == me)
        self._duplicate = "" if count <= 1 else (
            f"{count} nodes named {self.get_fully_qualified_name()} on this ROS domain: their outputs mix "
            f"(give each its own namespace, -r __ns:=/name)")
        if self._duplicate:
            self._warn("duplicate", self._duplicate, period=10.0)

    def _publish_diagnostics(self) -> None:
        self._check_duplicate_name()
        res = self.result
        stats = self.updater.stats()
        status = DiagnosticStatus(name=f"{self.get_fully_qualified_name()}: solver", hardware_id="dea_array_twin")
        problem = stats.thread_error or (stats.last_error and f"last solve failed: {stats.last_error}")
        warnings = res.warnings if res is not None else []
        if res is not None and res.stable is None and stats.stable is False:  # checked after the update
            warnings = warnings + ["the last stability check found no stable minimum (tangent not positive definite)"]
        if problem:
            status.level, status.message = DiagnosticStatus.ERROR, problem
        elif self.recording_error or self._duplicate:
            status.level, status.message = DiagnosticStatus.WARN, self.recording_error or self._duplicate
        elif warnings:
            status.level, status.message = DiagnosticStatus.WARN, "; ".join(warnings)
        else:
            status.level, status.message = DiagnosticStatus.OK, "ok"
        values = {
            "updates": stats.updates, "updates_per_s": round(stats.updates_per_s, 2),
            "outputs_per_s": round(stats.outputs_per_s, 2), "update_rate_hz": self.update_rate,
            "solve_time_p50_ms": round(1e3 * stats.solve_time_p50, 3),
            "solve_time_p95_ms": round(1e3 * stats.solve_time_p95, 3),
            "solve_time_max_ms": round(1e3 * stats.solve_time_max, 3),
            "solve_budget_s": self.solve_budget, "budget_overruns": stats.budget_overruns,
            "failed_solves": stats.failed_solves, "skipped_ticks": stats.skipped_ticks, "snaps": stats.snaps,
            "lift_offs": stats.lift_offs, "scheduling": self.scheduling, **self.counters,
            **{f"command_publishers_{kind}": self.command_publishers(kind) for kind in COMMAND_KINDS},
        }
        if self.recorder is not None:
            values.update(recording=self.recording_error or str(self.recorder.writer.path),
                          recorder_written=self.recorder.written, recorder_dropped=self.recorder.dropped,
                          recorder_backlog=self.recorder.backlog)
        else:
            values["recording"] = self.recording_error or "off"
        values["model"] = "fe"
        if self.rom_twin is None:
            values.update({f"background_tangents_{kind}": self._twin.tangents[kind]
                           for kind in ("installed", "dropped", "failed")})
        else:
            rom_problem = self._rom_diagnostics(values, res)
            if rom_problem and status.level == DiagnosticStatus.OK:
                status.level, status.message = DiagnosticStatus.WARN, rom_problem
        if res is not None:
            values.update(iterations=res.iterations, residual_N=res.residual, solve_time_ms=1e3 * res.solve_time,
                          stable=stats.stable, stability_checked_s_ago=round(stats.stability_age, 3),
                          wrinkled=res.wrinkled, field_exceeded=res.field_exceeded,
                          min_principal_stress_Pa=res.min_principal_stress,
                          peak_field_V_per_m=float(res.peak_field.max()))
        status.values = [KeyValue(key=k, value=str(v)) for k, v in values.items()]
        msg = DiagnosticArray(status=[status])
        msg.header.stamp = self.get_clock().now().to_msg()
        self.pub_diag.publish(msg)


    def _rom_diagnostics(self, values: dict, res: TwinResult | None) -> str:
        """Add the reduced twin's counters and the FE check's differences to ``values``; a problem, or ''."""
        twin = self.rom_twin
        fallbacks = twin.fallbacks
        values.update(model="rom", rom_file=twin.rom.config_hash, rom_tolerance=twin.tolerance,
                      rom_second_step=twin.second_step,
                      rom_hessian="BLAS products" if twin.blas_products else "per point",
                      blas_single_threaded=self.blas_single_threaded,
                      rom_threads=twin.threads, rom_helper_chunks=twin.team.helped,
                      rom_chunks_taken_over=twin.team.taken_over,
                      rom_validation=twin.rom.validation_warning() or "within its tolerance",
                      rom_updates=twin.updates, rom_refreshes=twin.refreshes, rom_resyncs=twin.resyncs,
                      **{f"rom_fallbacks_{kind}": fallbacks.get(kind, 0)
                         for kind in FALLBACKS})
        if res is not None:
            values.update(rom_error_indicator=getattr(res, "error_indicator", math.nan),
                          rom_fallback=getattr(res, "fallback", "") or "none")
        if self.fe_check is None:
            values["fe_check"] = "off"
            return ""
        check = self.fe_check.stats()
        values.update(fe_checks=check.checks, fe_check_failures=check.failures,
                      fe_check_ms=round(check.last_check_ms, 2),
                      rom_fe_force_difference=check.last_force_difference,
                      rom_fe_capacitance_difference=check.last_capacitance_difference,
                      rom_fe_force_difference_max=check.max_force_difference,
                      rom_fe_capacitance_difference_max=check.max_capacitance_difference)
        worst = max(check.last_force_difference, check.last_capacitance_difference)
        if worst > twin.tolerance:
            return (f"reduced model differs from the FE by {worst:.3%} at the last check, above its tolerance "
                    f"{twin.tolerance:.3%} (resynchronised)")
        return check.last_error and f"FE check failed: {check.last_error}"


def main(args: Sequence[str] | None = None) -> None:
    """Entry point of ``twin_node`` (``ros2 run dea_array_twin twin_node``)."""
    spin_node(TwinNode, "dea_array_twin", args)


if __name__ == "__main__":
    main()
