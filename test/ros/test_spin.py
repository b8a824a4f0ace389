"""The executables' start and stop (ros/spin.py): a signal at any moment ends them quietly."""

import pytest
import rclpy
from rclpy.node import Node

from dea_array_twin.ros.spin import spin_node


def _built_then_shut_down() -> Node:
    """A node whose start is cut by a signal: rclpy's handler shuts the context down (as it
    does on SIGINT) after the node is built and before the executor exists."""
    node = Node("spin_test")
    rclpy.shutdown()
    return node


def test_a_signal_right_after_the_node_is_built_ends_the_start_without_a_traceback():
    spin_node(_built_then_shut_down, "spin_test", args=[])  # an RCLError escaped here once (exit 1)
    assert not rclpy.ok()


def test_an_error_while_the_context_is_up_still_propagates():
    def broken() -> Node:
        raise RuntimeError("broken node")

    with pytest.raises(RuntimeError, match="broken node"):
        spin_node(broken, "spin_test", args=[])
    assert not rclpy.ok()  # and rclpy was shut down on the way out


def test_a_signal_during_the_demos_spin_ends_it_with_exit_code_0(monkeypatch):
    """The demo spins its own executor: a signal between two waits shuts the context down, and the
    next wait raises an rcl error (not ExternalShutdownException); that is the stop, exit code 0."""
    from rclpy.executors import SingleThreadedExecutor

    import dea_array_twin.ros.demo as demo

    class CutBySignal(SingleThreadedExecutor):
        def spin_once(self, timeout_sec=None):
            rclpy.shutdown()  # what rclpy's SIGINT handler does
            raise RuntimeError("failed to create guard_condition: the given context is not valid")

    monkeypatch.setattr(demo, "SingleThreadedExecutor", CutBySignal)
    assert demo.run_demo(["--ros-args", "-p", "update_rate:=10.0"], duration=5.0) == 0
    assert not rclpy.ok()
