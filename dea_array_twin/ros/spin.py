"""The shared start and stop of the package's ROS 2 executables.

* :func:`init_ros`: ``rclpy.init`` with a broken ``--params-file`` or ``--ros-args``
  reported in one line, exit code 2 (rcl's own error is a traceback);
* :func:`shutdown_signals`: SIGTERM (``docker stop``, systemd) and SIGHUP (a closed
  terminal) end the spin like Ctrl-C (SIGINT), so ``finally`` blocks run and a
  recording is finalised.  rclpy handles SIGINT and SIGTERM itself (it shuts the
  context down) but then calls the handler that was there before ``rclpy.init``,
  which for SIGTERM is the default one: the process dies before any clean-up.  So the
  handlers are installed before ``rclpy.init``, and rclpy chains to them.  gmsh, when
  it builds the twin's mesh, puts in a SIGTERM handler of its own that ends the
  process at once: the handlers are installed again once the node is built;
* :func:`spin_node`: the executables' ``main``;
* :func:`stopped_by_signal`: an rcl error after the context was shut down is the stop.
"""

from __future__ import annotations

import contextlib
import re
import signal
import sys
import threading
from typing import Callable, Iterator, Sequence

import rclpy
from rclpy.exceptions import ParameterException
from rclpy.executors import ExternalShutdownException
from rclpy.node import Node


def init_ros(args: Sequence[str] | None, name: str) -> None:
    """``rclpy.init(args)``; an invalid ROS argument or params file exits 2 with a one-line message."""
    try:
        rclpy.init(args=args)
    except RuntimeError as exc:  # rcl's RCLError: a params file that is missing or not valid YAML, ...
        text = re.sub(r",? at /\S+:\d+", "", str(exc)).replace("failed to initialize rcl: ", "")
        print(f"{name}: error: invalid ROS arguments: {text}", file=sys.stderr)
        raise SystemExit(2) from None


def _interrupt(signum, frame) -> None:
    raise KeyboardInterrupt(f"signal {signum}")


@contextlib.contextmanager
def shutdown_signals() -> Iterator[Callable[[], None]]:
    """While inside, SIGTERM and SIGHUP raise KeyboardInterrupt in the main thread, as SIGINT does.

    Enter it before ``rclpy.init``; it gives a function that installs the handlers
    again (call it after building a twin: gmsh replaces the SIGTERM handler).  Outside
    the main thread (where Python cannot set handlers) it changes nothing.
    """
    signals = (signal.SIGTERM, signal.SIGHUP)
    if threading.current_thread() is not threading.main_thread():
        yield lambda: None
        return
    previous = {sig: signal.getsignal(sig) for sig in signals}

    def install() -> None:
        for sig in signals:
            signal.signal(sig, _interrupt)

    install()
    try:
        yield install
    finally:
        for sig, handler in previous.items():
            signal.signal(sig, handler)


def stopped_by_signal() -> bool:
    """Whether rclpy's context is shut down, e.g. by its own SIGINT/SIGTERM handler.

    If the signal lands while a node is being built, before an executor exists or between
    two waits, the next rcl call raises (RCLError: context not valid) instead of
    ``ExternalShutdownException``: call this in an ``except Exception`` to tell that
    normal stop from a crash (re-raise when it is False).
    """
    return not rclpy.ok()


def spin_node(make_node: Callable[[], Node], name: str, args: Sequence[str] | None = None) -> None:
    """Init rclpy, build the node and spin it until Ctrl-C, SIGTERM, SIGHUP or shutdown, then clean up.

    An invalid parameter (``ValueError``, including ``ConfigError``, or an rclpy
    ``ParameterException``) is logged as FATAL under ``name`` and exits with code 2, as
    does an invalid params file.  A signal that arrives while the node is being built
    ends the start as quietly as one during the spin.
    """
    node = None
    with shutdown_signals() as install_again:
        init_ros(args, name)
        try:
            try:
                node = make_node()
            except (ValueError, ParameterException) as exc:
                rclpy.logging.get_logger(name).fatal(f"invalid parameter: {exc}")
                raise SystemExit(2) from None
            install_again()
            rclpy.spin(node)
        except (KeyboardInterrupt, ExternalShutdownException):
            pass
        except Exception:
            if not stopped_by_signal():
                raise
        finally:
            if node is not None:
                node.destroy_node()
            rclpy.try_shutdown()
