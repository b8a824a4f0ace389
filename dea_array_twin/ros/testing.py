"""Test harness for controllers developed against the twin (pytest-friendly).

::

    from dea_array_twin.ros.testing import TwinHarness

    def test_my_controller():
        with TwinHarness(parameters={"update_rate": 50.0}) as h:
            h.send_displacement([0.0, 0.01, 0.0])
            force = h.wait_for("force", lambda m: m.data[1] > 0.1, timeout=10.0)

Isolation: each harness runs on a ROS domain of its own with discovery limited to
localhost (``ROS_AUTOMATIC_DISCOVERY_RANGE=LOCALHOST``), so tests running in parallel
on one machine (pytest-xdist, two CI jobs) never see each other's twins.  The id comes
from ``domain_coordinator`` (the ``ros-jazzy-domain-coordinator`` wheel), which holds
a lock per id for as long as the harness lives, so no two harnesses on the machine get
the same one.  Pin an id with ``TwinHarness(domain_id=42)`` to watch a test from a
shell (``ROS_DOMAIN_ID=42 ros2 topic echo /force``); valid ids are 0-232 (the harness
then does not check that the id is free).

No race on the first command: the harness publishes commands reliably, and
``__enter__`` returns only when the twin's command subscriptions (and, when it
records, its recorder's) are connected to the harness's publishers on *their* side
(in-process: asked directly; as a process: read from the ``command_publishers_*``
values of the twin's ``/diagnostics``, which it publishes whenever a command publisher
connects).  A command sent after that is received: a controller test never loses its
first command.

``TwinHarness(process=True)`` starts the twin as a separate process (``python -m
dea_array_twin.ros.node``), as ``ros2 run`` would; otherwise it runs in this process on
the harness's executor thread (its solver and recorder have threads of their own).
``harness.node`` is the test-side node: add your controller's publishers and
subscriptions to it or spin your own nodes with ``harness.context``.
"""

from __future__ import annotations

import contextlib
import os
import subprocess
import sys
import threading
import time
from collections import deque
from typing import Any, Callable

import rclpy
from rclpy.context import Context
from rclpy.event_handler import PublisherEventCallbacks
from rclpy.executors import SingleThreadedExecutor
from rclpy.node import Node
from rclpy.parameter import Parameter
from rclpy.qos import QoSProfile, ReliabilityPolicy
from std_msgs.msg import Float64MultiArray
from std_srvs.srv import Trigger

from ..bag.msg_definitions import message_class
from .node import COMMAND_KINDS, TwinNode
from .recorder import RECORDED_TOPICS

#: QoS of the harness's command publishers and output subscriptions: reliable, deep enough for a flood.
HARNESS_QOS = QoSProfile(depth=1000, reliability=ReliabilityPolicy.RELIABLE)


def _output_types() -> dict[str, type]:
    """The twin's output topics (everything it records but the commands) and their classes."""
    return {topic: message_class(type_name) for topic, type_name in RECORDED_TOPICS.items()
            if not topic.startswith("command/")}


class TwinHarness:
    """A twin plus a test-side node on an isolated ROS domain.

    Parameters
    ----------
    parameters : dict, optional
        ROS parameters of the twin node (e.g. ``{"update_rate": 50.0}``).
    process : bool
        Run the twin in a subprocess instead of this process.
    namespace : str
        Namespace of the twin (its topics are relative).
    params_file : str, optional
        A ROS parameters YAML for the twin (``process=True`` only).
    domain_id : int, optional
        The ROS domain to use (0-232); default: a free one from ``domain_coordinator``.

    Attributes
    ----------
    sent : dict
        Commands published so far per kind (``"displacement"``, ``"voltage"``).
    """

    def __init__(self, parameters: dict[str, Any] | None = None, process: bool = False, namespace: str = "",
                 params_file: str | None = None, domain_id: int | None = None):
        if domain_id is not None and not (isinstance(domain_id, int) and 0 <= domain_id <= 232):
            raise ValueError(f"domain_id must be an integer in [0, 232], got {domain_id!r}")
        self.requested_domain = domain_id
        self.sent = {kind: 0 for kind in COMMAND_KINDS}
        self.parameters = dict(parameters or {})
        self.params_file = params_file
        self.process_mode = process
        self.namespace = namespace.rstrip("/")
        self._stack = contextlib.ExitStack()
        self._lock = threading.Lock()
        self._messages: dict[str, list] = {}
        self._times: dict[str, list[float]] = {}
        self.twin_node: TwinNode | None = None
        self.process: subprocess.Popen | None = None
        self._output: deque[str] = deque(maxlen=500)  # the twin process's last log lines
        #: Exception raised by a callback on the executor thread (which then stops).
        self.spin_error: Exception | None = None

    # ------------------------------------------------------------------ lifecycle
    def __enter__(self) -> "TwinHarness":
        from domain_coordinator import domain_id

        try:
            self.domain_id = self.requested_domain if self.requested_domain is not None else \
                self._stack.enter_context(domain_id())
            previous = os.environ.get("ROS_AUTOMATIC_DISCOVERY_RANGE")
            os.environ["ROS_AUTOMATIC_DISCOVERY_RANGE"] = "LOCALHOST"
            self._stack.callback(_restore_env, "ROS_AUTOMATIC_DISCOVERY_RANGE", previous)
            self.context = Context()
            rclpy.init(context=self.context, domain_id=self.domain_id)
            self._stack.callback(self.context.try_shutdown)
            self.executor = SingleThreadedExecutor(context=self.context)
            self.node = Node("twin_test_client", context=self.context)
            if self.process_mode:
                self._start_process()
            elif self.params_file:
                raise ValueError("params_file needs process=True")
            else:
                overrides = [Parameter(k, value=v) for k, v in self.parameters.items()]
                self.twin_node = TwinNode(context=self.context, parameter_overrides=overrides,
                                          namespace=self.namespace or None)
                self.executor.add_node(self.twin_node)
            self.executor.add_node(self.node)
            self._matched = dict.fromkeys(COMMAND_KINDS, 0)
            self._pubs = {kind: self.node.create_publisher(
                Float64MultiArray, self.topic(f"command/{kind}"), HARNESS_QOS,
                event_callbacks=PublisherEventCallbacks(matched=lambda info, k=kind: self._on_matched(k, info)))
                for kind in COMMAND_KINDS}
            for name, msg_type in _output_types().items():
                self.node.create_subscription(msg_type, self.topic(name),
                                              lambda m, n=name: self._store(n, m), HARNESS_QOS)
            self._reset = self.node.create_client(Trigger, self.topic("reset"))
            self._thread = threading.Thread(target=self._spin, daemon=True)
            self._thread.start()
            self._stack.callback(self._stop_spin)
            self._wait_until_connected(timeout=60.0)
        except BaseException:
            self._stack.close()
            raise
        return self

    def __exit__(self, *exc) -> None:
        self._stack.close()

    def _twin_receives_commands(self) -> bool:
        """Every subscription of the twin to each command topic is connected to our publisher, on its side."""
        if self.twin_node is not None:
            return all(self.twin_node.command_publishers(kind) >= 1 for kind in COMMAND_KINDS)
        for msg in reversed(self.messages("/diagnostics")):
            values = diagnostic_values(msg)
            if f"command_publishers_{COMMAND_KINDS[0]}" in values:
                return all(int(values[f"command_publishers_{kind}"]) >= 1 for kind in COMMAND_KINDS)
        return False

    def _commands_reach_the_twin(self) -> bool:
        """Our publishers have matched every subscription of the twin (the node's and the recorder's) to
        each command topic, on our side: discovery is not symmetric, and a message reaches only
        the subscriptions its publisher has matched."""
        for kind in COMMAND_KINDS:
            if self.twin_node is not None:
                recorder = self.twin_node.recorder is not None and not self.twin_node.recording_error
                expected = 1 + recorder
            else:  # another process: the subscriptions our graph knows of
                expected = max(1, self.node.count_subscribers(self.topic(f"command/{kind}")))
            if self.command_subscribers(kind) < expected:
                return False
        return True

    def _wait_until_connected(self, timeout: float) -> None:
        """Block until the twin receives our commands (on both sides of discovery) and we receive its outputs."""
        deadline = time.monotonic() + timeout
        while time.monotonic() < deadline:
            if (self._twin_receives_commands() and self._commands_reach_the_twin()
                    and self.node.count_publishers(self.topic("force")) >= 1):
                return
            if self.process is not None and self.process.poll() is not None:
                raise RuntimeError(f"twin process exited with {self.process.returncode}: "
                                   f"{self.output()[-2000:]}")
            time.sleep(0.02)
        raise TimeoutError(f"twin not discovered on ROS domain {self.domain_id} within {timeout} s")

    def _spin(self) -> None:
        while self.context.ok():
            try:
                self.executor.spin_once(timeout_sec=0.05)
            except Exception as exc:  # a callback raised: wait_for reports it
                if self.context.ok():
                    self.spin_error = exc
                return

    def _stop_spin(self) -> None:
        self.executor.shutdown()
        self.context.try_shutdown()
        self._thread.join(timeout=5.0)
        if self.twin_node is not None:
            self.twin_node.destroy_node()
        self.node.destroy_node()

    def _start_process(self) -> None:
        env = dict(os.environ, ROS_DOMAIN_ID=str(self.domain_id), ROS_AUTOMATIC_DISCOVERY_RANGE="LOCALHOST")
        args = [sys.executable, "-m", "dea_array_twin.ros.node", "--ros-args"]
        if self.params_file:
            args += ["--params-file", self.params_file]
        for key, value in self.parameters.items():
            args += ["-p", f"{key}:={_param_text(value)}"]
        if self.namespace:
            args += ["-r", f"__ns:={self.namespace}"]
        self.process = subprocess.Popen(args, env=env, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
        # Read its log all the time: a full pipe would block the twin at its next log line.
        reader = threading.Thread(target=self._read_output, daemon=True)
        reader.start()

        def stop() -> None:
            if self.process.poll() is None:
                self.process.send_signal(2)  # SIGINT: rclpy shuts down cleanly, the recording is finalised
                try:
                    self.process.wait(timeout=30.0)
                except subprocess.TimeoutExpired:
                    self.process.kill()
                    self.process.wait()
            reader.join(timeout=5.0)
            if not reader.is_alive():  # read to the end: the pipe can go (a reader still in it keeps it)
                self.process.stdout.close()

        self._stack.callback(stop)

    def _read_output(self) -> None:
        for line in self.process.stdout:
            self._output.append(line)

    def output(self) -> str:
        """The last lines the twin process logged (stdout and stderr; ``process=True`` only)."""
        return "".join(self._output)

    # ------------------------------------------------------------------ helpers
    def topic(self, name: str) -> str:
        """Full name of a twin topic (honours the namespace)."""
        return name if name.startswith("/") else f"{self.namespace}/{name}" if self.namespace else name

    def _store(self, name: str, msg: Any) -> None:
        now = time.monotonic()
        with self._lock:
            self._messages.setdefault(name, []).append(msg)
            self._times.setdefault(name, []).append(now)

    def messages(self, name: str) -> list:
        """Every message received on output ``name`` so far."""
        with self._lock:
            return list(self._messages.get(name, []))

    def receive_times(self, name: str) -> list[float]:
        """When each message of :meth:`messages` arrived (``time.monotonic()`` seconds)."""
        with self._lock:
            return list(self._times.get(name, []))

    def clear(self) -> None:
        """Forget received messages."""
        with self._lock:
            self._messages.clear()
            self._times.clear()

    def send(self, kind: str, values) -> None:
        """Publish a command of ``kind`` (``"displacement"`` [m], ``"voltage"`` [V] or ``"force"`` [N]), one value
        per unit."""
        self._pubs[kind].publish(Float64MultiArray(data=[float(v) for v in values]))
        self.sent[kind] += 1

    def _on_matched(self, kind: str, info) -> None:
        self._matched[kind] = info.current_count

    def command_subscribers(self, kind: str) -> int:
        """Subscriptions to ``command/<kind>`` the harness's publisher has matched (its side of discovery).

        The DDS writer's matched status (its ``matched`` event), not the ROS graph's count
        (``get_subscription_count``), which knows a subscription from discovery before the writer
        has matched it: a sample published in between never reaches a best-effort subscription
        (the recorder's), and nothing resends it."""
        return self._matched[kind]

    def send_displacement(self, values) -> None:
        """Publish a displacement command [m], one value per unit."""
        self.send("displacement", values)

    def send_voltage(self, values) -> None:
        """Publish a voltage command [V], one value per unit."""
        self.send("voltage", values)

    def send_force(self, values) -> None:
        """Publish an external force command [N] on the biased indenters, one value per unit."""
        self.send("force", values)

    def wait_for(self, name: str, predicate: Callable[[Any], bool] | None = None, timeout: float = 10.0,
                 after: int = 0) -> Any:
        """Wait for a message on output ``name`` (index >= ``after``) satisfying ``predicate``.

        Raises ``TimeoutError`` saying what was last seen.
        """
        deadline = time.monotonic() + timeout
        while time.monotonic() < deadline:
            for msg in self.messages(name)[after:]:
                if predicate is None or predicate(msg):
                    return msg
            if self.spin_error is not None:
                raise RuntimeError(f"a callback on the harness executor raised: {self.spin_error!r}") \
                    from self.spin_error
            if self.process is not None and self.process.poll() is not None:
                raise RuntimeError(f"twin process exited with {self.process.returncode}: "
                                   f"{self.output()[-2000:]}")
            time.sleep(0.01)
        seen = self.messages(name)
        raise TimeoutError(f"no matching message on {name!r} within {timeout} s "
                           f"({len(seen)} received, last: {seen[-1] if seen else None})")

    def reset(self, timeout: float = 10.0) -> Trigger.Response:
        """Call the twin's ``reset`` service."""
        if not self._reset.wait_for_service(timeout_sec=timeout):
            raise TimeoutError("reset service not available")
        future = self._reset.call_async(Trigger.Request())
        deadline = time.monotonic() + timeout
        while not future.done():
            if time.monotonic() > deadline:
                raise TimeoutError("reset service did not answer")
            time.sleep(0.01)
        return future.result()


def diagnostic_values(msg: Any) -> dict[str, str]:
    """The key/value pairs of the first status of a DiagnosticArray (the twin publishes one)."""
    return {kv.key: kv.value for kv in msg.status[0].values} if msg.status else {}


def _restore_env(name: str, value: str | None) -> None:
    if value is None:
        os.environ.pop(name, None)
    else:
        os.environ[name] = value


def _param_text(value: Any) -> str:
    """A parameter value as ``--ros-args -p`` text (YAML)."""
    if isinstance(value, bool):
        return "true" if value else "false"
    if isinstance(value, (list, tuple)):
        return "[" + ",".join(_param_text(v) for v in value) + "]"
    if isinstance(value, str):
        return value
    return repr(value)
