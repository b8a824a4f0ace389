"""Recording the twin's topics to MCAP from inside the node.

A :class:`TopicRecorder` adds ``raw=True`` subscriptions to the node's own command,
output and diagnostics topics and hands the exact bytes that went over the wire to a
:class:`~.mcap_writer.Ros2McapWriter` (log time = receive time).  The twin's config
and run-time parameters are stored as the MCAP metadata record
``dea_array_twin_config``, so a replay knows which model produced the file.  A
recording that cannot be written (unwritable directory, full disk) is stopped with
an error message; the node keeps running.
"""

from __future__ import annotations

import time
from pathlib import Path
from typing import Callable

from rclpy.node import Node
from rclpy.qos import QoSProfile, ReliabilityPolicy

from ..bag.msg_definitions import message_class
from ..bag.writer import CONFIG_RECORD, RecordingError, Ros2McapWriter, default_qos_yaml

#: Relative topic name -> ROS type recorded by the twin.
RECORDED_TOPICS = {
    "command/displacement": "std_msgs/msg/Float64MultiArray",
    "command/voltage": "std_msgs/msg/Float64MultiArray",
    "force": "std_msgs/msg/Float64MultiArray",
    "capacitance": "std_msgs/msg/Float64MultiArray",
    "unit_states": "sensor_msgs/msg/JointState",
    "membrane": "visualization_msgs/msg/Marker",
    "/diagnostics": "diagnostic_msgs/msg/DiagnosticArray",
}


class TopicRecorder:
    """Record the node's topics into ``directory/dea_twin_<time>.mcap``.

    Parameters
    ----------
    node : Node
        The node whose topics are recorded (its namespace applies).
    directory : str
        Output folder (created if missing).
    metadata : dict
        ``{key: text}`` stored as the ``dea_array_twin_config`` record.
    on_error : callable
        Called with the error text when recording stops because of an I/O error.
    split_size, split_duration : float, optional
        Start a new file after this many bytes / seconds.
    """

    def __init__(self, node: Node, directory: str, metadata: dict[str, str], on_error: Callable[[str], None],
                 split_size: float | None = None, split_duration: float | None = None):
        self.node = node
        self.on_error = on_error
        self.error = ""
        stamp = time.strftime("%Y%m%d_%H%M%S")
        self.writer = Ros2McapWriter(Path(directory).expanduser() / f"dea_twin_{stamp}.mcap",
                                     metadata={CONFIG_RECORD: metadata}, flush_period=1.0,
                                     split_size=int(split_size) if split_size else None,
                                     split_duration=split_duration or None)
        qos_yaml = default_qos_yaml(reliable=True, depth=10)
        self._subs = []
        for topic, type_name in RECORDED_TOPICS.items():
            cid = self.writer.add_topic(node.resolve_topic_name(topic), type_name, qos_yaml)  # namespace, remaps
            reliability = ReliabilityPolicy.BEST_EFFORT if topic.startswith("command/") else ReliabilityPolicy.RELIABLE
            qos = QoSProfile(depth=100, reliability=reliability)
            self._subs.append(node.create_subscription(
                message_class(type_name), topic, lambda data, cid=cid: self._write(cid, data), qos, raw=True))
        self._timer = node.create_timer(1.0, self.flush)

    def _write(self, cid: int, data: bytes) -> None:
        if self.error:
            return
        try:
            self.writer.write(cid, data, time.time_ns())
        except RecordingError as exc:
            self._fail(exc)

    def flush(self) -> None:
        """Close the open chunk (durability: a kill loses at most the last second)."""
        if self.error:
            return
        try:
            self.writer.flush()
        except RecordingError as exc:
            self._fail(exc)

    def _fail(self, exc: Exception) -> None:
        self.error = f"recording stopped: {exc}"
        self.on_error(self.error)
        self.close()

    def close(self) -> None:
        """Finish the file (summary written) and stop recording."""
        for sub in self._subs:
            self.node.destroy_subscription(sub)
        self._subs = []
        self.node.destroy_timer(self._timer)
        try:
            self.writer.close()
        except RecordingError:
            pass
