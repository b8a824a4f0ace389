"""Recording the twin's topics to MCAP from inside the node, keeping every message.

A :class:`TopicRecorder` subscribes (``raw=True``: the exact bytes that went over the
wire) to the twin's command, output and diagnostics topics and writes them with a
:class:`~dea_array_twin.bag.writer.Ros2McapWriter` (log time = receive time on the twin
node's clock, simulated time under ``use_sim_time`` as rosbag2 records it, so a replay
can place commands between the ticks of the node's dynamics).  Nothing
it does waits for the twin, and the twin never waits for it:

* its subscriptions belong to a small node of its own (``<twin name>_recorder``, same
  namespace, the twin's resolved topic names, so remaps apply) spun by an executor on
  its own thread: neither the twin's callbacks nor the executor the user spins the twin
  with can delay it;
* the subscriptions keep deep queues (:data:`QUEUE_DEPTH`, seconds of a command flood)
  so a burst waits in DDS instead of being dropped; their callbacks only append to an
  in-memory queue;
* a writer thread takes that queue in batches, writes, and closes the open chunk at
  least once a second (a killed node loses at most the last second);
* closing takes what DDS still holds for the subscriptions before the file is finished, so
  a command that arrived just before Ctrl-C is in the recording.

Counts for the node's diagnostics: messages written, messages dropped (DDS reports of
lost samples, plus the in-memory queue refusing more than :data:`BACKLOG_LIMIT`
messages when the disk cannot keep up) and the backlog.

Files are named ``dea_twin_<date>_<time to the ms>_<node>_<pid>.mcap`` and created
exclusively: two twins started in the same second, in one process or two, write two
files, and an existing file is never opened for writing.  The twin's config and
run-time parameters are stored as the MCAP metadata record ``dea_array_twin_config``.
A recording that cannot be written (unwritable directory, full disk) is stopped with an
error message; the node keeps running.
"""

from __future__ import annotations

import errno
import os
import threading
import time
from collections import deque
from pathlib import Path
from typing import Callable

from rclpy.event_handler import SubscriptionEventCallbacks
from rclpy.executors import ExternalShutdownException, SingleThreadedExecutor
from rclpy.node import Node
from rclpy.qos import QoSProfile, ReliabilityPolicy

from ..bag.msg_definitions import message_class
from ..bag.writer import CONFIG_RECORD, RecordingError, Ros2McapWriter, default_qos_yaml

__all__ = ["CONFIG_RECORD", "RECORDED_TOPICS", "TopicRecorder", "recording_name"]

#: Relative topic name -> ROS type recorded by the twin.
RECORDED_TOPICS = {
    "command/displacement": "std_msgs/msg/Float64MultiArray",
    "command/voltage": "std_msgs/msg/Float64MultiArray",
    "command/force": "std_msgs/msg/Float64MultiArray",
    "force": "std_msgs/msg/Float64MultiArray",
    "capacitance": "std_msgs/msg/Float64MultiArray",
    "unit_states": "sensor_msgs/msg/JointState",
    "membrane": "visualization_msgs/msg/Marker",
    "/diagnostics": "diagnostic_msgs/msg/DiagnosticArray",
}
#: Subscription queue depth per topic: 10 s of commands at 1 kHz; the outputs at 100 Hz for
#: 20 s; the membrane marker (about 100 kB each) for 20 s at 5 Hz.
QUEUE_DEPTH = {"command/displacement": 10_000, "command/voltage": 10_000, "command/force": 10_000, "membrane": 100,
               "/diagnostics": 100}
DEFAULT_DEPTH = 2_000
#: Messages the writer thread may fall behind by before new ones are dropped (and counted).
BACKLOG_LIMIT = 200_000
#: Seconds between the writer thread's batches.
BATCH_PERIOD = 0.05


def recording_name(node_name: str, when: float | None = None, pid: int | None = None) -> str:
    """``dea_twin_<YYYYmmdd_HHMMSS_mmm>_<node>_<pid>.mcap`` for a node's fully qualified name."""
    when = time.time() if when is None else when
    stamp = time.strftime("%Y%m%d_%H%M%S", time.localtime(when)) + f"_{int(when * 1000) % 1000:03d}"
    node = node_name.strip("/").replace("/", "_") or "node"
    return f"dea_twin_{stamp}_{node}_{os.getpid() if pid is None else pid}.mcap"


class TopicRecorder:
    """Record the twin node's topics into ``directory/<recording_name>``.

    Parameters
    ----------
    node : Node
        The twin node whose topics are recorded (its namespace and remaps apply).
    directory : str
        Output folder (created if missing).
    metadata : dict
        ``{key: text}`` stored as the ``dea_array_twin_config`` record.
    on_error : callable
        Called (on the writer thread) with the error text when recording stops because of
        an I/O error.
    on_matched : callable, optional
        Called (on the recorder's executor thread) when a publisher of a command topic
        connects or leaves.
    split_size, split_duration : float, optional
        Start a new file after this many bytes / seconds.

    Raises
    ------
    RecordingError
        The file cannot be created.
    """

    def __init__(self, node: Node, directory: str, metadata: dict[str, str], on_error: Callable[[str], None],
                 split_size: float | None = None, split_duration: float | None = None,
                 on_matched: Callable[[], None] | None = None):
        self.on_error = on_error
        self.error = ""
        self.written = 0
        self._lost = 0
        self._refused = 0
        self._queue: deque[tuple[int, bytes, int]] = deque()
        self._matched = dict.fromkeys(RECORDED_TOPICS, 0)  # publishers each subscription is matched with
        self._clock = node.get_clock()  # the twin's: ROS time (simulated under use_sim_time)
        self._stopping = threading.Event()  # stops the executor thread
        self._closing = threading.Event()  # the writer thread: write what is left, then end
        self.writer = _create_writer(Path(directory).expanduser(), node.get_fully_qualified_name(), metadata,
                                     split_size, split_duration)
        try:
            self._node = Node(f"{node.get_name()}_recorder", namespace=node.get_namespace(), context=node.context,
                              use_global_arguments=False, start_parameter_services=False)
            qos_yaml = default_qos_yaml(reliable=True, depth=10)
            self._subs = {}
            self._cids = {}
            for topic, type_name in RECORDED_TOPICS.items():
                resolved = node.resolve_topic_name(topic)  # namespace, remaps
                cid = self._cids[topic] = self.writer.add_topic(resolved, type_name, qos_yaml)
                reliability = ReliabilityPolicy.BEST_EFFORT if topic.startswith("command/") \
                    else ReliabilityPolicy.RELIABLE
                qos = QoSProfile(depth=QUEUE_DEPTH.get(topic, DEFAULT_DEPTH), reliability=reliability)
                call = on_matched if topic.startswith("command/") else None
                self._subs[topic] = self._node.create_subscription(
                    message_class(type_name), resolved, lambda data, cid=cid: self._receive(cid, data), qos,
                    raw=True, event_callbacks=SubscriptionEventCallbacks(
                        message_lost=self._on_lost, matched=lambda info, t=topic, c=call: self._on_matched(t, info, c)))
            self._executor = SingleThreadedExecutor(context=node.context)
            self._executor.add_node(self._node)
        except BaseException:
            self.writer.close()
            raise
        self._writer_thread = threading.Thread(target=self._write_loop, name="recorder-writer", daemon=True)
        self._spin_thread = threading.Thread(target=self._spin, name="recorder-executor", daemon=True)
        self._writer_thread.start()
        self._spin_thread.start()

    @property
    def dropped(self) -> int:
        """Messages lost: reported lost by DDS, or refused because the writer fell too far behind."""
        return self._lost + self._refused

    def publisher_count(self, topic: str) -> int:
        """Publishers the recorder's subscription to ``topic`` (a :data:`RECORDED_TOPICS` key) is matched with.

        The DDS reader's matched status (its ``matched`` event), not the ROS graph's count
        (``get_publisher_count``), which knows a publisher from discovery before the reader has
        matched it: a best-effort command sent in between is lost to the recording (the
        two-twins recording test missed one so under the full suite's load)."""
        return self._matched[topic]

    @property
    def backlog(self) -> int:
        """Messages received but not yet written."""
        return len(self._queue)

    # ------------------------------------------------------------------ receiving (recorder executor thread)
    def _receive(self, cid: int, data: bytes) -> None:
        if self.error:
            return
        if len(self._queue) >= BACKLOG_LIMIT:
            self._refused += 1
            return
        self._queue.append((cid, data, self._clock.now().nanoseconds))

    def _on_lost(self, info) -> None:
        self._lost += info.total_count_change

    def _on_matched(self, topic: str, info, then: Callable[[], None] | None) -> None:
        self._matched[topic] = info.current_count
        if then is not None:
            then()

    def _spin(self) -> None:
        while not self._stopping.is_set() and self._node.context.ok():
            try:
                self._executor.spin_once(timeout_sec=0.1)
            except ExternalShutdownException:
                return

    def _drain(self) -> None:
        """Queue what DDS already holds for the subscriptions: a message that arrived just before the
        close (while the executor thread was busy, or after a signal had shut the context down, which
        stops the executor but not a take) is recorded, not left behind."""
        if self.error:
            return
        for topic, sub in self._subs.items():
            try:
                with sub.handle:
                    while (taken := sub.handle.take_message(sub.msg_type, sub.raw)) is not None:
                        self._receive(self._cids[topic], taken[0])
            except Exception:  # noqa: BLE001 - the subscription is gone already; the file matters
                continue

    # ------------------------------------------------------------------ writing (writer thread)
    def _write_loop(self) -> None:
        last_flush = time.monotonic()
        while True:
            closing = self._closing.wait(BATCH_PERIOD)
            batch = len(self._queue)
            try:
                for _ in range(batch):
                    cid, data, stamp = self._queue.popleft()
                    self.writer.write(cid, data, stamp)
                self.written += batch
                if time.monotonic() - last_flush >= 1.0:
                    self.writer.flush()
                    last_flush = time.monotonic()
            except RecordingError as exc:
                self.error = f"recording stopped: {exc}"
                self._stopping.set()
                self._queue.clear()
                self.on_error(self.error)
                return
            if closing and not self._queue:
                return

    # ------------------------------------------------------------------ closing
    def close(self) -> None:
        """Stop receiving, write what was received, finish the file (summary written).  Safe to call twice."""
        self._stopping.set()
        if self._spin_thread.is_alive():
            self._spin_thread.join()
        self._drain()
        try:
            self._executor.remove_node(self._node)
            self._node.destroy_node()
        except Exception:  # noqa: BLE001 - the context may be shut down already (SIGTERM); the file matters
            pass
        self._closing.set()
        self._writer_thread.join()
        try:
            self.writer.close()
        except RecordingError as exc:
            if not self.error:
                self.error = f"recording not finished: {exc}"
                self.on_error(self.error)


def _create_writer(directory: Path, node_name: str, metadata: dict[str, str], split_size: float | None,
                   split_duration: float | None) -> Ros2McapWriter:
    """A writer on a new file: :func:`recording_name`, with ``-1``, ``-2``... if that exists already."""
    name = recording_name(node_name)
    for attempt in range(100):
        path = directory / (name if attempt == 0 else name.replace(".mcap", f"-{attempt}.mcap"))
        try:
            return Ros2McapWriter(path, metadata={CONFIG_RECORD: metadata}, flush_period=1.0,
                                  split_size=int(split_size) if split_size else None,
                                  split_duration=split_duration or None)
        except RecordingError as exc:
            if exc.errno != errno.EEXIST:
                raise
    raise RecordingError(f"cannot find a free file name like {directory / name}", path=directory / name)
