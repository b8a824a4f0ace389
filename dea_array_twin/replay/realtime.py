"""``dea-twin replay --realtime BAG``: republish a bag's recorded commands live, with their timing.

For a controller or a live twin in the loop without ``ros2 bag play``: the command
topics (chosen as :func:`~dea_array_twin.bag.topics.command_topics` chooses them, ``--topic-map``
included) go out as the recorded CDR bytes on rclpy publishers, their log-time spacing
scaled by ``1/rate``.  rclpy is imported only when :func:`realtime_replay` runs, so the
module imports without ROS.
"""

from __future__ import annotations

import math
import sys
import time

from ..bag.msg_definitions import message_class
from ..bag.reader import Bag, BagError
from ..bag.topics import FLOAT_ARRAY, command_topics

__all__ = ["realtime_replay"]


def _log(text: str) -> None:
    print(f"dea-twin replay: {text}", file=sys.stderr)


def _message_class(type_name: str) -> type:
    try:
        return message_class(type_name)
    except (ImportError, ValueError) as exc:
        raise BagError(str(exc)) from None


def realtime_replay(bag: Bag, topic_map: dict[str, str], rate: float = 1.0, wait: float = 2.0) -> int:
    """``dea-twin replay --realtime``: republish the recorded commands with their timing scaled by 1/rate.

    The raw CDR bytes go out on rclpy publishers (reliable, volatile, depth 10: reliable
    and best-effort subscribers both connect) of the recorded type, on the mapped name
    (``--topic-map``) or else the recorded name made relative, so they resolve the same
    in the root namespace.  Uses the caller's ROS domain.  Waits up to ``wait`` seconds
    for a subscriber on every topic first.

    Returns
    -------
    int
        0 after the last message, 130 on Ctrl-C.
    """
    import rclpy
    from rclpy.context import Context
    from rclpy.duration import Duration
    from rclpy.node import Node
    from rclpy.qos import QoSProfile, ReliabilityPolicy
    from rclpy.signals import SignalHandlerOptions
    from tqdm import tqdm

    if not (rate > 0 and math.isfinite(rate)):
        raise BagError(f"--rate must be a number > 0, got {rate}")
    commands = command_topics(bag, topic_map)
    names = {topic: topic_map.get(topic, topic.lstrip("/")) for topic in commands.values()}
    classes = {topic: _message_class(bag.topics[topic] or FLOAT_ARRAY) for topic in commands.values()}
    total = sum(bag.counts.get(t, 0) for t in commands.values())
    context = Context()
    # Nothing spins here, so rclpy's signal handlers are not needed; without them Ctrl-C
    # raises KeyboardInterrupt in the sleep between messages.
    rclpy.init(context=context, signal_handler_options=SignalHandlerOptions.NO)
    node = None
    sent = 0
    try:
        node = Node("dea_twin_replay", context=context)
        qos = QoSProfile(depth=10, reliability=ReliabilityPolicy.RELIABLE)
        pubs = {topic: node.create_publisher(classes[topic], names[topic], qos) for topic in commands.values()}
        _log("republishing " + ", ".join(f"{t} -> {pubs[t].topic_name}" for t in pubs)
             + f" ({total} msgs) at {rate:g}x on ROS domain {context.get_domain_id()}")
        deadline = time.monotonic() + max(0.0, wait)
        while time.monotonic() < deadline and not all(p.get_subscription_count() for p in pubs.values()):
            time.sleep(0.02)
        missing = [p.topic_name for p in pubs.values() if not p.get_subscription_count()]
        if missing:
            _log(f"no subscriber yet on {', '.join(missing)} after {wait:g} s; starting anyway")
        else:
            time.sleep(0.3)  # matched on our side; let the subscribers' side match too
        start_wall = None
        start_log = 0
        with tqdm(total=total, desc="republish", unit="msg", file=sys.stderr, disable=None) as bar:
            for msg in bag.messages(commands.values()):
                if start_wall is None:
                    start_wall, start_log = time.monotonic(), msg.log_time_ns
                delay = start_wall + (msg.log_time_ns - start_log) * 1e-9 / rate - time.monotonic()
                if delay > 0:
                    time.sleep(delay)
                pubs[msg.topic].publish(msg.data)
                sent += 1
                bar.update(1)
        # Let reliable subscribers acknowledge the last messages before the publishers go.
        # Bounded: Fast DDS readers acknowledge on the writer's heartbeat (seconds), and
        # best-effort readers never do; on localhost the data has arrived long before.
        linger = time.monotonic() + 0.5
        for pub in pubs.values():
            pub.wait_for_all_acked(Duration(nanoseconds=max(0, int((linger - time.monotonic()) * 1e9))))
        _log(f"published {sent} message(s)")
        return 0
    except KeyboardInterrupt:
        _log(f"interrupted after {sent} of {total} message(s)")
        return 130
    finally:
        if node is not None:
            node.destroy_node()
        context.try_shutdown()
