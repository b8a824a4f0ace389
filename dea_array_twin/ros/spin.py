"""The shared ``main()`` of the package's ROS 2 executables."""

from __future__ import annotations

from typing import Callable, Sequence

import rclpy
from rclpy.exceptions import ParameterException
from rclpy.executors import ExternalShutdownException
from rclpy.node import Node


def spin_node(make_node: Callable[[], Node], name: str, args: Sequence[str] | None = None) -> None:
    """Init rclpy, build the node and spin it until Ctrl-C / shutdown, then clean up.

    An invalid parameter (``ValueError``, including ``ConfigError``, or an rclpy
    ``ParameterException``) is logged as FATAL under ``name`` and exits with code 2.
    """
    rclpy.init(args=args)
    node = None
    try:
        try:
            node = make_node()
        except (ValueError, ParameterException) as exc:
            rclpy.logging.get_logger(name).fatal(f"invalid parameter: {exc}")
            raise SystemExit(2) from None
        rclpy.spin(node)
    except (KeyboardInterrupt, ExternalShutdownException):
        pass
    finally:
        if node is not None:
            node.destroy_node()
        rclpy.try_shutdown()
